"""``scandiff compare`` as scripts use it: a real subprocess on real files."""

from __future__ import annotations

import json

import numpy as np
import pytest
from plyfile import PlyData

from app.core.datasets.lidar import lidar_pair
from app.core.datasets.scenes import raycast_scene
from app.testing.files import ply_bytes
from tests.helpers.cli import run_cli

REQUIRED_KEYS = {
    "method",
    "variant",
    "score",
    "threshold",
    "changed",
    "registration",
    "regions",
    "n_reference",
    "n_scan",
    "timings",
    "sensor_origins",
    "warnings",
}
REGION_KEYS = {
    "kind",
    "n_points",
    "centroid",
    "bbox_min",
    "bbox_max",
    "mean_distance",
    "max_distance",
}


@pytest.fixture(scope="module")
def scene_files(tmp_path_factory):
    directory = tmp_path_factory.mktemp("scene")
    pair = raycast_scene(n_points=20_000, change="box", random_state=11)
    scan = pair.scan.copy()
    scan[[3, 4]] = np.nan  # dropped on load, must keep their place in the labels
    reference_path = directory / "reference.ply"
    reference_path.write_bytes(ply_bytes(pair.reference, coordinate_type="f8"))
    np.savetxt(directory / "scan.xyz", scan, fmt="%.6f")
    return reference_path, directory / "scan.xyz", pair


@pytest.fixture(scope="module")
def plain_run(scene_files, tmp_path_factory):
    """One ``compare --json --labels --export`` of the scene (no cache): its answer and files."""
    reference_path, scan_path, _ = scene_files
    directory = tmp_path_factory.mktemp("plain")
    labels_path = directory / "labels.npz"
    export_path = directory / "export.ply"
    completed = run_cli(
        reference_path, scan_path, "--json", "--labels", labels_path, "--export", export_path
    )
    return completed, labels_path, export_path


def test_json_output_labels_and_export(scene_files, plain_run):
    _, _, pair = scene_files
    completed, labels_path, export_path = plain_run
    assert completed.returncode == 0, completed.stderr
    report = json.loads(completed.stdout)  # exactly one JSON object
    assert REQUIRED_KEYS <= report.keys()
    assert report["method"] == "gmm" and report["variant"] == "improved"
    assert report["changed"] is True
    assert np.asarray(report["registration"]["transform"]).shape == (4, 4)
    assert 0.0 <= report["registration"]["fitness"] <= 1.0
    assert report["regions"] and all(REGION_KEYS <= region.keys() for region in report["regions"])
    assert report["n_scan"] == len(pair.scan) - 2

    with np.load(labels_path) as labels:
        assert set(labels.files) == {
            "reference_changed",
            "scan_changed",
            "reference_label",
            "scan_label",
        }
        assert labels["reference_changed"].dtype == bool
        assert labels["scan_label"].dtype == np.int8
        assert labels["reference_label"].shape == (len(pair.reference),)
        assert labels["scan_label"].shape == (len(pair.scan),)
        assert (labels["scan_label"][[3, 4]] == -1).all()
        assert not labels["scan_changed"][[3, 4]].any()
        np.testing.assert_array_equal(labels["scan_changed"], labels["scan_label"] == 1)

    exported = PlyData.read(str(export_path))["vertex"]
    assert {"label", "distance", "cloud"} <= set(exported.data.dtype.names)
    assert len(exported.data) == len(pair.reference) + len(pair.scan) - 2


def test_human_summary_without_json(scene_files):
    reference_path, scan_path, _ = scene_files
    completed = run_cli(reference_path, scan_path, "--method", "pca", "--no-align")
    assert completed.returncode == 0, completed.stderr
    assert "pca-EMD" in completed.stdout and "regions:" in completed.stdout


@pytest.mark.parametrize(
    ("content", "fragment"),
    [
        (b"ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nend_header\n1\n", "ply"),
        (b"\x00\x01garbage", "format"),
    ],
)
def test_bad_input_exits_2_with_one_line(tmp_path, scene_files, content, fragment):
    reference_path, _, _ = scene_files
    bad = tmp_path / "bad.ply"
    bad.write_bytes(content)
    completed = run_cli(reference_path, bad, "--json")
    assert completed.returncode == 2
    assert completed.stdout == ""
    lines = completed.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("scandiff: error:")
    assert fragment.lower() in lines[0].lower()


def test_missing_file_exits_2(tmp_path, scene_files):
    reference_path, _, _ = scene_files
    completed = run_cli(reference_path, tmp_path / "nope.ply")
    assert completed.returncode == 2
    assert "no such file" in completed.stderr


@pytest.mark.slow  # a comparison of two 120k-point frames in a subprocess; make test keeps the
# CLI's synthetic comparisons here and the KITTI frames' origins in core/test_origins.py
def test_real_kitti_frames(real_data_dir, tmp_path):
    frames = real_data_dir / "kitti_2011_09_26_drive_0002_pointcloudset"
    completed = run_cli(frames / "frame0.ply", frames / "frame1.ply", "--json", "--sensor-frame")
    assert completed.returncode == 0, completed.stderr
    report = json.loads(completed.stdout)
    assert report["registration"]["fitness"] > 0.5
    translation = np.asarray(report["registration"]["transform"])[:3, 3]
    assert 0.3 < np.linalg.norm(translation) < 3.0  # the car moves ~0.9 m per frame


def test_token_cli_roles_match_the_service():
    from app.cli import tokens
    from app.services import auth

    assert tokens.ROLES == auth.ROLES


@pytest.fixture(scope="module")
def survey_files(tmp_path_factory):
    """A 3-station survey pair (a box added) as PLY files with a per-point ``station`` field."""
    directory = tmp_path_factory.mktemp("survey")
    pair = lidar_pair(
        layout="room", change="added", n_stations=3, angular_step_deg=1.5, random_state=4
    )
    paths = []
    for name, points, station in (
        ("reference", pair.reference, pair.reference_station),
        ("scan", pair.scan, pair.scan_station),
    ):
        path = directory / f"{name}.ply"
        path.write_bytes(
            ply_bytes(points, coordinate_type="f8", extra={"station": station.astype(np.uint8)})
        )
        paths.append(path)
    return paths[0], paths[1], pair


def origin_flags(flag: str, origins: np.ndarray) -> list[str]:
    return [part for origin in origins for part in (flag, ",".join(map(repr, origin.tolist())))]


def test_station_origins_on_the_command_line(survey_files):
    reference_path, scan_path, pair = survey_files
    completed = run_cli(
        reference_path,
        scan_path,
        "--json",
        "--no-align",
        *origin_flags("--sensor-origin", pair.reference_origins),
        *origin_flags("--scan-origin", pair.scan_origins),
    )
    assert completed.returncode == 0, completed.stderr
    report = json.loads(completed.stdout)
    for side, origins in (("reference", pair.reference_origins), ("scan", pair.scan_origins)):
        entries = report["sensor_origins"][side]
        assert [entry["source"] for entry in entries] == ["given"] * 3
        np.testing.assert_allclose([entry["origin"] for entry in entries], origins)
    assert report["changed"] is True


@pytest.mark.parametrize(
    ("flags", "fragment"),
    [
        (["--sensor-origin", "1,2"], "--sensor-origin takes three finite numbers"),
        (["--scan-origin", "1,2,nan"], "--scan-origin takes three finite numbers"),
        (["--sensor-origin", "1,2,3", "--sensor-frame"], "not both"),
        (["--scan-origin", "1,2,3", "--param", "scan_origin=[0,0,0]"], "not both"),
        (["--sensor-origin", "1,2,3", "--sensor-origin", "4,5,6"], "station_index"),
    ],
    ids=["two-numbers", "nan", "sensor-frame", "param", "fewer-than-stations"],
)
def test_bad_origins_exit_2_saying_what_to_fix(survey_files, flags, fragment):
    reference_path, scan_path, _ = survey_files
    completed = run_cli(reference_path, scan_path, "--no-align", *flags)
    assert completed.returncode == 2, completed.stdout
    lines = completed.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("scandiff: error:")
    assert fragment in lines[0]


def test_geometry_cache_directory_is_filled_then_used_with_the_same_labels(
    scene_files, plain_run, tmp_path
):
    reference_path, scan_path, _ = scene_files
    plain, plain_labels, _ = plain_run  # the same comparison without a cache
    cache_dir = tmp_path / "geometry"
    assert plain.returncode == 0, plain.stderr
    for run in ("first", "second"):
        cached = run_cli(
            reference_path,
            scan_path,
            "--json",
            "--labels",
            tmp_path / f"{run}.npz",
            "--geometry-cache",
            cache_dir,
        )
        assert cached.returncode == 0, cached.stderr
        files = list(cache_dir.iterdir())
        assert len(files) == 1 and files[0].suffix == ".geometry"
        if run == "first":
            written = files[0].stat().st_mtime_ns
        assert files[0].stat().st_mtime_ns == written  # the second run read it, wrote nothing
        with np.load(plain_labels) as expected, np.load(tmp_path / f"{run}.npz") as got:
            for name in expected.files:
                np.testing.assert_array_equal(got[name], expected[name])
