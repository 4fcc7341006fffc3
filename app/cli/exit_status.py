"""Exit statuses of every ``scandiff`` subcommand."""

EXIT_BAD_INPUT = 2
"""Bad input or a refused setting; one line on stderr says what to fix."""
