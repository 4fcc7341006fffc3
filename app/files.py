"""Durable file writes: write a temporary file, fsync it, rename it into place, fsync the directory.

One module for every layer that writes files a crash must not leave half-written: the job
worker's result files (:mod:`app.jobs.results`) and the service's uploads
(:mod:`app.services.storage`).  It imports nothing from ``app``, so any layer may use it.

A temporary file is named ``.<stem>.<random><TEMP_MARKER><suffix>`` next to its target, so a
sweep can recognise (and delete) what a killed writer left behind.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Callable
from pathlib import Path

TEMP_MARKER = ".tmp"
"""Part of the name of every temporary file :func:`write_atomically` writes."""


def fsync_directory(directory: Path) -> None:
    """Make a rename inside ``directory`` durable."""
    descriptor = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


def write_atomically(path: Path, write: Callable[[Path], None]) -> None:
    """Call ``write(temp_path)`` next to ``path``, fsync it, then rename it over ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    # Keep the suffix last: numpy appends ".npz" to names not ending with it.
    temp_path = path.with_name(f".{path.stem}.{uuid.uuid4().hex}{TEMP_MARKER}{path.suffix}")
    try:
        write(temp_path)
        with open(temp_path, "rb+") as written:
            os.fsync(written.fileno())
        os.replace(temp_path, path)
    finally:
        temp_path.unlink(missing_ok=True)
    fsync_directory(path.parent)
