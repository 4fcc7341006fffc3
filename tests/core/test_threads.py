"""The numeric core's process-wide threading defaults."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from app.core.threads import for_each_chunk

PROGRAM = "import os, app.core.localise; print(os.environ['OMP_WAIT_POLICY'])"


def wait_policy_after_import(environment: dict[str, str]) -> str:
    completed = subprocess.run(
        [sys.executable, "-c", PROGRAM],
        capture_output=True,
        text=True,
        check=True,
        env=environment,
    )
    return completed.stdout.strip()


@pytest.mark.parametrize(("given", "expected"), [(None, "PASSIVE"), ("ACTIVE", "ACTIVE")])
def test_importing_the_core_makes_openmp_waits_passive_unless_the_caller_chose(given, expected):
    environment = {name: value for name, value in os.environ.items() if name != "OMP_WAIT_POLICY"}
    if given is not None:
        environment["OMP_WAIT_POLICY"] = given
    assert wait_policy_after_import(environment) == expected


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_each_chunk_is_worked_on_once_whatever_the_threads(threads):
    squares = np.zeros(1000)
    visits = np.zeros(1000, dtype=int)

    def square(rows: slice) -> None:
        squares[rows] = np.arange(1000)[rows] ** 2
        visits[rows] += 1

    for_each_chunk(square, (slice(start, start + 7) for start in range(0, 1000, 7)), threads)
    np.testing.assert_array_equal(squares, np.arange(1000) ** 2)
    np.testing.assert_array_equal(visits, 1)


@pytest.mark.parametrize("threads", [1, 2])
def test_an_error_in_a_chunk_reaches_the_caller(threads):
    def fail_on_five(chunk: int) -> None:
        if chunk == 5:
            raise ValueError("chunk five")

    with pytest.raises(ValueError, match="chunk five"):
        for_each_chunk(fail_on_five, range(10), threads)


def test_for_each_chunk_takes_only_a_few_chunks_ahead_of_the_finished_ones():
    """A generator of large chunks (the calibration's resamples) is not drawn to the end
    before the first is done: at most 2 * threads chunks wait beside the finished ones."""
    lock = threading.Lock()
    drawn = finished = ahead = 0

    def chunks():
        nonlocal drawn, ahead
        for index in range(60):
            with lock:
                drawn += 1
                ahead = max(ahead, drawn - finished)
            yield index

    def work(index):
        nonlocal finished
        time.sleep(0.002)
        with lock:
            finished += 1

    for_each_chunk(work, chunks(), 2)
    assert finished == 60
    assert ahead <= 2 * 2 + 1
