"""The Dockerfile and docker-compose.yml (no Docker engine runs here): they parse, name commands
the ``scandiff`` CLI has, and their healthcheck commands, run as written, tell a working service
from a missing or unmigrated one."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from functools import cache
from pathlib import Path
from typing import Any

import yaml

from app.config import Settings
from app.db.migrate import upgrade_to_head
from app.testing.network import free_port
from app.testing.paths import PROJECT_ROOT
from tests.helpers.server import running_api

DOCKERFILE = PROJECT_ROOT / "Dockerfile"
COMPOSE_FILE = PROJECT_ROOT / "docker-compose.yml"


@cache
def compose() -> dict[str, Any]:
    """docker-compose.yml as YAML (merge keys resolved)."""
    return yaml.safe_load(COMPOSE_FILE.read_text())


@cache
def dockerfile_instructions() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) for every instruction, continuation lines joined."""
    joined = re.sub(r"\\\n", " ", DOCKERFILE.read_text())
    instructions = []
    for line in joined.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            keyword, _, arguments = line.partition(" ")
            instructions.append((keyword.upper(), arguments.strip()))
    return instructions


def runtime_stage() -> list[tuple[str, str]]:
    """The instructions of the Dockerfile's last stage (the image that runs)."""
    instructions = dockerfile_instructions()
    last_from = max(i for i, (keyword, _) in enumerate(instructions) if keyword == "FROM")
    return instructions[last_from:]


def exec_form(arguments: str) -> list[str]:
    """A JSON exec-form argument list (``["scandiff", "serve"]``)."""
    parsed = json.loads(arguments)
    assert isinstance(parsed, list), arguments
    return parsed


def dockerfile_healthcheck() -> list[str]:
    (arguments,) = [arguments for keyword, arguments in runtime_stage() if keyword == "HEALTHCHECK"]
    return exec_form(arguments[arguments.index("CMD ") + len("CMD ") :])


def image_environment() -> dict[str, str]:
    environment: dict[str, str] = {}
    for keyword, arguments in runtime_stage():
        if keyword == "ENV":
            environment.update(pair.split("=", 1) for pair in shlex.split(arguments))
    return environment


def healthcheck_command(service: str) -> list[str]:
    test = compose()["services"][service]["healthcheck"]["test"]
    assert test[0] == "CMD", test
    return test[1:]


@cache
def cli_help(*arguments: str) -> str:
    """``scandiff [arguments] --help``, as the installed command prints it."""
    return subprocess.run(
        [sys.executable, "-m", "app", *arguments, "--help"],
        cwd=PROJECT_ROOT,
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    ).stdout


def subcommands() -> set[str]:
    return {line.split()[0] for line in cli_help().splitlines() if line.startswith("    ")}


def check_command_exists(command: list[str]) -> None:
    """``command`` is ``scandiff SUBCOMMAND [--option value ...]`` the CLI accepts."""
    assert command[0] == "scandiff", command
    assert command[1] in subcommands(), (command, cli_help())
    options = [argument for argument in command[2:] if argument.startswith("--")]
    for option in options:
        assert option in cli_help(command[1]), (option, cli_help(command[1]))


def run_check(command: list[str], environment: dict[str, str]) -> int:
    """Run a healthcheck command as the container would (``python`` is this interpreter), with
    no ``SCANDIFF_*`` setting but those in ``environment``."""
    assert command[0] == "python", command
    inherited = {k: v for k, v in os.environ.items() if not k.startswith("SCANDIFF_")}
    completed = subprocess.run(
        [sys.executable, *command[1:]],
        env=inherited | environment,
        cwd=PROJECT_ROOT,
        capture_output=True,
        timeout=120,
    )
    return completed.returncode


# ----------------------------------------------------------------------------------------------
# docker-compose.yml


def test_compose_runs_two_apis_three_workers_postgres_and_redis():
    services = compose()["services"]
    assert {"api", "worker", "postgres", "redis"} <= services.keys()
    assert services["api"]["deploy"]["replicas"] >= 2
    assert services["worker"]["deploy"]["replicas"] >= 3
    for role in ("api", "worker"):
        environment = services[role]["environment"]
        assert environment["SCANDIFF_DATABASE_URL"].startswith("postgresql+psycopg://")
        assert "@postgres:5432/" in environment["SCANDIFF_DATABASE_URL"]
        assert environment["SCANDIFF_QUEUE_URL"].startswith("redis://redis:6379/")


def test_api_and_worker_share_one_named_data_volume_at_the_data_dir():
    document = compose()
    services = document["services"]
    mounts = set()
    for role in ("api", "worker"):
        data_dir = services[role]["environment"]["SCANDIFF_DATA_DIR"]
        (volume,) = [
            entry.split(":")[0]
            for entry in services[role]["volumes"]
            if entry.split(":")[1] == data_dir
        ]
        mounts.add((volume, data_dir))
    assert len(mounts) == 1, mounts
    ((volume, data_dir),) = mounts
    assert volume in document["volumes"], "a named volume, declared at the top level"
    assert data_dir == image_environment()["SCANDIFF_DATA_DIR"]
    for service in ("postgres", "redis"):
        for entry in services[service]["volumes"]:
            assert entry.split(":")[0] in document["volumes"], (service, entry)


def test_every_service_has_a_healthcheck_and_waits_for_healthy_dependencies():
    services = compose()["services"]
    for name, service in services.items():
        assert service["healthcheck"]["test"], name
        for dependency, condition in service.get("depends_on", {}).items():
            assert dependency in services, (name, dependency)
            assert condition == {"condition": "service_healthy"}, (name, dependency)
    for role in ("api", "worker"):
        assert {"postgres", "redis"} <= services[role]["depends_on"].keys()
    assert "api" in services["worker"]["depends_on"], "workers wait for the API's migrations"


def test_compose_and_dockerfile_name_commands_the_cli_has():
    services = compose()["services"]
    check_command_exists(services["api"]["command"])
    assert services["api"]["command"][1] == "serve"
    (cmd,) = [arguments for keyword, arguments in runtime_stage() if keyword == "CMD"]
    check_command_exists(exec_form(cmd))
    worker = services["worker"]["command"]
    assert worker[:2] == ["scandiff", "worker"]
    check_command_exists(worker)  # fails, never skips, if `scandiff worker` were removed


# ----------------------------------------------------------------------------------------------
# Dockerfile


def test_the_image_is_slim_runs_unprivileged_and_keeps_its_data_in_a_volume():
    stage = runtime_stage()
    assert "-slim" in stage[0][1], stage[0]
    users = [arguments for keyword, arguments in stage if keyword == "USER"]
    assert users and users[-1] not in ("root", "0"), users
    user = users[-1]
    created = " ".join(arguments for keyword, arguments in stage if keyword == "RUN")
    assert re.search(rf"useradd [^&]*--shell /usr/sbin/nologin {user}\b", created), created
    data_dir = image_environment()["SCANDIFF_DATA_DIR"]
    (volume,) = [arguments for keyword, arguments in stage if keyword == "VOLUME"]
    assert exec_form(volume) == [data_dir]
    assert re.search(rf"-o {user} -g {user} [^&]*{re.escape(data_dir)}", created), created
    keywords = [keyword for keyword, _ in stage]
    assert keywords.index("RUN") < keywords.index("VOLUME"), "chown before VOLUME, or it is lost"


def test_the_image_installs_the_wheel_not_the_source_tree():
    stage_text = " ".join(arguments for keyword, arguments in runtime_stage() if keyword == "RUN")
    assert "pip install" in stage_text
    assert " -e " not in stage_text and "--editable" not in stage_text
    assert "--no-index" in stage_text, "only the wheels built in the build stage"
    assert not [a for keyword, a in runtime_stage() if keyword == "COPY" and "from=" not in a]
    sources = [
        arguments.split()[0]
        for keyword, arguments in dockerfile_instructions()
        if keyword == "COPY" and "--from" not in arguments
    ]
    ignored = {
        line.strip()
        for line in (PROJECT_ROOT / ".dockerignore").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    }
    for source in sources:
        assert (PROJECT_ROOT / source).exists(), source
        assert source not in ignored, source


def test_the_healthchecks_pass_on_a_serving_api_and_fail_without_one(tmp_path: Path):
    image_check = dockerfile_healthcheck()
    assert image_check == healthcheck_command("api"), "compose spells out the image's check"
    with running_api(Settings(data_dir=tmp_path / "data")) as api:
        port = api.base_url.rsplit(":", 1)[1]
        assert run_check(image_check, {"SCANDIFF_PORT": port}) == 0
    assert run_check(image_check, {"SCANDIFF_PORT": str(free_port())}) != 0


def test_the_worker_healthcheck_needs_a_migrated_database_and_a_queue(tmp_path: Path):
    check = healthcheck_command("worker")
    settings = Settings(data_dir=tmp_path / "data")
    environment = {"SCANDIFF_DATA_DIR": str(settings.data_dir)}
    assert run_check(check, environment) != 0, "no database at the code's revision yet"
    upgrade_to_head(settings.sqlalchemy_url)
    assert run_check(check, environment) == 0
