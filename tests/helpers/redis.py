"""The conftest files' names for :mod:`app.testing.redis` (new code imports from there)."""

from app.testing.redis import (
    REDIS_SERVER_ENV as REDIS_SERVER_ENV,
)
from app.testing.redis import (
    RedisServer as RedisServer,
)
from app.testing.redis import (
    redis_server_binary as redis_server_binary,
)
