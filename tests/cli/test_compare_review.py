"""``scandiff compare`` explains its decision on stdout and prints quality warnings on stderr;
the paper's detector names work as ``--method``."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from app.core.datasets.scenes import raycast_scene
from app.core.quality import LARGE_ROTATION_DEGREES
from app.core.registration import apply_transform
from app.testing.files import ply_bytes


def run_cli(*arguments: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "app", "compare", *map(str, arguments)],
        capture_output=True,
        text=True,
        timeout=240,
    )


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A ray-cast room with a box added; the scan also turned by more than the warning limit."""
    directory = tmp_path_factory.mktemp("review-scene")
    pair = raycast_scene(n_points=12_000, change="box", random_state=5)
    angle = np.radians(LARGE_ROTATION_DEGREES + 3.0)
    turn = np.eye(4)
    turn[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    paths = {
        "reference": directory / "reference.ply",
        "scan": directory / "scan.ply",
        "turned": directory / "turned.ply",
    }
    paths["reference"].write_bytes(ply_bytes(pair.reference, coordinate_type="f8"))
    paths["scan"].write_bytes(ply_bytes(pair.scan, coordinate_type="f8"))
    paths["turned"].write_bytes(ply_bytes(apply_transform(pair.scan, turn), coordinate_type="f8"))
    return paths, pair


def origin_params(pair) -> list[str]:
    return [
        *("--param", f"reference_origin={json.dumps(list(map(float, pair.reference_origin)))}"),
        *("--param", f"scan_origin={json.dumps(list(map(float, pair.scan_origin)))}"),
    ]


def test_warnings_go_to_stderr_and_the_summary_explains(scene) -> None:
    paths, _ = scene
    completed = run_cli(paths["reference"], paths["turned"], "--param", "estimate_origins=false")
    assert completed.returncode == 0, completed.stderr
    warnings = completed.stderr.strip().splitlines()
    assert warnings and all(line.startswith("scandiff: warning: ") for line in warnings)
    assert any("degrees" in line and "--no-align" in line for line in warnings)
    assert sum("sensor origin is unknown" in line for line in warnings) == 2
    # the CLI's own flags, never the API's parameters or --param; no stale frame advice
    unknown = [line for line in warnings if "sensor origin is unknown" in line]
    assert all("--sensor-origin" in line and "--scan-origin" in line for line in unknown)
    assert not any("--param" in line or "sensor_origin=" in line for line in warnings)
    assert not any('"align"' in line or "moving sensor's frame" in line for line in warnings)
    lines = completed.stdout.splitlines()
    assert lines[1].startswith("  why: changed: ") or lines[1].startswith("  why: no change: ")
    assert "the detector's score" in lines[1]
    assert f"  warnings: {len(warnings)} (on stderr)" in lines
    assert "sensor origin is unknown" not in completed.stdout


def test_json_on_stdout_stays_parseable_with_warnings_on_stderr(scene) -> None:
    paths, _ = scene
    completed = run_cli(
        paths["reference"], paths["turned"], "--json", "--param", "estimate_origins=false"
    )
    assert completed.returncode == 0, completed.stderr
    report = json.loads(completed.stdout)
    expected = [
        f"scandiff: warning: {warning['message']} To fix: {warning['how_to_fix']['text']}."
        for warning in report["quality_warnings"]
    ]
    assert completed.stderr.strip().splitlines() == expected
    for warning in report["quality_warnings"]:  # flags, each a flag of this command
        assert all(flag.startswith("--") for flag in warning["how_to_fix"]["flags"])
    assert "large_rotation" in [warning["code"] for warning in report["quality_warnings"]]
    assert report["explanation"]["decision"] == ("changed" if report["changed"] else "unchanged")


def test_a_clean_rescan_with_origins_prints_no_warning(scene) -> None:
    paths, pair = scene
    completed = run_cli(paths["reference"], paths["scan"], *origin_params(pair))
    assert completed.returncode == 0, completed.stderr
    assert completed.stderr == ""
    assert "  why: changed: " in completed.stdout
    assert "warnings:" not in completed.stdout


def test_the_papers_name_as_method(scene) -> None:
    paths, pair = scene
    completed = run_cli(
        paths["reference"], paths["scan"], "--method", "PE-EMD", "--json", *origin_params(pair)
    )
    assert completed.returncode == 0, completed.stderr
    assert json.loads(completed.stdout)["method"] == "planes"
    refused = run_cli(paths["reference"], paths["scan"], "--method", "pe-gmm")
    assert refused.returncode == 2
    assert "pe-gmm" in refused.stderr and "pe-emd" in refused.stderr


def test_a_failed_alignment_names_the_clis_flag(scene, tmp_path: Path) -> None:
    paths, pair = scene
    elsewhere = tmp_path / "elsewhere.ply"
    elsewhere.write_bytes(ply_bytes(pair.scan + np.array([500.0, 0.0, 0.0]), coordinate_type="f8"))
    completed = run_cli(paths["reference"], elsewhere)
    assert completed.returncode == 2, completed.stderr
    (line,) = completed.stderr.strip().splitlines()
    assert line.startswith("scandiff: error: ") and "does not overlap" in line
    assert line.endswith("(--no-align)")
    assert '"align"' not in line and "API" not in line
