"""Performance round 2 (issue 18), the 5M pair alone: the command against the floor.

``bench/perf_round2.py --large`` runs the 5M pair after the 1M pair, its cached re-run and the
service; on a shared 2-core machine that is over an hour.  This script runs only what the 5M
targets need (<= 3.5x the floor, <= 3 GB peak RSS): the floor and ``scandiff compare REF SCAN
--json --labels OUT.npz``, taking turns for ``--repeats`` rounds, measured exactly as
bench/perf_round2.py measures them (its :func:`run_floor` and :func:`run_command`: wall
seconds and CPU seconds of the child, peak RSS from ``os.wait4``).  The pair is written once
into ``--work-dir`` (about 12 minutes and 2.5 GB RSS at 5M; 120 MB of PLY) and reused.

Run: ``.venv/bin/python -m bench.perf_round2_large --work-dir /tmp/round2 [--repeats 2]``;
prints a markdown section (the figures of bench/results/perf_round2.md's "5M pair").
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from typing import Any

from bench.perf_round2 import (
    LARGE_SIZE,
    TARGETS,
    best,
    run_command,
    run_floor,
    write_pair,
)


def measure(scene_dir: Path, repeats: int) -> dict[str, list[dict[str, Any]]]:
    """The floor and the command, interleaved ``repeats`` times."""
    paths = write_pair(scene_dir, LARGE_SIZE)
    labels = str(scene_dir / "labels.npz")
    arguments = ["compare", str(paths["reference"]), str(paths["scan"]), "--json"]
    arguments += ["--labels", labels]
    runs: dict[str, list[dict[str, Any]]] = {"floor": [], "compare": []}
    for round_index in range(repeats):
        runs["floor"].append(run_floor(scene_dir))
        runs["compare"].append(run_command(arguments))
        print(
            f"round {round_index + 1}: floor {runs['floor'][-1]}, "
            f"compare {runs['compare'][-1]}, load {os.getloadavg()}",
            flush=True,
        )
    return runs


def render(runs: dict[str, list[dict[str, Any]]], loads: list[tuple]) -> str:
    """The markdown lines of the 5M section."""
    floor, command = best(runs["floor"]), best(runs["compare"])
    ratio_target, rss_target = TARGETS[LARGE_SIZE]
    if "error" in floor or "error" in command:
        return f"error: floor {floor.get('error')}, compare {command.get('error')}\n"
    ratio = command["seconds"] / floor["seconds"]
    cpu_ratio = command["cpu_seconds"] / floor["cpu_seconds"]
    stages = ", ".join(f"{k} {v:.1f}" for k, v in command["timings"].items())
    return "\n".join(
        [
            f"| points a scan | seconds | floor s | ratio (target <= {ratio_target}x) | "
            f"peak RSS MB (target <= {rss_target:.0f}) | CPU s | floor CPU s | CPU ratio | "
            "all runs s | floor runs s |",
            "|---|---|---|---|---|---|---|---|---|---|",
            f"| {LARGE_SIZE:,} | {command['seconds']:.1f} | {floor['seconds']:.1f} | "
            f"{ratio:.2f}x | {command['peak_rss_mb']:.0f} | {command['cpu_seconds']:.1f} | "
            f"{floor['cpu_seconds']:.1f} | {cpu_ratio:.2f}x | "
            f"{' / '.join(str(s) for s in command['all_seconds'])} | "
            f"{' / '.join(str(s) for s in floor['all_seconds'])} |",
            "",
            f"Stage seconds of the fastest run: {stages}.  Floor peak RSS "
            f"{floor['peak_rss_mb']:.0f} MB.  Load average (1, 5, 15 min) at start "
            f"{', '.join(f'{v:.1f}' for v in loads[0])}, at end "
            f"{', '.join(f'{v:.1f}' for v in loads[-1])}.",
            "",
        ]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work-dir", type=Path, required=True, help="the pair is kept here")
    parser.add_argument("--repeats", type=int, default=2, help="interleaved rounds")
    args = parser.parse_args()
    loads = [os.getloadavg()]
    started = time.perf_counter()
    runs = measure(args.work_dir / f"warehouse-{LARGE_SIZE}", args.repeats)
    loads.append(os.getloadavg())
    print(f"{time.perf_counter() - started:.0f} s in all")
    print(render(runs, loads))


if __name__ == "__main__":
    main()
