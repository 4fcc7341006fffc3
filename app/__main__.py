"""``python -m app`` runs the ``scandiff`` command."""

import sys

from app.cli import main

sys.exit(main())
