"""The ``scandiff`` command: ``compare``, ``serve``, ``worker`` and ``token`` subcommands.

Each subcommand lives in its own module exposing ``add_parser(subparsers)``, which registers the
subparser and sets ``handler`` (a function ``(args) -> int`` returning the exit status).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING

from app.cli import compare, serve, tokens, worker
from app.cli.exit_status import EXIT_BAD_INPUT

if TYPE_CHECKING:  # pydantic is imported by the commands that read settings, not to parse
    from pydantic import ValidationError


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every subcommand."""
    parser = argparse.ArgumentParser(
        prog="scandiff", description="Detect and locate changes between 3D scans of a site."
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in (compare, serve, worker, tokens):
        module.add_parser(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the console script; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    handler = getattr(args, "handler", None)
    if handler is None:
        parser.print_help()
        return 0
    try:
        return int(handler(args) or 0)
    except Exception as exc:  # a SCANDIFF_* variable (or option) the settings reject
        pydantic = sys.modules.get("pydantic")  # not imported: not a settings error
        if pydantic is None or not isinstance(exc, pydantic.ValidationError):
            raise
        if exc.title != "Settings":
            raise
        print(f"scandiff: error: {settings_error_message(exc)}", file=sys.stderr)
        return EXIT_BAD_INPUT


def settings_error_message(exc: ValidationError) -> str:
    """One line naming each rejected setting, its environment variable and why."""
    problems = []
    for error in exc.errors(include_url=False):
        name = ".".join(str(part) for part in error["loc"])
        reason = str(error["msg"]).removeprefix("Value error, ")
        problems.append(f"{name} (SCANDIFF_{name.upper()}): {reason}")
    return "invalid settings: " + "; ".join(problems)


if __name__ == "__main__":
    sys.exit(main())
