"""worker.registry.WorkerRegistry: workers count while their heartbeat lives, and are forgotten after."""

from __future__ import annotations

import uuid

import pytest

from worker.registry import WorkerRegistry
from worker.settings import Settings


@pytest.fixture
def registry(redis_server):
    redis = redis_server.client()
    yield WorkerRegistry(redis, Settings(key_prefix=f"test-{uuid.uuid4().hex[:12]}", heartbeat_ttl=5))
    redis.close()


def test_a_worker_counts_from_its_first_beat_until_it_withdraws(registry):
    assert registry.count_live() == 0
    registry.beat("worker-1")
    registry.beat("worker-2")
    registry.beat("worker-1")
    assert registry.count_live() == 2
    registry.withdraw("worker-1")
    assert registry.count_live() == 1


def test_a_worker_whose_heartbeat_lapsed_is_not_counted_and_is_forgotten(registry):
    registry.beat("worker-1")
    registry.beat("worker-2")
    assert 0 < registry.redis.ttl(f"{registry.prefix}:worker:worker-2") <= 5
    registry.redis.delete(f"{registry.prefix}:worker:worker-2")  # as if 5 s passed without a beat
    assert registry.count_live() == 1
    assert registry.redis.smembers(f"{registry.prefix}:workers") == {b"worker-1"}
