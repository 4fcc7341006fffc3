"""The benchmark scripts use the public API only (issue 28): run as ``python -m bench.NAME``,
they edit no ``sys.path``, import nothing from ``tests`` and no private name of ``app``."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


def _is_private(dotted: str) -> bool:
    return any(part.startswith("_") and not part.startswith("__") for part in dotted.split("."))


def breaches(source: str) -> list[str]:
    """What in ``source`` reaches past the public API: sys.path edits, tests.*, app privates."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if (
            isinstance(node, ast.Attribute)
            and node.attr == "path"
            and isinstance(node.value, ast.Name)
            and node.value.id == "sys"
        ):
            found.append(f"line {node.lineno}: sys.path")
        modules: list[str] = []
        if isinstance(node, ast.Import):
            modules = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            modules = [f"{node.module}.{alias.name}" for alias in node.names]
        for module in modules:
            top = module.split(".")[0]
            if top == "tests" or (top == "app" and _is_private(module)):
                found.append(f"line {node.lineno}: {module}")
    return found


def test_bench_is_a_package_run_with_python_m() -> None:
    assert (BENCH / "__init__.py").is_file()


def test_no_bench_script_reaches_past_the_public_api() -> None:
    offenders = [
        f"{path.relative_to(BENCH.parent)} {breach}"
        for path in sorted(BENCH.rglob("*.py"))
        for breach in breaches(path.read_text())
    ]
    assert offenders == []


@pytest.mark.parametrize(
    "source",
    [
        "import sys\nsys.path.insert(0, '.')\n",
        "from tests.helpers.http import upload\n",
        "from app.core.origins.station_recovery import _subset\n",
        "import app.core._private\n",
    ],
)
def test_the_check_finds_each_breach(source: str) -> None:
    assert breaches(source)


def test_the_check_lets_public_imports_pass() -> None:
    assert breaches("import sys\nfrom app.core.pipeline import compare\nprint(sys.argv)\n") == []
