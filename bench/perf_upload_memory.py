"""Memory of the API process while it receives and checks a large text or ``.npy`` upload.

Starts the real ``scandiff serve`` (app/testing/service.py), creates a site and uploads, as
its reference, a large XYZ text file and a large ``.npy`` file streamed from disk.  For each,
the API child's (``python -m app.cli.serve --child api``) peak resident memory is read from
``/proc/<pid>/status`` (``VmHWM``, the kernel's high-water mark, reset before each upload:
anonymous and file-backed pages both count) against its resident set before the upload; the
growth is what receiving and checking that file cost.  Bounded means: about the same for a
file twice as large, and far below the file's size.

Run: ``.venv/bin/python -m bench.perf_upload_memory [--rows 2000000]``; to measure another
checkout's code (the code before), run this file from that checkout with the same interpreter.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from app.testing.service import ServiceProcess, process_group_members

PROJECT_ROOT = Path(__file__).resolve().parent.parent

BODY_CHUNK_BYTES = 1024 * 1024
WRITE_ROWS = 250_000
"""Rows generated and written at a time (the bench's own memory stays small too)."""


def write_text(path: Path, n_rows: int, seed: int = 7) -> None:
    """An XYZ file of ``n_rows`` random rows (mm resolution), with a few NaN rows."""
    rng = np.random.default_rng(seed)
    with open(path, "w") as output:
        output.write("x y z\n")
        for start in range(0, n_rows, WRITE_ROWS):
            rows = rng.uniform(-50.0, 50.0, size=(min(WRITE_ROWS, n_rows - start), 3))
            rows[::100_003, 1] = np.nan
            np.savetxt(output, rows, fmt="%.3f")


def write_npy(path: Path, n_rows: int, seed: int = 8) -> None:
    """A float64 (n_rows, 3) ``.npy`` file written a block at a time (memory-mapped)."""
    rng = np.random.default_rng(seed)
    array = np.lib.format.open_memmap(path, mode="w+", dtype=np.float64, shape=(n_rows, 3))
    for start in range(0, n_rows, WRITE_ROWS):
        stop = min(n_rows, start + WRITE_ROWS)
        array[start:stop] = rng.uniform(-50.0, 50.0, size=(stop - start, 3))
    array.flush()
    del array


def api_pid(service: ServiceProcess) -> int:
    """The pid of the service's API child."""
    for pid in process_group_members(service.pid):
        try:
            command = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"--child" in command and b"api" in command:
            return pid
    raise RuntimeError("no API child found")


def memory_mb(pid: int, field: str) -> float:
    """A memory line of ``/proc/<pid>/status`` (``VmHWM``: peak resident set since the last
    reset, ``VmRSS``: now) in MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError(f"no {field} for {pid}")


def reset_peak(pid: int) -> None:
    """Make ``VmHWM`` start again from the current resident set (Linux ``clear_refs`` 5)."""
    Path(f"/proc/{pid}/clear_refs").write_text("5")


def file_chunks(path: Path):
    """The file as a stream of chunks (the client holds one at a time)."""
    with open(path, "rb") as stream:
        while chunk := stream.read(BODY_CHUNK_BYTES):
            yield chunk


def upload(service: ServiceProcess, pid: int, path: Path) -> dict[str, Any]:
    """Upload ``path`` as a new site's reference; the API's peak RSS growth and the answer."""
    with service.client(timeout=600.0) as client:
        site = client.post("/api/v1/sites", json={"name": path.name}).json()
        reset_peak(pid)
        before = memory_mb(pid, "VmRSS")
        started = time.perf_counter()
        response = client.post(
            f"/api/v1/sites/{site['id']}/scans",
            params={"reference": "true", "filename": path.name},
            content=file_chunks(path),
            headers={
                "Content-Type": "application/octet-stream",
                "Content-Length": str(path.stat().st_size),
            },
        )
        seconds = time.perf_counter() - started
        after = memory_mb(pid, "VmHWM")
    body = response.json()
    return {
        "file": path.name,
        "file_mb": path.stat().st_size / 1e6,
        "status": response.status_code,
        "n_points": body.get("scan", {}).get("n_points"),
        "n_dropped": body.get("scan", {}).get("n_dropped"),
        "error": body.get("detail") if response.status_code >= 400 else None,
        "seconds": seconds,
        "rss_before_mb": before,
        "peak_mb": after,
        "growth_mb": after - before,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=2_000_000, help="rows of the larger files")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="scandiff-upload-memory-") as temporary:
        work = Path(temporary)
        files = []
        for n_rows in (args.rows // 2, args.rows):
            text_path, npy_path = work / f"scan-{n_rows}.xyz", work / f"scan-{n_rows}.npy"
            write_text(text_path, n_rows)
            write_npy(npy_path, n_rows)
            files += [text_path, npy_path]
        service = ServiceProcess(
            work / "data",
            workers=1,
            env={"SCANDIFF_MAX_UPLOAD_BYTES": str(4 * 1024**3)},
        )
        service.start()
        try:
            pid = api_pid(service)
            results = [upload(service, pid, path) for path in files]
        finally:
            service.stop()
    print(f"code: {PROJECT_ROOT}; load average {', '.join(f'{v:.1f}' for v in os.getloadavg())}")
    print("| file | MB | status | points | dropped | s | API peak RSS growth MB |")
    print("|---|---|---|---|---|---|---|")
    for row in results:
        print(
            f"| {row['file']} | {row['file_mb']:.0f} | {row['status']} | {row['n_points']} | "
            f"{row['n_dropped']} | {row['seconds']:.1f} | {row['growth_mb']:.0f} |"
            + (f" {row['error']}" if row["error"] else "")
        )


if __name__ == "__main__":
    main()
