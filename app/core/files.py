"""Durable file writes: write a temporary file, fsync it, rename it into place, fsync the directory.

One module for everything that writes files a crash must not leave half-written: the core's
exports (:mod:`app.core.formats`), the job worker's result files (:mod:`app.jobs.results`) and
the service's uploads (:mod:`app.services.storage`); the service's secret files
(:func:`app.kit.files.write_private_file`) use its temporary names.  It uses only the standard
library, so it works from a notebook like the rest of the core.

A temporary file is named ``.<stem>.<random><TEMP_MARKER><suffix>`` next to its target, so a
sweep can recognise (and delete) what a killed writer left behind.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
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


def temporary_path(path: Path) -> Path:
    """A fresh temporary name next to ``path`` that a sweep recognises by :data:`TEMP_MARKER`."""
    # Keep the suffix last: numpy appends ".npz" to names not ending with it.
    return path.with_name(f".{path.stem}.{uuid.uuid4().hex}{TEMP_MARKER}{path.suffix}")


@contextmanager
def atomic_output(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; fsync it and rename it over ``path`` on success.

    Readers never see a half-written file, and a failed write leaves no debris.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    temp_path = temporary_path(target)
    try:
        yield temp_path
        with open(temp_path, "rb+") as written:
            os.fsync(written.fileno())
        os.replace(temp_path, target)
    finally:
        temp_path.unlink(missing_ok=True)
    fsync_directory(target.parent)


def write_atomically(path: Path, write: Callable[[Path], None]) -> None:
    """Call ``write(temp_path)`` next to ``path``, fsync it, then rename it over ``path``."""
    with atomic_output(path) as temp_path:
        write(temp_path)
