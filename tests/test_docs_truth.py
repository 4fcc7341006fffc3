"""The docs name only things that exist (issue 31): every code path, module path, setting, CLI
flag and API path named in ``docs/*.md`` and ``README.md`` is checked against the code.

* code paths (``app/...py``, ``bench/...py``, ``tests/...py``, ``static/...js``...): the file
  exists in the repository;
* module paths (``app.services.schedules.runs.tick``): the module imports and the rest are
  attributes of it;
* settings (``SCANDIFF_*``): a field of :class:`app.config.Settings`, or a variable the code,
  tests or deployment files read (``SCANDIFF_TESTING``, ``SCANDIFF_REQUIRE_SERVICES``...);
* CLI flags: in a ``scandiff <command> ...`` line, each ``--flag`` is an option of that command's
  parser; a flag quoted alone (```--sensor-origin```) is an option of some ``scandiff``
  command, or of a ``bench/`` or test script that the docs run;
* API paths (``/api/v1/...``): a route of the FastAPI app (``{id}`` segments match any value).
"""

from __future__ import annotations

import argparse
import importlib
import re
import shutil
import tempfile
from collections.abc import Iterator
from functools import cache
from pathlib import Path

import pytest

from app.cli import build_parser
from app.config import Settings
from app.main import create_app
from app.testing.paths import PROJECT_ROOT

DOCUMENTS = [*sorted((PROJECT_ROOT / "docs").glob("*.md")), PROJECT_ROOT / "README.md"]
CODE_PATH = re.compile(
    r"(?<![\w./-])((?:app|bench|tests|static|migrations|docs)/[\w./-]*\.(?:py|json|js|css|html|md)(?!\w))"
)
MODULE_PATH = re.compile(r"(?<![\w./-])(app(?:\.[A-Za-z_]\w*)+)")
SETTING = re.compile(r"\bSCANDIFF_[A-Z0-9_]*[A-Z0-9](?![A-Z0-9_]*\*)")
API_PATH = re.compile(r"/api/v1(?:/[\w{}.:-]+)*/?")
INLINE_CODE = re.compile(r"`([^`\n]+)`")
FLAG = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")
COMMAND = re.compile(r"(?:^|[\s`$(])(?:scandiff|python -m app)\s+([a-z][a-z-]*)((?:[^`\n|;&])*)")

SEARCHED_FOR_NAMES = (
    "app",
    "tests",
    "bench",
    ".ci",
    "Makefile",
    "docker-compose.yml",
    "Dockerfile",
)
"""Where a ``SCANDIFF_*`` name that is no setting may be read (test and deployment switches)."""


def document_lines() -> Iterator[tuple[Path, int, str]]:
    """Every line of every document, with its file and line number."""
    for path in DOCUMENTS:
        for number, line in enumerate(path.read_text().splitlines(), start=1):
            yield path, number, line


def code_texts() -> Iterator[tuple[Path, int, str]]:
    """The code of every document: lines of fenced blocks, and inline code spans."""
    for path in DOCUMENTS:
        fenced = False
        for number, line in enumerate(path.read_text().splitlines(), start=1):
            if line.lstrip().startswith("```"):
                fenced = not fenced
                continue
            if fenced:
                yield path, number, line
            else:
                for span in INLINE_CODE.findall(line):
                    yield path, number, span


def where(path: Path, number: int) -> str:
    return f"{path.relative_to(PROJECT_ROOT)}:{number}"


@cache
def source_text() -> str:
    """The text of the code, tests and deployment files (for names read outside Settings)."""
    parts: list[str] = []
    for name in SEARCHED_FOR_NAMES:
        root = PROJECT_ROOT / name
        files = [root] if root.is_file() else [p for p in root.rglob("*") if p.is_file()]
        for file in files:
            if file.suffix in {".py", ".sh", ".yml", ".yaml", ""} or file.name == "Makefile":
                try:
                    parts.append(file.read_text(errors="replace"))
                except OSError:
                    continue
    return "\n".join(parts)


def test_every_code_path_named_in_the_docs_exists() -> None:
    missing = [
        f"{where(path, number)}: {found}"
        for path, number, line in document_lines()
        for found in CODE_PATH.findall(line)
        if not (PROJECT_ROOT / found).exists()
    ]
    assert not missing, "\n".join(missing)


PACKAGE_PATH = re.compile(r"`((?:[a-z_]+/)+[a-z_0-9]+\.py)`")
"""A path given within a package the text is about (```localise/gaps.py```)."""


def test_every_path_within_a_package_named_in_the_docs_exists() -> None:
    """A path such as ``localise/gaps.py`` (not from the repository's root) ends some file."""
    files = {
        path.relative_to(PROJECT_ROOT).as_posix()
        for root in ("app", "bench", "tests")
        for path in (PROJECT_ROOT / root).rglob("*.py")
    }
    missing = [
        f"{where(path, number)}: {found}"
        for path, number, line in document_lines()
        for found in PACKAGE_PATH.findall(line)
        if not CODE_PATH.fullmatch(found)
        and found not in files
        and not any(file.endswith("/" + found) for file in files)
    ]
    assert not missing, "\n".join(missing)


def resolves(dotted: str) -> bool:
    """Whether ``dotted`` is a module, or attributes of the longest importable module in it."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            target: object = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        for attribute in parts[cut:]:
            if not hasattr(target, attribute):
                return False
            target = getattr(target, attribute)
        return True
    return False


def test_every_module_path_named_in_the_docs_imports() -> None:
    missing = []
    for path, number, line in document_lines():
        for span in INLINE_CODE.findall(line):
            for found in MODULE_PATH.findall(span):
                dotted = found.rstrip(".")
                if dotted.endswith((".py", ".js")) or not resolves(dotted):
                    missing.append(f"{where(path, number)}: {dotted}")
    assert not missing, "\n".join(missing)


def test_every_setting_named_in_the_docs_exists() -> None:
    settings = {f"SCANDIFF_{name.upper()}" for name in Settings.model_fields}
    missing = [
        f"{where(path, number)}: {found}"
        for path, number, line in document_lines()
        for found in SETTING.findall(line)
        if found not in settings and not re.search(rf"\b{found}\b", source_text())
    ]
    assert not missing, "\n".join(missing)


def parser_flags(parser: argparse.ArgumentParser) -> set[str]:
    """The long options of ``parser``."""
    return {
        option
        for action in parser._actions
        for option in action.option_strings
        if option.startswith("--")
    }


@cache
def command_flags() -> dict[str, set[str]]:
    """Each ``scandiff`` command's long options, with the nested commands' under ``a b``."""
    flags: dict[str, set[str]] = {}

    def walk(prefix: str, parser: argparse.ArgumentParser) -> None:
        flags[prefix] = parser_flags(parser) | flags.get(prefix.split(" ")[0], set())
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, child in action.choices.items():
                    walk(f"{prefix} {name}".strip(), child)

    walk("", build_parser())
    return flags


@cache
def script_flags() -> set[str]:
    """Long options the bench and test scripts define (``"--flag"`` in their source)."""
    found: set[str] = set()
    for root in ("bench", "tests", "app"):
        for file in (PROJECT_ROOT / root).rglob("*.py"):
            found.update(re.findall(r"[\"'](--[a-z][a-z0-9-]*)[\"']", file.read_text()))
    return found


EXTERNAL_FLAGS = {
    # pytest, pip, docker compose, uvicorn, curl and other tools the docs show
    "--durations",
    "--build",
    "--scale",
    "--factory",
    "--host",
    "--port",
    "--header",
    "--data-binary",
    "--no-access-log",
    "--upgrade",
    "--editable",
    "--help",
}


def test_every_cli_flag_named_in_the_docs_exists() -> None:
    flags = command_flags()
    every_flag = set().union(*flags.values())
    missing = []
    for path, number, line in code_texts():
        for command, rest in COMMAND.findall(line):
            words = rest.split()
            name = command
            if words and f"{command} {words[0]}" in flags:
                name = f"{command} {words[0]}"
            if name not in flags:
                missing.append(f"{where(path, number)}: scandiff {command} (no such command)")
                continue
            for flag in FLAG.findall(rest):
                if flag not in flags[name]:
                    missing.append(f"{where(path, number)}: scandiff {name} {flag}")
        for span in [line]:
            alone = re.fullmatch(r"(--[a-z][a-z0-9-]*)(?:[ =].*)?", span.strip())
            if alone is None:
                continue
            flag = alone.group(1)
            if flag not in every_flag | script_flags() | EXTERNAL_FLAGS:
                missing.append(f"{where(path, number)}: {flag}")
    assert not missing, "\n".join(missing)


@cache
def route_patterns() -> list[re.Pattern[str]]:
    """A pattern per API path of the app's OpenAPI schema (``{param}`` matches one segment)."""
    data_dir = Path(tempfile.mkdtemp(prefix="docs-truth-"))
    try:
        paths = create_app(Settings(data_dir=data_dir)).openapi()["paths"]
    finally:
        shutil.rmtree(data_dir, ignore_errors=True)
    return [
        re.compile(re.sub(r"\\\{[^/]+?\\\}", "[^/]+", re.escape(path.rstrip("/"))))
        for path in paths
        if path.startswith("/api/v1")
    ]


def test_every_api_path_named_in_the_docs_is_a_route() -> None:
    missing = []
    for path, number, line in document_lines():
        for found in API_PATH.findall(line):
            candidate = found.rstrip("/.:")
            if candidate in ("/api/v1",):
                continue
            if not any(pattern.fullmatch(candidate) for pattern in route_patterns()):
                missing.append(f"{where(path, number)}: {candidate}")
    assert not missing, "\n".join(missing)


@pytest.mark.parametrize(
    ("text", "found"),
    [
        ("see `app/services/nowhere.py`", "app/services/nowhere.py"),
        ("run `bench/nothing_here.py --fast`", "bench/nothing_here.py"),
        ("the table `tests/no_such_table.json`", "tests/no_such_table.json"),
    ],
)
def test_the_code_path_check_catches_a_missing_file(text: str, found: str) -> None:
    assert CODE_PATH.findall(text) == [found]
    assert not (PROJECT_ROOT / found).exists()


def test_the_package_path_check_catches_a_renamed_module() -> None:
    assert PACKAGE_PATH.findall("see `localise/stations.py` and `origins/apex.py`") == [
        "localise/stations.py",
        "origins/apex.py",
    ]
    assert not list((PROJECT_ROOT / "app").rglob("localise/stations.py"))


def test_the_checks_catch_made_up_names() -> None:
    assert not resolves("app.services.schedules.runs.no_such_function")
    assert resolves("app.services.schedules.runs.tick")
    assert "--no-such-flag" not in command_flags()["compare"]
    assert "--sensor-origin" in command_flags()["compare"]
    assert not any(pattern.fullmatch("/api/v1/no-such-route") for pattern in route_patterns())
    assert any(pattern.fullmatch("/api/v1/jobs/abc123") for pattern in route_patterns())


DENIED_FEATURES = {
    r"\bno webhooks\b": "/api/v1/webhooks",
    r"\bno schedules\b": "/api/v1/sites/{site_id}/schedules",
}
"""A phrase denying a feature, and the route that shows the service has it."""


def test_the_docs_do_not_deny_features_the_service_has() -> None:
    wrong = [
        f"{where(path, number)}: {line.strip()}"
        for path, number, line in document_lines()
        for phrase, route in DENIED_FEATURES.items()
        if re.search(phrase, line, re.IGNORECASE)
        and any(pattern.fullmatch(route) for pattern in route_patterns())
    ]
    assert not wrong, "\n".join(wrong)
