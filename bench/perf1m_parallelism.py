"""The 1M class's wall time on a quiet machine, estimated on a loaded one from thread states.

``bench/perf_1m.py``'s target is a wall-time ratio (the whole ``scandiff compare`` against the
two-thread cKDTree floor of the same pair), but on a 2-core machine shared by other jobs wall
seconds measure the load, not the code.  What a quiet machine's wall time depends on is how
much CPU each stretch of the process needs and how many of its threads can run at once.  Both
can be observed under load: this script runs a command as a child and samples every thread's
state (``/proc/PID/task/*/stat``: running or runnable ``R``, else waiting: the GIL, a lock,
a join, I/O) every few milliseconds.

Between two samples ``n`` threads were runnable; under load each progresses at about the same
rate ``r`` (CPU seconds per second of wall time), which the run's own CPU total gives:
``r = CPU / sum(n dt)``.  On a quiet machine with ``C`` cores the same stretch takes
``r n dt / min(n, C)`` seconds.  Summed, that is the estimate (ignoring stretches with no
runnable thread, e.g. waiting for a disk, which a page-cached file makes rare; their share is
reported).  It assumes the threads' work and the GIL hand-offs are what they would be on a
quiet machine, so it is a model, not a measurement: it ranks the code before and after a
change in the same conditions and says where the serial stretches are.

With ``--baseline`` the command and the baseline swap slots every round (:func:`slot_order`):
the first slot after the floor runs slower for the same code, so an even ``--repeats`` measures
both orders and each row says its ``slot``.

For the floor (bench/perf.py's floor worker, 2 query threads) only its timed section counts
(the last ``seconds`` of the process it reports, as the target does).

The command runs from compiled bytecode, as installed (:func:`bench.perf_1m.compile_bytecode`;
``--from-source``: compiled at each start, as before s20).

Run: ``.venv/bin/python -m bench.perf1m_parallelism [--pairs bench,room/30/scanner]
[--baseline DIR] [--repeats 2] [--work-dir DIR] [--from-source]`` (pairs as in
``bench.perf_1m``).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.perf import worker_environment
from bench.perf_1m import HELD_OUT, compile_bytecode, write_named_pair
from bench.perf_round2 import SCANDIFF

PROJECT_ROOT = Path(__file__).resolve().parent.parent
SAMPLE_SECONDS = 0.005
CORES = 2
CLOCK_TICKS = os.sysconf("SC_CLK_TCK")


def _thread_states(pid: int) -> tuple[int, int] | None:
    """(runnable threads, CPU ticks of all threads) of process ``pid``; None once it is gone."""
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except FileNotFoundError:
        return None
    runnable = ticks = 0
    for task in tasks:
        try:
            with open(f"/proc/{pid}/task/{task}/stat", "rb") as handle:
                fields = handle.read().rsplit(b")", 1)[1].split()
        except (FileNotFoundError, ProcessLookupError):
            continue
        # after "pid (comm)": state is field 0, utime 11, stime 12
        runnable += fields[0] == b"R"
        ticks += int(fields[11]) + int(fields[12])
    return runnable, ticks


def sampled_run(command: list[str], environment: dict[str, str]) -> dict[str, Any]:
    """Run ``command``, sampling its threads' states; the samples, its output, CPU and wall."""
    with tempfile.TemporaryFile() as output, tempfile.TemporaryFile() as errors:
        children_cpu = _children_cpu_seconds()
        started = time.perf_counter()
        child = subprocess.Popen(
            command, stdout=output, stderr=errors, cwd=PROJECT_ROOT, env=environment
        )
        samples: list[tuple[float, int]] = []
        while child.poll() is None:
            state = _thread_states(child.pid)
            if state is not None:
                samples.append((time.perf_counter() - started, state[0]))
            time.sleep(SAMPLE_SECONDS)
        wall = time.perf_counter() - started
        output.seek(0)
        errors.seek(0)
        stdout = output.read().decode(errors="replace")
        stderr = errors.read().decode(errors="replace")
    if child.returncode != 0:
        raise RuntimeError(f"{command[:3]} failed: {stderr.strip().splitlines()[-1:]}")
    cpu_seconds = _children_cpu_seconds() - children_cpu
    return {"samples": samples, "stdout": stdout, "wall": wall, "cpu_seconds": cpu_seconds}


def _children_cpu_seconds() -> float:
    """CPU seconds (user + system) of this process's reaped children so far."""
    times = os.times()
    return times.children_user + times.children_system


def quiet_estimate(
    samples: list[tuple[float, int]], cpu_seconds: float, window: tuple[float, float] | None
) -> dict[str, float]:
    """The quiet-machine wall seconds of the sampled stretch (see the module docstring).

    ``window``: (start, end) seconds of the run to count (None: all of it); ``cpu_seconds``
    is the CPU of that stretch.
    """
    thread_seconds = quiet = serial = idle = busy = 0.0
    for (time_now, runnable), (time_next, _) in itertools.pairwise(samples):
        if window is not None:
            time_now, time_next = max(time_now, window[0]), min(time_next, window[1])
            if time_next <= time_now:
                continue
        step = time_next - time_now
        if runnable == 0:
            idle += step
            continue
        busy += step
        thread_seconds += runnable * step
        quiet += runnable * step / min(runnable, CORES)
        serial += step if runnable == 1 else 0.0
    if thread_seconds == 0:
        return {"quiet_seconds": float("nan"), "serial_cpu_share": float("nan")}
    rate = cpu_seconds / thread_seconds
    return {
        "quiet_seconds": rate * quiet,
        "serial_cpu_share": serial / thread_seconds,
        "no_runnable_share": idle / (idle + busy),
    }


def measure(scene: dict[str, Path], code_root: Path | None) -> dict[str, Any]:
    """The command (from ``code_root``'s ``app`` when given) on one pair, sampled."""
    environment = dict(os.environ)
    if code_root is not None:
        environment["PYTHONPATH"] = str(code_root)
    labels = scene["reference"].parent / "labels-parallelism.npz"
    command = [str(SCANDIFF), "compare", str(scene["reference"]), str(scene["scan"])]
    run = sampled_run([*command, "--json", "--labels", str(labels)], environment)
    estimate = quiet_estimate(run["samples"], run["cpu_seconds"], None)
    return {"cpu_seconds": run["cpu_seconds"], "loaded_wall": run["wall"], **estimate}


def measure_floor(scene_dir: Path) -> dict[str, Any]:
    """The floor worker, sampled; only its timed section is estimated."""
    command = [sys.executable, "-m", "bench.perf", "--worker", "floor", str(scene_dir)]
    run = sampled_run([*command, "--threads", "2"], worker_environment("floor"))
    report = json.loads([line for line in run["stdout"].splitlines() if line.startswith("{")][-1])
    end = run["samples"][-1][0] if run["samples"] else run["wall"]
    window = (end - report["seconds"], end)
    # the CPU of the window: the whole run's share by runnable-thread seconds
    whole = quiet_estimate(run["samples"], run["cpu_seconds"], None)
    share = _thread_seconds(run["samples"], window)
    total = _thread_seconds(run["samples"], None)
    cpu_window = run["cpu_seconds"] * share / total if total else float("nan")
    timed = quiet_estimate(run["samples"], cpu_window, window)
    return {
        "cpu_seconds": run["cpu_seconds"],
        "timed_cpu_seconds": cpu_window,
        "loaded_seconds": report["seconds"],
        "process_quiet_seconds": whole["quiet_seconds"],
        **timed,
    }


def _thread_seconds(samples: list[tuple[float, int]], window: tuple[float, float] | None) -> float:
    """Runnable-thread seconds of the samples within ``window`` (None: all)."""
    total = 0.0
    for (time_now, runnable), (time_next, _) in itertools.pairwise(samples):
        if window is not None:
            time_now, time_next = max(time_now, window[0]), min(time_next, window[1])
        total += runnable * max(0.0, time_next - time_now)
    return total


def slot_order(runs: list[str], round_index: int) -> list[str]:
    """``runs`` in the order they run in round ``round_index`` (0-based): as given in even
    rounds, reversed in odd ones.

    The command in the first slot runs ~0.4 CPU s (~0.2 quiet s) slower than the same code in
    the second (s26), so the runs swap slots every round: an even number of rounds puts each
    in each slot equally often.
    """
    return list(runs) if round_index % 2 == 0 else list(reversed(runs))


def _measure_round(
    spec: str, scene_dir: Path, scene: dict[str, Path], round_index: int, baseline: Path | None
) -> list[dict[str, Any]]:
    """One round on one pair: the floor, then the command (and baseline) in the round's order."""
    measured = {"floor": measure_floor(scene_dir)}
    slots = {"floor": 0}
    runs = ["compare"] if baseline is None else ["compare", "baseline"]
    for slot, run in enumerate(slot_order(runs, round_index), start=1):
        measured[run] = measure(scene, None if run == "compare" else baseline)
        slots[run] = slot
    floor = measured["floor"]["quiet_seconds"]
    rows = []
    for key, value in measured.items():
        row = {"pair": spec, "round": round_index + 1, "run": key, "slot": slots[key], **value}
        if key != "floor":
            row["quiet_ratio"] = value["quiet_seconds"] / floor
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", default=f"bench,{HELD_OUT}")
    parser.add_argument("--repeats", type=int, default=2, help="rounds (even: both slot orders)")
    parser.add_argument(
        "--baseline", type=Path, help="another checkout, sampled in the same rounds"
    )
    parser.add_argument("--work-dir", type=Path, help="keep the pairs here (reused when present)")
    parser.add_argument("--output", type=Path, help="write the rows as JSON here")
    parser.add_argument(
        "--from-source", action="store_true", help="do not compile app's bytecode first"
    )
    args = parser.parse_args()
    if not args.from_source:
        for code_root in (PROJECT_ROOT, args.baseline):
            if code_root is not None:
                compile_bytecode(code_root)
    rows = []
    with tempfile.TemporaryDirectory(prefix="scandiff-parallelism-") as temporary:
        work_dir = args.work_dir or Path(temporary)
        for spec in args.pairs.split(","):
            scene_dir, scene = write_named_pair(work_dir, spec)
            for round_index in range(args.repeats):
                rows.extend(_measure_round(spec, scene_dir, scene, round_index, args.baseline))
    if args.output is not None:
        args.output.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
