"""Browser-test helpers: where Chromium is, screenshots, the review service and its scans, an
API-only process and the TCP ports a process group listens on.

Screenshots go to ``test-artifacts/browser/`` (git-ignored); ``SCANDIFF_UPDATE_SCREENSHOTS=1``
also refreshes the small PNGs under ``docs/screenshots/``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from app.testing.paths import PROJECT_ROOT
from app.testing.service import ServiceProcess, process_group_members
from app.testing.waiting import wait_until
from tests.helpers.http import unique_name, upload

Value = TypeVar("Value")

ARTIFACTS_DIR = PROJECT_ROOT / "test-artifacts" / "browser"
DOCS_SCREENSHOTS_DIR = PROJECT_ROOT / "docs" / "screenshots"
CHROMIUM_CANDIDATES = ("chromium", "chromium-browser", "google-chrome")
FAILING_SCAN_NAME = "sensor-fault.pcd"
FAILING_SCAN_REASON = "simulated sensor fault for the browser test"
SCENE_POINTS = 8_000  # rays per synthetic scan: software WebGL stays fast
PAGE_POLL_SECONDS = 0.2


def find_chromium() -> tuple[str | None, str | None]:
    """Paths of the Chromium binary and of chromedriver, when installed."""
    browser = next((path for name in CHROMIUM_CANDIDATES if (path := shutil.which(name))), None)
    return browser, shutil.which("chromedriver")


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


def count_colour(png: bytes, colour: tuple[int, int, int], tolerance: int = 40) -> int:
    """Pixels of a screenshot within ``tolerance`` (per channel) of ``colour``."""
    import io

    import numpy as np
    from PIL import Image

    pixels = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)
    return int((np.abs(pixels - np.array(colour)).max(axis=2) <= tolerance).sum())


def view_scene(service: ReviewService, job_id: str) -> dict[str, Any]:
    """The server-side record of the job's 3D view (``/api/v1/jobs/{id}/view/scene``)."""
    with service.client() as client:
        answer = client.get(f"/api/v1/jobs/{job_id}/view/scene")
        answer.raise_for_status()
        return answer.json()


def dismiss_notifications(driver: Any) -> None:
    """Close viser's toasts (e.g. "software WebGL rendering detected") before a screenshot."""
    driver.execute_script(
        "document.querySelectorAll('.mantine-Notification-closeButton, "
        "[class*=Notification] button').forEach(b => b.click())"
    )


def wait_for_page(condition: Callable[[], Value], timeout: float, message: str) -> Value:
    """Poll ``condition`` every 0.2 s until it returns something truthy (a page that
    re-rendered under us, live updates, only means "look again"); that value."""
    return wait_until(
        condition,
        timeout,
        message,
        interval=PAGE_POLL_SECONDS,
        transient=("StaleElementReferenceException",),
    )


def by_css(driver: Any, selector: str, timeout: float = 30.0) -> Any:
    """The first element matching ``selector`` once it is displayed."""
    from selenium.webdriver.common.by import By

    return wait_for_page(
        lambda: next(
            (e for e in driver.find_elements(By.CSS_SELECTOR, selector) if e.is_displayed()), None
        ),
        timeout,
        f"no visible {selector!r} on {driver.current_url}",
    )


def retry(action: Any, timeout: float = 10.0) -> None:
    """Do ``action`` again while the live page replaces its elements under it."""
    wait_for_page(lambda: action() or True, timeout, "the page kept changing under the action")


def text_of(driver: Any, selector: str) -> str:
    """Text of every element matching ``selector``."""
    from selenium.webdriver.common.by import By

    return " ".join(element.text for element in driver.find_elements(By.CSS_SELECTOR, selector))


@dataclass
class ScanFiles:
    """Synthetic reference and scan files of one place, with a changed object."""

    reference: Path
    scan: Path
    failing_scan: Path


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
            site = client.post("/api/v1/sites", json={"name": unique_name("API-made site")})
            site.raise_for_status()
            site_id = site.json()["id"]
            for path, reference in ((self.files.reference, True), (self.files.scan, False)):
                answer = upload(
                    client, site_id, path.read_bytes(), filename=path.name, reference=reference
                )
                assert answer.status_code in (201, 202), answer.text
            job = self.process.wait_for_job(client, answer.json()["job"]["id"], timeout=120)
            assert job["status"] == "succeeded", job
            regions = client.get(
                f"/api/v1/jobs/{job['id']}/regions", params={"limit": 1000}
            ).json()["items"]
        self.made["job"] = job
        self.made["regions"] = regions
        return job


def _socket_inodes(pid: int) -> set[str]:
    """Inodes of the sockets process ``pid`` holds open (Linux /proc)."""
    inodes = set()
    fd_dir = Path(f"/proc/{pid}/fd")
    try:
        links = [os.readlink(entry) for entry in fd_dir.iterdir()]
    except OSError:
        return inodes
    for link in links:
        if link.startswith("socket:["):
            inodes.add(link[len("socket:[") : -1])
    return inodes


def listening_tcp_ports(process_group: int) -> set[int]:
    """TCP ports (IPv4 and IPv6) on which a process of ``process_group`` listens."""
    inodes = set().union(*(_socket_inodes(pid) for pid in process_group_members(process_group)))
    ports = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with open(table) as rows:
            next(rows)
            for row in rows:
                fields = row.split()
                local, state, inode = fields[1], fields[3], fields[9]
                if state == "0A" and inode in inodes:  # 0A: LISTEN
                    ports.add(int(local.rsplit(":", 1)[1], 16))
    return ports
