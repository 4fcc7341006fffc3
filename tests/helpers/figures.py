"""Figures of the reliability tests: each test records one row of ``docs/reliability.md``.

A row is printed (``pytest -s`` shows it) and written as JSON to
``test-artifacts/reliability/<test>.json`` (or ``$SCANDIFF_RELIABILITY_FIGURES``);
``bench/reliability_report.py`` runs the tests and renders the rows as the table.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from app.testing.paths import PROJECT_ROOT


def figures_directory() -> Path:
    """Where the JSON rows go."""
    configured = os.environ.get("SCANDIFF_RELIABILITY_FIGURES")
    return Path(configured) if configured else PROJECT_ROOT / "test-artifacts" / "reliability"


def record_figure(
    test: str, *, load: str, faults: str, inputs: str, result: str, **details: Any
) -> dict[str, Any]:
    """Print and store one row: what ran, what was injected, what was tried, what came out."""
    row = {"test": test, "load": load, "faults": faults, "inputs": inputs, "result": result}
    row.update(details)
    print(f"\n[reliability] {test}: {inputs} -> {result}")
    directory = figures_directory()
    directory.mkdir(parents=True, exist_ok=True)
    (directory / f"{test}.json").write_text(json.dumps(row, indent=2, sort_keys=True, default=str))
    return row


def percentile(values: list[float], fraction: float) -> float:
    """The ``fraction`` quantile of ``values`` (nearest rank below; 0.5 = median)."""
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[int(fraction * (len(ordered) - 1))]
