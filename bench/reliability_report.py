"""Regenerate the figures table of ``docs/reliability.md`` from the reliability tests.

    .venv/bin/python -m bench.reliability_report            # run tests/reliability (slow too)
    .venv/bin/python -m bench.reliability_report --fast     # only what `make test` runs
    .venv/bin/python -m bench.reliability_report --no-run   # re-render the last figures

Each test writes one JSON row (``tests/helpers/figures.py``) to
``test-artifacts/reliability/``; the rows replace the text between the table markers of
``docs/reliability.md``.  Loopback only: the tests start their own servers on 127.0.0.1.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parent.parent
FIGURES = PROJECT_ROOT / "test-artifacts" / "reliability"
DOCUMENT = PROJECT_ROOT / "docs" / "reliability.md"
BEGIN = "<!-- figures:begin (bench/reliability_report.py) -->"
END = "<!-- figures:end -->"
ROW_ORDER = [
    "malformed-uploads",
    "accepted-strange-files-in-a-worker",
    "authorisation-matrix",
    "view-links",
    "view-websocket",
    "schema-fuzzing",
    "schema-fuzzing-slow",
    "upload-limits-cap",
    "upload-limits-lying-length",
    "upload-limits-parallel-oversize",
    "crash-recovery",
    "worker-kills",
    "sqlite-contention",
    "load-script",
]


def run_tests(include_slow: bool) -> int:
    """Run the reliability tests with a clean figures directory; pytest's exit status."""
    for stale in FIGURES.glob("*.json"):
        stale.unlink()
    marker = "slow or not slow" if include_slow else "not slow"
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:logging", "-m", marker]
    command.append("tests/reliability")
    environment = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.call(command, cwd=PROJECT_ROOT, env=environment)


def cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def render_table() -> str:
    """The markdown table of every recorded row, in a stable order."""
    rows = {path.stem: json.loads(path.read_text()) for path in FIGURES.glob("*.json")}
    ordered = [name for name in ROW_ORDER if name in rows] + sorted(set(rows) - set(ROW_ORDER))
    lines = [
        "| test | load | faults injected | inputs tried | result |",
        "|---|---|---|---|---|",
    ]
    for name in ordered:
        row = rows[name]
        lines.append(
            "| "
            + " | ".join(cell(row[key]) for key in ("test", "load", "faults", "inputs", "result"))
            + " |"
        )
    return "\n".join(lines)


def write_document(table: str) -> None:
    text = DOCUMENT.read_text()
    start, end = text.index(BEGIN) + len(BEGIN), text.index(END)
    DOCUMENT.write_text(text[:start] + "\n" + table + "\n" + text[end:])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fast", action="store_true", help="skip the slow tests")
    parser.add_argument("--no-run", action="store_true", help="render the last figures only")
    arguments = parser.parse_args()
    status = 0 if arguments.no_run else run_tests(include_slow=not arguments.fast)
    table = render_table()
    write_document(table)
    print(table)
    return status


if __name__ == "__main__":
    raise SystemExit(main())
