"""Maps from moving sensors (issue 29): handheld RGB-D, robot / MLS and terrestrial scans.

Scenes: :func:`app.core.datasets.maps.map_pair` (rooms with chairs, boxes, boards and desks
filmed by a depth camera; corridors, offices and warehouses swept by a 16- or 32-ring lidar;
terrestrial surveys of 2-4 stations), every second one misaligned by 0.3 degrees and 2-3 cm.
Layouts, densities, paths and changes vary with the seed.  Modes:

- ``default``: the bare files, nothing given (what a new user runs);
- ``trajectory``: the clouds with their per-point ``time`` attribute and their ``trajectory``.

Scene ``k`` of a class for seed ``s`` (its ``k``-th scene: :func:`scenes`) is drawn with
``random_state = 100 * s + k`` (the table's seed column): a scene is named by its class and
that number, whichever other classes run with it (``--classes robot,rgbd`` draws the same RGB-D
rooms as ``--classes rgbd``).  Per scene and mode: the decision, IoU of changed points over the
scored points (both clouds pooled), each change's recall (the share of its object's truly
changed, scored points called changed), regions and changed points on unchanged scenes, seconds
of the compare.  Then the issue's targets, PASS or FAIL:

- every map class: each change >= 70 % recall, mean >= 85 %, <= 2,000 changed points over the
  unchanged pairs;
- robot maps: every decision right, IoU >= 0.80 on each changed scene, 0 regions on unchanged
  scenes; with trajectories (``trajectory`` mode) IoU >= 0.90.

``--real`` runs the real pairs of ``../shared/data/real/multichange3d_samples`` against the
hand-made truth of ``bench/real_changes.json`` (:mod:`bench.real_changes`): each plain change's
recall, the mean, changed points outside every annotated change, regions and seconds.

``--realism drift`` gives the RGB-D rooms the artefacts of real fused maps (tracking drift with
a partial loop closure, flying pixels at depth edges, missing patches:
:mod:`app.core.datasets.rgbd_artefacts`); the rooms, paths and changes are those without.

Run: ``.venv/bin/python -m bench.moving_maps [--seeds 1] [--classes rgbd,robot,tls]
[--modes default,trajectory] [--size 1.0] [--realism none|drift] [--output FILE] [--real]``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from app.core.datasets.maps import MAP_CLASSES, MapPair, class_layouts, map_pair
from app.core.datasets.rgbd_artefacts import REALISM_LEVELS
from app.core.formats import read_point_cloud
from app.core.labels import LABEL_CHANGED
from app.core.pipeline import compare
from bench.real_changes import load_changes, score_changes

REAL = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real"
REAL_PAIRS = ("classroom_tls", "bike_parking_mls")
MODES = ("default", "trajectory")
RGBD_CHANGES = ("removed", "added", "moved", "rotated", "none")
CHANGES = ("removed", "added", "moved", "rotated", "mixed")
RECALL_EACH, RECALL_MEAN, QUIET_POINTS = 0.70, 0.85, 2000
ROBOT_IOU, ROBOT_TRAJECTORY_IOU = 0.80, 0.90
SCENE_NOTE = (
    "Scenes are named by class and seed (the seed column: 100 x --seed + the scene's number "
    "within its class); the same class and seed is the same scene whatever --classes holds."
)


def scenes(seed: int, classes: list[str]) -> list[tuple[str, str, str, bool, int]]:
    """(class, layout, change, misaligned, scene seed) of one seed's scenes: per RGB-D seed one
    of each change and an unchanged room; per lidar layout one changed and one unchanged pair.

    The scene seed is ``100 * seed`` plus the scene's number within its class, so a scene
    depends on its class and seed only, not on which other classes are run."""
    found = []
    for map_class in classes:
        if map_class == "rgbd":
            for number, change in enumerate(RGBD_CHANGES):
                found.append(
                    (map_class, "room", change, (number + seed) % 2 == 1, 100 * seed + number)
                )
            continue
        for number, layout in enumerate(class_layouts(map_class)):
            change = CHANGES[(seed + number + len(map_class)) % len(CHANGES)]
            found.append(
                (map_class, layout, change, (number + seed) % 2 == 0, 100 * seed + 2 * number)
            )
            found.append(
                (map_class, layout, "none", (number + seed) % 2 == 1, 100 * seed + 2 * number + 1)
            )
    return found


def score(pair: MapPair, reference_label: np.ndarray, scan_label: np.ndarray) -> dict:
    """IoU over scored points, each change's recall and the changed point count."""
    intersection = union = 0
    for label, changed, scored in (
        (reference_label, pair.reference_changed, pair.reference_scored),
        (scan_label, pair.scan_changed, pair.scan_scored),
    ):
        predicted = label == LABEL_CHANGED
        intersection += np.count_nonzero(predicted & changed & scored)
        union += np.count_nonzero((predicted | changed) & scored)
    recalls = []
    for number, change in enumerate(pair.changes):
        found = total = 0
        for label, membership, changed, scored in (
            (reference_label, pair.reference_change, pair.reference_changed, pair.reference_scored),
            (scan_label, pair.scan_change, pair.scan_changed, pair.scan_scored),
        ):
            mine = (membership == number) & changed & scored
            total += np.count_nonzero(mine)
            found += np.count_nonzero(mine & (label == LABEL_CHANGED))
        if total:
            recalls.append((f"{change.kind} {change.name}", found / total, total))
    return {
        "iou": intersection / union if union else 1.0,
        "recalls": recalls,
        "changed_points": int(
            np.count_nonzero(reference_label == LABEL_CHANGED)
            + np.count_nonzero(scan_label == LABEL_CHANGED)
        ),
    }


def run_scene(pair: MapPair, mode: str) -> dict:
    """Compare one pair in one mode and score it."""
    reference, scan = pair.clouds(with_trajectory=mode == "trajectory")
    started = time.perf_counter()
    result = compare(reference, scan)
    seconds = time.perf_counter() - started
    row = score(pair, result.reference_label, result.scan_label)
    row.update(
        changed=bool(result.changed),
        right=bool(result.changed) == (pair.change != "none"),
        regions=len(result.regions),
        seconds=seconds,
        points=len(reference) + len(scan),
        test="/".join(str(side.test) for side in result.visibility.values()),
    )
    return row


def target_lines(rows: list[dict], classes: list[str], modes: list[str]) -> list[str]:
    """The issue's targets, PASS or FAIL, per class and mode."""
    lines = []

    def verdict(ok: bool) -> str:
        return "PASS" if ok else "FAIL"

    for map_class in classes:
        for mode in modes:
            mine = [row for row in rows if row["class"] == map_class and row["mode"] == mode]
            if not mine:
                continue
            recalls = [value for row in mine for _, value, _ in row["recalls"]]
            quiet_points = sum(row["changed_points"] for row in mine if row["change"] == "none")
            name = f"{map_class:5s} {mode:10s}"
            if recalls:
                lines.append(
                    f"{verdict(min(recalls) >= RECALL_EACH)} {name} every change >= 70 % recall "
                    f"(min {min(recalls):.0%}, {len(recalls)} changes)"
                )
                lines.append(
                    f"{verdict(np.mean(recalls) >= RECALL_MEAN)} {name} mean recall >= 85 % "
                    f"({np.mean(recalls):.0%})"
                )
            lines.append(
                f"{verdict(quiet_points <= QUIET_POINTS)} {name} <= 2,000 changed points over "
                f"unchanged pairs ({quiet_points})"
            )
            if map_class != "robot":
                continue
            right = sum(row["right"] for row in mine)
            lines.append(
                f"{verdict(right == len(mine))} {name} every decision right ({right}/{len(mine)})"
            )
            changed_iou = [row["iou"] for row in mine if row["change"] != "none"]
            floor = ROBOT_TRAJECTORY_IOU if mode == "trajectory" else ROBOT_IOU
            if changed_iou:
                lines.append(
                    f"{verdict(min(changed_iou) >= floor)} {name} IoU >= {floor:.2f} on each "
                    f"changed scene (min {min(changed_iou):.3f})"
                )
            quiet_regions = sum(row["regions"] for row in mine if row["change"] == "none")
            lines.append(
                f"{verdict(quiet_regions == 0)} {name} 0 regions on unchanged scenes "
                f"({quiet_regions})"
            )
    return lines


def run_real(real: Path = REAL) -> list[str]:
    """Per annotated change (``bench/real_changes.json``) its recall, then per pair the
    regions, changed points per side and outside every change, and seconds; the issue's
    targets over the set last."""
    lines = [
        "| real pair | change | kind | points | recall |",
        "|---|---|---|---|---|",
    ]
    totals = []
    recalls: list[float] = []
    annotated = load_changes()
    for name in REAL_PAIRS:
        folder = real / "multichange3d_samples" / name
        if not folder.is_dir():
            lines.append(f"| {name} | missing ({folder}) | | | |")
            continue
        reference = read_point_cloud(folder / "epoch0.ply")
        scan = read_point_cloud(folder / "epoch1.ply")
        started = time.perf_counter()
        result = compare(reference, scan)
        seconds = time.perf_counter() - started
        epochs = (
            np.asarray(reference.points, dtype=np.float64),
            np.asarray(scan.points, dtype=np.float64),
        )
        labels = (result.reference_label, result.scan_label)
        scored, outside = score_changes(epochs, labels, annotated[name])
        for change, recall, total in scored:
            recalls.append(recall)
            lines.append(f"| {name} | {change.name} | {change.kind} | {total} | {recall:.0%} |")
            print(lines[-1], flush=True)
        counts = [int(np.count_nonzero(label == LABEL_CHANGED)) for label in labels]
        totals.append(
            f"| {name} | {len(reference)} / {len(scan)} | {len(result.regions)} | "
            f"{counts[0]} / {counts[1]} | {outside} | {seconds:.1f} |"
        )
    lines += [
        "",
        "| real pair | points (epoch 0 / 1) | regions | changed points (0 / 1) | "
        "changed outside the annotated changes | s |",
        "|---|---|---|---|---|---|",
        *totals,
    ]
    if recalls:
        verdict = "PASS" if min(recalls) >= RECALL_EACH else "FAIL"
        lines += [
            "",
            f"{verdict} real every annotated change >= 70 % recall (min {min(recalls):.0%}, "
            f"{len(recalls)} changes)",
            f"{'PASS' if np.mean(recalls) >= RECALL_MEAN else 'FAIL'} real mean recall >= 85 % "
            f"({np.mean(recalls):.0%})",
        ]
    print("\n".join(lines[-len(totals) - 6 :]), flush=True)
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--classes", default=",".join(MAP_CLASSES))
    parser.add_argument("--modes", default="default")
    parser.add_argument("--size", type=float, default=1.0, help="scales the rays per epoch")
    parser.add_argument(
        "--realism",
        choices=REALISM_LEVELS,
        default="none",
        help="RGB-D artefacts of real fused maps (drift: pose drift, flying pixels, holes)",
    )
    parser.add_argument("--output", type=Path, help="also write the report to this file")
    parser.add_argument("--real", action="store_true", help="run the real pairs instead")
    parser.add_argument("--real-dir", type=Path, default=REAL, help="where the real data is")
    args = parser.parse_args()
    if args.real:
        report = run_real(args.real_dir)
    else:
        classes = args.classes.split(",")
        modes = args.modes.split(",")
        for mode in modes:
            if mode not in MODES:
                parser.error(f"--modes: {mode!r} is not one of {MODES}")
        rows = []
        header = (
            "| class | layout | change | mis. | seed | points | mode | changed | regions | IoU | "
            "recall per change | changed points | test | gen s | compare s |"
        )
        print(SCENE_NOTE)
        print(header)
        print("|" + "---|" * 15, flush=True)
        table = [SCENE_NOTE, "", header, "|" + "---|" * 15]
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            for map_class, layout, change, misaligned, scene_seed in scenes(seed, classes):
                started = time.perf_counter()
                try:
                    pair = map_pair(
                        map_class,
                        layout=layout,
                        change=change,
                        misaligned=misaligned,
                        size=args.size,
                        realism=args.realism if map_class == "rgbd" else "none",
                        random_state=scene_seed,
                    )
                except ValueError as error:  # no visible change drawn: say so, go on
                    line = (
                        f"| {map_class} | {layout} | {change} | | {scene_seed} | skipped: {error} |"
                    )
                    print(line, flush=True)
                    table.append(line)
                    continue
                generated = time.perf_counter() - started
                for mode in modes:
                    row = run_scene(pair, mode)
                    row.update({"class": map_class, "change": change, "mode": mode})
                    rows.append(row)
                    recalls = ", ".join(f"{name} {value:.0%}" for name, value, _ in row["recalls"])
                    line = (
                        f"| {map_class} | {layout} | {change} | {'y' if misaligned else 'n'} | "
                        f"{scene_seed} | {row['points']} | {mode} | {row['changed']} | "
                        f"{row['regions']} | {row['iou']:.3f} | {recalls or '-'} | "
                        f"{row['changed_points']} | {row['test']} | {generated:.1f} | "
                        f"{row['seconds']:.1f} |"
                    )
                    print(line, flush=True)
                    table.append(line)
        targets = target_lines(rows, classes, modes)
        print()
        print("\n".join(targets))
        report = [*table, "", *targets]
    if args.output:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text("\n".join(report) + "\n")


if __name__ == "__main__":
    main()
