"""Redis memory is bounded: against a real redis-server with a small ``maxmemory`` (noeviction), the
API, and a worker, new jobs are refused with 507 when it is nearly full, while status, downloads
and health keep working, and memory comes back as jobs end (their input is deleted at once)."""

from __future__ import annotations

import httpx
import numpy as np

from tests.helpers import TINY, Service, ply_binary, sphere, wait_for
from worker.redis_server import RedisServer

MAXMEMORY = 32 * 2**20


def test_a_full_store_refuses_new_jobs_with_507_and_keeps_serving_the_others(tmp_path):
    redis = RedisServer(tmp_path, maxmemory=MAXMEMORY).start()
    service = Service(redis.url, tmp_path)
    try:
        service.start_api()
        worker = service.start_worker()
        service.wait_workers(1)
        done = service.submit(ply_binary(sphere(500)), **TINY)["id"]
        service.wait_status(done, {"succeeded"})
        worker.terminate(), worker.wait(30)  # from now on, jobs wait in the queue with their input

        big = ply_binary(np.random.default_rng(0).normal(size=(300_000, 3)))  # about 4.5 MB in Redis
        accepted, refused = [], None
        for _ in range(10):
            response = httpx.post(f"{service.url}/v1/jobs", files={"points": ("big.ply", big)}, timeout=30)
            if response.status_code != 202:
                refused = response
                break
            accepted.append(response.json()["id"])
        assert refused is not None and refused.status_code == 507, refused
        assert "full" in refused.json()["detail"] and "Try again later" in refused.json()["detail"]
        assert 2 <= len(accepted) <= 8  # 90 % of 32 MiB, about 4.5 MB each
        assert service.redis.info("memory")["used_memory"] <= MAXMEMORY

        # Status, downloads and health keep working.
        assert service.job(done)["status"] == "succeeded"
        assert httpx.get(f"{service.url}/v1/jobs/{done}/mesh.obj").status_code == 200
        assert httpx.get(f"{service.url}/healthz").status_code == 200
        assert service.job(accepted[0])["status"] == "queued"

        # A job that ends (here: canceled) frees its input at once, and new jobs are accepted again.
        assert httpx.delete(f"{service.url}/v1/jobs/{accepted[0]}").status_code == 204
        assert not service.redis.exists(f"{service.prefix}:job:{accepted[0]}:points")
        wait_for(
            lambda: (
                httpx.post(f"{service.url}/v1/jobs", files={"points": ("big.ply", big)}, timeout=30).status_code == 202
            ),
            10,
            0.5,
            "a new job to be accepted",
        )
    finally:
        service.stop()
        redis.stop()
