"""``scandiff compare``'s default memory budget: the settings' value, pydantic only when needed."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from app.cli import compare
from app.kit.memory_budget import DEFAULT_MEMORY_BUDGET_BYTES, SETTING_VARIABLES

PROBE = (
    "import sys\n"
    "from app.cli.compare import _default_memory_budget\n"
    "print(_default_memory_budget(), 'app.config' in sys.modules, 'pydantic' in sys.modules)\n"
)


def _scandiff_free(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in list(os.environ):
        if name.upper().startswith("SCANDIFF_"):
            monkeypatch.delenv(name)


def test_without_a_setting_the_default_is_the_settings_default(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _scandiff_free(monkeypatch)
    from app.config import Settings

    assert compare._default_memory_budget() == DEFAULT_MEMORY_BUDGET_BYTES
    assert Settings().worker_memory_budget_bytes == DEFAULT_MEMORY_BUDGET_BYTES


def test_without_a_setting_neither_the_settings_nor_pydantic_are_imported(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _scandiff_free(monkeypatch)
    completed = subprocess.run(
        [sys.executable, "-c", PROBE], capture_output=True, text=True, check=True, timeout=60
    )
    assert completed.stdout.split() == [str(DEFAULT_MEMORY_BUDGET_BYTES), "False", "False"]


def test_a_scandiff_variable_that_is_no_setting_imports_neither(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # the benches' and tests' SCANDIFF_SHARED_DATA: Settings ignores it (extra="ignore"), so
    # the default stands without pydantic's 0.15 CPU s import (on main: imported for it)
    _scandiff_free(monkeypatch)
    monkeypatch.setenv("SCANDIFF_SHARED_DATA", "/nowhere")
    monkeypatch.setenv("scandiff_not_a_setting", "-1")
    completed = subprocess.run(
        [sys.executable, "-c", PROBE], capture_output=True, text=True, check=True, timeout=60
    )
    assert completed.stdout.split() == [str(DEFAULT_MEMORY_BUDGET_BYTES), "False", "False"]


def test_the_setting_variables_are_the_ones_settings_reads() -> None:
    from app.config import Settings

    read = set()
    for name, field in Settings.model_fields.items():
        alias = field.validation_alias
        choices = [f"SCANDIFF_{name}"] if alias is None else alias.choices  # type: ignore[union-attr]
        read.update(str(choice).upper() for choice in choices)
    assert Settings.model_config.get("env_prefix") == "SCANDIFF_"
    assert not Settings.model_config.get("env_file")
    assert read == SETTING_VARIABLES


@pytest.mark.parametrize(
    "name", ["SCANDIFF_WORKER_MEMORY_BUDGET_BYTES", "scandiff_worker_memory_budget_bytes"]
)
def test_a_budget_setting_in_any_case_is_read(monkeypatch: pytest.MonkeyPatch, name: str) -> None:
    _scandiff_free(monkeypatch)
    monkeypatch.setenv(name, "800000000")
    assert compare._default_memory_budget() == 800_000_000


def test_another_bad_setting_is_still_reported(monkeypatch: pytest.MonkeyPatch) -> None:
    from pydantic import ValidationError

    _scandiff_free(monkeypatch)
    monkeypatch.setenv("SCANDIFF_TOKEN_CACHE_SECONDS", "-1")
    with pytest.raises(ValidationError, match="token_cache_seconds"):
        compare._default_memory_budget()
