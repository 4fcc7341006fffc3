"""``scandiff token create|list|revoke``: manage API tokens from the command line.

``create --org NAME --role admin|writer|reader [--name N]`` applies the migrations first (a fresh
data directory works), creates the organisation if it does not exist, and prints the new token
alone on stdout (it is shown only this once; the database keeps its SHA-256).

``list [--org NAME] [--json]`` prints one line per token (id, organisation, role, name, created,
revoked), never a secret or its digest.

``revoke TOKEN_ID`` (or ``revoke --token-secret-stdin`` with the secret on stdin, so it stays out
of shell history and the process list) revokes through :func:`app.services.auth.revoke_token`
and advances ``<data_dir>/token-revocations``: running API processes on the same data directory
refuse the token from their next request, whatever their cache TTL.

Every action takes ``--data-dir DIR``; exit status 0, or 2 with one line on stderr.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from app.cli.exit_status import EXIT_BAD_INPUT

if TYPE_CHECKING:  # SQLAlchemy and pydantic are imported when a command runs, not to parse
    from app.config import Settings
    from app.services.auth import TokenSummary

ROLES = ("reader", "writer", "admin")  # app.services.auth.ROLES, without importing SQLAlchemy
LIST_COLUMNS = ("id", "organisation", "role", "name", "created", "revoked")


def add_parser(subparsers: Any) -> None:
    """Register ``scandiff token create|list|revoke``."""
    parser = subparsers.add_parser(
        "token", help="manage API tokens", description="Manage API tokens."
    )
    actions = parser.add_subparsers(dest="token_command", metavar="ACTION", required=True)
    create = actions.add_parser(
        "create",
        help="create a token and print it",
        description="Create an API token for an organisation and print it alone on stdout.",
    )
    create.add_argument("--org", required=True, help="organisation name (created if new)")
    create.add_argument("--role", required=True, choices=ROLES, help="what the token may do")
    create.add_argument("--name", default=None, help="a label for the token (e.g. robot-7)")
    create.add_argument("--data-dir", type=Path, default=None, help="data directory")
    create.set_defaults(handler=handle_create)

    listing = actions.add_parser(
        "list",
        help="list tokens (never their secrets)",
        description="List tokens: id, organisation, role, name, created, revoked.",
    )
    listing.add_argument("--org", default=None, help="only this organisation's tokens")
    listing.add_argument("--json", action="store_true", help="print one JSON array on stdout")
    listing.add_argument("--data-dir", type=Path, default=None, help="data directory")
    listing.set_defaults(handler=handle_list)

    revoke = actions.add_parser(
        "revoke",
        help="revoke a token at once",
        description="Revoke a token: running API processes on the same data directory refuse "
        "it from their next request. Give its id (see 'scandiff token list'), or its secret on "
        "stdin with --token-secret-stdin.",
    )
    revoke.add_argument("token_id", nargs="?", metavar="TOKEN_ID", help="the token's id")
    revoke.add_argument(
        "--token-secret-stdin",
        action="store_true",
        help="read the token itself (sdt_...) from stdin instead of giving an id",
    )
    revoke.add_argument("--data-dir", type=Path, default=None, help="data directory")
    revoke.set_defaults(handler=handle_revoke)


def _settings(args: argparse.Namespace) -> Settings:
    from app.config import Settings

    return Settings(data_dir=args.data_dir) if args.data_dir else Settings()


def _existing_database(settings: Settings, command: str) -> bool:
    """Migrate the database if it exists; False (with a message) if there is none to read."""
    from app.db.migrate import upgrade_to_head

    if settings.database_url is None:
        database = Path(settings.sqlalchemy_url.removeprefix("sqlite:///"))
        if not database.is_file():
            print(
                f"scandiff token {command}: no database in {settings.data_dir} (wrong --data-dir? "
                "'scandiff serve' or 'scandiff token create' creates it)",
                file=sys.stderr,
            )
            return False
    upgrade_to_head(settings.sqlalchemy_url)
    return True


def handle_create(args: argparse.Namespace) -> int:
    """Create the token; exit status 0, or 2 with a message on stderr."""
    from app.db.migrate import upgrade_to_head
    from app.db.session import transaction
    from app.services.auth import create_token
    from app.services.errors import AppError

    settings = _settings(args)
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    upgrade_to_head(settings.sqlalchemy_url)
    try:
        with transaction(settings.sqlalchemy_url) as session:
            token = create_token(session, args.org, args.role, name=args.name)
    except AppError as exc:
        print(f"scandiff token create: {exc.detail}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(token)
    return 0


def format_token_table(tokens: list[TokenSummary]) -> str:
    """A header and one aligned line per token ('-' for no name / not revoked)."""
    from app.clock import iso_utc

    rows = [LIST_COLUMNS] + [
        (
            token.id,
            token.organisation,
            token.role,
            token.name or "-",
            iso_utc(token.created_at),
            iso_utc(token.revoked_at) if token.revoked_at else "-",
        )
        for token in tokens
    ]
    widths = [max(len(row[column]) for row in rows) for column in range(len(LIST_COLUMNS))]
    return "\n".join(
        "  ".join(value.ljust(width) for value, width in zip(row, widths, strict=True)).rstrip()
        for row in rows
    )


def handle_list(args: argparse.Namespace) -> int:
    """Print the tokens; exit status 0, or 2 for an unknown organisation."""
    from app.db.session import transaction
    from app.services.auth import list_tokens
    from app.services.errors import AppError

    settings = _settings(args)
    if not _existing_database(settings, "list"):
        return EXIT_BAD_INPUT
    try:
        with transaction(settings.sqlalchemy_url) as session:
            tokens = list_tokens(session, args.org)
    except AppError as exc:
        print(f"scandiff token list: {exc.detail}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.json:
        json.dump([token.to_json_dict() for token in tokens], sys.stdout, indent=1)
        sys.stdout.write("\n")
    else:
        print(format_token_table(tokens))
    return 0


def _read_secret() -> str:
    """The token secret from stdin (its first line; prompted without echo on a terminal)."""
    if sys.stdin.isatty():
        import getpass

        return getpass.getpass("token secret: ").strip()
    return sys.stdin.readline().strip()


def handle_revoke(args: argparse.Namespace) -> int:
    """Revoke the token; exit status 0 with a confirmation on stderr, or 2 saying why not."""
    from app.db.session import transaction
    from app.services.auth import (
        revocation_counter,
        revocations_path,
        revoke_existing_token,
        token_id_of_secret,
    )
    from app.services.errors import AppError

    if (args.token_id is None) == (not args.token_secret_stdin):
        print(
            "scandiff token revoke: give either TOKEN_ID or --token-secret-stdin (not both)",
            file=sys.stderr,
        )
        return EXIT_BAD_INPUT
    secret = _read_secret() if args.token_secret_stdin else None
    if secret == "":
        print("scandiff token revoke: no token secret on stdin", file=sys.stderr)
        return EXIT_BAD_INPUT
    settings = _settings(args)
    if not _existing_database(settings, "revoke"):
        return EXIT_BAD_INPUT
    revocations = revocations_path(settings.data_dir)
    counter_before = revocation_counter(revocations)
    try:
        with transaction(settings.sqlalchemy_url) as session:
            token_id = args.token_id if secret is None else token_id_of_secret(session, secret)
            token = revoke_existing_token(session, token_id, revocations)
    except AppError as exc:
        print(f"scandiff token revoke: {exc.detail}", file=sys.stderr)
        return EXIT_BAD_INPUT
    name = f", name {token.name}" if token.name else ""
    print(
        f"scandiff token revoke: revoked token {token.id} (organisation {token.organisation}, "
        f"role {token.role}{name})",
        file=sys.stderr,
    )
    if revocation_counter(revocations) == counter_before:
        print(
            f"scandiff token revoke: warning: could not advance {revocations}: running API "
            "processes may accept the token until their token cache expires "
            "(SCANDIFF_TOKEN_CACHE_SECONDS)",
            file=sys.stderr,
        )
    return 0
