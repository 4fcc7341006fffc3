"""Fixtures for the browser tests: Debian's Chromium through Selenium, and review data.

Chromium runs headless with software WebGL (SwiftShader), so the 3D view renders without a GPU.
Missing Chromium/chromedriver/selenium skips locally with the reason and fails in CI
(``SCANDIFF_REQUIRE_SERVICES=1``).  The helpers (screenshots, the review service) are in
:mod:`tests.helpers.browser`.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest

from app.testing.files import pcd_bytes
from app.testing.service import ServiceProcess
from tests.helpers.browser import (
    FAILING_SCAN_NAME,
    FAILING_SCAN_REASON,
    SCENE_POINTS,
    ReviewService,
    ScanFiles,
    find_chromium,
)
from tests.helpers.environment import require


@pytest.fixture(scope="session")
def chromium() -> tuple[str, str]:
    """Paths of Chromium and chromedriver; skips (locally) or fails (CI) when missing."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        require(False, "selenium is not installed (pip install -e '.[dev]')")
    browser, driver = find_chromium()
    require(
        browser is not None and driver is not None,
        "Chromium and chromedriver are not installed "
        "(apt-get install chromium chromium-driver; .ci/run does this)",
    )
    return str(browser), str(driver)


def reset_session(session: Any) -> None:
    """Bring a used session back to a fresh one's state: one blank tab, the default window
    size, no cookies (the only state the dashboard and the view keep), no cached files."""
    handles = session.window_handles
    for handle in handles[1:]:
        session.switch_to.window(handle)
        session.close()
    session.switch_to.window(handles[0])
    session.get("about:blank")
    session.execute_cdp_cmd("Network.clearBrowserCookies", {})
    session.execute_cdp_cmd("Network.clearBrowserCache", {})
    session.set_window_size(1280, 860)
    session.set_page_load_timeout(60)
    session.set_script_timeout(30)
    assert not session.get_cookies()


@dataclass
class ChromePool:
    """The browser tests' plain Chromium sessions by their extra flags, and their profiles."""

    sessions: dict[tuple[str, ...], list[Any]] = field(default_factory=dict)
    profiles: list[str] = field(default_factory=list)


@pytest.fixture(scope="package")
def chrome_pool(chromium: tuple[str, str]) -> Iterator[ChromePool]:
    """Chromium sessions reused from test to test and module to module of tests/browser
    (starting one costs seconds; each is reset to a fresh one's state after a test, and the
    dashboard keeps nothing but cookies); all quit after the package."""
    pool = ChromePool()
    yield pool
    for sessions in pool.sessions.values():
        for session in sessions:
            with contextlib.suppress(Exception):
                session.quit()
    for profile in pool.profiles:
        shutil.rmtree(profile, ignore_errors=True)


@pytest.fixture
def chrome_factory(
    chromium: tuple[str, str], chrome_pool: ChromePool
) -> Iterator[Callable[[], Any]]:
    """Headless Chromium sessions, as fresh ones: cookies cleared, one blank tab.

    The n-th session a test asks for with the same flags is the package's n-th such session,
    reset after each test (a test's sessions are distinct); sessions with the performance log
    are started for the test alone and quit after it.
    """
    from selenium import webdriver
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    browser, driver = chromium
    own: list[Any] = []
    profiles: list[str] = []
    used: dict[tuple[str, ...], int] = {}

    def launch(extra_arguments: tuple[str, ...], performance_log: bool, into: list[str]) -> Any:
        profile = tempfile.mkdtemp(prefix="scandiff-chromium-")
        into.append(profile)
        options = Options()
        options.binary_location = browser
        for argument in (
            "--headless=new",
            "--no-sandbox",
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
            "--disable-dev-shm-usage",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--no-first-run",
            "--window-size=1280,860",
            "--force-device-scale-factor=1",
            f"--user-data-dir={profile}",
            *extra_arguments,
        ):
            options.add_argument(argument)
        if performance_log:
            options.set_capability("goog:loggingPrefs", {"performance": "ALL"})
        session = webdriver.Chrome(options=options, service=Service(executable_path=driver))
        session.set_page_load_timeout(60)
        return session

    def start(*extra_arguments: str, performance_log: bool = False) -> Any:
        """A session; ``extra_arguments`` are more Chromium flags (e.g. a network block);
        ``performance_log`` records DevTools network events (``session.get_log("performance")``).
        """
        if performance_log:
            session = launch(extra_arguments, performance_log, profiles)
            own.append(session)
            return session
        sessions = chrome_pool.sessions.setdefault(extra_arguments, [])
        index = used.get(extra_arguments, 0)
        used[extra_arguments] = index + 1
        if index == len(sessions):
            sessions.append(launch(extra_arguments, performance_log, chrome_pool.profiles))
        return sessions[index]

    os.environ.setdefault("SE_AVOID_STATS", "true")
    yield start
    for session in own:
        with contextlib.suppress(Exception):
            session.quit()
    for arguments, count in used.items():
        sessions = chrome_pool.sessions[arguments]
        for session in list(sessions[:count]):
            try:
                reset_session(session)
            except Exception:  # a session the test broke: started again when next asked for
                sessions.remove(session)
                with contextlib.suppress(Exception):
                    session.quit()
    for profile in profiles:
        shutil.rmtree(profile, ignore_errors=True)


@pytest.fixture(scope="session")
def scan_files(tmp_path_factory: pytest.TempPathFactory) -> ScanFiles:
    """A ray-cast rescan of two rooms with a box added and one removed (PCD with VIEWPOINT)."""
    from app.core.datasets.scenes import raycast_scene

    pair = raycast_scene(
        n_points=SCENE_POINTS, change="mixed", pose_error=(0.02, 0.3), random_state=7
    )
    directory = tmp_path_factory.mktemp("scans")
    files = {
        "reference-2024-05-01.pcd": pcd_bytes(
            pair.reference, viewpoint=(*pair.reference_origin, 1, 0, 0, 0)
        ),
        "rescan-2024-06-01.pcd": pcd_bytes(pair.scan, viewpoint=(*pair.scan_origin, 1, 0, 0, 0)),
    }
    files[FAILING_SCAN_NAME] = files["rescan-2024-06-01.pcd"]
    for name, content in files.items():
        (directory / name).write_bytes(content)
    return ScanFiles(
        reference=directory / "reference-2024-05-01.pcd",
        scan=directory / "rescan-2024-06-01.pcd",
        failing_scan=directory / FAILING_SCAN_NAME,
    )


@pytest.fixture(scope="session")
def review_process(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """``scandiff serve`` with one worker; scans named like the failing one fail at once.

    One for the session (starting one costs seconds): each module makes its own sites and jobs
    through :func:`review_service`, so modules do not read each other's.
    """
    hooks = json.dumps({"scan_filename": FAILING_SCAN_NAME, "raise_error": FAILING_SCAN_REASON})
    process = ServiceProcess(
        tmp_path_factory.mktemp("service") / "data",
        workers=1,
        env={
            "SCANDIFF_TEST_JOB_HOOKS": hooks,
            "SCANDIFF_JOB_MAX_ATTEMPTS": "1",
            "SCANDIFF_VIEW_LINK_TTL_SECONDS": "3600",
        },
    )
    process.start()
    try:
        yield process
    finally:
        process.kill()  # no graceful stop to wait for: nothing here checks it


@pytest.fixture(scope="module")
def review_service(review_process: ServiceProcess, scan_files: ScanFiles) -> ReviewService:
    """The review service with an empty record of what this module's tests made."""
    return ReviewService(review_process, scan_files)
