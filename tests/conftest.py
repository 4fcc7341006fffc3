"""Fixtures shared by every test directory: the real data, and ``scandiff serve`` subprocesses.

The skip policy for missing dependencies is :func:`tests.helpers.environment.require`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import pytest

from app.testing.service import ServiceProcess
from tests.helpers.environment import require, shared_data_dir


@pytest.fixture
def real_data_dir() -> Path:
    """The real third-party scans; skips where ../shared/data is absent (as on a user's machine)."""
    path = shared_data_dir() / "real"
    require(path.is_dir(), f"real point-cloud data not found at {path}")
    return path


@pytest.fixture
def service_factory(tmp_path: Path) -> Iterator[Callable[..., ServiceProcess]]:
    """Make started services (``service_factory(workers=2, env={...})``); all killed after.

    Killed, not stopped: a graceful stop waits seconds for idle workers, and the tests that check
    it call ``stop()`` themselves (tests/jobs/test_serve.py).
    """
    started: list[ServiceProcess] = []

    def make(
        *,
        workers: int = 1,
        env: Mapping[str, str] | None = None,
        data_dir: str | Path | None = None,
        start: bool = True,
        **kwargs: Any,
    ) -> ServiceProcess:
        directory = Path(data_dir) if data_dir else tmp_path / f"service{len(started)}"
        service = ServiceProcess(directory, workers=workers, env=env, **kwargs)
        started.append(service)
        return service.start() if start else service

    yield make
    for service in started:
        service.kill()


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """In an xdist process, order the tests longest file first (tests/helpers/heavy_first.py):
    ``make test``'s processes then take the long files first instead of last."""
    if hasattr(config, "workerinput"):
        from tests.helpers.heavy_first import order_longest_first

        order_longest_first(items)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """``--dist loadfile``: the longest files first, tests/browser as one unit."""
    if config.getvalue("dist") != "loadfile":
        return None
    from tests.helpers.heavy_first import LongestFirstScheduling

    return LongestFirstScheduling(config, log)
