"""``scandiff compare --memory-budget``: a pair over the budget is compared in tiles; a budget
too small for one tile, or not a size, is exit status 2 with a message saying what to set."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from app.core.datasets.lidar import lidar_pair
from app.core.tiling.plan import (
    BASELINE_BYTES,
    LEAN_RESIDENT_BYTES_PER_POINT,
    LOCALISATION_BYTES_PER_POINT,
)
from app.testing.files import ply_bytes


def run_compare(*arguments: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "app", "compare", *map(str, arguments)],
        capture_output=True,
        text=True,
        timeout=400,
    )


@pytest.fixture(scope="module")
def pair_files(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, int]:
    """A three-station warehouse pair as PLY files, and its points (written once, read only)."""
    tmp_path = tmp_path_factory.mktemp("tiled-pair")
    pair = lidar_pair(
        layout="warehouse", change="added", n_stations=3, angular_step_deg=1.2, random_state=4
    )
    paths = []
    for name, cloud in (("reference", pair.reference), ("scan", pair.scan)):
        path = tmp_path / f"{name}.ply"
        path.write_bytes(ply_bytes(cloud, coordinate_type="f8"))
        paths.append(path)
    return paths[0], paths[1], len(pair.reference) + len(pair.scan)


@pytest.fixture(scope="module")
def over_budget_run(
    tmp_path_factory: pytest.TempPathFactory, pair_files: tuple[Path, Path, int]
) -> tuple[subprocess.CompletedProcess[str], int, Path]:
    """One ``compare --json --labels --memory-budget`` of the pair just over its budget: its
    answer, the budget and the labels file (run once: two tests read it)."""
    reference, scan, total = pair_files
    budget = _budget_just_over(total)
    labels = tmp_path_factory.mktemp("over-budget") / "labels.npz"
    done = run_compare(
        reference, scan, "--json", "--labels", labels, "--memory-budget", str(budget)
    )
    return done, budget, labels


def _budget_just_over(total: int) -> int:
    """A budget the pair is just over, read lean (float32 whole clouds: app.core.tiling.lean)."""
    return (
        BASELINE_BYTES
        + total * LEAN_RESIDENT_BYTES_PER_POINT
        + int(0.97 * total) * LOCALISATION_BYTES_PER_POINT
    )


@pytest.mark.slow  # two whole CLI comparisons (~9 CPU s); the streamed CLI test stays in make test
def test_a_pair_over_the_budget_is_compared_in_tiles(
    pair_files: tuple[Path, Path, int],
    over_budget_run: tuple[subprocess.CompletedProcess[str], int, Path],
) -> None:
    reference, scan, _ = pair_files
    done, budget, labels = over_budget_run
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["localisation"]["tiles"]["count"] >= 2
    assert report["params"]["memory_budget_bytes"] == budget
    with np.load(labels) as written:
        assert written["scan_label"].shape == (report["n_scan"],)
        assert (
            np.count_nonzero(written["scan_changed"]) == report["label_counts"]["scan"]["changed"]
        )
    one_process = run_compare(reference, scan, "--json", "--memory-budget", "none")
    assert one_process.returncode == 0, one_process.stderr
    assert "tiles" not in json.loads(one_process.stdout)["localisation"]


def test_a_budget_too_small_for_one_tile_is_exit_2_naming_the_budget(
    pair_files: tuple[Path, Path, int],
) -> None:
    reference, scan, _ = pair_files
    done = run_compare(reference, scan, "--memory-budget", "401M")
    assert done.returncode == 2
    assert "does not fit the memory budget of 401 MiB" in done.stderr
    assert "raise the memory budget by at least" in done.stderr
    assert "Traceback" not in done.stderr


def test_a_memory_budget_that_is_not_a_size_is_exit_2(pair_files: tuple[Path, Path, int]) -> None:
    reference, scan, _ = pair_files
    done = run_compare(reference, scan, "--memory-budget", "lots")
    assert done.returncode == 2
    assert "not a size in bytes: 'lots'" in done.stderr


def test_a_pair_over_the_budget_is_streamed_and_equals_the_lean_tiled_comparison(
    pair_files: tuple[Path, Path, int],
    over_budget_run: tuple[subprocess.CompletedProcess[str], int, Path],
) -> None:
    """Coordinates-only files over the budget: the command reads them in chunks
    (app.core.tiling.streamed); within the subsample its labels are the lean tiled ones."""
    from app.core.formats import read_point_cloud
    from app.core.tiling.compare import compare_tiled
    from app.core.tiling.lean import read_pair

    reference, scan, _ = pair_files
    done, budget, labels = over_budget_run
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert "streamed" in report["timings"], "the streamed path ran"
    paths = {"reference": reference, "scan": scan}
    clouds = read_pair(reference, scan, lambda side: read_point_cloud(paths[side]), budget)
    expected = compare_tiled(clouds[0], clouds[1], budget_bytes=budget, frame_offset=clouds[2])
    tiles = report["localisation"]["tiles"]
    assert tiles["count"] == expected.localisation["tiles"]["count"] >= 2
    assert tiles["max_crop_points"] == expected.localisation["tiles"]["max_crop_points"]
    with np.load(labels) as written:
        np.testing.assert_array_equal(written["reference_label"], expected.reference_label)
        np.testing.assert_array_equal(written["scan_label"], expected.scan_label)
        np.testing.assert_array_equal(written["scan_changed"], expected.scan_label == 1)
    assert report["changed"] == expected.changed
    assert report["score"] == expected.score
