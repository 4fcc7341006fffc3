"""The conftest files' names for :mod:`app.testing.service` (new code imports from there)."""

from app.testing.service import (
    ConsumerProcess as ConsumerProcess,
)
from app.testing.service import (
    ServiceProcess as ServiceProcess,
)
