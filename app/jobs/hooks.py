"""The one seam through which tests reach into a job run: :data:`job_hooks`.

A job run asks :data:`job_hooks` for three things, and nothing else in ``app`` knows about tests:

* :meth:`JobHooks.comparison`: the function that compares two clouds.  It is
  :func:`app.core.tiling.compare.compare_within_budget` (:func:`app.core.pipeline.compare`,
  in tiles when the pair does not fit the worker's memory budget) unless a test set
  :attr:`JobHooks.compare` to a stand-in (``app/testing/fake_pipeline.py`` installs a
  fast, deterministic one, in-process or in a consumer it starts);
* :meth:`JobHooks.inject_faults`: faults described by the JSON object in env
  ``SCANDIFF_TEST_JOB_HOOKS`` (an environment variable, so that it reaches the workers of a
  ``scandiff serve`` a test starts).  Honoured only when ``SCANDIFF_TESTING=1``, which the test
  harness sets and production never does.

Filters: ``scan_filename`` (only jobs whose scan has that filename), ``on_attempts`` (list of
attempt numbers).  Actions, in this order: ``sleep_seconds`` (sleep while heart-beating, stage
``testing-sleep``), ``allocate_bytes`` (allocate that much: hits the memory cap),
``kill_worker`` (SIGKILL this worker process: a crash), ``raise_error`` (raise ``RuntimeError``
with that message: a transient failure).

* :meth:`JobHooks.in_tile`: in a job compared tile by tile (:mod:`app.jobs.tiles`), once a
  worker claimed a tile: ``tile_sleep_seconds`` (every worker, every tile) and ``kill_in_tile``
  (N: the job's own worker SIGKILLs itself in the tile after storing N tiles).
* :meth:`JobHooks.in_crop_pass`: in a streamed job's crop pass (:mod:`app.jobs.crop_passes`),
  once a worker claimed it: ``crop_pass_sleep_seconds`` (every worker, every pass) and
  ``kill_in_crop_pass`` (``"helper"``: a worker running a pass from its queue message
  SIGKILLs itself there; ``"parent"``: the job's own worker does, ``on_attempts`` filtering).
* :meth:`JobHooks.free_disk`: the free disk a streamed job checks its files against; the
  figure ``free_disk_bytes`` when given.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from app.jobs.leases import PROGRESS_LOADED, ClaimedJob, LeaseKeeper, job_log

logger = logging.getLogger("scandiff.jobs")

TESTING_ENV = "SCANDIFF_TESTING"
TEST_HOOKS_ENV = "SCANDIFF_TEST_JOB_HOOKS"


def testing_enabled() -> bool:
    """Whether test hooks are honoured (env ``SCANDIFF_TESTING=1``; never set in production)."""
    return os.environ.get(TESTING_ENV) == "1"


@dataclass
class JobHooks:
    """What a job run takes from tests: a stand-in comparison and injected faults."""

    compare: Callable[..., Any] | None = None
    """Used instead of :func:`app.core.pipeline.compare` when set (tests only)."""

    def comparison(self) -> Callable[..., Any]:
        """The function a job compares its two clouds with."""
        if self.compare is not None:
            return self.compare
        # Imported on first use, not with this module: the API process imports the jobs package
        # to enqueue jobs and must stay small, without scipy, scikit-learn and POT (~4 s to
        # import).  The consumer calls this before forking, so its workers start with it loaded.
        from app.core.tiling.compare import compare_within_budget

        return compare_within_budget

    def faults_for(self, job: ClaimedJob) -> dict[str, Any]:
        """The faults to inject into ``job`` (none unless ``SCANDIFF_TESTING=1``)."""
        raw = os.environ.get(TEST_HOOKS_ENV)
        if not raw:
            return {}
        if not testing_enabled():
            logger.warning(
                f"{TEST_HOOKS_ENV} is set but {TESTING_ENV} is not 1; ignoring the test hooks",
                extra={"job_id": job.id, "stage": "claimed"},
            )
            return {}
        faults = json.loads(raw)
        if "scan_filename" in faults and faults["scan_filename"] != job.scan_filename:
            return {}
        on_attempts = faults.get("on_attempts")
        if on_attempts is not None and job.attempt not in on_attempts:
            return {}
        return dict(faults)

    def inject_faults(self, job: ClaimedJob, keeper: LeaseKeeper) -> None:
        """Act out the faults of :meth:`faults_for` (see the module docstring), in order."""
        faults = self.faults_for(job)
        if not faults:
            return
        sleep_seconds = float(faults.get("sleep_seconds", 0.0))
        if sleep_seconds > 0:
            deadline = time.monotonic() + sleep_seconds
            while (remaining := deadline - time.monotonic()) > 0:
                keeper.report("testing-sleep", PROGRESS_LOADED * (1 - remaining / sleep_seconds))
                time.sleep(min(0.05, remaining))
        if faults.get("allocate_bytes"):
            ballast = np.ones(int(faults["allocate_bytes"]), dtype=np.uint8)
            del ballast
        if faults.get("kill_worker"):
            job_log("test hook: killing this worker", job.id, "testing-kill", attempt=job.attempt)
            logging.shutdown()
            os.kill(os.getpid(), signal.SIGKILL)
        if faults.get("raise_error"):
            raise RuntimeError(str(faults["raise_error"]))

    def in_tile(self, job: ClaimedJob | None, tiles_done_here: int) -> None:
        """Act out the tile faults once a worker claimed a tile: ``tile_sleep_seconds`` (every
        worker), and ``kill_in_tile: N`` (the job's own worker kills itself in its tile after
        storing N tiles, so that a claimed tile is left running)."""
        faults = self.faults_for(job) if job is not None else self.process_faults()
        if not faults:
            return
        time.sleep(float(faults.get("tile_sleep_seconds", 0.0)))
        kill_after = faults.get("kill_in_tile")
        if job is not None and kill_after is not None and tiles_done_here >= int(kill_after):
            job_log("test hook: killing this worker in a tile", job.id, "testing-kill")
            logging.shutdown()
            os.kill(os.getpid(), signal.SIGKILL)

    def in_crop_pass(self, job: ClaimedJob | None, pass_index: int) -> None:
        """Act out the crop pass faults once a worker claimed pass ``pass_index`` of a job
        (``job``: the job's own worker; None: a worker that took the pass's message)."""
        faults = self.faults_for(job) if job is not None else self.process_faults()
        if not faults:
            return
        time.sleep(float(faults.get("crop_pass_sleep_seconds", 0.0)))
        who = "parent" if job is not None else "helper"
        if faults.get("kill_in_crop_pass") == who:
            logger.info(
                "test hook: killing this worker in crop pass %d",
                pass_index,
                extra={"stage": "testing-kill"},
            )
            logging.shutdown()
            os.kill(os.getpid(), signal.SIGKILL)

    def free_disk(self, directory: Path) -> int:
        """Free bytes of the disk under ``directory``, or the figure ``free_disk_bytes`` of the
        faults (tests only: a disk too small without filling one)."""
        faults = self.process_faults()
        if "free_disk_bytes" in faults:
            return int(faults["free_disk_bytes"])
        from app.core.tiling.disk import free_disk_bytes  # the worker's import, not the API's

        return free_disk_bytes(directory)

    def process_faults(self) -> dict[str, Any]:
        """The faults of this process's environment that concern every job (tests only)."""
        raw = os.environ.get(TEST_HOOKS_ENV)
        return dict(json.loads(raw)) if raw and testing_enabled() else {}


job_hooks = JobHooks()
"""This process's job hooks (the only instance)."""
