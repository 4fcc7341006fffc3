"""The skip policy of the scaled-out topology (the topology itself: :mod:`app.testing.topology`)."""

from __future__ import annotations

from app.testing.topology import missing_topology_services
from tests.helpers.environment import require


def require_topology() -> None:
    """Skip (locally) or fail (in CI) unless PostgreSQL, redis-server and redis-py are here."""
    missing = missing_topology_services()
    require(not missing, "; ".join(missing))
