"""What ``scandiff compare`` prints of a result: the summary or the JSON document on stdout,
and the quality warnings on stderr, with each warning's fix in the CLI's flags."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from app.core.pipeline import ComparisonResult
    from app.core.quality import QualityWarning


def print_summary(result: ComparisonResult, reference: Path, scan: Path) -> None:
    verdict = "CHANGED" if result.changed else "no significant change"
    registration = result.registration
    counts = result.label_counts()
    print(f"{scan.name} vs {reference.name}: {verdict}")
    print(f"  why: {result.explanation.text}")
    print(
        f"  {result.method}-EMD ({result.variant}): score {result.score:.4g}, "
        f"threshold {result.threshold:.4g}"
    )
    print(
        f"  registration: fitness {registration.fitness:.3f}, "
        f"rmse {float('nan') if registration.rmse is None else registration.rmse:.4f}"
    )
    print(
        f"  points: reference {result.n_reference} ({counts['reference']['changed']} removed, "
        f"{counts['reference']['unobserved']} unobserved), scan {result.n_scan} "
        f"({counts['scan']['changed']} added, {counts['scan']['unobserved']} unobserved)"
    )
    for side in ("reference", "scan"):
        for entry in result.sensor_origins.get(side, []):
            if entry.trajectory is not None:
                trajectory = entry.trajectory
                print(
                    f"  {side} trajectory: {trajectory['poses']} poses, {trajectory['groups']} "
                    f"pseudo-stations ({trajectory['assignment']}), "
                    f"{trajectory['points_outside']} points outside its times"
                )
                continue
            where = ", ".join(f"{value:.2f}" for value in entry.origin or [])
            print(f"  {side} sensor origin: ({where}), {entry.source}")
    if result.quality_warnings:
        print(f"  warnings: {len(result.quality_warnings)} (on stderr)")
    print(f"  regions: {len(result.regions)}")
    for region in result.regions[:10]:
        centroid = ", ".join(f"{value:.2f}" for value in region.centroid)
        print(
            f"    {region.kind:<7} {region.n_points:>7} points at ({centroid})"
            f"  {region.evidence}, confidence {region.confidence:.2f}"
        )
    if len(result.regions) > 10:
        print(f"    ... and {len(result.regions) - 10} more")
    if result.uncertain_regions:
        points = sum(region.n_points for region in result.uncertain_regions)
        print(
            f"  not covered by the other scan (not counted as change): "
            f"{len(result.uncertain_regions)} regions, {points} points"
        )
    timing = ", ".join(f"{stage} {seconds:.2f} s" for stage, seconds in result.timings.items())
    print(f"  timings: {timing}")


CLI_FIXES: dict[str, tuple[str, list[str]]] = {
    "check_pairing": (
        "check that both files are of the same place, or compare without aligning (--no-align)",
        ["--no-align"],
    ),
    "check_alignment": (
        "check that the alignment found the right match, or compare without aligning (--no-align)",
        ["--no-align"],
    ),
    "widen_coverage": ("rescan so that both files cover the same part of the place", []),
    "give_sensor_origin": (
        "give the sensor position with --sensor-origin X,Y,Z (reference) and --scan-origin "
        "X,Y,Z (scan), or --sensor-frame when both files are in their sensor's frame",
        ["--sensor-origin", "--scan-origin", "--sensor-frame"],
    ),
    "check_sensor_origin": (
        "check the sensor position given with --sensor-origin, --scan-origin or --sensor-frame",
        ["--sensor-origin", "--scan-origin", "--sensor-frame"],
    ),
    "check_trajectory": (
        "check that the file given with --trajectory or --scan-trajectory was recorded with "
        "that cloud, on the same clock, and covers its whole recording",
        ["--trajectory", "--scan-trajectory"],
    ),
}
"""For each ``how_to_fix["action"]`` of :mod:`app.core.quality`: the CLI's advice and flags."""


def cli_warnings(warnings: Sequence[QualityWarning]) -> list[dict[str, Any]]:
    """Quality warnings as JSON, with ``how_to_fix`` in the CLI's flags."""
    from app.core.jsonable import json_safe

    rendered = []
    for warning in warnings:
        document = json_safe(warning.to_json_dict())
        if warning.action in CLI_FIXES:
            text, flags = CLI_FIXES[warning.action]
            document["how_to_fix"] = {**document["how_to_fix"], "text": text, "flags": flags}
        rendered.append(document)
    return rendered


def print_warnings(result: ComparisonResult) -> None:
    """Every quality warning on stderr, one line each (the sentence, then how to fix it in
    the CLI's flags), whatever the output format."""
    for warning in result.quality_warnings:
        fix = CLI_FIXES.get(warning.action)
        advice = f" To fix: {fix[0]}." if fix else ""
        print(f"scandiff: warning: {warning.message}{advice}", file=sys.stderr)


def report(args: argparse.Namespace, result: ComparisonResult) -> None:
    """The result on stdout: JSON or the summary."""
    if args.json:
        document = result.to_json_dict()
        document["quality_warnings"] = cli_warnings(result.quality_warnings)
        json.dump(document, sys.stdout)
        sys.stdout.write("\n")
    else:
        print_summary(result, args.reference, args.scan)
