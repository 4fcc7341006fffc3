"""The project as the Dockerfile installs it: a wheel (not editable) in a fresh venv, run from
elsewhere, serves the dashboard (``static/`` ships inside the wheel as ``app/static``)."""

from __future__ import annotations

import shutil
import site
import subprocess
import sys
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from app.testing.network import free_port
from app.testing.paths import PROJECT_ROOT
from app.testing.waiting import wait_until
from tests.helpers.environment import c_compiler_found

BUILD_INPUTS = ("pyproject.toml", "setup.py", "README.md", "app", "static", "migrations")
"""What the Dockerfile copies into its build stage before ``pip wheel``."""

pytestmark = pytest.mark.slow  # builds a wheel in an isolated build env: about a minute


def build_wheel(workdir: Path) -> Path:
    """``pip wheel . --no-deps`` on a copy of the build inputs (the checkout stays clean)."""
    source = workdir / "source"
    source.mkdir()
    for name in BUILD_INPUTS:
        origin = PROJECT_ROOT / name
        if origin.is_dir():
            shutil.copytree(
                origin,
                source / name,
                symlinks=True,
                ignore=shutil.ignore_patterns("__pycache__", "*.so"),
            )
        else:
            shutil.copy2(origin, source / name)
    wheelhouse = workdir / "wheelhouse"
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w", wheelhouse, source],
        check=True,
        timeout=600,
    )
    (wheel,) = wheelhouse.glob("scandiff-*.whl")
    return wheel


def install_in_fresh_venv(wheel: Path, venv: Path) -> Path:
    """A venv holding ``wheel`` (not editable); its dependencies come from this interpreter's
    site-packages through a ``.pth`` line (offline, seconds), after the venv's own."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", venv], check=True, timeout=120)
    subprocess.run(
        [
            *(sys.executable, "-m", "pip", "--python", venv / "bin" / "python", "install"),
            *("--no-deps", "--quiet", wheel),
        ],
        check=True,
        timeout=300,
    )
    (site_packages,) = venv.glob("lib/python3.*/site-packages")
    dependencies = "\n".join(site.getsitepackages())
    (site_packages / "zz-test-dependencies.pth").write_text(dependencies + "\n")
    return venv / "bin"


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, Path]]:
    """The built wheel and the ``bin`` directory of a fresh venv it is installed in."""
    workdir = tmp_path_factory.mktemp("wheel")
    wheel = build_wheel(workdir)
    yield wheel, install_in_fresh_venv(wheel, workdir / "venv")


@pytest.mark.parametrize(
    ("directory", "suffixes"), [("static", None), ("migrations", (".py", ".mako"))]
)
def test_the_wheel_holds_every_dashboard_file_and_migration(installed, directory, suffixes):
    wheel, _ = installed
    with zipfile.ZipFile(wheel) as archive:
        shipped = {name for name in archive.namelist() if name.startswith(f"app/{directory}/")}
    expected = {
        f"app/{directory}/{path.relative_to(PROJECT_ROOT / directory).as_posix()}"
        for path in (PROJECT_ROOT / directory).rglob("*")
        if path.is_file()
        and "__pycache__" not in path.parts
        and (suffixes is None or path.suffix in suffixes)
    }
    assert expected, f"the checkout's {directory}/ is empty"
    assert shipped == expected


def _printed(bin_dir: Path, directory: Path, code: str) -> str:
    """What ``code`` prints, run by the installed venv's Python from ``directory``."""
    return subprocess.run(
        [bin_dir / "python", "-c", code],
        cwd=directory,
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    ).stdout.strip()


def test_the_installed_wheel_fits_planes_with_its_compiled_kernel(installed, tmp_path):
    """setup.py builds the plane-fit kernel into the wheel where a C compiler is."""
    if not c_compiler_found():
        pytest.skip("no C compiler: the wheel falls back to the numpy passes")
    _, bin_dir = installed
    located = _printed(
        bin_dir, tmp_path, "import app.core.localise.surface as s; print(s.PLANE_KERNEL)"
    )
    assert "_plane_kernel" in located and str(bin_dir.parent) in located, located


def test_the_installed_wheel_serves_the_dashboard_from_another_directory(installed, tmp_path):
    _, bin_dir = installed
    located = _printed(bin_dir, tmp_path, "import app.api.browser as b; print(b.STATIC_DIR)")
    assert Path(located).is_relative_to(bin_dir.parent), located  # not the checkout's static/

    port = free_port()
    log = (tmp_path / "serve.log").open("w")
    server = subprocess.Popen(
        [
            *(bin_dir / "scandiff", "serve", "--data-dir", tmp_path / "data"),
            *("--host", "127.0.0.1", "--port", str(port), "--workers", "1"),
        ],
        cwd=tmp_path,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    base_url = f"http://127.0.0.1:{port}"
    try:

        def serving() -> bool:
            assert server.poll() is None, (tmp_path / "serve.log").read_text()
            try:
                return httpx.get(f"{base_url}/api/v1/health", timeout=2).status_code == 200
            except httpx.TransportError:
                return False

        wait_until(serving, 120, "scandiff serve from the installed wheel answers", interval=0.2)
        for url_path, file_name in (("/", "index.html"), ("/static/main.js", "main.js")):
            response = httpx.get(base_url + url_path, timeout=10)
            assert response.status_code == 200, (url_path, response.text[:300])
            assert response.content == (PROJECT_ROOT / "static" / file_name).read_bytes()
    finally:
        server.terminate()
        server.wait(timeout=60)
        log.close()
