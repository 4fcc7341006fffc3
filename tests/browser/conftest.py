"""Fixtures for the browser tests: Debian's Chromium through Selenium, and review data.

Chromium runs headless with software WebGL (SwiftShader), so the 3D view renders without a GPU.
Missing Chromium/chromedriver/selenium skips locally with the reason and fails in CI
(``SCANDIFF_REQUIRE_SERVICES=1``).  Screenshots go to ``test-artifacts/browser/`` (git-ignored);
``SCANDIFF_UPDATE_SCREENSHOTS=1`` also refreshes the small PNGs under ``docs/screenshots/``.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.conftest import PROJECT_ROOT, require
from tests.service_harness import ServiceProcess

ARTIFACTS_DIR = PROJECT_ROOT / "test-artifacts" / "browser"
DOCS_SCREENSHOTS_DIR = PROJECT_ROOT / "docs" / "screenshots"
CHROMIUM_CANDIDATES = ("chromium", "chromium-browser", "google-chrome")
FAILING_SCAN_NAME = "sensor-fault.pcd"
FAILING_SCAN_REASON = "simulated sensor fault for the browser test"
SCENE_POINTS = 8_000  # rays per synthetic scan: software WebGL stays fast


def find_chromium() -> tuple[str | None, str | None]:
    """Paths of the Chromium binary and of chromedriver, when installed."""
    browser = next((path for name in CHROMIUM_CANDIDATES if (path := shutil.which(name))), None)
    return browser, shutil.which("chromedriver")


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


@pytest.fixture
def chrome_factory(chromium: tuple[str, str]) -> Iterator[Callable[[], Any]]:
    """Start headless Chromium sessions (each with a fresh profile); all quit after the test."""
    from selenium import webdriver
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    browser, driver = chromium
    drivers: list[Any] = []
    profiles: list[str] = []

    def start() -> Any:
        profile = tempfile.mkdtemp(prefix="scandiff-chromium-")
        profiles.append(profile)
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
        ):
            options.add_argument(argument)
        session = webdriver.Chrome(options=options, service=Service(executable_path=driver))
        session.set_page_load_timeout(60)
        drivers.append(session)
        return session

    os.environ.setdefault("SE_AVOID_STATS", "true")
    yield start
    for session in drivers:
        with contextlib.suppress(Exception):
            session.quit()
    for profile in profiles:
        shutil.rmtree(profile, ignore_errors=True)


def save_screenshot(driver: Any, name: str, *, docs_name: str | None = None) -> Path:
    """Save a PNG of the window under test-artifacts (and docs/screenshots when asked)."""
    ARTIFACTS_DIR.mkdir(parents=True, exist_ok=True)
    path = ARTIFACTS_DIR / f"{name}.png"
    path.write_bytes(driver.get_screenshot_as_png())
    if docs_name and os.environ.get("SCANDIFF_UPDATE_SCREENSHOTS") == "1":
        write_small_png(path, DOCS_SCREENSHOTS_DIR / docs_name)
    return path


def write_small_png(source: Path, target: Path, max_bytes: int = 300_000) -> None:
    """A palette PNG of ``source`` under ``max_bytes`` (shrunk until it fits)."""
    from PIL import Image

    target.parent.mkdir(parents=True, exist_ok=True)
    image = Image.open(source).convert("RGB")
    width = image.width
    while True:
        scaled = (
            image
            if width == image.width
            else image.resize(
                (width, round(image.height * width / image.width)), Image.Resampling.LANCZOS
            )
        )
        scaled.quantize(colors=128, method=Image.Quantize.MEDIANCUT).save(target, optimize=True)
        if target.stat().st_size <= max_bytes or width < 400:
            return
        width = int(width * 0.85)


def write_pcd(path: Path, points: np.ndarray, sensor_origin: np.ndarray) -> Path:
    """A binary PCD of ``points`` (n, 3) whose VIEWPOINT is the sensor position, as a robot's."""
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\n"
        "SIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {len(points)}\nHEIGHT 1\n"
        f"VIEWPOINT {' '.join(repr(float(value)) for value in sensor_origin)} 1 0 0 0\n"
        f"POINTS {len(points)}\nDATA binary\n"
    )
    path.write_bytes(header.encode() + points.astype("<f4").tobytes())
    return path


@dataclass
class ScanFiles:
    """Synthetic reference and scan files of one place, with a changed object."""

    reference: Path
    scan: Path
    failing_scan: Path


@pytest.fixture(scope="session")
def scan_files(tmp_path_factory: pytest.TempPathFactory) -> ScanFiles:
    """A ray-cast rescan of two rooms with a box added and one removed (PCD with VIEWPOINT)."""
    from app.core.synthetic import raycast_scene

    pair = raycast_scene(
        n_points=SCENE_POINTS, change="mixed", pose_error=(0.02, 0.3), random_state=7
    )
    directory = tmp_path_factory.mktemp("scans")
    return ScanFiles(
        reference=write_pcd(
            directory / "reference-2024-05-01.pcd", pair.reference, pair.reference_origin
        ),
        scan=write_pcd(directory / "rescan-2024-06-01.pcd", pair.scan, pair.scan_origin),
        failing_scan=write_pcd(directory / FAILING_SCAN_NAME, pair.scan, pair.scan_origin),
    )


@dataclass
class ReviewService:
    """A running service and what the tests made in it."""

    process: ServiceProcess
    files: ScanFiles
    made: dict[str, Any] = field(default_factory=dict)

    @property
    def base_url(self) -> str:
        """``http://127.0.0.1:<port>``."""
        return self.process.base_url

    def client(self, token: str | None = None) -> Any:
        """An httpx client with a bearer token (the admin one by default)."""
        return self.process.client(token)

    def create_token(self, org: str, role: str = "writer") -> str:
        """A new token from ``scandiff token create``."""
        return self._token_command("create", "--org", org, "--role", role).splitlines()[-1]

    def revoke_token(self, token: str) -> None:
        """Revoke a token with ``scandiff token revoke``, the secret given on stdin."""
        self._token_command("revoke", "--token-secret-stdin", stdin=token + "\n")

    def _token_command(self, *arguments: str, stdin: str | None = None) -> str:
        """Run ``scandiff token ...`` on this server's data directory; its standard output."""
        import subprocess
        import sys

        completed = subprocess.run(
            [
                sys.executable,
                *("-m", "app", "token", *arguments),
                *("--data-dir", str(self.process.data_dir)),
            ],
            cwd=PROJECT_ROOT,
            input=stdin,
            capture_output=True,
            text=True,
            check=True,
            timeout=60,
        )
        return completed.stdout.strip()

    def finished_job(self) -> dict[str, Any]:
        """A succeeded comparison: the one the mouse test made, else one made over the API."""
        if "job" in self.made:
            return self.made["job"]
        with self.client() as client:
            site = client.post("/api/v1/sites", json={"name": "API-made site"})
            site.raise_for_status()
            site_id = site.json()["id"]
            for path, reference in ((self.files.reference, True), (self.files.scan, False)):
                answer = client.post(
                    f"/api/v1/sites/{site_id}/scans",
                    params={"reference": str(reference).lower(), "filename": path.name},
                    content=path.read_bytes(),
                    headers={"Content-Type": "application/octet-stream"},
                )
                assert answer.status_code in (201, 202), answer.text
            job = self.process.wait_for_job(client, answer.json()["job"]["id"], timeout=120)
            assert job["status"] == "succeeded", job
            regions = client.get(f"/api/v1/jobs/{job['id']}/regions").json()
        self.made["job"] = job
        self.made["regions"] = regions
        return job


@pytest.fixture(scope="module")
def review_service(
    tmp_path_factory: pytest.TempPathFactory, scan_files: ScanFiles
) -> Iterator[ReviewService]:
    """``scandiff serve`` with one worker; scans named like the failing one fail at once."""
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
        yield ReviewService(process, scan_files)
    finally:
        process.stop(timeout=20)


def wait_until(condition: Callable[[], Any], timeout: float, message: str) -> Any:
    """Poll ``condition`` until it returns something truthy; fail with ``message``."""
    deadline = time.monotonic() + timeout
    last: Any = None
    while time.monotonic() < deadline:
        try:
            last = condition()
        except Exception as exc:  # the page re-rendered under us (live updates): look again
            if type(exc).__name__ != "StaleElementReferenceException":
                raise
            last = None
        if last:
            return last
        time.sleep(0.2)
    raise AssertionError(f"{message} (after {timeout:.0f} s; last: {last!r})")
