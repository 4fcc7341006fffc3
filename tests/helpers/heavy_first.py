"""The order ``make test``'s xdist processes take the test files in: the longest first.

xdist's ``--dist loadfile`` hands each process whole files, by default the files with the most
tests first.  The suite's longest files have few tests (a tiled comparison, a load run, a
schemathesis run), so they started last and one process ran them while the others sat idle.
Here the files are ordered by the seconds they took in a recorded run (``tests/file_seconds.json``),
the longest first, which is the classic longest-job-first rule for balancing parallel queues.

The browser tests are one unit: they share one package's Chromium sessions and one session's
review service, which are started again each time a process comes back to ``tests/browser``
after other files, so the whole package runs in one process, in one go.

Unknown files (new ones) count :data:`DEFAULT_SECONDS_PER_TEST` a test.  Refresh the table after
big changes of the suite from a run with the CPU plugin (:mod:`tests.helpers.cpu_per_test`)::

    CPU_PER_TEST=/tmp/cpu PYTHONPATH=. python -m pytest -q -n 3 --dist loadfile \\
        -p tests.helpers.cpu_per_test
    PYTHONPATH=. python -m tests.helpers.heavy_first /tmp/cpu.gw*.json
"""

from __future__ import annotations

import json
import sys
from collections import Counter
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import pytest
from xdist.remote import Producer
from xdist.scheduler import LoadFileScheduling

FILE_SECONDS_PATH = Path(__file__).resolve().parents[1] / "file_seconds.json"
"""Seconds each test file took in one ``-n 3 --dist loadfile`` run (files of at least
:data:`LISTED_SECONDS`); only their ratios matter."""

LISTED_SECONDS = 5.0
"""Files shorter than this in the recorded run are left out of the table."""

DEFAULT_SECONDS_PER_TEST = 0.05
"""What a test of a file missing from the table counts (most unlisted files' tests are unit
tests of a few milliseconds to a few tenths of a second)."""

ONE_UNIT_DIRECTORIES = ("tests/browser/",)
"""Directories whose files run in one process in one go (they share package and session
fixtures that are costly to start: Chromium sessions, a review service)."""


def work_unit(nodeid: str) -> str:
    """The unit a test is scheduled with: its file, or its directory in
    :data:`ONE_UNIT_DIRECTORIES`."""
    path = nodeid.split("::", 1)[0]
    for directory in ONE_UNIT_DIRECTORIES:
        if path.startswith(directory):
            return directory
    return path


def load_file_seconds(path: Path = FILE_SECONDS_PATH) -> dict[str, float]:
    """The recorded seconds by test file (empty when the table is missing)."""
    if not path.is_file():
        return {}
    return {str(name): float(seconds) for name, seconds in json.loads(path.read_text()).items()}


def unit_seconds(nodeids: Iterable[str], file_seconds: dict[str, float]) -> dict[str, float]:
    """Expected seconds of each work unit of ``nodeids``: the sum of its files' recorded
    seconds, unlisted files at :data:`DEFAULT_SECONDS_PER_TEST` a test."""
    tests_per_file = Counter(nodeid.split("::", 1)[0] for nodeid in nodeids)
    seconds: dict[str, float] = {}
    for path, count in tests_per_file.items():
        unit = work_unit(path)
        expected = file_seconds.get(path, count * DEFAULT_SECONDS_PER_TEST)
        seconds[unit] = seconds.get(unit, 0.0) + expected
    return seconds


def longest_first(nodeids: Sequence[str], file_seconds: dict[str, float]) -> list[int]:
    """Positions of ``nodeids`` reordered so that the longest work unit comes first.

    The sort is stable: a unit's tests keep their order (so module fixtures and parametrised
    groups stay as pytest arranged them), and units of equal seconds keep theirs.
    """
    seconds = unit_seconds(nodeids, file_seconds)
    return sorted(range(len(nodeids)), key=lambda index: -seconds[work_unit(nodeids[index])])


def order_longest_first(items: list[pytest.Item]) -> None:
    """Reorder collected ``items`` in place, the longest work unit first (an xdist process's
    collection, which the scheduler below hands out in that order)."""
    order = longest_first([item.nodeid for item in items], load_file_seconds())
    items[:] = [items[index] for index in order]


class LongestFirstScheduling(LoadFileScheduling):
    """``--dist loadfile`` with :data:`ONE_UNIT_DIRECTORIES` as one unit each, handing out the
    units in the order the processes collected them (:func:`order_longest_first`)."""

    def __init__(self, config: pytest.Config, log: Producer | None = None) -> None:
        super().__init__(config, log)
        # xdist would otherwise reorder the units by their number of tests (pytest-xdist >= 3.8
        # has the option; the collection is already in the order wanted).
        config.option.loadscopereorder = False

    def _split_scope(self, nodeid: str) -> str:
        """The work unit of ``nodeid``: its file or its one-unit directory."""
        return work_unit(nodeid)


def recorded_file_seconds(record_paths: Iterable[str]) -> dict[str, int]:
    """Seconds by file from the CPU plugin's ``[test, CPU s, wall s]`` records, longest first,
    files of at least :data:`LISTED_SECONDS`."""
    totals: Counter[str] = Counter()
    for record_path in record_paths:
        rows: list[list[Any]] = json.loads(Path(record_path).read_text())
        for nodeid, _cpu, wall in rows:
            totals[nodeid.split("::", 1)[0]] += wall
    return {
        path: round(seconds) for path, seconds in totals.most_common() if seconds >= LISTED_SECONDS
    }


def main(argv: Sequence[str]) -> int:
    """Write ``tests/file_seconds.json`` from the CPU plugin's record files given."""
    if not argv:
        print("usage: python -m tests.helpers.heavy_first /tmp/cpu.gw*.json", file=sys.stderr)
        return 2
    table = recorded_file_seconds(argv)
    FILE_SECONDS_PATH.write_text(json.dumps(table, indent=1) + "\n")
    print(f"{len(table)} files written to {FILE_SECONDS_PATH}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
