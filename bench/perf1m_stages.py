"""Where the 1M class's CPU goes: each stage's CPU seconds of ``scandiff compare``, one thread.

``bench/perf_1m.py`` gives the whole process's CPU against the floor's; this script splits it.
``scandiff compare REF SCAN --json --labels OUT.npz`` runs as a child with
``OMP_NUM_THREADS=1``, so every stage runs on the main thread, one after the other (the
comparison's own threads do the same work with two; the results do not depend on it).  The
child wraps the stages' public functions (the pipeline's and the localiser's steps, looked up
through their modules at call time) with the main thread's CPU clock (``time.thread_time``):
no profiler, so Python-heavy stages are not inflated.  What is left:

* ``start-up``: the main thread's CPU before the pipeline starts (imports, arguments, reading);
* ``other threads``: the process's CPU (``getrusage``, user + system) minus the main
  thread's: the detectors' libraries imported on a thread of their own
  (:func:`app.core.detectors.warm_up`) and OpenMP / BLAS helpers;
* ``system``: the process's system CPU (page faults), part of the stages above.

``--baseline DIR`` runs another checkout's ``app`` (e.g. the code before a change) in the same
rounds, the two swapping slots every round (the first runs slower for the same code; use an
even ``--repeats``).  The median of ``--repeats`` rounds is printed.  The machine may be loaded: CPU
seconds, not wall seconds, are the measure.

Both checkouts run from compiled bytecode, as installed (:func:`bench.perf_1m.compile_bytecode`;
``--from-source``: compiled at each start, as before s20).

Run: ``.venv/bin/python -m bench.perf1m_stages [--pairs bench,room/30/scanner]
[--baseline DIR] [--repeats 3] [--work-dir DIR] [--from-source]`` (pairs as in
``bench.perf_1m``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path
from typing import Any

from bench.perf1m_parallelism import slot_order
from bench.perf_1m import HELD_OUT, compile_bytecode, write_named_pair

PROJECT_ROOT = Path(__file__).resolve().parent.parent

STAGES = (
    ("load", "app.core.pipeline", "load_pair"),
    ("origins: reference", "app.core.comparison.origins", "resolve_stations"),
    ("origins: scan", "app.core.comparison.origins", "resolve_moved_cloud"),
    ("align", "app.core.pipeline", "align_scan"),
    ("reference neighbourhoods", "app.core.comparison.localise", "reference_neighbourhoods"),
    ("localise", "app.core.pipeline", "localise_pair"),
    ("detect", "app.core.pipeline", "detect_change"),
    ("assemble", "app.core.pipeline", "assemble_result"),
    ("k-NN of both clouds", "app.core.cache.geometry", "nearest_neighbourhoods"),
    ("k-NN of both clouds", "app.core.localise.surface", "nearest_neighbourhoods"),
    ("plane fits of both clouds", "app.core.localise.surface", "fit_surfaces"),
    ("nearest point each way", "app.core.localise.changes", "nearest_in"),
    ("misalignment residual", "app.core.localise.changes", "alignment_residual"),
    ("distances to the other surface", "app.core.localise.changes", "surface_distance"),
    ("surface levels near the threshold", "app.core.localise.changes", "surface_offset_candidates"),
    ("candidates", "app.core.localise.changes", "find_candidates"),
    ("ray test", "app.core.localise.changes", "label_candidates"),
    ("regions (changed and unobserved)", "app.core.localise.changed_regions", "find_regions"),
    ("regions (changed and unobserved)", "app.core.localise.changed_regions", "cluster_changed"),
    ("small-cluster rules", "app.core.localise.changed_regions", "with_small_faces"),
)
"""(label, module, public function looked up in that module at call time).  The first eight
follow one another; the others are parts of "reference neighbourhoods" and "localise"."""
FORMER_STAGES = (("regions (changed and unobserved)", "app.core.localise.changes", "find_regions"),)
"""Where a baseline from before a move has a stage (the regions' step left ``changes`` in
s27), timed too; a module or function a checkout lacks is skipped."""

CHILD = textwrap.dedent(
    """
    import functools, importlib, json, resource, sys, threading, time

    stages = json.loads(sys.argv[1])
    spent = {label: 0.0 for label, _, _ in stages}
    first_call = {}
    main_thread = threading.main_thread()

    def timed(label, function):
        @functools.wraps(function)
        def wrapper(*args, **kwargs):
            if threading.current_thread() is not main_thread:
                return function(*args, **kwargs)
            started = time.thread_time()
            first_call.setdefault("start", started)
            try:
                return function(*args, **kwargs)
            finally:
                spent[label] += time.thread_time() - started
        return wrapper

    for label, module_name, name in stages:
        try:  # a stage another checkout does not have (a baseline's) is left out
            module = importlib.import_module(module_name)
        except ImportError:
            continue
        if hasattr(module, name):
            setattr(module, name, timed(label, getattr(module, name)))
    from app.cli import main

    sys.argv = ["scandiff", *sys.argv[2:]]
    status = main()
    usage = resource.getrusage(resource.RUSAGE_SELF)
    report = {
        "status": status,
        "stages": spent,
        "start-up": first_call.get("start"),
        "main thread": time.thread_time(),
        "process": usage.ru_utime + usage.ru_stime,
        "system": usage.ru_stime,
        "peak_rss_mb": usage.ru_maxrss / 1024,
    }
    print("STAGES " + json.dumps(report), file=sys.stderr)
    """
)


def run_child(code_root: Path, reference: Path, scan: Path, labels: Path) -> dict[str, Any]:
    """One profiled ``scandiff compare`` of the pair (one thread); its CPU seconds by stage."""
    environment = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(code_root))
    arguments = ["compare", str(reference), str(scan), "--json", "--labels", str(labels)]
    command = [sys.executable, "-c", CHILD, json.dumps([*STAGES, *FORMER_STAGES]), *arguments]
    completed = subprocess.run(
        command, cwd=code_root, env=environment, capture_output=True, text=True, check=False
    )
    lines = [line for line in completed.stderr.splitlines() if line.startswith("STAGES ")]
    if completed.returncode != 0 or not lines:
        tail = completed.stderr.strip().splitlines()[-1:] or [f"exit {completed.returncode}"]
        return {"error": tail[0]}
    report = json.loads(lines[-1].removeprefix("STAGES "))
    row = dict(report["stages"])
    row["start-up"] = report["start-up"]
    row["other threads"] = report["process"] - report["main thread"]
    row["system"] = report["system"]
    row["whole process"] = report["process"]
    row["peak RSS MB"] = report["peak_rss_mb"]
    return row


def median_rows(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Each figure's median over the rounds that succeeded."""
    good = [row for row in rows if "error" not in row]
    if not good:
        return {}
    return {key: statistics.median(row[key] for row in good) for key in good[0]}


def render(results: dict[str, dict[str, dict[str, float]]]) -> str:
    """A markdown table per pair: each stage's CPU seconds, this code and the code before."""
    lines = []
    labels = [
        "start-up",
        *dict.fromkeys(label for label, _, _ in STAGES),
        "other threads",
        "whole process",
        "system",
        "peak RSS MB",
    ]
    for pair, configurations in results.items():
        names = list(configurations)
        lines += [
            f"### {pair}",
            "",
            "| stage (CPU s, one thread) | " + " | ".join(names) + " |",
            "|---|" + "---|" * len(names),
        ]
        for label in labels:
            cells = []
            for name in names:
                value = configurations[name].get(label)
                cells.append("" if value is None else f"{value:.2f}")
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", default=f"bench,{HELD_OUT}", help="as bench.perf_1m's")
    parser.add_argument("--baseline", type=Path, help="a checkout of the code before")
    parser.add_argument("--repeats", type=int, default=3, help="interleaved rounds a pair")
    parser.add_argument("--work-dir", type=Path, help="keep the pairs here (reused)")
    parser.add_argument(
        "--from-source", action="store_true", help="do not compile app's bytecode first"
    )
    args = parser.parse_args()
    roots = {"this code": PROJECT_ROOT}
    if args.baseline is not None:
        roots["code before"] = args.baseline.resolve()
    if not args.from_source:
        for root in roots.values():
            compile_bytecode(root)
    results: dict[str, dict[str, dict[str, float]]] = {}
    with tempfile.TemporaryDirectory(prefix="scandiff-perf1m-stages-") as temporary:
        work_dir = args.work_dir or Path(temporary)
        for spec in args.pairs.split(","):
            scene_dir, paths = write_named_pair(work_dir, spec)
            name = "held-out class" if spec == HELD_OUT else spec
            rounds: dict[str, list[dict[str, Any]]] = {key: [] for key in roots}
            for round_index in range(args.repeats):
                for key in slot_order(list(roots), round_index):  # the first slot is slower
                    root = roots[key]
                    labels = scene_dir / f"labels-stages-{key.replace(' ', '-')}.npz"
                    row = run_child(root, paths["reference"], paths["scan"], labels)
                    rounds[key].append(row)
                    figure = row.get("whole process", row.get("error"))
                    print(f"[{name}] round {round_index + 1} {key}: {figure}", flush=True)
            results[name] = {key: median_rows(rows) for key, rows in rounds.items()}
    print(render(results))


if __name__ == "__main__":
    main()
