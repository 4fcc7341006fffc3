"""The real pairs as other users would bring them: misaligned, swapped, thinned, unevenly dense.

Issue 29's hidden real set is "of the same kind" as ``../shared/data/real/multichange3d_samples``
(indoor and MLS maps), not these two pairs.  A rule tuned to how these two files happen to be
(their exact registration, their order, their density) would pass ``--real`` and fail the
hidden set.  This bench runs each real pair in variants that keep its changes and truth but
change what a tuned rule could have leaned on, and scores every variant against the hand-made
truth of ``bench/real_changes.json`` (:mod:`bench.real_changes`):

- ``given``: the files as they are;
- ``misaligned``: the later epoch turned by 0.3 degrees about a tilted axis through its centre
  and moved by 2.5 cm (the issue's misaligned class), scored in its own, unmoved coordinates;
- ``swapped``: the later epoch as the reference (what was removed is now added);
- ``thinned``: both epochs voxel-thinned to 1.5 times the coarser epoch's median point spacing
  (the samples are already thinned, to ~5 cm indoors and ~10 cm outdoors: a thinner map of the
  same place);
- ``scan half``: a random half of the later epoch's points (the epochs' densities differ).

Per variant: each annotated change's recall, their minimum and mean (targets >= 70 % each,
>= 85 % mean), changed points outside every annotated change, regions and CPU seconds.

Two unchanged variants check the issue's "<= 2,000 changed points over the set where the epochs
do not differ at all" on real geometry (the real pairs are all changed):

- ``same place``: each real epoch on its own, split into two disjoint random halves, the second
  half turned and moved as ``misaligned`` (one row per epoch): nothing differs but the samples;
- ``changes cut``: both epochs without the points within :data:`CUT_MARGIN` of an annotated
  change's boxes (the same hole in both); the changes nobody annotated remain (the MLS site's
  scaffolding and parked things), so its count is an upper bound on false points.

Their rows give the changed points and regions; the total over them is held to 2,000.

Run: ``OMP_NUM_THREADS=1 .venv/bin/python -m bench.real_variants [--real-dir DIR]
[--variants given,misaligned,...,same place,changes cut]``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from app.core.cloud import PointCloud
from app.core.datasets.map_world import voxel_thin
from app.core.formats import read_point_cloud
from app.core.labels import LABEL_CHANGED
from app.core.pipeline import compare
from bench.moving_maps import REAL, REAL_PAIRS
from bench.real_changes import RealChange, in_box, load_changes, score_changes

MISALIGN_DEGREES = 0.3
MISALIGN_METRES = 0.025
THIN_SPACINGS = 1.5
CUT_MARGIN = 0.5
"""Metres: ``changes cut`` drops the points this close to an annotated change's boxes."""
QUIET_POINTS = 2000
"""Issue 29: changed points allowed over the set where the epochs do not differ."""
Points = NDArray[np.float64]


def rotation_about(axis: Points, degrees: float) -> Points:
    """The 3x3 rotation by ``degrees`` about ``axis`` (shape (3,), any length)."""
    axis = axis / np.linalg.norm(axis)
    angle = np.radians(degrees)
    cross = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(angle) * cross + (1.0 - np.cos(angle)) * cross @ cross


def misaligned(points: Points) -> Points:
    """``points`` (shape (n, 3)) turned about a tilted axis through their centre, then moved."""
    centre = points.mean(axis=0)
    turn = rotation_about(np.array([0.3, -0.2, 1.0]), MISALIGN_DEGREES)
    shift = MISALIGN_METRES * np.array([0.6, -0.8, 0.0])
    return (points - centre) @ turn.T + centre + shift


def run_variant(
    name: str,
    epochs: tuple[Points, Points],
    changes: list[RealChange],
) -> tuple[list[tuple[RealChange, float, int]], int, int, float]:
    """Compare one variant and score it: (recalls, changed outside, regions, CPU seconds).

    ``epochs`` are the coordinates the truth is scored in; the compare sees them as the
    variant makes them.
    """
    compared = list(epochs)
    swap = False
    if name == "misaligned":
        compared[1] = misaligned(epochs[1])
    elif name == "swapped":
        swap = True
    reference, scan = (compared[1], compared[0]) if swap else (compared[0], compared[1])
    started = time.process_time()
    result = compare(PointCloud.from_array(reference), PointCloud.from_array(scan))
    seconds = time.process_time() - started
    labels = (result.reference_label, result.scan_label)
    if swap:
        labels = (labels[1], labels[0])
    recalls, outside = score_changes(epochs, labels, changes)
    return recalls, outside, len(result.regions), seconds


def median_spacing(points: Points) -> float:
    """The median distance from a point (of shape (n, 3) ``points``) to its nearest other."""
    distances, _ = cKDTree(points).query(points, k=2)
    return float(np.median(distances[:, 1]))


def variant_epochs(name: str, epochs: tuple[Points, Points]) -> tuple[Points, Points]:
    """The coordinates a variant scores in (thinned or subsampled where it says so)."""
    if name == "thinned":
        voxel = THIN_SPACINGS * max(median_spacing(points) for points in epochs)
        return voxel_thin(epochs[0], voxel)[0], voxel_thin(epochs[1], voxel)[0]
    if name == "scan half":
        keep = np.random.default_rng(29).random(epochs[1].shape[0]) < 0.5
        return epochs[0], epochs[1][keep]
    return epochs


VARIANTS = ("given", "misaligned", "swapped", "thinned", "scan half")
UNCHANGED_VARIANTS = ("same place", "changes cut")


def unchanged_pairs(
    name: str, epochs: tuple[Points, Points], changes: list[RealChange]
) -> list[tuple[str, tuple[Points, Points]]]:
    """The unchanged comparisons of variant ``name``: (label, (reference, scan)) each.

    ``same place``: per epoch (shape (n, 3)), a random half against the other half turned by
    0.3 degrees and moved by 2.5 cm.  ``changes cut``: both epochs without the points within
    :data:`CUT_MARGIN` of any annotated box (of either epoch).
    """
    if name == "same place":
        found = []
        for epoch, points in enumerate(epochs):
            half = np.random.default_rng(29 + epoch).random(points.shape[0]) < 0.5
            found.append((f"epoch {epoch}", (points[half], misaligned(points[~half]))))
        return found
    if name == "changes cut":
        kept = []
        for points in epochs:
            near = np.zeros(points.shape[0], dtype=bool)
            for change in changes:
                for box in change.boxes:
                    grown = dict(box, size=[side + 2.0 * CUT_MARGIN for side in box["size"]])
                    near |= in_box(points, grown)
            kept.append(points[~near])
        return [("both epochs", (kept[0], kept[1]))]
    raise ValueError(f"{name!r} is not one of {UNCHANGED_VARIANTS}")


def run_unchanged(epochs: tuple[Points, Points]) -> tuple[int, int, float]:
    """Compare an unchanged pair: (changed points of both epochs, regions, CPU seconds)."""
    started = time.process_time()
    result = compare(PointCloud.from_array(epochs[0]), PointCloud.from_array(epochs[1]))
    seconds = time.process_time() - started
    changed = sum(
        int(np.count_nonzero(label == LABEL_CHANGED))
        for label in (result.reference_label, result.scan_label)
    )
    return changed, len(result.regions), seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--real-dir", type=Path, default=REAL, help="where the real data is")
    parser.add_argument(
        "--variants", default=",".join(VARIANTS + UNCHANGED_VARIANTS), help="comma-separated"
    )
    args = parser.parse_args()
    annotated = load_changes()
    print("| pair | variant | recall per change | min | mean | outside | regions | CPU s |")
    print("|---|---|---|---|---|---|---|---|")
    every: dict[str, list[float]] = {}
    quiet: dict[str, list[int]] = {}
    for pair in REAL_PAIRS:
        folder = args.real_dir / "multichange3d_samples" / pair
        if not folder.is_dir():
            print(f"| {pair} | missing ({folder}) | | | | | | |")
            continue
        given = tuple(
            np.asarray(read_point_cloud(folder / f"epoch{epoch}.ply").points, dtype=np.float64)
            for epoch in (0, 1)
        )
        for name in args.variants.split(","):
            if name in UNCHANGED_VARIANTS:
                for label, epochs in unchanged_pairs(name, given, annotated[pair]):
                    changed, regions, seconds = run_unchanged(epochs)
                    quiet.setdefault(name, []).append(changed)
                    print(
                        f"| {pair} | {name} ({label}) | unchanged | | | {changed:,} | {regions} "
                        f"| {seconds:.1f} |",
                        flush=True,
                    )
                continue
            epochs = variant_epochs(name, given)
            recalls, outside, regions, seconds = run_variant(name, epochs, annotated[pair])
            shares = [recall for _, recall, _ in recalls]
            every.setdefault(name, []).extend(shares)
            listed = " / ".join(f"{share:.0%}" for share in shares)
            print(
                f"| {pair} | {name} | {listed} | {min(shares):.0%} | {np.mean(shares):.0%} | "
                f"{outside:,} | {regions} | {seconds:.1f} |",
                flush=True,
            )
    print()
    for name, shares in every.items():
        verdict = "PASS" if min(shares) >= 0.70 and np.mean(shares) >= 0.85 else "FAIL"
        print(f"{verdict} {name}: min {min(shares):.0%}, mean {np.mean(shares):.0%}")
    for name, counts in quiet.items():
        verdict = "PASS" if sum(counts) <= QUIET_POINTS else "FAIL"
        note = " (an upper bound: unannotated changes remain)" if name == "changes cut" else ""
        print(
            f"{verdict} {name}: <= 2,000 changed points over the unchanged set "
            f"({sum(counts):,}){note}"
        )


if __name__ == "__main__":
    main()
