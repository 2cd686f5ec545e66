"""Redis clients for the service: patient ones for workers, fail-fast ones for the API."""

from __future__ import annotations

from typing import Any

from redis import Redis
from redis.asyncio import Redis as AsyncRedis
from redis.asyncio.retry import Retry as AsyncRetry
from redis.backoff import NoBackoff
from redis.retry import Retry


def _fail_fast(connect_timeout: float, socket_timeout: float) -> dict[str, Any]:
    """The API's client options: short timeouts and no retry, so that a request answers 503 within
    about ``socket_timeout`` while Redis is hung or gone (a retry would also send a write twice)."""
    return {
        "socket_connect_timeout": connect_timeout,
        "socket_timeout": socket_timeout,
        "health_check_interval": 30,
    }


def connect(url: str, *, fail_fast: bool = False, connect_timeout: float = 0.5, socket_timeout: float = 0.5) -> Redis:
    """A Redis client for ``url``; ``fail_fast`` (with its timeouts, in seconds) for the API."""
    if not fail_fast:
        return Redis.from_url(url, health_check_interval=30)
    return Redis.from_url(url, retry=Retry(NoBackoff(), 0), **_fail_fast(connect_timeout, socket_timeout))


def text(value: bytes | str) -> str:
    """A string Redis returned (bytes, as these clients do not decode responses)."""
    return value.decode() if isinstance(value, bytes) else value


def connect_async(url: str, *, connect_timeout: float = 0.5, socket_timeout: float = 0.5) -> AsyncRedis:
    """The API's asyncio client for ``url`` (fail-fast too)."""
    return AsyncRedis.from_url(url, retry=AsyncRetry(NoBackoff(), 0), **_fail_fast(connect_timeout, socket_timeout))
