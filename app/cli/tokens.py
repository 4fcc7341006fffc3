"""``scandiff token create --org NAME --role admin|writer|reader [--data-dir DIR] [--name N]``.

Applies the migrations first (a fresh data directory works), creates the organisation if it
does not exist, and prints the new token alone on stdout (it is shown only this once; the
database keeps its SHA-256).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from app.config import Settings

ROLES = ("reader", "writer", "admin")  # app.services.auth.ROLES, without importing SQLAlchemy


def add_parser(subparsers: Any) -> None:
    """Register ``scandiff token create``."""
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


def handle_create(args: argparse.Namespace) -> int:
    """Create the token; exit status 0, or 2 with a message on stderr."""
    from app.db.migrate import upgrade_to_head
    from app.db.session import transaction
    from app.services.auth import create_token
    from app.services.errors import AppError

    settings = Settings(data_dir=args.data_dir) if args.data_dir else Settings()
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    upgrade_to_head(settings.sqlalchemy_url)
    try:
        with transaction(settings.sqlalchemy_url) as session:
            token = create_token(session, args.org, args.role, name=args.name)
    except AppError as exc:
        print(f"scandiff token create: {exc.detail}", file=sys.stderr)
        return 2
    print(token)
    return 0
