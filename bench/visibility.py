"""Change detection without being told where the sensor was (issue 15): the single-station class.

Scenes from :func:`app.core.datasets.lidar.lidar_pair` (random rooms, corridors, warehouses; a
regular-grid spinning lidar; world-frame files; half of them misaligned 0.3-0.4 degrees and 2-3
cm), each compared twice: with the true origins given and with none (the pipeline estimates
them).  Per case: the decision, IoU of changed points over truth-observed points (changed
scenes), changed regions (unchanged scenes), the estimated origins' error and the share of the
compare's time spent on origins.  ``--large`` adds a 1M-point warehouse pair; real Velodyne
frames (sensor frame) moved by a rigid transform give the estimate's error on real data.

Run: ``.venv/bin/python -m bench.visibility [--seeds 2] [--quick] [--large]``; writes
``bench/results/visibility.md`` (``--quick``: ``visibility_quick.md``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from app.core.cloud import PointCloud
from app.core.datasets.lidar import LAYOUTS, lidar_pair, steps_for_points
from app.core.formats import read_point_cloud
from app.core.origins import estimate_origin
from app.core.pipeline import compare
from bench.scenes import changed_points_iou

RESULTS = Path(__file__).resolve().parent / "results"
REAL = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real"


def _run(pair, given: bool) -> dict:
    params = {}
    if given:
        params = {
            "reference_origin": pair.reference_origin.tolist(),
            "scan_origin": pair.scan_origin.tolist(),
        }
    started = time.perf_counter()
    result = compare(
        PointCloud.from_array(pair.reference), PointCloud.from_array(pair.scan), params=params
    )
    total = time.perf_counter() - started
    errors = []
    for side, truth in (("reference", pair.reference_origin), ("scan", pair.scan_origin)):
        entries = result.sensor_origins[side]
        if entries and entries[0].source == "estimated":
            errors.append(float(np.linalg.norm(np.array(entries[0].origin) - truth)))
        elif not given:
            errors.append(float("inf"))  # no confident estimate
    return {
        "decided": result.changed,
        "iou": changed_points_iou(result, pair),
        "regions": len(result.regions),
        "origin_error": max(errors) if errors else float("nan"),
        "origin_share": result.timings.get("origins", 0.0) / total,
        "seconds": total,
        "warnings": len(result.warnings),
    }


def _flatten(runs: dict[bool, dict]) -> dict:
    return {
        f"{key}_{'given' if given else 'none'}": value
        for given, run in runs.items()
        for key, value in run.items()
    }


def _case_rows(seeds: int, changes: tuple[str, ...], step: float) -> list[dict]:
    rows = []
    for seed in range(seeds):
        for layout in LAYOUTS:
            for change in changes:
                pair = lidar_pair(
                    layout=layout,
                    change=change,
                    angular_step_deg=step,
                    misaligned=bool((seed + len(change)) % 2),
                    random_state=1000 + seed,
                )
                runs = {given: _run(pair, given) for given in (True, False)}
                row = {"seed": seed, "layout": layout, "change": change, "n": len(pair.reference)}
                for given, run in runs.items():
                    row.update(
                        {f"{key}_{'given' if given else 'none'}": v for key, v in run.items()}
                    )
                rows.append(row)
                print(row, flush=True)
    return rows


def _real_rows() -> list[str]:
    lines = []
    yaw = np.deg2rad(37.0)
    rotation = np.array(
        [[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]]
    )
    translation = np.array([123.4, -56.7, 8.9])
    for path in sorted(REAL.glob("*/*.p[cl][dy]")):
        points = np.asarray(read_point_cloud(path).points, dtype=np.float64)
        found = estimate_origin(points @ rotation.T + translation)
        error = float(np.linalg.norm(found.origin - translation))
        lines.append(
            f"| {path.parent.name}/{path.name} | {len(points)} | {error:.2f} | "
            f"{found.confidence:.2f} | {'yes' if found.confident else 'no'} |"
        )
        print(lines[-1], flush=True)
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--step", type=float, default=0.6, help="lidar grid step, degrees")
    parser.add_argument("--quick", action="store_true", help="1 seed, added/none, 1 deg grid")
    parser.add_argument("--large", action="store_true", help="add a 1M-point warehouse pair")
    args = parser.parse_args()
    changes = ("added", "removed", "moved", "none")
    if args.quick:
        args.seeds, args.step, changes = 1, 1.0, ("added", "none")
    rows = _case_rows(args.seeds, changes, args.step)
    if args.large:
        step = steps_for_points(1_000_000)
        for change in ("added", "none"):
            pair = lidar_pair(
                layout="warehouse", change=change, angular_step_deg=step, random_state=2000
            )
            runs = {given: _run(pair, given) for given in (True, False)}
            row = {"seed": "1M", "layout": "warehouse", "change": change, "n": len(pair.reference)}
            row.update(_flatten(runs))
            rows.append(row)
            print(row, flush=True)

    lines = [
        f"Single-station lidar rescans (`bench/visibility.py`), grid {args.step} deg, "
        f"{args.seeds} seed(s) x {len(LAYOUTS)} layouts; half misaligned. Machine shared with "
        "other jobs: times are indicative.\n",
        "| seed | layout | change | points | decided (given / none) | IoU given | IoU none | "
        "regions given / none | origin error m | origins share of compare | warnings |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        changed = row["change"] != "none"
        lines.append(
            f"| {row['seed']} | {row['layout']} | {row['change']} | {row['n']} | "
            f"{row['decided_given']} / {row['decided_none']} | "
            f"{row['iou_given']:.3f} | {row['iou_none']:.3f} | "
            f"{row['regions_given']} / {row['regions_none']} | {row['origin_error_none']:.4f} | "
            f"{100 * row['origin_share_none']:.0f} % | {row['warnings_none']} |"
            if changed
            else f"| {row['seed']} | {row['layout']} | none | {row['n']} | "
            f"{row['decided_given']} / {row['decided_none']} | - | - | "
            f"{row['regions_given']} / {row['regions_none']} | {row['origin_error_none']:.4f} | "
            f"{100 * row['origin_share_none']:.0f} % | {row['warnings_none']} |"
        )
    right = sum(row["decided_none"] == (row["change"] != "none") for row in rows)
    changed_rows = [row for row in rows if row["change"] != "none"]
    quiet_regions = sum(row["regions_none"] for row in rows if row["change"] == "none")
    lines.append(
        f"\nNo origin given: {right}/{len(rows)} decisions right; IoU min "
        f"{min(row['iou_none'] for row in changed_rows):.3f}; largest IoU drop vs given "
        f"{max(row['iou_given'] - row['iou_none'] for row in changed_rows):.3f}; changed "
        f"regions on unchanged scenes {quiet_regions}"
        f"; largest origin error {max(row['origin_error_none'] for row in rows):.4f} m."
    )
    if REAL.is_dir():
        lines += [
            "\nReal Velodyne frames (sensor frame) yawed 37 deg and moved (123.4, -56.7, 8.9):\n",
            "| file | points | origin error m | confidence | used |",
            "|---|---|---|---|---|",
            *_real_rows(),
        ]
    RESULTS.mkdir(exist_ok=True)
    name = "visibility_quick.md" if args.quick else "visibility.md"  # quick never overwrites
    (RESULTS / name).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
