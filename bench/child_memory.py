"""Run a bench module's ``--child`` mode in a fresh interpreter and read back its peak RSS.

The child prints one JSON object with ``peak_rss_kb`` (its ``VmHWM``) and
``rss_after_imports_kb``; a fresh interpreter is the only way to measure a reader's memory
without the parent's (a forked child's ``ru_maxrss`` starts at the parent's size).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys


def measure_child(module: str, *arguments: str) -> dict:
    """``python -m module --child *arguments``'s JSON output plus ``peak_rss_mb`` and
    ``growth_mb`` (peak minus the RSS after imports), in MB."""
    process = subprocess.Popen(
        [sys.executable, "-m", module, "--child", *arguments],
        stdout=subprocess.PIPE,
        env={**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS") or "1"},
    )
    assert process.stdout is not None
    output = process.stdout.read()
    if process.wait() != 0:
        raise RuntimeError(f"the child {module} {' '.join(arguments)} failed")
    result = json.loads(output)
    result["peak_rss_mb"] = result["peak_rss_kb"] / 1024.0
    result["growth_mb"] = (result["peak_rss_kb"] - result["rss_after_imports_kb"]) / 1024.0
    return result
