"""``scandiff compare --trajectory/--scan-trajectory``: a real subprocess on real files.

Rules checked: PLY maps with per-point times and their TUM / CSV trajectories are compared with
the trajectory test (reported in the JSON), the removed box found; bad trajectory input exits
with status 2, one line on stderr saying what to fix, and writes no labels (times not covering
the points', non-unit or non-finite quaternions, an unknown format, pose times without a
trajectory, KITTI poses without times for points with times).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from app.cli.compare_report import cli_warnings
from app.core.quality import origin_warnings
from app.core.trajectory import Trajectory
from app.testing.files import ply_bytes
from tests.helpers.trajectory_scenes import SEEN_BOX, corridor_pair, in_box


def run_cli(*arguments: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "app", "compare", *map(str, arguments)],
        capture_output=True,
        text=True,
        timeout=240,
    )


def tum_text(trajectory: Trajectory, shift: float = 0.0, quaternion: str = "0 0 0 1") -> str:
    return "\n".join(
        f"{time + shift:.6f} {x:.6f} {y:.6f} {z:.6f} {quaternion}"
        for time, (x, y, z) in zip(trajectory.times, trajectory.positions, strict=True)
    )


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    directory = tmp_path_factory.mktemp("swept")
    reference, scan = corridor_pair()
    paths = {
        "reference": directory / "reference.ply",
        "scan": directory / "scan.ply",
        "reference_tum": directory / "reference.txt",
        "scan_csv": directory / "scan.csv",
        "late_tum": directory / "late.txt",
        "kitti": directory / "poses.txt",
        "long_quaternions": directory / "long.txt",
        "nan_quaternions": directory / "nan.txt",
    }
    for name, swept in (("reference", reference), ("scan", scan)):
        paths[name].write_bytes(
            ply_bytes(
                swept.cloud.points,
                coordinate_type="f8",
                extra={"time": swept.cloud.attributes["time"]},
            )
        )
    paths["reference_tum"].write_text(tum_text(reference.trajectory))
    rows = [
        f"{time:.6f},{x:.6f},{y:.6f},{z:.6f}"
        for time, (x, y, z) in zip(scan.trajectory.times, scan.trajectory.positions, strict=True)
    ]
    paths["scan_csv"].write_text("Timestamp,X,Y,Z\n" + "\n".join(rows))
    paths["late_tum"].write_text(tum_text(scan.trajectory, shift=1000.0))
    paths["long_quaternions"].write_text(tum_text(scan.trajectory, quaternion="0 0 0.5 1"))
    paths["nan_quaternions"].write_text(tum_text(scan.trajectory, quaternion="0 0 nan 1"))
    paths["kitti"].write_text(
        "\n".join(f"1 0 0 {x} 0 1 0 {y} 0 0 1 {z}" for x, y, z in scan.trajectory.positions)
    )
    paths["labels"] = directory / "labels.npz"
    return paths


def test_maps_with_trajectories_get_the_trajectory_test(files: dict[str, Path]) -> None:
    completed = run_cli(
        files["reference"],
        files["scan"],
        "--trajectory",
        files["reference_tum"],
        "--scan-trajectory",
        files["scan_csv"],
        "--json",
        "--labels",
        files["labels"],
    )

    assert completed.returncode == 0, completed.stderr
    result = json.loads(completed.stdout)
    for side in ("reference", "scan"):
        (entry,) = result["sensor_origins"][side]
        assert entry["source"] == "trajectory" and entry["assignment"] == "times"
        assert result["calibration"]["visibility"][side]["test"] == "trajectory"
    reference, _ = corridor_pair()
    labels = np.load(files["labels"])["reference_label"]
    assert (labels[in_box(reference.cloud.points, SEEN_BOX)] == 1).mean() >= 0.85


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (("--scan-trajectory", "late_tum"), "do not cover the points' times"),
        (("--scan-trajectory", "long_quaternions"), "not 1: give unit quaternions"),
        (("--scan-trajectory", "nan_quaternions"), "non-finite value"),
        (("--trajectory", "reference"), "expected TUM"),
        (("--trajectory-rate", "10"), "need --trajectory FILE"),
        (("--scan-trajectory", "kitti"), "trajectory has none"),
        (("--scan-trajectory", "kitti", "--scan-trajectory-rate", "-1"), "positive number"),
    ],
    ids=[
        "times-not-covered",
        "non-unit-quaternion",
        "nan-quaternion",
        "unknown-format",
        "rate-alone",
        "kitti-untimed",
        "bad-rate",
    ],
)
def test_bad_trajectory_input_exits_2_saying_what_to_fix(
    files: dict[str, Path], arguments: tuple[str, ...], message: str, tmp_path: Path
) -> None:
    resolved = [str(files.get(value, value)) for value in arguments]
    labels = tmp_path / "labels.npz"

    completed = run_cli(files["reference"], files["scan"], *resolved, "--labels", labels)

    assert completed.returncode == 2, completed.stderr
    (line,) = completed.stderr.strip().splitlines()
    assert line.startswith("scandiff: error: ") and message in line
    assert not labels.exists()


def test_points_outside_the_trajectorys_span_are_warned_in_the_clis_flags() -> None:
    reported = {"source": "trajectory", "time_span": [0.0, 9.5], "points_outside": 150}

    (warning,) = cli_warnings(origin_warnings({"reference": [reported], "scan": []})[:1])

    assert warning["code"] == "trajectory_time_span"
    assert warning["how_to_fix"]["flags"] == ["--trajectory", "--scan-trajectory"]
    assert "--trajectory or --scan-trajectory" in warning["how_to_fix"]["text"]
