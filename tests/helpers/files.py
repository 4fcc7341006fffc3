"""The conftest files' names for :mod:`app.testing.files` (new code imports from there)."""

from app.testing.files import (
    pcd_bytes as pcd_bytes,
)
