"""Where the project checkout and its shared data are."""

from __future__ import annotations

import os
from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parent.parent.parent
"""The checkout holding ``app/`` (child processes start here; the docs are read from here)."""


def shared_data_dir() -> Path:
    """Where ../shared/data lives (override with SCANDIFF_SHARED_DATA)."""
    configured = os.environ.get("SCANDIFF_SHARED_DATA")
    if configured:
        return Path(configured)
    return PROJECT_ROOT.parent / "shared" / "data"
