"""A finished job's result against the truth of a pair written by ``bench.tiled
--write-pair-streamed`` (issue 30's 100M row): per changed object, the share of its points
called changed; the points called changed elsewhere; the regions on and off the objects; the
decision; the stations the job used against the true ones.

The job is read from a service's data directory (``bench.tiled_service --work-dir W`` keeps it
as ``W/service-2-workers``): its ``labels.npz`` and, from ``scandiff.sqlite3``, its regions,
decision and sensor origins.  The changed objects are the boxes of one epoch's world that the
other's lacks (``truth.npz``: ``scan_box_*`` / ``reference_box_*``); each changed row
(``*_changed_rows``) is counted for the box it lies in (its point read from the PLY file).

Run: ``python -m bench.truth_regions --pair-dir DIR --data-dir W/service-2-workers [--job ID]``
(the latest succeeded job by default).  Reads only the changed rows of the files.
"""

from __future__ import annotations

import argparse
import json
import sqlite3
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

REGION_MARGIN = 0.5
"""A region is on a changed object when its centroid is within this many metres of its box."""
BOX_TOLERANCE = 0.05
"""A changed point belongs to a box when within this many metres of it (range noise: 1 cm)."""


def ply_rows(path: Path, rows: NDArray[np.int64]) -> NDArray[np.float64]:
    """The points of ``rows`` of a binary little-endian PLY holding float32 x, y, z only."""
    with path.open("rb") as handle:
        header = b""
        while not header.endswith(b"end_header\n"):
            header += handle.readline()
    if b"binary_little_endian" not in header or header.count(b"property") != 3:
        raise SystemExit(f"{path}: not a float32 x, y, z binary PLY")
    vertices = np.memmap(path, dtype="<f4", mode="r", offset=len(header)).reshape(-1, 3)
    return np.asarray(vertices[np.sort(rows)], dtype=np.float64)


def changed_objects(truth: Any, side: str) -> list[tuple[NDArray, NDArray]]:
    """Boxes of ``side``'s world that the other epoch's lacks, as (low (3,), high (3,))."""
    other = "reference" if side == "scan" else "scan"
    others = {tuple(np.round(low, 6)) for low in truth[f"{other}_box_low"]}
    return [
        (low, high)
        for low, high in zip(truth[f"{side}_box_low"], truth[f"{side}_box_high"], strict=True)
        if tuple(np.round(low, 6)) not in others
    ]


def job_row(data_dir: Path, job_id: str | None) -> dict[str, Any]:
    """The job's decision, origins, labels path and regions from the service's database."""
    with sqlite3.connect(f"file:{data_dir / 'scandiff.sqlite3'}?mode=ro", uri=True) as db:
        query = "SELECT id, changed, n_regions, sensor_origins, labels_path, score, threshold"
        query += " FROM job WHERE status = 'succeeded'"
        query += " AND id = ?" if job_id else " ORDER BY finished_at DESC LIMIT 1"
        row = db.execute(query, (job_id,) if job_id else ()).fetchone()
        if row is None:
            raise SystemExit("no succeeded job")
        regions = db.execute(
            "SELECT kind, n_points, centroid FROM region WHERE job_id = ? ORDER BY ordinal",
            (row[0],),
        ).fetchall()
    return {
        "id": row[0],
        "changed": bool(row[1]),
        "n_regions": row[2],
        "sensor_origins": json.loads(row[3]) if row[3] else None,
        "labels_path": data_dir / row[4],
        "score": row[5],
        "threshold": row[6],
        "regions": [(kind, n, json.loads(centroid)) for kind, n, centroid in regions],
    }


def object_figures(pair_dir: Path, truth: Any, labels: Any) -> tuple[list[dict], list[int]]:
    """Per changed object its points called changed / unobserved, and per side the points
    called changed off every changed object."""
    objects, elsewhere = [], []
    for side in ("reference", "scan"):
        label = labels[f"{side}_label"]
        rows = np.sort(truth[f"{side}_changed_rows"])
        points = ply_rows(pair_dir / f"{side}.ply", rows) if len(rows) else np.zeros((0, 3))
        if side == "scan":  # the boxes are in the reference file's frame
            transform = truth["true_transform"]
            points = points @ transform[:3, :3].T + transform[:3, 3]
        on_objects = np.zeros(len(rows), dtype=bool)
        for low, high in changed_objects(truth, side):
            inside = np.all(
                (points >= low - BOX_TOLERANCE) & (points <= high + BOX_TOLERANCE), axis=1
            )
            on_objects |= inside
            mine = label[rows[inside]]
            objects.append(
                {
                    "side": side,
                    "box": [np.round(low, 2).tolist(), np.round(high, 2).tolist()],
                    "points": int(inside.sum()),
                    "called_changed": round(float(np.mean(mine == 1)), 4) if len(mine) else None,
                    "called_unobserved": round(float(np.mean(mine == -1)), 4)
                    if len(mine)
                    else None,
                }
            )
        truly = np.zeros(len(label), dtype=bool)
        truly[rows] = True
        elsewhere.append(int(np.count_nonzero((label == 1) & ~truly)))
    return objects, elsewhere


def station_errors(truth: Any, origins: dict | None) -> dict[str, Any]:
    """Each side's stations used by the job (``sensor_origins``: each cloud's file frame, as
    the truth's), the top-view distance of each to the nearest true station and the height
    difference to it (metres)."""
    figures: dict[str, Any] = {}
    for side in ("reference", "scan"):
        entries = [entry for entry in (origins or {}).get(side) or [] if entry.get("origin")]
        used = np.array([entry["origin"] for entry in entries], dtype=np.float64).reshape(-1, 3)
        true = truth[f"{side}_origins"]
        figures[side] = {"stations": len(used), "sources": sorted({e["source"] for e in entries})}
        if len(used):
            offsets = used[:, None, :2] - true[None, :, :2]
            nearest = np.linalg.norm(offsets, axis=2).argmin(axis=1)
            top_view = np.linalg.norm(used[:, :2] - true[nearest, :2], axis=1)
            figures[side]["top_view_m"] = top_view.round(3).tolist()
            figures[side]["height_m"] = (used[:, 2] - true[nearest, 2]).round(3).tolist()
    return figures


def main() -> None:
    """Print the figures as JSON lines."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pair-dir", type=Path, required=True)
    parser.add_argument("--data-dir", type=Path, required=True)
    parser.add_argument("--job", default=None)
    args = parser.parse_args()
    job = job_row(args.data_dir, args.job)
    truth = np.load(args.pair_dir / "truth.npz")
    with np.load(job["labels_path"]) as labels:
        objects, elsewhere = object_figures(args.pair_dir, truth, labels)
    boxes = [
        (np.asarray(low), np.asarray(high))
        for side in ("reference", "scan")
        for low, high in changed_objects(truth, side)
    ]
    on, off = [], []
    for kind, n_points, centroid in job["regions"]:
        centre = np.asarray(centroid)
        near = any(
            np.all((centre > low - REGION_MARGIN) & (centre < high + REGION_MARGIN))
            for low, high in boxes
        )
        (on if near else off).append((kind, n_points))
    print(json.dumps({"job": job["id"], "decision_changed": job["changed"]}))
    for figures in objects:
        print(json.dumps({"changed_object": figures}))
    print(
        json.dumps(
            {"called_changed_elsewhere": dict(zip(("reference", "scan"), elsewhere, strict=True))}
        )
    )
    print(json.dumps({"regions_on_objects": on, "regions_elsewhere": off}))
    print(json.dumps({"stations": station_errors(truth, job["sensor_origins"])}))


if __name__ == "__main__":
    main()
