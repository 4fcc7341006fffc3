"""``scandiff token list`` and ``scandiff token revoke`` as operators run them: real subprocesses
on a temporary data directory (the database they write is then read back directly)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from app.config import Settings
from app.db.session import transaction
from app.services import auth
from app.services.errors import AuthenticationError

PROJECT_ROOT = Path(__file__).resolve().parents[2]
ISO_SECONDS = re.compile(r"^\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ$")


def scandiff(*arguments: str | Path, stdin: str | None = None) -> subprocess.CompletedProcess[str]:
    """Run ``python -m app ARGUMENTS`` and capture its output."""
    return subprocess.run(
        [sys.executable, "-m", "app", *map(str, arguments)],
        cwd=PROJECT_ROOT,
        input=stdin if stdin is not None else "",
        capture_output=True,
        text=True,
        timeout=120,
    )


@dataclass
class IssuedToken:
    secret: str
    id: str
    organisation: str
    role: str
    name: str | None


@pytest.fixture
def data_dir(tmp_path: Path) -> Path:
    return tmp_path / "data"


def create(data_dir: Path, organisation: str, role: str, name: str | None = None) -> IssuedToken:
    """A token from ``scandiff token create``, with its id read from the database."""
    arguments = ["token", "create", "--org", organisation, "--role", role]
    completed = scandiff(*arguments, *(["--name", name] if name else []), "--data-dir", data_dir)
    assert completed.returncode == 0, completed.stderr
    secret = completed.stdout.strip()
    with transaction(Settings(data_dir=data_dir).sqlalchemy_url) as session:
        token_id = auth.authenticate(session, secret).token_id
    return IssuedToken(secret, token_id, organisation, role, name)


def revocation_lines(data_dir: Path) -> int:
    path = auth.revocations_path(data_dir.resolve())
    return len(path.read_text().splitlines()) if path.exists() else 0


def assert_no_secret(tokens: list[IssuedToken], *outputs: str) -> None:
    for token in tokens:
        for output in outputs:
            assert token.secret not in output
            assert auth.hash_token(token.secret) not in output


def test_list_prints_one_line_per_token_and_never_a_secret(data_dir: Path) -> None:
    tokens = [
        create(data_dir, "acme", "writer", "robot-7"),
        create(data_dir, "acme", "reader"),
        create(data_dir, "beta", "admin", "ops"),
    ]
    completed = scandiff("token", "list", "--data-dir", data_dir)
    assert completed.returncode == 0, completed.stderr
    header, *lines = completed.stdout.splitlines()
    assert header.split() == ["id", "organisation", "role", "name", "created", "revoked"]
    assert len(lines) == len(tokens)
    by_id = {line.split()[0]: line.split() for line in lines}
    for token in tokens:
        _id, organisation, role, name, created, revoked = by_id[token.id]
        assert (organisation, role, name) == (token.organisation, token.role, token.name or "-")
        assert ISO_SECONDS.match(created) and revoked == "-"
    assert_no_secret(tokens, completed.stdout, completed.stderr)

    only_beta = scandiff("token", "list", "--org", "beta", "--json", "--data-dir", data_dir)
    assert only_beta.returncode == 0, only_beta.stderr
    listed = json.loads(only_beta.stdout)
    assert [item["id"] for item in listed] == [tokens[2].id]
    assert listed[0].keys() == {"id", "organisation", "role", "name", "created_at", "revoked_at"}
    assert (listed[0]["organisation"], listed[0]["role"], listed[0]["name"]) == (
        "beta",
        "admin",
        "ops",
    )
    assert ISO_SECONDS.match(listed[0]["created_at"]) and listed[0]["revoked_at"] is None
    assert_no_secret(tokens, only_beta.stdout)


def test_list_of_an_unknown_organisation_or_a_missing_database_exits_2(data_dir: Path) -> None:
    missing = scandiff("token", "list", "--data-dir", data_dir)
    assert missing.returncode == 2
    assert "no database in" in missing.stderr and "Traceback" not in missing.stderr
    assert not data_dir.exists()  # a read command creates nothing

    create(data_dir, "acme", "reader")
    unknown = scandiff("token", "list", "--org", "nobody", "--data-dir", data_dir)
    assert unknown.returncode == 2
    assert unknown.stdout == ""
    assert unknown.stderr.strip() == "scandiff token list: no organisation named 'nobody'"


def test_revoke_by_id_revokes_once_and_says_why_it_cannot_twice(data_dir: Path) -> None:
    token = create(data_dir, "acme", "writer", "robot-7")
    other = create(data_dir, "acme", "writer")

    revoked = scandiff("token", "revoke", token.id, "--data-dir", data_dir)
    assert revoked.returncode == 0, revoked.stderr
    assert revoked.stdout == ""
    assert f"revoked token {token.id}" in revoked.stderr and "robot-7" in revoked.stderr
    assert revocation_lines(data_dir) == 1  # what running API processes watch
    with transaction(Settings(data_dir=data_dir).sqlalchemy_url) as session:
        with pytest.raises(AuthenticationError):
            auth.authenticate(session, token.secret)
        assert auth.authenticate(session, other.secret).token_id == other.id  # only that one

    listed = {
        item["id"]: item
        for item in json.loads(scandiff("token", "list", "--json", "--data-dir", data_dir).stdout)
    }
    assert ISO_SECONDS.match(listed[token.id]["revoked_at"])
    assert listed[other.id]["revoked_at"] is None

    again = scandiff("token", "revoke", token.id, "--data-dir", data_dir)
    assert again.returncode == 2
    assert f"token {token.id} is already revoked (since " in again.stderr
    assert "Traceback" not in again.stderr

    unknown = scandiff("token", "revoke", "0123456789abcdef", "--data-dir", data_dir)
    assert unknown.returncode == 2
    assert unknown.stderr.strip() == "scandiff token revoke: no token with id '0123456789abcdef'"


def test_revoke_reads_the_secret_from_stdin(data_dir: Path) -> None:
    token = create(data_dir, "acme", "reader")
    revoked = scandiff(
        "token", "revoke", "--token-secret-stdin", "--data-dir", data_dir, stdin=token.secret + "\n"
    )
    assert revoked.returncode == 0, revoked.stderr
    assert f"revoked token {token.id}" in revoked.stderr
    assert_no_secret([token], revoked.stdout, revoked.stderr)
    with (
        transaction(Settings(data_dir=data_dir).sqlalchemy_url) as session,
        pytest.raises(AuthenticationError),
    ):
        auth.authenticate(session, token.secret)

    again = scandiff(
        "token", "revoke", "--token-secret-stdin", "--data-dir", data_dir, stdin=token.secret
    )
    assert again.returncode == 2 and "already revoked" in again.stderr

    wrong = scandiff(
        "token", "revoke", "--token-secret-stdin", "--data-dir", data_dir, stdin="sdt_not-a-token\n"
    )
    assert wrong.returncode == 2
    assert wrong.stderr.strip() == "scandiff token revoke: no token has this secret"
    assert "sdt_not-a-token" not in wrong.stderr

    empty = scandiff("token", "revoke", "--token-secret-stdin", "--data-dir", data_dir, stdin="")
    assert empty.returncode == 2 and "no token secret on stdin" in empty.stderr


@pytest.mark.parametrize(
    ("arguments", "stdin"),
    [((), ""), (("some-id", "--token-secret-stdin"), "sdt_x\n")],
    ids=["neither", "both"],
)
def test_revoke_needs_exactly_one_of_id_and_secret(
    data_dir: Path, arguments: tuple[str, ...], stdin: str
) -> None:
    completed = scandiff("token", "revoke", *arguments, "--data-dir", data_dir, stdin=stdin)
    assert completed.returncode == 2
    assert "give either TOKEN_ID or --token-secret-stdin" in completed.stderr
