"""The 1M single-station class (issue 30, item 7): the whole CLI against the floor, two pairs.

Both pairs are one-station lidar rescans on a uniform angular grid
(:func:`app.core.datasets.lidar.lidar_pair`, about 1M + 1M points, an added box, the scan
misaligned), float32 binary PLY:

* ``bench``: the pair of ``bench/perf_round2.py`` (a warehouse, points shuffled);
* ``held-out class``: a room (another layout, seed and size of building) with its points in
  the order a scanner writes them: column by column (azimuth), each column bottom to top.  A
  spatially coherent file order makes the floor's tree walks stay in cache, about 2-3x faster
  than on a shuffled cloud: that floor is the one the target is measured against.

For each pair, interleaved rounds (``--repeats``) of the floor (one cKDTree build and
nearest-neighbour query each way, 2 query threads, in its own child process: bench/perf.py's
floor worker) and of ``scandiff compare REF SCAN --json --labels OUT.npz`` as a child process,
timed from start to exit, peak RSS from ``os.wait4`` (bench/perf_round2.py's ``run_command``);
each keeps its fastest run.  ``--baseline DIR`` also runs the ``app`` package of another
checkout in the same rounds, and the labels of both are compared (identical or not).

Targets: <= 3x the floor of the same pair and <= 600 MB, for both pairs.  ``--pairs`` adds
other ``LAYOUT/SEED/ORDER`` pairs (e.g. ``room/30/shuffled``: the same room shuffled, or
``corridor/1/scanner``), to check that time and memory follow the size, not the kind of data.

Peak RSS is the child's own only when the process that starts it is small: Linux carries the
parent's resident size at ``fork`` into the child's ``ru_maxrss`` (``exec`` does not reset it).
Pairs are generated in a child process for that reason; ``--hold-mb N`` makes this process hold
N MB while it runs the commands, which shows the effect (a harness that generated its pairs in
its own process reports its own size as every command's peak).

The command runs from compiled bytecode, as installed (:func:`compile_bytecode`);
``--from-source`` runs it as before s20, compiling every module of ``app`` at each start.

Run: ``.venv/bin/python -m bench.perf_1m [--repeats 3] [--pairs ...] [--baseline DIR]
[--work-dir DIR] [--from-source]``;
writes ``bench/results/perf_1m.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.datasets.lidar import LAYOUTS, LidarPair, lidar_pair, steps_for_points
from bench.perf_round2 import (
    best,
    format_met,
    format_number,
    run_command,
    run_floor,
    runs_cells,
    stage_lines,
    write_pair,
)
from bench.perf_workers import write_binary_ply

PROJECT_ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results"
N_POINTS = 1_000_000
HELD_OUT = "room/30/scanner"
"""The held-out-class pair: a room, seed 30, points in scanner order."""
ORDERS = ("scanner", "shuffled")
RATIO_TARGET = 3.0
RSS_TARGET_MB = 600.0


def compile_bytecode(code_root: Path) -> None:
    """Compile ``code_root``'s ``app`` package to bytecode (``__pycache__``, ignored by git).

    An installed scandiff runs from bytecode (pip compiles it when it installs the wheel), but
    a checkout run with ``PYTHONDONTWRITEBYTECODE=1`` (as in this project's containers and dev
    machines) compiles each of the ~150 modules a comparison imports at every start: ~0.15-0.3
    CPU s of the 1M command that no installed command spends.  Python checks each cached file
    against its source (size and time), so a stale one is never used.
    """
    command = [sys.executable, "-m", "compileall", "-q", str(code_root / "app")]
    subprocess.run(command, check=True, cwd=code_root, capture_output=True)


def scanner_order(
    points: NDArray[np.float64], station: NDArray[np.float64], step_deg: float
) -> NDArray[np.intp]:
    """The order a spinning scanner at ``station`` writes ``points`` (n, 3): by azimuth column,
    each column by elevation (ring), for a grid of ``step_deg`` degrees; shape (n,)."""
    offset = points - station
    elevation = np.degrees(np.arctan2(offset[:, 2], np.hypot(offset[:, 0], offset[:, 1])))
    azimuth = np.degrees(np.arctan2(offset[:, 1], offset[:, 0])) % 360.0
    ring = np.round(elevation / step_deg).astype(np.int64)
    column = np.floor(azimuth / step_deg + 0.5).astype(np.int64)
    return np.lexsort((ring, column))


def _scan_in_world(pair: LidarPair) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The scan's points and station in the frame its grid was cast in (misalignment undone)."""
    rotation, translation = pair.true_transform[:3, :3], pair.true_transform[:3, 3]
    return pair.scan @ rotation.T + translation, rotation @ pair.scan_origins[0] + translation


def write_lidar_pair(scene_dir: Path, spec: str) -> dict[str, Path]:
    """Write the pair of ``spec`` (``LAYOUT/SEED/ORDER``, see :func:`parse_spec`) once (reused
    if present), generated in a child process (so that this process's pages do not count in
    the commands' peak RSS)."""
    scene_dir.mkdir(parents=True, exist_ok=True)
    reference_path, scan_path = scene_dir / "reference.ply", scene_dir / "scan.ply"
    if not (reference_path.exists() and scan_path.exists()):
        command = [sys.executable, "-m", "bench.perf_1m", "--write-pair", str(scene_dir), spec]
        subprocess.run(command, check=True, cwd=PROJECT_ROOT)
    return {"reference": reference_path, "scan": scan_path}


def parse_spec(spec: str) -> tuple[str, int, str]:
    """``LAYOUT/SEED/ORDER`` -> (layout, seed, order): a ``lidar_pair`` layout (room, corridor,
    warehouse), its seed, and ``scanner`` (column by column) or ``shuffled`` file order."""
    layout, seed, order = spec.split("/")
    if layout not in LAYOUTS or order not in ORDERS:
        raise SystemExit(f"pair {spec!r}: want LAYOUT/SEED/ORDER, {LAYOUTS} and {ORDERS}")
    return layout, int(seed), order


def write_named_pair(work_dir: Path, spec: str) -> tuple[Path, dict[str, Path]]:
    """The directory and files of the pair named ``spec``: ``bench`` (the bench's own 1M
    warehouse) or a ``LAYOUT/SEED/ORDER`` lidar pair (:func:`write_lidar_pair`), written once
    under ``work_dir``."""
    if spec == "bench":
        scene_dir = work_dir / f"warehouse-{N_POINTS}"
        return scene_dir, write_pair(scene_dir, N_POINTS)
    scene_dir = work_dir / spec.replace("/", "-")
    return scene_dir, write_lidar_pair(scene_dir, spec)


def _write_pair_here(scene_dir: Path, spec: str) -> None:
    """The child of :func:`write_lidar_pair`."""
    layout, seed, order = parse_spec(spec)
    step = steps_for_points(N_POINTS)
    pair = lidar_pair(
        layout=layout, change="added", angular_step_deg=step, misaligned=True, random_state=seed
    )
    reference_order = np.arange(pair.reference.shape[0])
    scan_order = np.arange(pair.scan.shape[0])
    if order == "scanner":
        reference_order = scanner_order(pair.reference, pair.reference_origins[0], step)
        scan_world, scan_station = _scan_in_world(pair)
        scan_order = scanner_order(scan_world, scan_station, step)
    write_binary_ply(scene_dir / "reference.ply", pair.reference[reference_order])
    write_binary_ply(scene_dir / "scan.ply", pair.scan[scan_order])


def _labels_equal(first: Path, second: Path) -> bool | None:
    """Whether two ``--labels`` files hold the same arrays (None: one is missing)."""
    if not (first.exists() and second.exists()):
        return None
    with np.load(first) as one, np.load(second) as other:
        if sorted(one.files) != sorted(other.files):
            return False
        return all(np.array_equal(one[name], other[name]) for name in one.files)


def measure_pair(
    name: str, scene_dir: Path, paths: dict[str, Path], repeats: int, baseline: Path | None
) -> dict[str, Any]:
    """Interleaved rounds of the floor, the command (and the code before) on one pair."""
    runs: dict[str, list[dict[str, Any]]] = {"floor": [], "compare": []}
    if baseline is not None:
        runs["baseline"] = []
    labels = {key: scene_dir / f"labels-{key}.npz" for key in ("compare", "baseline")}

    def arguments(key: str) -> list[str]:
        reference, scan = str(paths["reference"]), str(paths["scan"])
        return ["compare", reference, scan, "--json", "--labels", str(labels[key])]

    for round_index in range(repeats):
        runs["floor"].append(run_floor(scene_dir))
        runs["compare"].append(run_command(arguments("compare")))
        if baseline is not None:
            runs["baseline"].append(run_command(arguments("baseline"), code_root=baseline))
        line = ", ".join(
            f"{key} {run[-1].get('seconds', float('nan')):.2f} s "
            f"{run[-1].get('peak_rss_mb', float('nan')):.0f} MB"
            for key, run in runs.items()
        )
        print(f"[{name}] round {round_index + 1}: {line}", flush=True)
    same = _labels_equal(labels["compare"], labels["baseline"]) if baseline else None
    return {"pair": name, "runs": runs, "labels_identical_to_baseline": same}


def summarise(measured: dict[str, Any]) -> list[dict[str, Any]]:
    """Rows of the table for one pair: the command (and the code before) against the floor."""
    floor = best(measured["runs"]["floor"])
    rows = []
    for key in ("compare", "baseline"):
        if key not in measured["runs"]:
            continue
        run = best(measured["runs"][key])
        seconds, floor_seconds = run.get("seconds"), floor.get("seconds")
        ratio = seconds / floor_seconds if seconds and floor_seconds else None
        cpu, floor_cpu = run.get("cpu_seconds"), floor.get("cpu_seconds")
        rows.append(
            {
                "pair": measured["pair"],
                "configuration": "scandiff compare" if key == "compare" else "code before",
                "seconds": seconds,
                "all_seconds": run.get("all_seconds"),
                "floor_seconds": floor_seconds,
                "floor_all_seconds": floor.get("all_seconds"),
                "ratio": ratio,
                "ratio_met": None if ratio is None else ratio <= RATIO_TARGET,
                "peak_rss_mb": run.get("peak_rss_mb"),
                "rss_met": (
                    None if run.get("peak_rss_mb") is None else run["peak_rss_mb"] <= RSS_TARGET_MB
                ),
                "cpu_seconds": cpu,
                "cpu_ratio": cpu / floor_cpu if cpu and floor_cpu else None,
                "timings": run.get("timings"),
                "error": run.get("error"),
            }
        )
    return rows


def render(rows: list[dict[str, Any]], measured: list[dict[str, Any]], loads: list) -> str:
    """The markdown report."""
    lines = [
        "# The 1M single-station class (bench/perf_1m.py, issue 30 item 7)",
        "",
        f"Machine: {os.cpu_count()} CPUs, shared; load average (1, 5, 15 min) at start "
        f"{', '.join(f'{v:.1f}' for v in loads[0])}, at end "
        f"{', '.join(f'{v:.1f}' for v in loads[-1])}.  Time: wall seconds of the whole "
        "`scandiff compare REF SCAN --json --labels OUT.npz` process (fastest of the "
        "interleaved rounds); floor: one cKDTree build + NN query each way, 2 query threads, "
        "same pair, same rounds; peak RSS: the child's `ru_maxrss` (os.wait4), the highest of "
        "its runs.  CPU: user + system seconds of the whole process (the floor's too).",
        "",
        "| pair | configuration | seconds | floor s | ratio (<= 3x) | peak RSS MB (<= 600) | "
        "CPU s | CPU ratio | all runs s | floor runs s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        if row.get("error"):
            lines.append(f"| {row['pair']} | {row['configuration']} | error: {row['error']} |")
            continue
        lines.append(
            f"| {row['pair']} | {row['configuration']} | {format_number(row['seconds'])} | "
            f"{format_number(row['floor_seconds'])} | {format_number(row['ratio'])}x "
            f"{format_met(row['ratio_met'])} | {format_number(row['peak_rss_mb'], 0)} "
            f"{format_met(row['rss_met'])} | {format_number(row['cpu_seconds'])} | "
            f"{format_number(row['cpu_ratio'])}x | {runs_cells(row)}"
        )
    lines += stage_lines(rows, lambda row: row["pair"])
    for size in measured:
        same = size["labels_identical_to_baseline"]
        if same is not None:
            lines.append(
                f"- {size['pair']}: labels {'identical to' if same else 'DIFFER from'} "
                "the code before"
            )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="interleaved rounds a pair")
    parser.add_argument("--work-dir", type=Path, help="keep the pairs here (reused when present)")
    parser.add_argument("--output", type=Path, default=RESULTS / "perf_1m.md")
    parser.add_argument(
        "--baseline", type=Path, help="a checkout of the code before, timed in the same rounds"
    )
    parser.add_argument(
        "--pairs",
        default=f"bench,{HELD_OUT}",
        help="comma-separated: bench (the warehouse of perf_round2) and LAYOUT/SEED/ORDER "
        f"lidar pairs (ORDER: scanner or shuffled); default: bench,{HELD_OUT}",
    )
    parser.add_argument(
        "--hold-mb",
        type=int,
        default=0,
        help="hold this many MB in this process while the commands run (shows how a large "
        "parent inflates the children's ru_maxrss)",
    )
    parser.add_argument(
        "--from-source", action="store_true", help="do not compile app's bytecode first"
    )
    args = parser.parse_args()
    if not args.from_source:
        for code_root in (PROJECT_ROOT, args.baseline):
            if code_root is not None:
                compile_bytecode(code_root)
    held = np.ones(args.hold_mb * (1 << 20) // 8) if args.hold_mb > 0 else None
    loads = [os.getloadavg()]
    wanted = args.pairs.split(",")
    with tempfile.TemporaryDirectory(prefix="scandiff-perf-1m-") as temporary:
        work_dir = args.work_dir or Path(temporary)
        measured = []
        for spec in sorted(wanted, key=lambda spec: spec != "bench"):  # the bench's pair first
            name = "held-out class" if spec == HELD_OUT else spec
            scene_dir, paths = write_named_pair(work_dir, spec)
            measured.append(measure_pair(name, scene_dir, paths, args.repeats, args.baseline))
    loads.append(os.getloadavg())
    del held
    rows = [row for pair in measured for row in summarise(pair)]
    report = render(rows, measured, loads)
    if args.hold_mb > 0:
        report += f"\nThis process held {args.hold_mb} MB while the commands ran (--hold-mb).\n"
    print(report)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(report)
    details = {"rows": rows, "pairs": measured, "load_average": loads}
    args.output.with_suffix(".json").write_text(json.dumps(details, indent=1, default=str))


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--write-pair":
        _write_pair_here(Path(sys.argv[2]), sys.argv[3])
        sys.exit(0)
    main()
