"""Several stations per cloud: localisation on merged multi-station lidar scans.

Scenes: :func:`app.core.datasets.lidar.lidar_pair` with 3-5 stations per epoch (rooms,
corridors, warehouses; 1 cm range noise; the scan misaligned by 0.3-0.4 degrees and 2-3 cm, then
put back with the true transform so that only visibility is measured).  Modes:

- ``given``: every station's origin and each point's station index;
- ``origins``: the origins only (points assigned to stations from the ring structure);
- ``recovered``: nothing given; stations recovered from the points
  (:func:`app.core.origins.station_recovery.recover_stations`), else the origin-free test;
- ``origin-free``: nothing given; the sampling-gap and coverage tests
  (``origin_free_test="gaps"``);
- ``coverage``: nothing given, the coverage test alone (before issue 15);
- ``fallback``: nothing given and no recovery: the origin-free surface test
  (``origin_free_test="surfaces"``, :mod:`app.core.localise.origin_free`), what a merged
  cloud whose stations are not recovered needs;
- ``default``: nothing given, no parameter at all: :func:`app.core.pipeline.compare` on the
  two files as a new user runs it (the scan aligned by the pipeline; origins estimated, the
  stations of lidar clouds recovered, ``recover_stations="auto"``).

Per scene and mode: changed regions (the decision: changed when there is one), IoU of changed
points over the points some station of the other epoch saw.

Run: ``.venv/bin/python -m bench.merged_stations [--seeds 2] [--step 1.0] [--modes given,recovered]
[--output FILE]``; prints a table and writes it as the section "Several stations per cloud" of
``bench/results/visibility.md`` (other sections are kept) or ``FILE``.
``--sampling`` instead prints :func:`app.core.origins.sampling.lidar_sampling`'s figures on
each class of cloud (single and merged lidar scans, the paper's scenes, random points, the
real Velodyne frames in ``../shared/data/real``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from app.core.cloud import PointCloud
from app.core.datasets.lidar import lidar_pair, steps_for_points
from app.core.datasets.scenes import paper_corridor, raycast_scene
from app.core.ground_truth import changed_iou
from app.core.localise import EpochCloud, localise_changes
from app.core.origins.sampling import lidar_sampling
from app.core.origins.station_recovery import recover_stations
from app.core.pipeline import compare
from app.core.registration import apply_transform

RESULTS = Path(__file__).resolve().parent / "results"
MODES = ("given", "origins", "recovered", "origin-free", "coverage", "fallback", "default")
CHANGES = ("added", "removed", "mixed", "none")
LAYOUTS = ("room", "corridor", "warehouse")
SECTION = "Several stations per cloud (bench/merged_stations.py)"


def localise(pair, scan, scan_origins, mode: str):
    """Localisation of one pair in one mode, and the stations recovered (or None)."""
    options: dict = {}
    recovered = None
    if mode in ("given", "origins"):
        options = {"reference_origin": pair.reference_origins, "scan_origin": scan_origins}
        if mode == "given":
            options["reference_station"] = pair.reference_station
            options["scan_station"] = pair.scan_station
    elif mode == "recovered":
        started = time.perf_counter()
        recovered = (recover_stations(pair.reference), recover_stations(scan))
        options["recovery_seconds"] = time.perf_counter() - started
        for side, found in zip(("reference", "scan"), recovered, strict=True):
            if found.several:
                options[f"{side}_origin"] = found.origins
    elif mode == "origin-free":
        options["origin_free_test"] = "gaps"
    elif mode == "fallback":
        options["origin_free_test"] = "surfaces"
    elif mode == "default":
        result = compare(PointCloud.from_array(pair.reference), PointCloud.from_array(pair.scan))
        recovered = tuple(
            SimpleNamespace(origins=np.array([entry.origin for entry in entries]).reshape(-1, 3))
            for entries in (result.sensor_origins["reference"], result.sensor_origins["scan"])
        )
        return result, recovered, result.timings.get("origins", 0.0)
    recovery_seconds = options.pop("recovery_seconds", 0.0)
    reference_epoch = EpochCloud(
        pair.reference,
        origin=options.pop("reference_origin", None),
        station=options.pop("reference_station", None),
    )
    scan_epoch = EpochCloud(
        scan, origin=options.pop("scan_origin", None), station=options.pop("scan_station", None)
    )
    localisation = localise_changes(reference_epoch, scan_epoch, **options)
    return localisation, recovered, recovery_seconds


def nearest_station_error(found: np.ndarray, truth: np.ndarray) -> float:
    """Largest distance (m) from a true station (n, 3) to the nearest found one (k, 3); inf
    when their counts differ."""
    if len(found) != len(truth):
        return float("inf")
    return float(np.linalg.norm(truth[:, None, :] - found[None], axis=2).min(axis=1).max())


def station_error(recovered, true_origins) -> float:
    """Largest distance (m) from a true station to the nearest recovered one (inf: too few)."""
    return max(
        nearest_station_error(np.asarray(found.origins).reshape(-1, 3), true)
        for found, true in zip(recovered, true_origins, strict=True)
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--step", type=float, default=1.0, help="lidar grid step, degrees")
    parser.add_argument("--modes", default=",".join(MODES))
    parser.add_argument("--changes", default=",".join(CHANGES))
    parser.add_argument("--layouts", default=",".join(LAYOUTS))
    parser.add_argument("--output", type=Path, default=RESULTS / "visibility.md")
    parser.add_argument("--sampling", action="store_true", help="lidar-likeness per cloud class")
    args = parser.parse_args()
    if args.sampling:
        print_sampling(args.seeds, args.first_seed)
        return
    modes = args.modes.split(",")
    rows = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        for layout in args.layouts.split(","):
            for change in args.changes.split(","):
                n_stations = 3 + (seed + len(layout) + len(change)) % 3
                pair = lidar_pair(
                    layout=layout,
                    change=change,
                    n_stations=n_stations,
                    angular_step_deg=args.step,
                    misaligned=True,
                    random_state=seed,
                )
                scan = apply_transform(pair.scan, pair.true_transform)
                scan_origins = apply_transform(pair.scan_origins, pair.true_transform)
                for mode in modes:
                    started = time.perf_counter()
                    localisation, recovered, recovery_seconds = localise(
                        pair, scan, scan_origins, mode
                    )
                    seconds = time.perf_counter() - started
                    found = (
                        ""
                        if recovered is None
                        else "/".join(str(len(side.origins)) for side in recovered)
                    )
                    error = (
                        float("nan")
                        if recovered is None
                        else station_error(
                            recovered,
                            (
                                pair.reference_origins,
                                pair.scan_origins if mode == "default" else scan_origins,
                            ),
                        )
                    )
                    row = {
                        "layout": layout,
                        "change": change,
                        "seed": seed,
                        "stations": n_stations,
                        "points": len(pair.reference) + len(pair.scan),
                        "mode": mode,
                        "regions": len(localisation.regions),
                        "right": getattr(localisation, "changed", len(localisation.regions) > 0)
                        == (change != "none"),
                        "iou": changed_iou(pair, localisation),
                        "found": found,
                        "station_error": error,
                        "seconds": seconds,
                        "recovery_seconds": recovery_seconds,
                    }
                    rows.append(row)
                    print(
                        f"{layout:9s} {change:7s} seed {seed} k={n_stations} {mode:11s} "
                        f"regions {row['regions']:3d} right {row['right']!s:5s} "
                        f"IoU {row['iou']:.3f} {found:5s} {seconds:5.1f} s"
                        + (
                            f" (recovery {recovery_seconds:.1f} s, station error {error:.4f} m)"
                            if recovered is not None
                            else ""
                        ),
                        flush=True,
                    )
    lines = [
        f"Multi-station scenes: grid step {args.step} deg, {args.seeds} seeds, "
        f"layouts {args.layouts}, changes {args.changes} (`bench/merged_stations.py`).",
        "",
        "| mode | decisions right | IoU min (changed) | IoU mean (changed) | "
        "changed regions on unchanged scenes |",
        "|---|---|---|---|---|",
    ]
    for mode in modes:
        mine = [row for row in rows if row["mode"] == mode]
        changed = [row["iou"] for row in mine if row["change"] != "none"]
        quiet = [row["regions"] for row in mine if row["change"] == "none"]
        lines.append(
            f"| {mode} | {sum(row['right'] for row in mine)}/{len(mine)} | "
            f"{min(changed, default=float('nan')):.3f} | "
            f"{np.mean(changed) if changed else float('nan'):.3f} | {sum(quiet)} |"
        )
    table = "\n".join(lines)
    print(table)
    write_section(args.output, SECTION, table)


def sampling_clouds(seeds: int, first_seed: int):
    """(class, name, points) of each class of cloud :func:`lidar_sampling` must tell apart."""
    for seed in range(first_seed, first_seed + seeds):
        for layout in LAYOUTS:
            single = lidar_pair(layout=layout, change="added", random_state=1000 + seed)
            yield "single lidar", f"{layout} seed {seed}", single.reference
            n_stations = 3 + (seed + len(layout)) % 3
            merged = lidar_pair(
                layout=layout,
                change="added",
                n_stations=n_stations,
                angular_step_deg=1.0,
                misaligned=True,
                random_state=seed,
            )
            yield "merged lidar", f"{layout} seed {seed} k={n_stations}", merged.reference
        scene = raycast_scene(n_points=200_000, change="box", random_state=100 + seed)
        yield "paper ray-cast scene", f"seed {seed}", scene.reference
        for n_points in (300, 30_000):
            corridor = paper_corridor(n_points, noise_variance=1e-4, random_state=seed)
            yield "paper corridor (uniform)", f"{n_points} points seed {seed}", corridor.reference
        rng = np.random.default_rng(seed)
        yield "random points", f"seed {seed}", rng.uniform(0.0, 10.0, (50_000, 3))
        grid = np.stack(np.meshgrid(*[np.arange(0.0, 10.0, 0.05)] * 2, indexing="ij"), -1)
        flat = np.column_stack([grid.reshape(-1, 2), np.zeros(grid[..., 0].size)])
        yield "regular grid", f"5 cm seed {seed}", flat + rng.normal(0.0, 0.003, flat.shape)
        for noise in (0.02, 0.05):  # lattice-free and as noisy as a dense survey
            yield (
                "uniform planes",
                f"{noise * 100:.0f} cm noise seed {seed}",
                (_box_faces(rng, 100_000) + rng.normal(0.0, noise, (100_000, 3))),
            )
        for noise in (0.01, 0.04, 0.0894):  # bench/tiled.py's survey at 250k points: the noise
            survey = lidar_pair(  # against the spacing of 250k, 4M and 20M points
                layout="warehouse",
                change="added",
                n_stations=5,
                angular_step_deg=steps_for_points(250_000, 5),
                range_noise=noise,
                random_state=18,
            )
            yield "merged lidar, noisy", f"warehouse 18, {noise * 100:.1f} cm", survey.reference
    real = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real"
    from app.core.formats import read_point_cloud

    for path in sorted(real.glob("*/*.p[cl][dy]")):
        points = np.asarray(read_point_cloud(path).points, dtype=np.float64)
        yield "real Velodyne frame", f"{path.parent.name[:12]}/{path.name}", points


def _box_faces(rng: np.random.Generator, n_points: int) -> np.ndarray:
    """``n_points`` uniform points on the faces of a 20 x 10 x 5 m box."""
    size = np.array([20.0, 10.0, 5.0])
    points = rng.uniform(0.0, 1.0, (n_points, 3)) * size
    face = rng.integers(0, 6, n_points)
    for axis in range(3):
        points[face == axis, axis] = 0.0
        points[face == axis + 3, axis] = size[axis]
    return points


def print_sampling(seeds: int, first_seed: int) -> None:
    """Print :func:`lidar_sampling`'s figures for each cloud of :func:`sampling_clouds`."""
    print(
        "| class | cloud | points | twin share | spacing spread | noise ratio | share needed "
        "| lidar-like | ms |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for kind, name, points in sampling_clouds(seeds, first_seed):
        started = time.perf_counter()
        found = lidar_sampling(points)
        milliseconds = 1000 * (time.perf_counter() - started)
        print(
            f"| {kind} | {name} | {len(points)} | {found.twin_share:.3f} | "
            f"{found.spacing_spread:.1f} | {found.noise_ratio:.2f} | "
            f"{found.twin_share_needed:.3f} | {found.lidar_like} | {milliseconds:.0f} |",
            flush=True,
        )


def write_section(path: Path, title: str, body: str) -> None:
    """Replace (or append) the ``## title`` section of a Markdown file with ``body``."""
    text = path.read_text() if path.exists() else "# Visibility without being told\n"
    heading = f"## {title}\n"
    start = text.find(heading)
    if start < 0:
        text = text.rstrip("\n") + "\n\n" + heading + "\n" + body + "\n"
    else:
        end = text.find("\n## ", start + len(heading))
        rest = "" if end < 0 else text[end:]
        text = text[:start] + heading + "\n" + body + "\n" + rest
    path.parent.mkdir(exist_ok=True)
    path.write_text(text)


if __name__ == "__main__":
    main()
