"""``scandiff compare`` on COPC files (``.copc.laz``): read as LAZ, the same answer as the same
clouds in PLY; an edited COPC header is refused with exit status 2."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from app.core.datasets.scenes import raycast_scene
from app.core.formats import read_point_cloud
from app.testing.files import ply_bytes
from tests.helpers.copc import COPC_SCALE, copc_bytes, with_point_count


def run_compare(*arguments: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "app", "compare", *map(str, arguments)],
        capture_output=True,
        text=True,
        timeout=240,
    )


def test_compare_reads_copc_like_the_same_points_in_ply(tmp_path: Path) -> None:
    pair = raycast_scene(n_points=4000, change="box", random_state=5)
    reference, scan = (
        np.round(cloud / COPC_SCALE) * COPC_SCALE for cloud in (pair.reference, pair.scan)
    )
    for name, cloud in (("reference", reference), ("scan", scan)):
        copc_path = tmp_path / f"{name}.copc.laz"
        copc_path.write_bytes(copc_bytes(cloud))
        in_file_order = read_point_cloud(copc_path).points  # the octree reorders the points
        (tmp_path / f"{name}.ply").write_bytes(ply_bytes(in_file_order, coordinate_type="f8"))
    options = ("--json", "--method", "pca", "--no-align")
    from_copc = run_compare(tmp_path / "reference.copc.laz", tmp_path / "scan.copc.laz", *options)
    from_ply = run_compare(tmp_path / "reference.ply", tmp_path / "scan.ply", *options)
    assert from_copc.returncode == 0, from_copc.stderr
    assert from_ply.returncode == 0, from_ply.stderr
    copc_report, ply_report = json.loads(from_copc.stdout), json.loads(from_ply.stdout)
    assert copc_report["n_reference"] == len(reference) and copc_report["n_scan"] == len(scan)
    assert copc_report["changed"] == ply_report["changed"]
    assert copc_report["score"] == ply_report["score"]


def test_compare_refuses_a_copc_whose_header_disagrees_with_its_points(tmp_path: Path) -> None:
    cloud = np.random.default_rng(3).uniform(0.0, 5.0, size=(500, 3))
    edited = tmp_path / "edited.copc.laz"
    edited.write_bytes(with_point_count(copc_bytes(cloud), 600))
    good = tmp_path / "good.ply"
    good.write_bytes(ply_bytes(cloud))
    completed = run_compare(good, edited, "--method", "pca", "--no-align")
    assert completed.returncode == 2, completed.stderr
    assert "declares 600 points but its octree holds 500" in completed.stderr
