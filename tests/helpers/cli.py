"""``scandiff compare`` run as a user runs it: a child process of this interpreter."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path


def run_cli(*arguments: str | Path) -> subprocess.CompletedProcess[str]:
    """``python -m app compare ARGUMENTS``, its output captured as text."""
    return subprocess.run(
        [sys.executable, "-m", "app", "compare", *map(str, arguments)],
        capture_output=True,
        text=True,
        timeout=240,
    )
