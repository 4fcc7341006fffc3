"""Private files written once: a secret readable by its owner only, durably and atomically.

The durable write itself (temporary file, fsync, rename, fsync of the directory) is the core's
:mod:`app.core.files`, which the core's exports use too; this module adds the owner-only mode and
the first-writer-wins creation the service's secret files need (:mod:`app.kit.signing`,
``scandiff serve``'s first token).
"""

from __future__ import annotations

import os
from pathlib import Path

from app.core.files import fsync_directory, temporary_path

__all__ = ["write_private_file"]


def write_private_file(path: Path, content: str, *, overwrite: bool) -> bool:
    """Write ``content`` to ``path`` readable by its owner only (0600), durably and atomically.

    With ``overwrite=False`` an existing ``path`` is kept (another process that got there first
    wins the race); returns whether ``path`` now holds ``content``.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    temp_path = temporary_path(path)
    descriptor = os.open(temp_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        with os.fdopen(descriptor, "w") as handle:
            handle.write(content)
            handle.flush()
            os.fsync(handle.fileno())
        if overwrite:
            os.replace(temp_path, path)
        else:
            try:
                os.link(temp_path, path)
            except FileExistsError:
                return False
    finally:
        temp_path.unlink(missing_ok=True)
    fsync_directory(path.parent)
    return True
