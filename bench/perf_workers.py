"""The per-configuration measurements of ``bench/perf.py``, each run in a fresh process.

A scene directory holds ``reference.ply`` and ``scan.ply`` (binary little-endian float32
x, y, z, as scanners write them) and ``truth.npz`` (sensor origins, the true transform and the
ground-truth changed/observed masks).  Each worker prints one JSON object.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from plyfile import PlyData, PlyElement
from scipy.spatial import cKDTree

from app.core.datasets.scenes import raycast_scene
from app.core.formats import read_point_cloud
from app.core.labels import LABEL_CHANGED
from app.core.pipeline import compare
from app.kit.allocator import release_freed_memory_promptly

SCENE_SEED = 100
M3C2_CYLINDER_RADIUS_1M = 0.025
M3C2_NORMAL_RADIUS_1M = 0.05
M3C2_MAX_DISTANCE = 0.5
"""M3C2 radii (metres) at 1M points a scan, scaled by the point spacing (sqrt(1M / n)) at
other sizes: the normal radius is about two of our localiser's 10-neighbour radii (median 2.6 cm
at 1M), the cylinder about one, so both methods look at the same neighbourhood scale.  Wider
radii make M3C2 much slower (0.1 / 0.2 m took 138 s for both directions at 1M)."""


def write_binary_ply(path: Path, points: NDArray[np.float64]) -> None:
    """A binary little-endian PLY with float32 x, y, z."""
    vertex = np.empty(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    vertex["x"], vertex["y"], vertex["z"] = points.T
    PlyData([PlyElement.describe(vertex, "vertex")], text=False, byte_order="<").write(str(path))


def write_scene(scene_dir: Path, n_points: int, change: str = "box") -> None:
    """Ray-cast one rescan pair (by default an added box; any of
    ``app.core.datasets.scenes.CHANGE_KINDS``) and write it as binary PLY + ground truth."""
    pair = raycast_scene(
        n_points=n_points, change=change, pose_error=(0.03, 0.4), random_state=SCENE_SEED
    )
    scene_dir.mkdir(parents=True, exist_ok=True)
    write_binary_ply(scene_dir / "reference.ply", pair.reference)
    write_binary_ply(scene_dir / "scan.ply", pair.scan)
    np.savez(
        scene_dir / "truth.npz",
        reference_origin=pair.reference_origin,
        scan_origin=pair.scan_origin,
        true_transform=pair.true_transform,
        reference_changed=pair.reference_changed,
        scan_changed=pair.scan_changed,
        reference_observed=pair.reference_observed,
        scan_observed=pair.scan_observed,
    )


def _status_mb(field: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no {field} in /proc/self/status")


def peak_rss_mb() -> float:
    """This process's peak resident set size (VmHWM) in MiB."""
    return _status_mb("VmHWM")


def resident_mb() -> float:
    """This process's resident set size now (VmRSS) in MiB."""
    return _status_mb("VmRSS")


def changed_iou(
    reference_changed: NDArray[np.bool_], scan_changed: NDArray[np.bool_], truth: Any
) -> float:
    """IoU of changed points over ground-truth-observed points (as in bench/scenes.py)."""
    reference_observed, scan_observed = truth["reference_observed"], truth["scan_observed"]
    predicted = np.concatenate([reference_changed[reference_observed], scan_changed[scan_observed]])
    actual = np.concatenate(
        [truth["reference_changed"][reference_observed], truth["scan_changed"][scan_observed]]
    )
    union = np.count_nonzero(predicted | actual)
    return float(np.count_nonzero(predicted & actual) / union) if union else 1.0


def _load_pair(scene_dir: Path) -> tuple[Any, Any, float]:
    started = time.perf_counter()
    reference = read_point_cloud(scene_dir / "reference.ply")
    scan = read_point_cloud(scene_dir / "scan.ply")
    return reference, scan, time.perf_counter() - started


def pipeline_worker(scene_dir: Path, *, method: str, **_: Any) -> dict[str, Any]:
    """Load both PLY files and run ``compare()``; stage times, peak RSS, IoU."""
    release_freed_memory_promptly()  # as the CLI and the job workers do
    imports_mb = resident_mb()  # the libraries, before any data
    truth = np.load(scene_dir / "truth.npz")
    reference, scan, load_seconds = _load_pair(scene_dir)
    started = time.perf_counter()
    result = compare(
        reference,
        scan,
        method=method,
        params={
            "reference_origin": truth["reference_origin"].tolist(),
            "scan_origin": truth["scan_origin"].tolist(),
        },
    )
    compare_seconds = time.perf_counter() - started
    return {
        "load": load_seconds,
        **{stage: float(result.timings[stage]) for stage in ("align", "localise", "detect")},
        "total": load_seconds + compare_seconds,
        "peak_rss_mb": peak_rss_mb(),
        "imports_rss_mb": imports_mb,
        # scikit-learn imports pandas when it is installed (the bench extra brings it, through
        # py4dgeo's seaborn; `make install` does not): tens of MB of this process's RSS
        "pandas_loaded": "pandas" in sys.modules,
        "iou": changed_iou(
            result.reference_label == LABEL_CHANGED, result.scan_label == LABEL_CHANGED, truth
        ),
        "changed": bool(result.changed),
        "n_regions": len(result.regions),
        "changed_points": int(
            np.count_nonzero(result.reference_label == LABEL_CHANGED)
            + np.count_nonzero(result.scan_label == LABEL_CHANGED)
        ),
        "truly_changed_points": int(
            np.count_nonzero(truth["reference_changed"]) + np.count_nonzero(truth["scan_changed"])
        ),
        "points": len(reference) + len(scan),
    }


def floor_worker(scene_dir: Path, *, threads: int = 1, **_: Any) -> dict[str, Any]:
    """One cKDTree build + nearest-neighbour query each way, queries on ``threads`` threads
    (1: scipy's default, as the issue measured its floor)."""
    reference, scan, load_seconds = _load_pair(scene_dir)
    reference_points, scan_points = reference.points, scan.points
    started = time.perf_counter()
    for tree_points, query_points in (
        (reference_points, scan_points),
        (scan_points, reference_points),
    ):
        tree = cKDTree(tree_points, balanced_tree=False, compact_nodes=False)
        tree.query(query_points, k=1, workers=threads)
    return {
        "load": load_seconds,
        "seconds": time.perf_counter() - started,
        "peak_rss_mb": peak_rss_mb(),
    }


def m3c2_worker(scene_dir: Path, *, core_points: str, **_: Any) -> dict[str, Any]:
    """py4dgeo M3C2 on the truly aligned pair: both directions over every point, or one
    direction over every 10th reference point; changed = |distance| > level of detection."""
    import logging

    import py4dgeo

    logging.getLogger("py4dgeo").setLevel(logging.WARNING)
    truth = np.load(scene_dir / "truth.npz")
    reference, scan, load_seconds = _load_pair(scene_dir)
    transform = truth["true_transform"]
    reference_points = np.ascontiguousarray(reference.points)
    scan_points = np.ascontiguousarray(scan.points @ transform[:3, :3].T + transform[:3, 3])
    scale = np.sqrt(1_000_000 / len(reference_points))
    cylinder_radius = M3C2_CYLINDER_RADIUS_1M * scale
    unlabelled: list[float] = []

    def label(
        core: NDArray[np.float64], first: NDArray[np.float64], second: NDArray[np.float64]
    ) -> NDArray[np.bool_]:
        algorithm = py4dgeo.M3C2(
            epochs=(py4dgeo.Epoch(first), py4dgeo.Epoch(second)),
            corepoints=core,
            cyl_radius=cylinder_radius,
            normal_radii=(M3C2_NORMAL_RADIUS_1M * scale,),
            max_distance=M3C2_MAX_DISTANCE,
        )
        distances, uncertainties = algorithm.run()
        unlabelled.append(float(np.isnan(distances).mean()))
        with np.errstate(invalid="ignore"):
            return np.abs(distances) > uncertainties["lodetection"]

    started = time.perf_counter()
    if core_points == "all":
        reference_changed = label(reference_points, reference_points, scan_points)
        scan_changed = label(scan_points, scan_points, reference_points)
        reference_rows = None
    else:
        reference_rows = np.arange(0, len(reference_points), 10)
        reference_changed = label(reference_points[reference_rows], reference_points, scan_points)
        scan_changed = np.zeros(0, dtype=bool)
    seconds = time.perf_counter() - started
    return {
        "load": load_seconds,
        "seconds": seconds,
        "peak_rss_mb": peak_rss_mb(),
        # every 10th reference point only: the added box has no changed reference point
        "iou": None
        if reference_rows is not None
        else changed_iou(reference_changed, scan_changed, truth),
        "cylinder_radius": cylinder_radius,
        "unlabelled_share": float(np.mean(unlabelled)),
    }


WORKERS: dict[str, Callable[..., dict[str, Any]]] = {
    "pipeline": pipeline_worker,
    "floor": floor_worker,
    "m3c2": m3c2_worker,
}
