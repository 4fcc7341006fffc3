"""The app is built from every router, unconditionally: the API's, the browser's and the 3D
view's (a router the API builds for the viewer), with the dashboard's files through StaticFiles,
the viewer's settings and the API's error shape."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError

from app.config import Settings
from app.main import create_app
from app.testing.paths import PROJECT_ROOT
from app.viewer.routes import new_viewer_manager


@pytest.fixture
def client(tmp_path) -> Iterator[TestClient]:
    """An in-process client of a fresh app (nothing in its database is needed here)."""
    with TestClient(create_app(Settings(data_dir=tmp_path / "data"))) as test_client:
        yield test_client


def test_the_app_has_the_api_browser_and_viewer_routes(client: TestClient) -> None:
    app = client.app
    paths = set(app.openapi()["paths"])  # type: ignore[attr-defined]
    assert {
        "/api/v1/sites",
        "/api/v1/session",
        "/api/v1/jobs/{job_id}/view-link",
        "/api/v1/jobs/{job_id}/view/scene",
    } <= paths
    assert app.url_path_for("job_view", job_id="abc") == "/jobs/abc/view"  # type: ignore[attr-defined]
    assert app.url_path_for("static", path="main.js") == "/static/main.js"  # type: ignore[attr-defined]


def test_dashboard_files_are_served_revalidated_and_a_missing_one_is_the_api_404(
    client: TestClient,
) -> None:
    for path in ("/", "/static/index.html", "/static/main.js", "/static/style.css"):
        response = client.get(path)
        assert response.status_code == 200, path
        assert response.headers["cache-control"] == "no-cache", path
    # The dashboard is ES modules: a browser runs them only with a JavaScript MIME type.
    for module in ("main.js", "api.js", "dom.js", "timeline.js"):
        assert "javascript" in client.get(f"/static/{module}").headers["content-type"], module
    missing = client.get("/static/no-such-file.js")
    assert missing.status_code == 404
    assert missing.json()["error"] == "not_found"
    assert client.get("/static/../pyproject.toml").status_code == 404


def test_session_errors_have_the_api_shape(client: TestClient) -> None:
    signed_out = client.get("/api/v1/session")
    assert signed_out.status_code == 401
    assert signed_out.json()["error"] == "unauthorized"
    assert signed_out.headers["www-authenticate"] == "Bearer"
    client.cookies.set("scandiff_session", "forged.value")
    ended = client.get("/api/v1/session")
    assert ended.status_code == 401
    assert ended.json()["error"] == "session_ended"
    client.cookies.clear()
    cross_site = client.post(
        "/api/v1/session", json={"token": "sdt_x"}, headers={"Origin": "http://evil.example"}
    )
    assert cross_site.status_code == 403
    assert cross_site.json()["error"] == "forbidden"


def test_the_viewer_settings_are_read_validated_and_used(monkeypatch, tmp_path) -> None:
    monkeypatch.setenv("SCANDIFF_VIEWER_POINT_BUDGET", "2500")
    monkeypatch.setenv("SCANDIFF_VIEWER_IDLE_SECONDS", "7.5")
    settings = Settings(data_dir=tmp_path)
    assert (settings.viewer_point_budget, settings.viewer_idle_seconds) == (2500, 7.5)
    manager = new_viewer_manager(settings)
    assert manager.idle_seconds == 7.5
    assert manager.loader.keywords == {"point_budget": 2500}  # type: ignore[attr-defined]
    for name, value in (("viewer_point_budget", 0), ("viewer_idle_seconds", float("inf"))):
        with pytest.raises(ValidationError, match=name):
            Settings(data_dir=tmp_path, **{name: value})


def test_the_viewer_loads_without_the_api() -> None:
    code = (
        "import sys, app.viewer.routes, app.viewer.access\n"
        "print(sorted(name for name in sys.modules if name.startswith('app.api')))\n"
    )
    completed = subprocess.run(
        [sys.executable, "-c", code], cwd=PROJECT_ROOT, capture_output=True, text=True, check=True
    )
    assert completed.stdout.strip() == "[]"
