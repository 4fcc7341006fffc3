"""A pytest plugin: CPU seconds of each test, for finding what makes the suite slow.

Wall-clock durations (``--durations``) swing with the machine's load; CPU seconds do not.  Run
``CPU_PER_TEST=/tmp/cpu python -m pytest -p tests.helpers.cpu_per_test ...``: each process (each
xdist worker) writes ``/tmp/cpu.<worker>.json``, a list of ``[test id, CPU s, wall s]``.  CPU is
this process's and its reaped children's (``resource.getrusage``), so a subprocess the test ran
and waited for counts; a service thread's counts too.
"""

from __future__ import annotations

import json
import os
import resource
import time
from collections.abc import Iterator

import pytest

_RECORDS: list[tuple[str, float, float]] = []


def _cpu_seconds() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    """Time one test (setup, call and teardown)."""
    cpu, wall = _cpu_seconds(), time.monotonic()
    yield
    _RECORDS.append((item.nodeid, _cpu_seconds() - cpu, time.monotonic() - wall))


def pytest_sessionfinish(session: pytest.Session) -> None:
    """Write the records where ``CPU_PER_TEST`` says, one file a process."""
    prefix = os.environ.get("CPU_PER_TEST")
    if prefix:
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        with open(f"{prefix}.{worker}.json", "w") as handle:
            json.dump(_RECORDS, handle)
