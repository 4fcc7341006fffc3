"""``bench/load.py`` keeps working (issue 5, item 9): 4 clients for 3 s against its own service.

The script runs as a user would run it (a subprocess; it starts ``scandiff serve`` on a
temporary data directory on 127.0.0.1 and stops it), mixing uploads of small valid scans (a
share of 0.2) and job status polls.  Pass: exit status 0, both kinds of request made, 0 errors,
no "database is locked" in the service's log; the figures (requests/s, p50/p99) are reported.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from app.testing.paths import PROJECT_ROOT
from tests.helpers.figures import record_figure

CLIENTS = 4
SECONDS = 3.0
UPLOAD_SHARE = 0.2


@pytest.mark.slow  # the load script against a live service (~10 CPU s): make test-slow
def test_the_load_script_runs_and_reports(tmp_path: Path) -> None:
    figures_path = tmp_path / "load.json"
    markdown_path = tmp_path / "load.md"
    command = [
        sys.executable,
        "-m",
        "bench.load",
        "--clients",
        str(CLIENTS),
        "--seconds",
        str(SECONDS),
        "--upload-share",
        str(UPLOAD_SHARE),
        "--points",
        "1500",
        "--json",
        str(figures_path),
        "--markdown",
        str(markdown_path),
    ]
    environment = {**os.environ, "OMP_NUM_THREADS": "1", "TMPDIR": str(tmp_path)}
    environment.pop("SCANDIFF_DATA_DIR", None)
    completed = subprocess.run(
        command,
        cwd=PROJECT_ROOT,
        env=environment,
        capture_output=True,
        text=True,
        timeout=180,
    )
    print(completed.stdout)
    assert completed.returncode == 0, completed.stdout + completed.stderr
    figures = json.loads(figures_path.read_text())
    kinds = figures["kinds"]
    assert kinds["upload"]["requests"] > 0 and kinds["status"]["requests"] > 0
    assert kinds["total"]["errors"] == 0, kinds
    assert figures["server_log_locked"] is False
    assert "| status |" in markdown_path.read_text()
    assert not any(tmp_path.glob("scandiff-load-*")), "the scratch data directory was left"

    def describe(kind: str) -> str:
        row = kinds[kind]
        return (
            f"{kind} {row['throughput_per_s']:.1f}/s p50 {row['p50_ms']:.0f} ms "
            f"p99 {row['p99_ms']:.0f} ms"
        )

    record_figure(
        "load-script",
        load=(
            f"`bench/load.py --clients {CLIENTS} --seconds {SECONDS:g} --upload-share "
            f"{UPLOAD_SHARE:g} --points 1500` (own `serve`, 2 workers)"
        ),
        faults="none (load only)",
        inputs=(
            f"{kinds['total']['requests']} requests ({kinds['upload']['requests']} uploads, "
            f"{kinds['status']['requests']} status polls)"
        ),
        result=(
            f"{kinds['total']['errors']} errors; {describe('upload')}; {describe('status')}; "
            f"total {kinds['total']['throughput_per_s']:.0f} requests/s"
        ),
        figures=figures,
    )
