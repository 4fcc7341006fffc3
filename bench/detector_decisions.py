"""The detectors' decisions and scores on many scenes: do two versions decide alike?

``bench.label_digests`` checks a whole comparison's labels; this script checks the detectors
alone, more widely and to the last bit: every method and variant
(:func:`app.core.detectors.make_detector`, seeded with the scene's seed) on
:func:`app.core.datasets.scenes.raycast_scene` pairs (six seeds, the five change kinds,
``--points`` a cloud), one row per detection: the decision, the score, the threshold and the
calibration's null values (or the error, e.g. the paper's plane extraction finding no plane).

``--save FILE`` writes the rows as JSON; ``--against FILE`` compares with a saved run: the
decisions (and errors) must be identical (exit status 1 otherwise); it prints how many scores
and thresholds are bit-identical and, per method and variant, the largest relative difference
of the score, the threshold and the null values.  Run the code before a change with
``PYTHONPATH=<checkout>``.

Run: ``OMP_NUM_THREADS=1 .venv/bin/python -m bench.detector_decisions --save /tmp/after.json
[--against /tmp/before.json]``.
"""

from __future__ import annotations

import argparse
import json
import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from app.core.datasets.scenes import CHANGE_KINDS, raycast_scene
from app.core.detectors import METHODS, VARIANTS, make_detector

SEEDS = range(6)


def rows(n_points: int) -> list[dict[str, Any]]:
    """One row per scene, method and variant."""
    found = []
    for seed in SEEDS:
        for change in CHANGE_KINDS:
            scene = raycast_scene(n_points=n_points, change=change, random_state=seed)
            for method in METHODS:
                for variant in VARIANTS:
                    case = f"seed {seed} {change} {method} {variant}"
                    detector = make_detector(method, variant, random_state=seed)
                    try:
                        with warnings.catch_warnings():
                            warnings.simplefilter("ignore")
                            detection = detector.detect(scene.reference, scene.scan)
                    except Exception as error:  # the same error is expected of both versions
                        found.append({"case": case, "error": f"{type(error).__name__}: {error}"})
                        continue
                    null = detection.calibration.get("null_values", [])
                    found.append(
                        {
                            "case": case,
                            "changed": bool(detection.changed),
                            "score": float(detection.score),
                            "threshold": float(detection.threshold),
                            "null": [float(value) for value in np.asarray(null).ravel()],
                        }
                    )
    return found


def relative(first: float, second: float) -> float:
    """|first - second| relative to the larger; 0 when equal (infinities included)."""
    if first == second:
        return 0.0
    if not (math.isfinite(first) and math.isfinite(second)):
        return math.inf
    return abs(first - second) / max(abs(first), abs(second))


def compare_rows(before: list[dict[str, Any]], after: list[dict[str, Any]]) -> int:
    """Print the comparison; the number of cases whose decision or error differs."""
    earlier = {row["case"]: row for row in before}
    differing, identical, decided = [], 0, 0
    worst: dict[str, float] = {}
    for row in after:
        old = earlier.get(row["case"], {})
        if old.get("error") != row.get("error") or old.get("changed") != row.get("changed"):
            differing.append(row["case"])
            continue
        if "error" in row:  # the same error both times
            continue
        decided += 1
        identical += old["score"] == row["score"] and old["threshold"] == row["threshold"]
        null_pairs = zip(old["null"], row["null"], strict=True)
        largest = max(
            [relative(old["score"], row["score"]), relative(old["threshold"], row["threshold"])]
            + [relative(first, second) for first, second in null_pairs]
        )
        key = " ".join(row["case"].split()[3:])
        worst[key] = max(worst.get(key, 0.0), largest)
    print(
        f"{len(after) - len(differing)} of {len(after)} detections decided as before "
        f"({len(after) - decided - len(differing)} the same error); scores and thresholds "
        f"bit-identical in {identical} of {decided}"
    )
    for key, value in sorted(worst.items()):
        print(f"  {key}: largest relative difference (score, threshold, null) {value:.1e}")
    for case in differing:
        print(f"  differs: {case}")
    return len(differing)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=6000, help="points a cloud")
    parser.add_argument("--save", type=Path)
    parser.add_argument("--against", type=Path)
    args = parser.parse_args()
    found = rows(args.points)
    if args.save:
        args.save.write_text(json.dumps(found))
    if args.against:
        return 1 if compare_rows(json.loads(args.against.read_text()), found) else 0
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
