"""Redis clients for the service: patient ones for workers, fail-fast ones for the API."""

from __future__ import annotations

from typing import Any

from redis import Redis
from redis.asyncio import Redis as AsyncRedis
from redis.asyncio.retry import Retry as AsyncRetry
from redis.backoff import ExponentialWithJitterBackoff
from redis.retry import Retry

# The API's clients fail fast (short timeouts, one quick retry), so that a request answers 503
# promptly while Redis is down; workers keep redis-py's patient defaults.
_FAIL_FAST: dict[str, Any] = {"socket_connect_timeout": 2, "socket_timeout": 5, "health_check_interval": 30}
_QUICK_RETRY = ExponentialWithJitterBackoff(base=0.01, cap=0.1), 1


def connect(url: str, *, fail_fast: bool = False) -> Redis:
    """A Redis client for ``url``; ``fail_fast`` for the API."""
    if not fail_fast:
        return Redis.from_url(url, health_check_interval=30)
    return Redis.from_url(url, retry=Retry(*_QUICK_RETRY), **_FAIL_FAST)


def text(value: bytes | str) -> str:
    """A string Redis returned (bytes, as these clients do not decode responses)."""
    return value.decode() if isinstance(value, bytes) else value


def connect_async(url: str) -> AsyncRedis:
    """The API's asyncio client for ``url`` (fail-fast too)."""
    return AsyncRedis.from_url(url, retry=AsyncRetry(*_QUICK_RETRY), **_FAIL_FAST)
