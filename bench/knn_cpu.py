"""The k-NN of one 1M cloud on its own: CPU seconds of ``nearest_neighbourhoods``, this code
against another checkout in the same rounds.

``bench/perf1m_stages.py`` gives the k-NN stage inside the whole ``scandiff compare``, where
a change of a few hundredths of a second drowns in the load of a shared machine.  This script
times only :func:`app.core.localise.neighbourhoods.nearest_neighbourhoods` (k = 10, one
thread: the tree builds, the compiled kernel's search, the pykdtree queries of tied points) on
each cloud of a ``bench.perf_1m`` pair, in a child per checkout, the checkouts interleaved, and
prints each cloud's fastest and median CPU seconds (the main thread's ``time.thread_time``)
and whether both checkouts found the same neighbours (a digest of the neighbour index and the
k-th distances).

Run: ``.venv/bin/python -m bench.knn_cpu [--pairs room/30/scanner] [--baseline DIR]
[--rounds 5] [--work-dir DIR]``.
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

from bench.perf_1m import HELD_OUT, write_named_pair

PROJECT_ROOT = Path(__file__).resolve().parent.parent

CHILD = textwrap.dedent(
    """
    import hashlib, json, sys, time
    import numpy as np
    from app.core.formats import read_point_cloud
    from app.core.localise.neighbourhoods import nearest_neighbourhoods

    with open(sys.argv[1], "rb") as handle:
        cloud = read_point_cloud(handle, filename=sys.argv[1])
    points = np.ascontiguousarray(np.asarray(cloud.points, dtype=np.float64))
    started = time.thread_time()
    found = nearest_neighbourhoods(points, 10)
    seconds = time.thread_time() - started
    digest = hashlib.sha256(found.neighbor_index.tobytes() + found.kth_distance.tobytes())
    print(json.dumps({"seconds": seconds, "digest": digest.hexdigest()[:16]}))
    """
)


def run_child(code_root: Path, cloud: Path) -> dict[str, object]:
    """One timed k-NN of ``cloud`` with the code of ``code_root`` (one thread)."""
    environment = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(code_root))
    completed = subprocess.run(
        [sys.executable, "-c", CHILD, str(cloud)],
        cwd=code_root,
        env=environment,
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(completed.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", default=HELD_OUT, help="as bench.perf_1m's")
    parser.add_argument("--baseline", type=Path, help="a checkout of the code before")
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds")
    parser.add_argument("--work-dir", type=Path, help="keep the pairs here (reused)")
    args = parser.parse_args()
    roots = {"this code": PROJECT_ROOT}
    if args.baseline is not None:
        roots["code before"] = args.baseline.resolve()
    print("| pair | cloud | code | fastest CPU s | median CPU s | neighbours digest |")
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory(prefix="scandiff-knn-cpu-") as temporary:
        work_dir = args.work_dir or Path(temporary)
        for spec in args.pairs.split(","):
            _, paths = write_named_pair(work_dir, spec)
            for cloud in ("reference", "scan"):
                runs: dict[str, list[dict[str, object]]] = {key: [] for key in roots}
                for _ in range(args.rounds):
                    for key, root in roots.items():
                        runs[key].append(run_child(root, paths[cloud]))
                for key, rows in runs.items():
                    seconds = [float(row["seconds"]) for row in rows]
                    digests = sorted({str(row["digest"]) for row in rows})
                    print(
                        f"| {spec} | {cloud} | {key} | {min(seconds):.3f} | "
                        f"{statistics.median(seconds):.3f} | {', '.join(digests)} |",
                        flush=True,
                    )


if __name__ == "__main__":
    main()
