"""Per-site calibration on a synthetic site's history (issue 16): false alarms before and after
the site learns its threshold, and whether real changes still fire.

Each layout (:func:`app.core.datasets.site.site_history`: the bin's spots, the crate's spot,
the sensor path) gives a reference and a history of rescans in which a bin moves on every
visit (a nuisance a reviewer marks ``false_alarm``) and, on the test visits, sometimes a 1 m
crate appears (a real change).  Per layout:

1. the first ``n`` visits (nuisance only) are compared with the default rule and reviewed:
   every one is a reviewed-null job (``false_alarm`` when it fired, ``confirmed`` unchanged
   otherwise);
2. the site calibration is learned from them (:func:`learn_site_calibration`, the split-
   conformal bound at ``--rate``) for ``n`` in ``--learn``;
3. the test visits (half with the crate) are decided by the default rule ("before") and with
   the site's calibration ("after", :func:`decide`, exactly what the worker applies).

Each visit is compared once (``compare`` with the PCA detector, the default ``regions`` rule);
both decisions come from that result's statistics.  The conformal bound promises a false-alarm
rate <= ``--rate`` on exchangeable nuisance visits (here: the bin at a random other spot,
the sensor 0.3-0.8 m from the reference's).

Run: ``.venv/bin/python -m bench.calibration [--layouts 6] [--quick]``; writes
``bench/results/calibration.md`` (``--quick``: ``calibration_quick.md``).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.core.cloud import PointCloud
from app.core.datasets.site import SiteVisit, site_history
from app.core.pipeline import compare
from app.core.site_calibration import (
    DecisionInputs,
    ReviewedSample,
    decide,
    largest_extent,
    learn_site_calibration,
)

RESULTS = Path(__file__).resolve().parent / "results"
METHOD, VARIANT = "pca", "improved"


@dataclass(frozen=True)
class Outcome:
    """One compared visit: what it measured and whether the crate was there."""

    inputs: DecisionInputs
    real_change: bool
    default_changed: bool


def run_visit(reference: PointCloud, visit: SiteVisit) -> Outcome:
    """Compare one visit against the reference with the default rule."""
    result = compare(
        reference,
        PointCloud.from_array(visit.points, sensor_origin=visit.sensor_origin),
        method=METHOD,
        variant=VARIANT,
    )
    inputs = DecisionInputs(
        rule="regions",
        method=METHOD,
        variant=VARIANT,
        score=result.score,
        detector_threshold=result.threshold,
        n_regions=len(result.regions),
        largest_region_extent_m=largest_extent(result.regions),
        min_region_points=int(result.localisation.get("min_region_points", 1)),
    )
    return Outcome(inputs, visit.real_change, bool(result.changed))


def rate(flags: list[bool]) -> str:
    """``k/n (pct)``."""
    return f"{sum(flags)}/{len(flags)} ({100.0 * np.mean(flags):.0f}%)" if flags else "-"


def run_layouts(args: argparse.Namespace, crate_size: float) -> tuple[list[str], list[str]]:
    """One run over every layout with a crate of edge ``crate_size``; per-layout and summary
    table rows."""
    learn_counts = sorted(int(count) for count in args.learn.split(","))
    n_learn = max(learn_counts)
    before: dict[str, list[bool]] = {"nuisance": [], "crate": []}
    after = {count: {"nuisance": [], "crate": []} for count in learn_counts}
    lines = []
    for layout in range(args.layouts):
        real = tuple(range(n_learn + 1, n_learn + args.test_visits, 2))  # every other test visit
        reference_visit, visits = site_history(
            n_learn + args.test_visits,
            layout_seed=layout,
            real_change_visits=real,
            crate_size=crate_size,
            n_points=args.points,
        )
        reference = PointCloud.from_array(
            reference_visit.points, sensor_origin=reference_visit.sensor_origin
        )
        outcomes = [run_visit(reference, visit) for visit in visits]
        learning, testing = outcomes[:n_learn], outcomes[n_learn:]
        for outcome in testing:
            before["crate" if outcome.real_change else "nuisance"].append(outcome.default_changed)
        learned_text = []
        for count in learn_counts:
            samples = [
                ReviewedSample(
                    f"visit{index}", outcome.inputs.score, outcome.inputs.largest_region_extent_m
                )
                for index, outcome in enumerate(learning[:count])
            ]
            calibration = learn_site_calibration(
                samples,
                method=METHOD,
                variant=VARIANT,
                false_alarm_rate=args.rate,
                min_samples=count,
            )
            for outcome in testing:
                changed, _tests, _site = decide(outcome.inputs, calibration)
                after[count]["crate" if outcome.real_change else "nuisance"].append(changed)
            threshold = calibration["thresholds"]["largest_region_extent_m"]
            learned_text.append(f"n={count}: {threshold:.2f} m")
        fired = sum(outcome.default_changed for outcome in learning)
        crate_extents = [o.inputs.largest_region_extent_m for o in testing if o.real_change]
        lines.append(
            f"| {crate_size:.1f} m | {layout} | {fired}/{len(learning)} | "
            f"{', '.join(learned_text)} | {min(crate_extents, default=float('nan')):.2f} m |"
        )
        print(f"crate {crate_size} m, layout {layout} done", flush=True)
    summary = [
        f"| {crate_size:.1f} m | default rule (before) | {rate(before['nuisance'])} | "
        f"{rate(before['crate'])} |",
        *(
            f"| {crate_size:.1f} m | site calibration from {count} reviewed visits | "
            f"{rate(after[count]['nuisance'])} | {rate(after[count]['crate'])} |"
            for count in learn_counts
        ),
    ]
    return lines, summary


def main() -> None:
    """Run the layouts for each crate size and print (and write) the tables."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--layouts", type=int, default=6, help="site layouts (seeds)")
    parser.add_argument("--learn", default="5,10", help="reviewed visits to learn from")
    parser.add_argument("--test-visits", type=int, default=12, help="test visits per layout")
    parser.add_argument("--points", type=int, default=20_000, help="points per scan")
    parser.add_argument("--rate", type=float, default=0.2, help="target false-alarm rate")
    parser.add_argument(
        "--crate-sizes",
        default="1.0,0.5",
        help="edges (m) of the real change's crate, one run each",
    )
    parser.add_argument("--quick", action="store_true", help="3 layouts, 8 test visits")
    args = parser.parse_args()
    if args.quick:
        args.layouts, args.test_visits = 3, 8
    started = time.perf_counter()
    lines: list[str] = []
    summary: list[str] = []
    for crate_size in (float(size) for size in args.crate_sizes.split(",")):
        layout_lines, summary_lines = run_layouts(args, crate_size)
        lines += layout_lines
        summary += summary_lines
    command = " ".join(["bench/calibration.py", *sys.argv[1:]])
    report = [
        "# Per-site calibration on a synthetic site's history",
        "",
        f"Command: `.venv/bin/python {command}` ({args.layouts} layouts, {args.test_visits} "
        f"test visits each (half with the crate), {args.points} points a scan, target "
        f"false-alarm rate {args.rate}, detector {METHOD}/{VARIANT}, rule regions).  The bin "
        "is 0.4 x 0.4 x 0.7 m (bounding-box diagonal 0.9 m).",
        "",
        "| crate | layout | learning visits that fired (default) | learned threshold | "
        "smallest crate region |",
        "|---|---|---|---|---|",
        *lines,
        "",
        "| crate | decision | false alarms (bin only) | real changes detected (crate) |",
        "|---|---|---|---|",
        *summary,
        "",
        f"Total {time.perf_counter() - started:.0f} s.",
    ]
    text = "\n".join(report) + "\n"
    print(text)
    RESULTS.mkdir(exist_ok=True)
    name = "calibration_quick.md" if args.quick else "calibration.md"
    (RESULTS / name).write_text(text)


if __name__ == "__main__":
    main()
