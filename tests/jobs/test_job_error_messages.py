"""A job's error names the API's knob for the fix the core's error asks for (issue 31): the
core says "compare without aligning", the job's error adds the job's ``"align": false``."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.errors import InputError, RegistrationError
from app.core.registration import register_scan
from app.jobs.execution import api_error_message


def test_a_failed_alignment_names_the_jobs_align_parameter() -> None:
    generator = np.random.default_rng(2)
    reference = generator.uniform(0.0, 4.0, size=(3000, 3))
    with pytest.raises(RegistrationError) as raised:
        register_scan(reference, reference + np.array([60.0, 0.0, 0.0]))
    message = api_error_message(raised.value)
    assert message.startswith(str(raised.value))
    assert '"align": false' in message and "--no-align" not in message


def test_an_error_without_a_fix_is_kept_as_it_is() -> None:
    assert api_error_message(InputError("no such file: a.ply")) == "no such file: a.ply"
