"""``scandiff`` imports every subcommand unconditionally: its help lists them all."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parents[2]


def test_help_lists_every_subcommand() -> None:
    completed = subprocess.run(
        [sys.executable, "-m", "app", "--help"],
        cwd=PROJECT_ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    listed = {line.split()[0] for line in completed.stdout.splitlines() if line.startswith("    ")}
    assert {"compare", "serve", "token"} <= listed, completed.stdout
