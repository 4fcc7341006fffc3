"""Performance round 2 (issue 18): the whole ``scandiff compare`` process against the floor.

What users run is the command, so that is what is timed: ``scandiff compare REFERENCE SCAN
--json --labels OUT.npz`` in a child process, its wall time from start to exit (imports, load,
origins, align, localise, detect, writing the labels) and its peak RSS as the kernel reports it
for the child (``os.wait4``'s ``ru_maxrss``, never read from inside).  The floor, measured in the
same run, is bench/perf.py's: one ``cKDTree`` build and nearest-neighbour query each way with 2
query threads (compute only, in its own child process).  The command and the floor take turns
(``--repeats`` interleaved rounds) and each keeps its fastest run, so a neighbour's burst on the
shared machine slows one run, not one side of a ratio; every run is listed, with the load
average before and after, and the CPU seconds (user + system) of each command run.

Pairs: :func:`app.core.datasets.lidar.lidar_pair` warehouses (one station, an added box, the
scan misaligned by 0.3-0.4 degrees and 2-3 cm), float32 binary PLY as scanners write them.

* ``compare``: the command as a new user runs it (origins estimated, gmm);
* ``compare again``: the same with ``--geometry-cache DIR`` after one run filled it (the
  reference compared again, as a site's second and later scans are);
* ``service``: a 100k-point scan through the HTTP API, upload to ``succeeded``
  (bench/perf_service.py, the median of 3).

Targets: 1M compare <= 3x the floor and <= 600 MB; 5M (``--large``) <= 3.5x and <= 3 GB;
compare again <= 2x; service <= 2 s.

Run: ``.venv/bin/python -m bench.perf_round2 [--large] [--repeats 3]``; writes
``bench/results/perf_round2.md`` and ``.json``.
``--only service`` times just the HTTP API figure and prints where each upload's seconds went
(upload, worker pickup, run, seen by the client's long poll, the CPU seconds of the worker and of
the service's other processes, the job's stage timings), writing no file; ``--poll-seconds S``
reads the job every S seconds instead of the long poll (a client without it, for comparison).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from app.core.datasets.lidar import lidar_pair, steps_for_points
from bench.perf import worker_environment
from bench.perf_service import measure_service
from bench.perf_workers import write_binary_ply

PROJECT_ROOT = Path(__file__).resolve().parent.parent

RESULTS = Path(__file__).resolve().parent / "results"
SCENE_SEED = 18
SIZES = (1_000_000,)
LARGE_SIZE = 5_000_000
TARGETS = {1_000_000: (3.0, 600.0), LARGE_SIZE: (3.5, 3000.0)}
"""Points a scan: (most times the floor, most peak RSS MB) of the compare command."""
AGAIN_TARGET = 2.0
SERVICE_TARGET_SECONDS = 2.0
SCANDIFF = Path(sys.executable).with_name("scandiff")


def write_pair(scene_dir: Path, n_points: int) -> dict[str, Any]:
    """Write a warehouse pair of about ``n_points`` points a scan (once: reused if present).

    Generated in a child process: Linux counts the parent's resident pages at ``fork`` in each
    child's ``ru_maxrss``, so a bench process grown by the generation would report its own size
    as every command's peak.
    """
    scene_dir.mkdir(parents=True, exist_ok=True)
    reference_path, scan_path = scene_dir / "reference.ply", scene_dir / "scan.ply"
    if not (reference_path.exists() and scan_path.exists()):
        subprocess.run(
            [
                sys.executable,
                "-m",
                "bench.perf_round2",
                "--write-pair",
                str(scene_dir),
                str(n_points),
            ],
            check=True,
            cwd=PROJECT_ROOT,
        )
    return {"reference": reference_path, "scan": scan_path}


def _write_pair_here(scene_dir: Path, n_points: int) -> None:
    """The child of :func:`write_pair`: generate and write the pair."""
    pair = lidar_pair(
        layout="warehouse",
        change="added",
        angular_step_deg=steps_for_points(n_points),
        misaligned=True,
        random_state=SCENE_SEED,
    )
    write_binary_ply(scene_dir / "reference.ply", pair.reference)
    write_binary_ply(scene_dir / "scan.ply", pair.scan)


def _child(command: list[str], environment: dict[str, str], cwd: Path) -> dict[str, Any]:
    """Run ``command``; its exit code, stdout, stderr, wall seconds, and from ``os.wait4``
    its CPU seconds (user + system) and peak RSS."""
    started = time.perf_counter()
    with tempfile.TemporaryFile() as output, tempfile.TemporaryFile() as errors:
        child = subprocess.Popen(command, stdout=output, stderr=errors, cwd=cwd, env=environment)
        _, status, usage = os.wait4(child.pid, 0)
        wall = time.perf_counter() - started
        child.returncode = os.waitstatus_to_exitcode(status)
        output.seek(0)
        errors.seek(0)
        return {
            "code": child.returncode,
            "stdout": output.read().decode(errors="replace"),
            "stderr": errors.read().decode(errors="replace"),
            "wall": wall,
            "cpu_seconds": usage.ru_utime + usage.ru_stime,
            "peak_rss_mb": usage.ru_maxrss / 1024.0,
        }


def run_floor(scene_dir: Path) -> dict[str, Any]:
    """bench/perf.py's floor worker (2 query threads) as a child: its compute seconds, and
    the whole process's CPU seconds and peak RSS."""
    command = [sys.executable, "-m", "bench.perf", "--worker", "floor"]
    command += [str(scene_dir), "--threads", "2"]
    child = _child(command, worker_environment("floor"), PROJECT_ROOT)
    lines = [line for line in child["stdout"].splitlines() if line.startswith("{")]
    if child["code"] != 0 or not lines:
        return {"error": child["stderr"].strip().splitlines()[-1:] or [f"exit {child['code']}"]}
    report = json.loads(lines[-1])
    return {
        "seconds": report["seconds"],
        "cpu_seconds": child["cpu_seconds"],
        "peak_rss_mb": child["peak_rss_mb"],
    }


def run_command(arguments: list[str], code_root: Path | None = None) -> dict[str, Any]:
    """Run ``scandiff`` with ``arguments`` as a child; wall seconds, CPU seconds, peak RSS
    (the kernel's ``ru_maxrss`` of the child) and its JSON timings.  ``code_root``: run the
    ``app`` package of another checkout (e.g. the code before a change) instead."""
    environment = dict(os.environ)
    if code_root is not None:
        environment["PYTHONPATH"] = str(code_root)
    child = _child([str(SCANDIFF), *arguments], environment, code_root or PROJECT_ROOT)
    if child["code"] != 0:
        return {"error": child["stderr"].strip().splitlines()[-1:] or [f"exit {child['code']}"]}
    report = json.loads(child["stdout"].strip().splitlines()[-1])
    return {
        "seconds": child["wall"],
        "cpu_seconds": child["cpu_seconds"],
        "peak_rss_mb": child["peak_rss_mb"],
        "timings": report.get("timings", {}),
        "changed": report.get("changed"),
    }


def measure_size(
    n_points: int, work_dir: Path, repeats: int, baseline: Path | None = None
) -> dict[str, Any]:
    """The floor, the command and the command with a filled geometry cache, interleaved."""
    scene_dir = work_dir / f"warehouse-{n_points}"
    started = time.perf_counter()
    paths = write_pair(scene_dir, n_points)
    print(f"[{n_points}] pair ready in {time.perf_counter() - started:.0f} s", flush=True)
    labels = str(scene_dir / "labels.npz")
    cache_dir = str(scene_dir / "geometry-cache")
    plain = [str(paths["reference"]), str(paths["scan"]), "--json", "--labels", labels]
    cached = [*plain, "--geometry-cache", cache_dir]
    fill = run_command(["compare", *cached])  # fills the cache (its time is not a target)
    runs: dict[str, list[dict[str, Any]]] = {"floor": [], "compare": [], "again": []}
    if baseline is not None:
        runs["baseline"] = []
    for round_index in range(repeats):
        runs["floor"].append(run_floor(scene_dir))
        runs["compare"].append(run_command(["compare", *plain]))
        runs["again"].append(run_command(["compare", *cached]))
        if baseline is not None:
            runs["baseline"].append(run_command(["compare", *plain], code_root=baseline))
        line = ", ".join(
            f"{key} {run[-1].get('seconds', float('nan')):.2f} s" for key, run in runs.items()
        )
        print(f"[{n_points}] round {round_index + 1}: {line}", flush=True)
    return {"n_points": n_points, "fill": fill, "runs": runs}


def best(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The fastest run, with every run's seconds and the highest peak RSS of any."""
    good = [run for run in runs if "error" not in run]
    if not good:
        return {"error": runs[-1].get("error") if runs else "no run"}
    fastest = dict(min(good, key=lambda run: run["seconds"]))
    fastest["all_seconds"] = [round(run["seconds"], 2) for run in good]
    fastest["peak_rss_mb"] = max(run["peak_rss_mb"] for run in good)
    return fastest


def summarise(size: dict[str, Any]) -> list[dict[str, Any]]:
    """Rows of the table for one size: command and compare-again against the floor."""
    floor = best(size["runs"]["floor"])
    rows = []
    ratio_target, rss_target = TARGETS.get(size["n_points"], (None, None))
    configurations = [
        ("compare", "scandiff compare", ratio_target),
        ("again", "scandiff compare, reference cached", AGAIN_TARGET),
    ]
    if "baseline" in size["runs"]:
        configurations.append(("baseline", "scandiff compare, code before (--baseline)", None))
    for key, label, target in configurations:
        run = best(size["runs"][key])
        ratio = (
            run["seconds"] / floor["seconds"] if "seconds" in run and "seconds" in floor else None
        )
        rows.append(
            {
                "points": size["n_points"],
                "configuration": label,
                "seconds": run.get("seconds"),
                "all_seconds": run.get("all_seconds"),
                "cpu_seconds": run.get("cpu_seconds"),
                "floor_seconds": floor.get("seconds"),
                "floor_all_seconds": floor.get("all_seconds"),
                "floor_cpu_seconds": floor.get("cpu_seconds"),
                "ratio": ratio,
                "ratio_target": target,
                "ratio_met": None if ratio is None or target is None else ratio <= target,
                "peak_rss_mb": run.get("peak_rss_mb"),
                "rss_target_mb": rss_target if key == "compare" else None,
                "rss_met": (
                    None
                    if key != "compare" or rss_target is None or "peak_rss_mb" not in run
                    else run["peak_rss_mb"] <= rss_target
                ),
                "timings": run.get("timings"),
                "error": run.get("error"),
            }
        )
    return rows


def format_number(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def runs_cells(row: dict) -> str:
    """The last two cells of a table row: every run's seconds, every floor run's seconds."""
    runs = " / ".join(str(seconds) for seconds in row["all_seconds"] or [])
    floor_runs = " / ".join(str(seconds) for seconds in row["floor_all_seconds"] or [])
    return f"{runs} | {floor_runs} |"


def stage_lines(rows: list[dict], label: Callable[[dict], str]) -> list[str]:
    """The paragraph of stage seconds of each row's fastest run, its rows named by ``label``."""
    lines = ["", "Stage seconds of the fastest run (the command's own `timings`):", ""]
    for row in rows:
        if row.get("timings"):
            stages = ", ".join(f"{k} {v:.2f}" for k, v in row["timings"].items())
            lines.append(f"- {label(row)}, {row['configuration']}: {stages}")
    return lines


def format_met(value: bool | None) -> str:
    return "-" if value is None else ("met" if value else "NOT met")


def _cpu_ratio(row: dict[str, Any]) -> str:
    """CPU seconds of the command over those of the floor's process (both whole processes:
    imports and load included): a figure a busy machine disturbs less than wall time."""
    if row.get("cpu_seconds") is None or not row.get("floor_cpu_seconds"):
        return "-"
    return f"{row['cpu_seconds'] / row['floor_cpu_seconds']:.2f}x"


def _loads(values: tuple) -> str:
    return ", ".join(f"{value:.1f}" for value in values)


def render(rows: list[dict[str, Any]], service: dict[str, Any], loads: list[tuple]) -> str:
    """The markdown report."""
    lines = [
        "# Performance round 2 (bench/perf_round2.py)",
        "",
        f"Machine: {os.cpu_count()} CPUs, shared; load average (1, 5, 15 min) at start "
        f"{_loads(loads[0])}, at end {_loads(loads[-1])}.  "
        "Time: wall seconds of the whole `scandiff compare REF SCAN --json --labels OUT.npz` "
        "process (fastest of the interleaved rounds); floor: one cKDTree build + NN query each "
        "way, 2 query threads, same run; peak RSS: the child's `ru_maxrss` (os.wait4).",
        "",
        "| points a scan | configuration | seconds | floor s | ratio | target | "
        "peak RSS MB | RSS target | CPU s (process) | floor CPU s (process) | CPU ratio | "
        "all runs s | floor runs s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        if row.get("error"):
            lines.append(f"| {row['points']:,} | {row['configuration']} | error: {row['error']} |")
            continue
        target = row["ratio_target"]
        rss_target = row["rss_target_mb"]
        ratio_target = "-" if target is None else f"<= {target}x {format_met(row['ratio_met'])}"
        rss = "-" if rss_target is None else f"<= {rss_target:.0f} {format_met(row['rss_met'])}"
        lines.append(
            f"| {row['points']:,} | {row['configuration']} | "
            f"{format_number(row['seconds'])} | "
            f"{format_number(row['floor_seconds'])} | {format_number(row['ratio'])}x | "
            f"{ratio_target} | "
            f"{format_number(row['peak_rss_mb'], 0)} | {rss} | "
            f"{format_number(row['cpu_seconds'])} | "
            f"{format_number(row['floor_cpu_seconds'])} | {_cpu_ratio(row)} | {runs_cells(row)}"
        )
    lines += stage_lines(rows, lambda row: f"{row['points']:,}")
    lines.append("")
    if service:
        if "error" in service:
            lines.append(f"Service (100k, upload to succeeded): error: {service['error']}")
        else:
            latency = service["latency_seconds"]
            lines.append(
                f"Service (100k-point scan, HTTP upload to `succeeded`, median of "
                f"{len(service['latency_all_seconds'])}): {latency:.2f} s "
                f"(runs {' / '.join(f'{v:.2f}' for v in service['latency_all_seconds'])}); "
                f"target <= {SERVICE_TARGET_SECONDS} s "
                f"{format_met(latency <= SERVICE_TARGET_SECONDS)}."
            )
    return "\n".join(lines) + "\n"


def render_service_breakdown(service: dict[str, Any]) -> str:
    """One line a timed upload: where its seconds went (bench/perf_service.py's breakdown)."""
    lines = []
    for index, parts in enumerate(service.get("breakdown", []), start=1):
        phases = ", ".join(
            f"{key} {parts[key]:.2f}"
            for key in ("upload", "pickup", "run", "seen", "total", "worker_cpu", "other_cpu")
            if key in parts
        )
        stages = ", ".join(f"{key} {value:.2f}" for key, value in parts["timings"].items())
        lines.append(f"- run {index}: {phases}; job timings: {stages}")
    return "\n".join(lines)


def run_service_only(repeats: int, idle_seconds: float = 0.0, poll_seconds: float = 0.0) -> None:
    """``--only service``: the HTTP API figure and where its time goes, printed (no file)."""
    with tempfile.TemporaryDirectory(prefix="scandiff-round2-service-") as temporary:
        load_before = os.getloadavg()
        service = measure_service(
            Path(temporary),
            load_seconds=0.0,
            repeats=repeats,
            idle_seconds=idle_seconds,
            poll_seconds=poll_seconds,
        )
        load_after = os.getloadavg()
    if "error" in service:
        print(f"service: error: {service['error']}")
        return
    all_seconds = " / ".join(f"{value:.2f}" for value in service["latency_all_seconds"])
    print(
        f"service (100k-point scan, upload to succeeded): median {service['latency_seconds']:.2f} s"
        f" (runs {all_seconds}); target <= {SERVICE_TARGET_SECONDS} s "
        f"{format_met(service['latency_seconds'] <= SERVICE_TARGET_SECONDS)}; load average "
        f"{_loads(load_before)} -> {_loads(load_after)}"
    )
    print(render_service_breakdown(service))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--large", action="store_true", help="add the 5M-point pair")
    parser.add_argument("--repeats", type=int, default=3, help="interleaved rounds a size")
    parser.add_argument("--no-service", action="store_true", help="skip the HTTP API figure")
    parser.add_argument(
        "--only",
        choices=("service",),
        help="run only this part (service: the HTTP API figure, its breakdown, no load test)",
    )
    parser.add_argument(
        "--service-repeats", type=int, default=3, help="uploads timed for the service figure"
    )
    parser.add_argument(
        "--idle-seconds",
        type=float,
        default=0.0,
        help="with --only service: leave the service idle this long before each upload",
    )
    parser.add_argument(
        "--poll-seconds",
        type=float,
        default=0.0,
        help="with --only service: read the job this often instead of the long poll",
    )
    parser.add_argument("--work-dir", type=Path, help="keep the pairs here (reused when present)")
    parser.add_argument("--output", type=Path, default=RESULTS / "perf_round2.md")
    parser.add_argument(
        "--baseline", type=Path, help="a checkout of the code before, timed in the same rounds"
    )
    args = parser.parse_args()
    if args.only == "service":
        run_service_only(args.service_repeats, args.idle_seconds, args.poll_seconds)
        return
    loads = [os.getloadavg()]
    sizes = [*SIZES, LARGE_SIZE] if args.large else list(SIZES)
    with tempfile.TemporaryDirectory(prefix="scandiff-round2-") as temporary:
        work_dir = args.work_dir or Path(temporary)
        measured = []
        for n_points in sizes:
            repeats = args.repeats if n_points < LARGE_SIZE else max(1, args.repeats // 2)
            measured.append(measure_size(n_points, work_dir, repeats, args.baseline))
        # a fresh data directory each run (a kept --work-dir would hold last run's site)
        service_dir = Path(tempfile.mkdtemp(prefix="service-", dir=work_dir))
        service = (
            {}
            if args.no_service
            else measure_service(service_dir, load_seconds=1.0, repeats=args.service_repeats)
        )
    loads.append(os.getloadavg())
    rows = [row for size in measured for row in summarise(size)]
    report = render(rows, service, loads)
    print(report)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(report)
    details = {"rows": rows, "service": service, "load_average": loads, "sizes": measured}
    args.output.with_suffix(".json").write_text(json.dumps(details, indent=1, default=str))


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--write-pair":
        _write_pair_here(Path(sys.argv[2]), int(sys.argv[3]))
        sys.exit(0)
    main()
