"""The service of a benchmark: ``scandiff serve`` in a fresh data directory, uploads
streamed from files, a job waited for, and the peak RSS and CPU of the service's processes
(used by bench/tiled_service.py)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx

from app.core.formats.streamed import declared_rows


def _free_port() -> int:
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        return int(listener.getsockname()[1])


class Service:
    """``scandiff serve`` on loopback in a fresh data directory, killed on exit."""

    def __init__(self, data_dir: Path, workers: int, env: dict[str, str]) -> None:
        self.data_dir, self.port = data_dir, _free_port()
        environment = {**os.environ, "OMP_NUM_THREADS": "1", **env}
        environment.pop("SCANDIFF_DATA_DIR", None)
        command = [sys.executable, "-m", "app", "serve", "--data-dir", str(data_dir)]
        command += ["--port", str(self.port), "--workers", str(workers)]
        self.log = open(data_dir.with_suffix(".log"), "wb")  # noqa: SIM115 - closed in __exit__
        self.process = subprocess.Popen(
            command,
            env=environment,
            stdout=self.log,
            stderr=subprocess.STDOUT,
            start_new_session=True,  # its own process group: the workers are killed with it
        )
        self.base_url = f"http://127.0.0.1:{self.port}"

    def __enter__(self) -> httpx.Client:
        deadline = time.monotonic() + 120
        token_file = self.data_dir / "admin-token"
        while time.monotonic() < deadline:
            with contextlib.suppress(httpx.HTTPError):
                health = httpx.get(f"{self.base_url}/api/v1/health").status_code
                if health == 200 and token_file.exists():
                    break
            time.sleep(0.2)
        else:
            raise RuntimeError(f"scandiff serve did not start; see {self.log.name}")
        token = token_file.read_text().strip()
        self.client = httpx.Client(
            base_url=self.base_url, headers={"Authorization": f"Bearer {token}"}, timeout=60
        )
        return self.client

    def __exit__(self, *exc: object) -> None:
        self.client.close()
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.process.pid, signal.SIGKILL)
        self.process.wait()
        self.log.close()


def _file_body(path: Path) -> Any:
    """The file as an upload body, streamed in 16 MiB pieces (a 1.2 GB scan is never held)."""
    with path.open("rb") as source:
        while piece := source.read(1 << 24):
            yield piece


def upload(client: httpx.Client, path: str, file: Path, params: dict[str, str]) -> dict:
    """POST ``file`` as the raw body of ``path``, streamed; the response's JSON."""
    response = client.post(
        path,
        params=params,
        content=_file_body(file),
        headers={"Content-Length": str(file.stat().st_size)},
        timeout=None,
    )
    response.raise_for_status()
    return response.json()


def size_settings(files: tuple[Path, Path]) -> dict[str, str]:
    """Upload size and point limits raised above their defaults when the pair needs it."""
    env = {}
    largest = max(path.stat().st_size for path in files)
    if largest > 512 * 1024**2:
        env["SCANDIFF_MAX_UPLOAD_BYTES"] = str(2 * largest)
    most = max(declared_rows(path) or 0 for path in files)
    if most > 50_000_000:
        env["SCANDIFF_MAX_POINTS"] = str(2 * most)
    return env


def wait_for_job(
    client: httpx.Client, job_id: str, group: int, timeout: float, every: float = 60.0
) -> dict:
    """Poll the job until it ends, printing every ``every`` s its tiles done/total and each
    service process's peak RSS and CPU so far (a long run shows how far it got)."""
    started = last = time.perf_counter()
    while True:
        job = client.get(f"/api/v1/jobs/{job_id}", params={"wait": 10}).json()
        if job["status"] in ("succeeded", "failed"):
            return job
        now = time.perf_counter()
        if now - last >= every:
            last = now
            status = {"status": job["status"], "progress": job.get("progress")}
            print(
                json.dumps(
                    {
                        "at": time.strftime("%H:%M:%S"),
                        "elapsed_s": round(now - started),
                        "job": status,
                        "tiles": job.get("tiles"),
                        "processes": group_peak_rss(group, with_cpu=True),
                    }
                ),
                flush=True,
            )
        if now - started > timeout:
            raise RuntimeError(f"job {job_id} did not finish in {timeout:.0f} s")


def group_peak_rss(group: int, with_cpu: bool = False) -> dict[str, Any]:
    """Peak RSS (``VmHWM``, MB) of each live process of process group ``group``, by
    ``pid: command`` (the service's API process and its workers); ``with_cpu``: each as
    ``[peak MB, CPU s so far]``."""
    ticks = os.sysconf("SC_CLK_TCK")
    peaks: dict[str, Any] = {}
    for status in Path("/proc").glob("[0-9]*/status"):
        with contextlib.suppress(OSError, IndexError, ValueError):
            stat = (status.parent / "stat").read_text()
            if int(stat.rsplit(")", 1)[1].split()[2]) != group:
                continue
            fields = dict(
                line.split(":", 1) for line in status.read_text().splitlines() if ":" in line
            )
            command = (status.parent / "cmdline").read_bytes().replace(b"\0", b" ").decode()
            name = f"{status.parent.name}: {' '.join(command.split()[2:5])}"
            peaks[name] = round(int(fields["VmHWM"].split()[0]) / 1024)
            if with_cpu:
                cpu = sum(int(value) for value in stat.rsplit(")", 1)[1].split()[11:13])
                peaks[name] = [peaks[name], round(cpu / ticks, 1)]
    return peaks
