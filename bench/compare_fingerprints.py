"""Fingerprints of ``compare`` on small cases: does a refactoring change any result?

Issue 28 asks that restructuring ``compare`` leave every label, region, score, threshold and
report as it was, for every format, detector, sensor-origin source and thread count.  This
script runs :func:`app.core.pipeline.compare` on a set of small cases and prints, per case,
the SHA-256 (first 16 hex digits) of

* ``arrays``: both label arrays (int8), distances (float32) and region indices (int32);
* ``json``: ``to_json_dict()`` without ``timings`` (keys sorted): score, threshold, decision,
  calibration, registration, regions, localisation parameters, sensor origins, visibility,
  warnings, quality warnings and explanation, i.e. what a job stores and the API shows.

Cases: the three detectors in both variants; origins none, given (parameters), from the
file, estimated and recovered (a three-station survey); a robot map with and without its
trajectory; no alignment; the three decision rules and a site calibration; a geometry cache
(cold, then warm); the same pair written to and read from every writable or simple format
(ply, las, laz, xyz, csv, npy, npz, pcd) and the real pairs of ``../shared/data/real`` when
present.  Every case runs with ``threads=1`` and ``threads=2``; the two must also agree.

``--tiled`` runs every case through :func:`app.core.tiling.compare_tiled` instead, with tiles
of at most :data:`TILED_CROP_FRACTION` of the pair's points (so a case crosses tile borders):
the tiled comparison shares the stages around localisation, so a change to them shows there too.
Each row also has ``order``, the digest of the JSON in its stored key order (what the API
answers), beside ``json`` (keys sorted).

``--save FILE`` writes the rows (with the full JSON, to diff); ``--against FILE`` compares
with a saved run (exit status 1 on any difference, naming the keys that differ).

Run: ``.venv/bin/python -m bench.compare_fingerprints --save /tmp/before.json`` on the old
code, then ``--against /tmp/before.json`` on the new.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from app.core.cache.geometry import GeometryCache, cache_key
from app.core.cloud import PointCloud
from app.core.datasets.lidar import lidar_pair
from app.core.datasets.maps import map_pair
from app.core.datasets.scenes import raycast_scene
from app.core.formats import read_point_cloud, write_point_cloud
from app.core.pipeline import ComparisonResult, compare
from app.core.tiling.compare import compare_tiled

PROJECT_ROOT = Path(__file__).resolve().parent.parent
REAL_DATA = Path(os.environ.get("SCANDIFF_SHARED_DATA", PROJECT_ROOT.parent / "shared" / "data"))
REAL_PAIRS = (
    ("kitti_2011_09_26_drive_0002_pointcloudset", "frame0.ply", "frame1.ply", True),
    ("lidar_scu_velodyne_budapest", "Velo1.pcd", "Velo2.pcd", False),
)
SITE_CALIBRATION = {
    "status": "learned",
    "method": "gmm",
    "variant": "improved",
    "n_samples": 5,
    "thresholds": {"largest_region_extent_m": 0.5, "score": 0.01},
}
"""A learned site threshold (:func:`app.core.site_calibration.decide`) for the gmm cases."""

TILED_CROP_FRACTION = 0.9
"""``--tiled``: a tile's crop holds at most this share of both clouds' points."""
TILED_MARGIN_METRES = 0.5
TILED_RAY_REACH_METRES = 1.0
"""``--tiled``: small enough margins for the cases' rooms (a few metres) to cross tile borders."""

Case = tuple[str, Callable[[int], Any]]
Compare = Callable[..., ComparisonResult]


def compare_in_tiles(
    reference: PointCloud, scan: PointCloud, *, geometry_cache: Any = None, **options: Any
) -> ComparisonResult:
    """:func:`compare_tiled` with small tiles (no geometry cache: the tiled path has none)."""
    crop = int(TILED_CROP_FRACTION * (len(reference) + len(scan)))
    return compare_tiled(
        reference,
        scan,
        budget_bytes=1 << 40,
        max_crop_points=crop,
        margin=TILED_MARGIN_METRES,
        ray_reach=TILED_RAY_REACH_METRES,
        **options,
    )


def _scene(change: str = "mixed") -> Any:
    return raycast_scene(n_points=8_000, change=change, random_state=3, pose_error=(0.05, 1.0))


def _clouds(scene: Any, with_origins: bool = False) -> tuple[PointCloud, PointCloud]:
    if not with_origins:
        return PointCloud.from_array(scene.reference), PointCloud.from_array(scene.scan)
    return (
        PointCloud.from_array(scene.reference, sensor_origin=scene.reference_origin),
        PointCloud.from_array(scene.scan, sensor_origin=scene.scan_origin),
    )


def _write_pcd(path: Path, points: np.ndarray) -> None:
    header = (
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\n"
        "DATA ascii\n"
    )
    body = "\n".join(" ".join(repr(float(value)) for value in row) for row in points)
    path.write_text(header + body + "\n")


def _write(path: Path, points: np.ndarray) -> None:
    """``points`` in the format of ``path``'s suffix."""
    suffix = path.suffix.lstrip(".")
    if suffix in ("ply", "las", "laz"):
        write_point_cloud(path, points)
    elif suffix in ("xyz", "csv"):
        np.savetxt(path, points, delimiter="," if suffix == "csv" else " ", fmt="%.17g")
    elif suffix == "npy":
        np.save(path, points)
    elif suffix == "npz":
        np.savez(path, points=points)
    elif suffix == "pcd":
        _write_pcd(path, points)
    else:
        raise ValueError(suffix)


def cases(directory: Path, compare: Compare = compare) -> Iterator[Case]:
    """(name, run(threads) -> ComparisonResult) of every case, each run by ``compare``."""
    scene = _scene()
    plain = _clouds(scene)
    with_file_origins = _clouds(scene, with_origins=True)
    for method in ("gmm", "pca", "planes"):
        for variant in ("improved", "paper"):
            yield (
                f"detector {method} {variant}",
                lambda threads, m=method, v=variant: compare(
                    *plain, method=m, variant=v, threads=threads
                ),
            )
    yield (
        "origins none",
        lambda threads: compare(*plain, params={"estimate_origins": False}, threads=threads),
    )
    given = {
        "reference_origin": scene.reference_origin.tolist(),
        "scan_origin": scene.scan_origin.tolist(),
    }
    yield "origins given", lambda threads: compare(*plain, params=given, threads=threads)
    yield "origins file", lambda threads: compare(*with_file_origins, threads=threads)
    yield "origins estimated", lambda threads: compare(*plain, threads=threads)
    survey = lidar_pair(
        layout="room", change="mixed", n_stations=3, angular_step_deg=3.0, random_state=3
    )
    surveyed = PointCloud.from_array(survey.reference), PointCloud.from_array(survey.scan)
    yield (
        "origins recovered",
        lambda threads: compare(*surveyed, align=False, threads=threads),
    )
    robot = map_pair("robot", change="removed", misaligned=True, size=0.1, random_state=1)
    yield (
        "robot trajectory",
        lambda threads: compare(*robot.clouds(with_trajectory=True), threads=threads),
    )
    yield "robot bare", lambda threads: compare(*robot.clouds(), threads=threads)
    yield "no align", lambda threads: compare(*plain, align=False, threads=threads)
    for rule in ("detector", "either"):
        yield (
            f"decision {rule}",
            lambda threads, r=rule: compare(*plain, params={"decision": r}, threads=threads),
        )
    yield (
        "site calibration",
        lambda threads: compare(*plain, site_calibration=SITE_CALIBRATION, threads=threads),
    )
    yield "geometry cache", lambda threads: _cached(directory, plain, threads, compare)
    for suffix in ("ply", "las", "laz", "xyz", "csv", "npy", "npz", "pcd"):
        yield (
            f"format {suffix}",
            lambda threads, s=suffix: _through_files(directory, s, threads, compare),
        )
    for folder, first, second, align in REAL_PAIRS:
        if (REAL_DATA / "real" / folder / second).is_file():
            yield (
                f"real {folder[:5]} {first}-{second}",
                lambda threads, f=folder, a=first, b=second, al=align: compare(
                    read_point_cloud(REAL_DATA / "real" / f / a),
                    read_point_cloud(REAL_DATA / "real" / f / b),
                    align=al,
                    threads=threads,
                ),
            )


def _cached(
    directory: Path, clouds: tuple[PointCloud, PointCloud], threads: int, compare: Compare
) -> Any:
    """Compare twice through one geometry cache (written, then read); the second result."""
    path = directory / f"reference-{threads}.geometry"
    path.unlink(missing_ok=True)
    cache = GeometryCache(path, cache_key("reference", None))
    first = compare(*clouds, threads=threads, geometry_cache=cache)
    second = compare(*clouds, threads=threads, geometry_cache=cache)
    if fingerprint(first)["json"] != fingerprint(second)["json"]:
        raise AssertionError("a warm geometry cache changed the result")
    return second


def _through_files(directory: Path, suffix: str, threads: int, compare: Compare) -> Any:
    """The scene written as ``suffix`` files, read back and compared."""
    scene = _scene("box")
    paths = []
    for name, points in (("reference", scene.reference), ("scan", scene.scan)):
        path = directory / f"{name}.{suffix}"
        if not path.exists():
            _write(path, points)
        paths.append(path)
    return compare(read_point_cloud(paths[0]), read_point_cloud(paths[1]), threads=threads)


def _digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()[:16]


def fingerprint(result: Any) -> dict[str, Any]:
    """The digests of one result (see the module docstring) and its JSON without timings."""
    arrays = b"".join(
        np.ascontiguousarray(array).tobytes()
        for array in (
            np.asarray(result.reference_label, dtype=np.int8),
            np.asarray(result.scan_label, dtype=np.int8),
            np.asarray(result.reference_distance, dtype=np.float32),
            np.asarray(result.scan_distance, dtype=np.float32),
            np.asarray(result.reference_region, dtype=np.int32),
            np.asarray(result.scan_region, dtype=np.int32),
        )
    )
    document = result.to_json_dict()
    document.pop("timings", None)
    text = json.dumps(document, sort_keys=True)
    return {
        "arrays": _digest(arrays),
        "json": _digest(text.encode()),
        "order": _digest(json.dumps(document).encode()),
        "changed": bool(result.changed),
        "n_regions": len(result.regions),
        "document": document,
    }


def _attempt(run: Callable[[int], Any], threads: int) -> dict[str, Any]:
    """The fingerprint of ``run(threads)``, or of the error it raised (a case may fail)."""
    try:
        return fingerprint(run(threads))
    except Exception as error:  # the error is the result to keep
        text = f"{type(error).__name__}: {error}"
        return {"arrays": "", "json": _digest(text.encode()), "document": {"error": text}}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--save", type=Path)
    parser.add_argument("--against", type=Path)
    parser.add_argument("--only", help="run only the cases whose name contains this")
    parser.add_argument("--tiled", action="store_true", help="run the cases in tiles")
    args = parser.parse_args()
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="fingerprints-") as temporary:
        for name, run in cases(Path(temporary), compare_in_tiles if args.tiled else compare):
            if args.only and args.only not in name:
                continue
            by_threads = {threads: _attempt(run, threads) for threads in (1, 2)}
            row = {"name": name, **by_threads[1]}
            if {key: value for key, value in by_threads[2].items() if key != "document"} != {
                key: value for key, value in by_threads[1].items() if key != "document"
            }:
                row["threads_differ"] = True
            rows.append(row)
            shown = {key: value for key, value in row.items() if key != "document"}
            print(json.dumps(shown), flush=True)
    if args.save:
        args.save.write_text(json.dumps(rows, indent=1))
    if args.against:
        return _report_against(rows, json.loads(args.against.read_text()), args.against)
    return 0


def _report_against(rows: list[dict[str, Any]], saved: list[dict[str, Any]], path: Path) -> int:
    """Print which cases differ from a saved run (and in which JSON keys); 1 if any."""
    before = {row["name"]: row for row in saved}
    different = []
    for row in rows:
        old = before.get(row["name"])
        if old is None or any(
            old.get(key) != row.get(key) for key in ("arrays", "json", "order") if key in old
        ):
            different.append(row["name"])
            keys = sorted(
                key
                for key in set(row["document"]) | set((old or {}).get("document", {}))
                if row["document"].get(key) != (old or {}).get("document", {}).get(key)
            )
            print(f"  differs: {row['name']}: arrays {row['arrays']} json keys {keys}")
    print(f"{len(rows) - len(different)} of {len(rows)} cases as in {path}")
    return 1 if different else 0


if __name__ == "__main__":
    raise SystemExit(main())
