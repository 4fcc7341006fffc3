"""The data directory's layout: every file the service keeps there, and the stored-path check.

One object, :class:`DataLayout`, names every place under ``data_dir`` (``settings.data_layout``
for the service's settings), so no other module joins ``data_dir`` with a name of its own::

    scandiff.sqlite3                 the database (when SCANDIFF_DATABASE_URL is unset)
    queue.sqlite3                    the Huey queue (when SCANDIFF_QUEUE_URL is unset)
    secret-key                       the signing key (when SCANDIFF_SECRET_KEY is unset)
    admin-token                      the first admin token ``scandiff serve`` printed
    token-revocations                counter that tells API processes to drop cached tokens
    run/                             doorbell and worker pid files of the running consumers
    run/worker-<pid>                 one a live job worker (app.jobs.consumer)
    tmp/<pid>-<random>.part          uploads being received
    uploads/                         resumable (tus) uploads' bytes between requests
    scans/<site_id>/<scan_id>.<fmt>  original bytes of every scan (path stored relative)
    scans/<site_id>/<scan_id>.geometry  a reference's cached k-NN geometry (app.jobs.geometry)
    results/<job_id>/labels.npz      per-point labels of a job (written by the job worker)
    results/<job_id>/details.npz     per-point distances of a job
    results/<job_id>/tiles/          a job localised tile by tile on several workers: its
                                     inputs (plan, context, the aligned points as .npy) and
                                     one result file per tile (app.jobs.tiles)

A path stored in the database (a scan's ``storage_path``, a job's ``labels_path``) is read back
with :meth:`DataLayout.resolve`, which refuses one that leads outside the data directory
(:class:`StoredPathError`), whether by ``..``, an absolute path or a symbolic link.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

__all__ = [
    "DETAILS_FILENAME",
    "LABELS_FILENAME",
    "WORKER_PID_PREFIX",
    "DataLayout",
    "StoredPathError",
]

LABELS_FILENAME = "labels.npz"
"""A job's per-point labels (the arrays of ``scandiff compare --labels``)."""
DETAILS_FILENAME = "details.npz"
"""A job's per-point distances (``reference_distance``, ``scan_distance``), next to its labels."""
WORKER_PID_PREFIX = "worker-"
"""A live job worker's file in :attr:`DataLayout.run_dir`: this prefix, then its pid."""


class StoredPathError(ValueError):
    """A path stored in the database leads outside the data directory."""


@dataclass(frozen=True)
class DataLayout:
    """Where each file of the service lives under ``root`` (the data directory, absolute)."""

    root: Path

    @property
    def database_file(self) -> Path:
        """The SQLite database used when no database URL is set."""
        return self.root / "scandiff.sqlite3"

    @property
    def queue_file(self) -> Path:
        """The Huey SQLite queue file used when no queue URL is set."""
        return self.root / "queue.sqlite3"

    @property
    def secret_key_file(self) -> Path:
        """The generated signing key (mode 0600)."""
        return self.root / "secret-key"

    @property
    def admin_token_file(self) -> Path:
        """The first admin token ``scandiff serve`` created (mode 0600)."""
        return self.root / "admin-token"

    @property
    def revocations_file(self) -> Path:
        """The token revocation counter shared by the API processes."""
        return self.root / "token-revocations"

    @property
    def run_dir(self) -> Path:
        """Files of the running consumers (doorbell, worker pids)."""
        return self.root / "run"

    def worker_pid_file(self, pid: int) -> Path:
        """The file job worker ``pid`` keeps while alive."""
        return self.run_dir / f"{WORKER_PID_PREFIX}{pid}"

    def worker_pid_files(self) -> dict[str, Path]:
        """The workers' pid files there are, by the text after the prefix (a pid, if sound)."""
        if not self.run_dir.is_dir():
            return {}
        return {
            path.name.removeprefix(WORKER_PID_PREFIX): path
            for path in self.run_dir.glob(f"{WORKER_PID_PREFIX}*")
        }

    @property
    def tmp_dir(self) -> Path:
        """Where uploads are streamed before the atomic rename (same filesystem as scans)."""
        return self.root / "tmp"

    @property
    def uploads_dir(self) -> Path:
        """Where resumable (tus) uploads keep their bytes between requests (kept on restart)."""
        return self.root / "uploads"

    @property
    def scans_dir(self) -> Path:
        """Where uploaded scan files are stored, one directory per site."""
        return self.root / "scans"

    @property
    def results_dir(self) -> Path:
        """Where the per-point files of jobs are stored, one directory per job."""
        return self.root / "results"

    def site_scans_dir(self, site_id: str) -> Path:
        """The directory holding a site's scan files."""
        return self.scans_dir / site_id

    def scan_storage_path(self, site_id: str, scan_id: str, file_format: str) -> str:
        """Where a scan's original bytes live, as stored: relative to the data directory."""
        return f"scans/{site_id}/{scan_id}.{file_format}"

    def job_results_dir(self, job_id: str) -> Path:
        """The directory of job ``job_id``'s per-point files."""
        return self.results_dir / job_id

    def job_tiles_dir(self, job_id: str) -> Path:
        """The directory of job ``job_id``'s tile inputs and tile results (a fanned-out job)."""
        return self.job_results_dir(job_id) / "tiles"

    def labels_file(self, job_id: str) -> Path:
        """Job ``job_id``'s per-point labels file."""
        return self.job_results_dir(job_id) / LABELS_FILENAME

    def stored_form(self, path: Path) -> str:
        """``path`` (under the data directory) as stored in the database: relative, POSIX."""
        return self._inside(path, str(path)).relative_to(self.root.resolve()).as_posix()

    def resolve(self, stored_path: str) -> Path:
        """The absolute path of a stored path; :class:`StoredPathError` if it leads outside.

        A relative path is taken from the data directory; an absolute one (older rows) must lie
        inside it too.  Symbolic links are followed before the check.
        """
        if "\x00" in stored_path:
            raise StoredPathError(f"stored path {stored_path!r} holds a NUL character")
        path = Path(stored_path)
        return self._inside(path if path.is_absolute() else self.root / path, stored_path)

    def _inside(self, path: Path, shown: str) -> Path:
        resolved = path.resolve()
        if not resolved.is_relative_to(self.root.resolve()):
            raise StoredPathError(f"stored path {shown!r} points outside the data directory")
        return resolved
