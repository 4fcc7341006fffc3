"""bench.perf1m_stages: every stage it times exists where it looks, and its arithmetic."""

from __future__ import annotations

import importlib

import pytest

from bench.perf1m_stages import STAGES, median_rows, render


@pytest.mark.parametrize(("label", "module", "name"), STAGES)
def test_each_timed_stage_is_a_function_of_its_module(label: str, module: str, name: str) -> None:
    # a renamed or moved function would otherwise be timed as 0.00 s without a word
    assert callable(getattr(importlib.import_module(module), name, None)), (label, module, name)


def test_the_median_skips_failed_rounds_and_the_table_lists_each_stage_once() -> None:
    rows = [{"localise": 3.0, "detect": 0.5}, {"error": "exit 2"}, {"localise": 5.0, "detect": 0.7}]
    median = median_rows(rows)
    assert median == {"localise": 4.0, "detect": pytest.approx(0.6)}
    assert median_rows([{"error": "exit 2"}]) == {}
    table = render({"held-out class": {"this code": median, "code before": {}}})
    assert "| localise | 4.00 |  |" in table
    assert sum(line.startswith("| k-NN of both clouds |") for line in table.splitlines()) == 1
