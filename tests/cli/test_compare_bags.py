"""``scandiff compare`` on ROS bags: a real subprocess on bags written in the test.

Rules checked: a ROS 1 bag and a bare MCAP file are accepted as REFERENCE and SCAN; ``--bag-param``
applies to both and ``--scan-bag-param`` to the scan only (here: both maps built in ``odom``,
so no alignment is needed); the box missing from the scan's room is found as removed; a bad bag
parameter exits 2 with one line saying what to set.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from app.testing.bags import BOX_HIGH, BOX_LOW, MAP_TO_ODOM, write_lidar_bag
from tests.helpers.cli import run_cli


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    reference_directory = tmp_path_factory.mktemp("reference")
    scan_directory = tmp_path_factory.mktemp("scan")
    reference = write_lidar_bag(reference_directory, "bag", poses="tf")
    scan = write_lidar_bag(scan_directory, "mcap", poses="odometry", with_box=False, seed=1)
    return reference.path, scan.path


def test_bags_compared_with_bag_params(bags: tuple[Path, Path]) -> None:
    reference, scan = bags
    completed = run_cli(
        reference, scan, "--json", "--no-align", "--bag-param", "fixed_frame=odom",
        "--scan-bag-param", "voxel_size=0.06",
    )  # fmt: skip

    assert completed.returncode == 0, completed.stderr
    result = json.loads(completed.stdout)
    assert result["changed"] is True
    removed = [region for region in result["regions"] if region["kind"] == "removed"]
    assert removed
    centroid = np.array(max(removed, key=lambda region: region["n_points"])["centroid"])
    box_centre = (BOX_LOW[0] + BOX_HIGH[0]) / 2 - MAP_TO_ODOM  # both maps in odom
    assert np.linalg.norm(centroid[:2] - box_centre[:2]) < 0.6


def test_bad_bag_param_exits_2(bags: tuple[Path, Path]) -> None:
    completed = run_cli(*bags, "--bag-param", "voxel=0.1")

    assert completed.returncode == 2
    assert "unknown bag parameter(s) voxel; known: cloud_topic" in completed.stderr
    assert len(completed.stderr.strip().splitlines()) == 1
