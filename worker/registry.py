"""Which workers listen: each announces itself every few seconds, and counts while its key lives."""

from __future__ import annotations

from datetime import UTC, datetime

from redis import Redis
from redis.asyncio import Redis as AsyncRedis

from worker.connection import text
from worker.settings import Settings


class WorkerRegistry:
    """The workers of one service (one key prefix) in one Redis, by their heartbeats."""

    def __init__(self, redis: Redis, settings: Settings, async_redis: AsyncRedis | None = None):
        self.redis = redis
        self.async_redis = async_redis  # the API's asyncio client, for count_live_async
        self.prefix = settings.key_prefix
        self.heartbeat_ttl = settings.heartbeat_ttl

    def beat(self, worker: str) -> None:
        """Announce that ``worker`` listens (for ``heartbeat_ttl`` seconds)."""
        with self.redis.pipeline() as pipe:
            pipe.sadd(f"{self.prefix}:workers", worker)
            now = datetime.now(UTC).isoformat(timespec="milliseconds")
            pipe.set(f"{self.prefix}:worker:{worker}", now, ex=self.heartbeat_ttl)
            pipe.execute()

    def withdraw(self, worker: str) -> None:
        """Withdraw ``worker`` at a clean exit."""
        with self.redis.pipeline() as pipe:
            pipe.srem(f"{self.prefix}:workers", worker)
            pipe.delete(f"{self.prefix}:worker:{worker}")
            pipe.execute()

    def count_live(self) -> int:
        """How many workers signalled within the last ``heartbeat_ttl`` seconds (the others are forgotten)."""
        names = [text(name) for name in self.redis.smembers(f"{self.prefix}:workers")]
        if not names:
            return 0
        with self.redis.pipeline(transaction=False) as pipe:
            for name in names:
                pipe.exists(f"{self.prefix}:worker:{name}")
            alive = pipe.execute()
        dead = [name for name, ok in zip(names, alive) if not ok]
        if dead:
            self.redis.srem(f"{self.prefix}:workers", *dead)
        return len(names) - len(dead)

    async def count_live_async(self) -> int:
        """``count_live`` on the asyncio client (for /metrics, which must answer promptly)."""
        assert self.async_redis is not None, "count_live_async needs the registry's asyncio client"
        names = [text(name) for name in await self.async_redis.smembers(f"{self.prefix}:workers")]
        if not names:
            return 0
        async with self.async_redis.pipeline(transaction=False) as pipe:
            for name in names:
                pipe.exists(f"{self.prefix}:worker:{name}")
            alive = await pipe.execute()
        dead = [name for name, ok in zip(names, alive) if not ok]
        if dead:
            await self.async_redis.srem(f"{self.prefix}:workers", *dead)
        return len(names) - len(dead)
