"""The order make test's xdist processes take the files in (tests/helpers/heavy_first.py)."""

from __future__ import annotations

import json
from pathlib import Path

from tests.helpers.heavy_first import (
    DEFAULT_SECONDS_PER_TEST,
    FILE_SECONDS_PATH,
    longest_first,
    recorded_file_seconds,
    unit_seconds,
    work_unit,
)

PROJECT_ROOT = Path(__file__).resolve().parents[1]

NODEIDS = [
    "tests/api/test_a.py::test_one",
    "tests/api/test_a.py::test_two",
    "tests/browser/test_b.py::test_one",
    "tests/core/test_long.py::test_one[1]",
    "tests/core/test_long.py::test_one[2]",
    "tests/browser/test_c.py::test_one",
    "tests/core/test_unlisted.py::test_one",
]


def test_the_longest_unit_comes_first_and_each_unit_keeps_its_order() -> None:
    seconds = {
        "tests/api/test_a.py": 10,
        "tests/core/test_long.py": 100,
        "tests/browser/test_b.py": 30,
    }
    ordered = [NODEIDS[index] for index in longest_first(NODEIDS, seconds)]
    assert ordered == [
        "tests/core/test_long.py::test_one[1]",
        "tests/core/test_long.py::test_one[2]",
        "tests/browser/test_b.py::test_one",
        "tests/browser/test_c.py::test_one",
        "tests/api/test_a.py::test_one",
        "tests/api/test_a.py::test_two",
        "tests/core/test_unlisted.py::test_one",
    ]


def test_browser_files_are_one_unit_and_unlisted_files_count_by_their_tests() -> None:
    assert work_unit("tests/browser/test_b.py::test_one") == "tests/browser/"
    assert work_unit("tests/core/test_long.py::test_one[1]") == "tests/core/test_long.py"
    seconds = unit_seconds(NODEIDS, {"tests/browser/test_b.py": 30, "tests/browser/test_c.py": 5})
    assert seconds["tests/browser/"] == 35
    assert seconds["tests/api/test_a.py"] == 2 * DEFAULT_SECONDS_PER_TEST


def test_the_table_is_made_from_the_cpu_plugins_records(tmp_path: Path) -> None:
    record = tmp_path / "cpu.gw0.json"
    record.write_text(
        json.dumps(
            [["tests/x.py::a", 1.0, 4.0], ["tests/x.py::b", 1.0, 3.0], ["tests/y.py::a", 0, 1]]
        )
    )
    assert recorded_file_seconds([str(record)]) == {"tests/x.py": 7}


def test_every_file_in_the_recorded_table_exists() -> None:
    table = json.loads(FILE_SECONDS_PATH.read_text())
    assert len(table) > 20
    assert [path for path in table if not (PROJECT_ROOT / path).is_file()] == []
