"""``edgerecon serve`` and ``edgerecon worker`` as a user runs them: curl against the embedded
service, then Ctrl-C (SIGINT), after which no process of it may be left."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time

import httpx
import psutil
import pytest
import trimesh

from tests.helpers import ENDLESS, ROOT, TEST_ENV, TINY, clean_environ, stop_process, wait_for
from worker.redis_server import free_port


def _serve(tmp_path, workers: int, without: tuple[str, ...] = (), **env) -> tuple[subprocess.Popen, str]:
    """Start ``edgerecon serve`` with the tests' settings (less ``without``) and ``env``; wait until it is ready."""
    port = free_port()
    command = [sys.executable, "-m", "service.cli", "serve", "--port", str(port), "--workers", str(workers)]
    log = open(tmp_path / "serve.log", "ab")
    # Its data in the test's folder (not the user's), and its temporary files where they can be counted.
    (tmp_path / "tmp").mkdir(exist_ok=True)
    private = {"EDGERECON_DATA_DIR": str(tmp_path / "data"), "TMPDIR": str(tmp_path / "tmp")}
    environ = {**clean_environ(), **TEST_ENV, **private, **env}
    environ = {name: value for name, value in environ.items() if name not in without}
    process = subprocess.Popen(command, env=environ, cwd=ROOT, stdout=log, stderr=log)
    url = f"http://127.0.0.1:{port}"

    def ready():
        assert process.poll() is None, (tmp_path / "serve.log").read_text()
        try:
            return httpx.get(url + "/healthz", timeout=2).json().get("workers") == workers
        except httpx.HTTPError:
            return False

    # A deadline, not a wait: ready in a few seconds on an idle machine, but a worker that warms up
    # (niced, on one thread) took over 60 s on a two-core AVX2 machine busy with the suite's fits.
    wait_for(ready, 180, 0.2, "edgerecon serve to be ready")
    return process, url


def _curl(*args: str) -> str:
    return subprocess.run(["curl", "-sS", "--fail-with-body", *args], check=True, capture_output=True, text=True).stdout


@pytest.mark.skipif(shutil.which("curl") is None, reason="curl is not installed")
def test_serve_with_embedded_redis_answers_curl_and_stops_on_ctrl_c(tmp_path, example_cloud):
    (tmp_path / "cube.ply").write_bytes(example_cloud)
    process, url = _serve(tmp_path, workers=1)
    try:
        family = psutil.Process(process.pid).children(recursive=True)
        names = " ".join(" ".join(child.cmdline()) for child in family)
        assert "redis-server" in names and "uvicorn" in names and "worker" in names

        fields = [arg for name, value in TINY.items() for arg in ("-F", f"{name}={value}")]
        job = json.loads(_curl("-F", f"points=@{tmp_path / 'cube.ply'}", *fields, f"{url}/v1/jobs"))
        wait_for(lambda: json.loads(_curl(f"{url}/v1/jobs/{job['id']}"))["status"] == "succeeded", 60, 0.2, "the job")
        for name in ("mesh.obj", "normals.json", "edges.json"):
            _curl("-o", str(tmp_path / name), f"{url}/v1/jobs/{job['id']}/{name}")
        assert len(trimesh.load(tmp_path / "mesh.obj").vertices) > 0
        assert len(json.loads((tmp_path / "normals.json").read_text())["normals"]) == 6000
        assert "indices" in json.loads((tmp_path / "edges.json").read_text())

        # Ctrl-C while a job runs: everything stops promptly, nothing is left behind.
        fields = [arg for name, value in ENDLESS.items() for arg in ("-F", f"{name}={value}")]
        running = json.loads(_curl("-F", f"points=@{tmp_path / 'cube.ply'}", *fields, f"{url}/v1/jobs"))
        wait_for(lambda: json.loads(_curl(f"{url}/v1/jobs/{running['id']}"))["status"] == "running", 30, 0.1, "run")
        family = psutil.Process(process.pid).children(recursive=True)
        started = time.monotonic()
        process.send_signal(signal.SIGINT)
        assert process.wait(timeout=30) == 0
        # Within serve's STOP_SECONDS (15 s), after which it kills: every child stopped by itself.
        assert time.monotonic() - started < 10
        assert [child.pid for child in family if child.is_running() and child.status() != psutil.STATUS_ZOMBIE] == []
    finally:
        stop_process(process, signal.SIGKILL)


def _job(url: str, job_id: str) -> dict:
    response = httpx.get(f"{url}/v1/jobs/{job_id}", timeout=10)
    assert response.status_code == 200, response.text
    return response.json()


def _polled(url: str, job_id: str) -> dict:
    """The job as a client polling it sees it: {} for a 503, which the API answers when Redis takes
    longer than its socket timeout (0.5 s), as it did once in CI on two cores busy with fits, and
    which a client polls through."""
    response = httpx.get(f"{url}/v1/jobs/{job_id}", timeout=10)
    if response.status_code == 503:
        return {}
    assert response.status_code == 200, response.text
    return response.json()


def _submit(url: str, cloud: bytes, params: dict) -> str:
    data = {name: str(value) for name, value in params.items()}
    response = httpx.post(f"{url}/v1/jobs", files={"points": ("cloud.ply", cloud)}, data=data, timeout=30)
    assert response.status_code == 202, response.text
    return response.json()["id"]


def _alive(processes: list[psutil.Process]) -> list[int]:
    return [child.pid for child in processes if child.is_running() and child.status() != psutil.STATUS_ZOMBIE]


def test_serve_keeps_every_job_across_a_sigkill_and_brings_its_redis_back_within_5_s(tmp_path, example_cloud):
    process, url = _serve(tmp_path, workers=1)
    try:
        done = _submit(url, example_cloud, TINY)
        wait_for(lambda: _polled(url, done).get("status") == "succeeded", 60, 0.2, "the first job")
        mesh = httpx.get(f"{url}/v1/jobs/{done}/mesh.obj").content
        busy = _submit(url, example_cloud, {**ENDLESS, "iterations": 2000})
        waiting = _submit(url, example_cloud, TINY)  # queued behind it
        wait_for(lambda: (_polled(url, busy).get("progress") or {}).get("stage") == "fitting", 60, 0.1, "the busy job")
        family = psutil.Process(process.pid).children(recursive=True)
        process.kill()  # no clean-up by serve itself: its children stop on their own (PDEATHSIG)
        process.wait()
        wait_for(lambda: _alive(family) == [], 20, 0.1, "the children of the killed serve to stop")
        # Nothing left in temporary folders, but torch's compile cache (kept on purpose, shared by runs).
        assert [path.name for path in (tmp_path / "tmp").iterdir() if not path.name.startswith("torchinductor")] == []
        assert any((tmp_path / "data").rglob("*.aof"))  # the data is in the data folder
    finally:
        stop_process(process, signal.SIGKILL)

    started = time.monotonic()
    process, url = _serve(tmp_path, workers=1)  # the same data folder
    try:
        assert time.monotonic() - started < 30
        assert _job(url, done)["status"] == "succeeded"
        assert httpx.get(f"{url}/v1/jobs/{done}/mesh.obj").content == mesh
        for job_id in (busy, waiting):  # the running job runs again, the queued one runs
            wait_for(
                lambda job_id=job_id: _polled(url, job_id).get("status") == "succeeded", 120, 0.2, "the jobs to run"
            )
        assert _job(url, busy)["attempts"] == 2 and _job(url, waiting)["attempts"] == 1

        # The embedded Redis dies: the API answers 503 meanwhile (or nothing but 200, when the new Redis
        # is up before the next request: serve restarts it within a few tenths of a second), and serve
        # brings it back with its data.
        def redis_servers() -> list[psutil.Process]:
            found = []
            for child in psutil.Process(process.pid).children():
                try:  # the killed one is a zombie until serve reaps it
                    if child.status() != psutil.STATUS_ZOMBIE and "redis-server" in " ".join(child.cmdline()):
                        found.append(child)
                except psutil.Error:
                    continue
            return found

        redis = redis_servers()[0]
        redis.kill()
        killed_at, answers, restarted = time.monotonic(), [], False
        while time.monotonic() - killed_at < 15:
            answers.append(httpx.get(f"{url}/v1/jobs/{done}", timeout=5).status_code)
            restarted = restarted or any(server.pid != redis.pid for server in redis_servers())
            if restarted and answers[-1] == 200:
                break
            time.sleep(0.05)
        assert restarted and set(answers) <= {503, 200} and answers[-1] == 200, answers
        assert time.monotonic() - killed_at < 5
        assert httpx.get(f"{url}/v1/jobs/{done}/mesh.obj").content == mesh
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=30) == 0
    finally:
        stop_process(process, signal.SIGKILL)


def test_serve_uses_redis_url_when_set_and_its_worker_warms_up(tmp_path, redis_server):
    # This worker also runs its warm-up fit (with eager kernels, to stay cheap).
    process, _ = _serve(
        tmp_path,
        workers=1,
        REDIS_URL=redis_server.url,
        EDGERECON_KEY_PREFIX="serve-test",
        EDGERECON_QUEUE="serve-test",
        EDGERECON_WORKER_WARMUP="1",
    )
    try:
        family = psutil.Process(process.pid).children(recursive=True)
        assert not any("redis-server" in " ".join(child.cmdline()) for child in family)
        assert redis_server.client().exists("serve-test:workers")
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=30) == 0
        assert not any(child.is_running() and child.status() != psutil.STATUS_ZOMBIE for child in family)
    finally:
        stop_process(process, signal.SIGKILL)
        for key in redis_server.client().keys("serve-test:*"):
            redis_server.client().delete(key)


def test_serve_gives_its_lone_worker_every_core(tmp_path):
    # (cores // N for each of N workers: tests/worker/test_settings.py)
    process, _ = _serve(tmp_path, 1, without=("EDGERECON_WORKER_THREADS", "OMP_NUM_THREADS"))
    try:
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=30) == 0
    finally:
        stop_process(process, signal.SIGKILL)
    said = re.findall(r"torch ready: (\d+) thread", (tmp_path / "serve.log").read_text())
    assert said == [str(len(os.sched_getaffinity(0)))]


def test_worker_without_redis_url_says_so():
    result = subprocess.run(
        [sys.executable, "-m", "service.cli", "worker"],
        env={**clean_environ(), **TEST_ENV},
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2 and "REDIS_URL is not set" in result.stderr
