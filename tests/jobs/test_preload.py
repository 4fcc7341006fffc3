"""The consumer loads the comparison and the libraries of a job's first run before forking."""

from __future__ import annotations

import importlib.util
import logging
from types import SimpleNamespace

import pytest

from app.jobs import consumer
from app.jobs.hooks import job_hooks


@pytest.fixture
def imported(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The names ``preload_pipeline`` imports (recorded, not imported)."""
    names: list[str] = []
    monkeypatch.setattr(consumer, "importlib", SimpleNamespace(import_module=names.append))
    monkeypatch.setattr(job_hooks, "comparison", lambda: None)
    return names


def test_the_real_pipeline_preloads_what_a_first_job_would_import(imported: list[str]) -> None:
    consumer.preload_pipeline()
    assert imported == list(consumer.first_use_libraries())
    assert {"scipy.optimize", "small_gicp"} <= set(imported)


def test_a_stand_in_comparison_preloads_no_library(
    imported: list[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(job_hooks, "compare", lambda *args, **kwargs: None)
    consumer.preload_pipeline()
    assert imported == []


def test_a_missing_library_is_skipped(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    missing = "scipy.optimize"
    tried: list[str] = []

    def import_module(name: str) -> None:
        tried.append(name)
        if name == missing:
            raise ImportError(name)

    monkeypatch.setattr(consumer, "importlib", SimpleNamespace(import_module=import_module))
    monkeypatch.setattr(job_hooks, "comparison", lambda: None)
    with caplog.at_level(logging.WARNING, logger=consumer.logger.name):
        consumer.preload_pipeline()  # does not raise: the job that needs it reports it
    assert tried == list(consumer.first_use_libraries())  # the ones after it are still loaded
    skipped = [
        record for record in caplog.records if record.getMessage() == "library not preloaded"
    ]
    assert [record.library for record in skipped] == [missing]  # type: ignore[attr-defined]


@pytest.mark.parametrize("name", consumer.first_use_libraries())
def test_every_preloaded_library_is_installed(name: str) -> None:
    assert importlib.util.find_spec(name) is not None
