"""Chaos run: a stream of small jobs through ``edgerecon serve --workers 2`` while its processes are
killed, stopped and restarted at random moments, then a count of what became of every job.

Loopback only, bounded in jobs and time. The faults, drawn from ``--seed``: SIGKILL or SIGTERM of a
worker, SIGKILL of the embedded Redis, SIGSTOP of it for 1 to 4 s, and a restart of ``serve``
itself (SIGTERM or SIGKILL, then a new ``serve`` on the same data folder). Jobs are submitted while
fewer than ``--backlog`` are unfinished; every unfinished job is polled each second. At the end,
once the faults have stopped, each job must reach a final state: one that never does, or that
vanishes (404), is lost. A job is a duplicate if it ended twice (a final status that changed, or
two "succeeded" lines for it in the workers' logs). 503 is what the API answers on purpose while
Redis is down or restarting; any other 5xx is a failure.

    .venv/bin/python bench/chaos.py --seed 1 --jobs 200 --faults 30
"""

from __future__ import annotations

import argparse
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np
import psutil

ROOT = Path(__file__).resolve().parents[1]
TINY = {"iterations": 30, "resolution": 32, "width": 32, "depth": 2, "batch_points": 256}
FINAL = {"succeeded", "failed", "canceled"}
# Fast failure detection and no compile time, so that a run of hundreds of jobs takes minutes.
ENV = {
    "EDGERECON_COMPILE": "0",
    "EDGERECON_WORKER_WARMUP": "0",
    "EDGERECON_HEARTBEAT_TTL": "6",
    "EDGERECON_SWEEP_INTERVAL": "1",
    "EDGERECON_PROGRESS_INTERVAL": "0.25",
}
FAULTS = {
    "worker SIGKILL": 0.22,
    "worker SIGTERM": 0.2,
    "Redis SIGKILL": 0.15,
    "Redis SIGSTOP": 0.15,
    "serve SIGTERM + restart": 0.14,
    "serve SIGKILL + restart": 0.14,
}


def cloud(seed: int) -> bytes:
    """A 500-point sphere as a binary PLY."""
    points = np.random.default_rng(seed).normal(size=(500, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    header = (
        "ply\nformat binary_little_endian 1.0\nelement vertex 500\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    )
    return header.encode() + points.astype("<f4").tobytes()


@dataclass
class Tracked:
    status: str = "queued"
    seen: tuple = ()
    changed: float = field(default_factory=time.monotonic)
    finals: set[str] = field(default_factory=set)
    attempts: int = 0
    error: str | None = None
    vanished: bool = False


class Chaos:
    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.random = random.Random(args.seed)
        self.url = f"http://127.0.0.1:{args.port}"
        self.data = Path(tempfile.mkdtemp(prefix="edgerecon-chaos-"))
        self.log_path = self.data / "serve.log"
        self.serve: subprocess.Popen[bytes] | None = None
        self.jobs: dict[str, Tracked] = {}
        self.lock = threading.Lock()
        self.codes: Counter[int] = Counter()
        self.faults: Counter[str] = Counter()
        self.unknown_posts = 0
        self.longest_stall = 0.0
        self.peak_rss = 0
        self.stop = threading.Event()

    # --- the service ---------------------------------------------------------------------------

    def start_serve(self) -> None:
        env = {k: v for k, v in os.environ.items() if not k.startswith(("EDGERECON_", "REDIS_URL"))}
        env.update(ENV)
        command = [sys.executable, "-m", "service.cli", "serve", "--port", str(self.args.port)]
        command += ["--workers", "2", "--data-dir", str(self.data / "redis")]
        with open(self.log_path, "ab") as log:
            self.serve = subprocess.Popen(command, env=env, cwd=ROOT, stdout=log, stderr=log)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                if httpx.get(self.url + "/healthz", timeout=2).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        raise RuntimeError(f"serve did not start (see {self.log_path})")

    def children(self, word: str) -> list[psutil.Process]:
        if self.serve is None:
            return []
        try:
            family = psutil.Process(self.serve.pid).children(recursive=True)
        except psutil.NoSuchProcess:
            return []
        found = []
        for child in family:
            try:
                if word in " ".join(child.cmdline()):
                    found.append(child)
            except psutil.Error:
                pass
        return found

    # --- the clients ---------------------------------------------------------------------------

    def request(self, method: str, path: str, **kwargs) -> httpx.Response | None:
        try:
            response = httpx.request(method, self.url + path, timeout=15, **kwargs)
        except httpx.HTTPError:
            return None  # serve restarting: no answer at all
        with self.lock:
            self.codes[response.status_code] += 1
        return response

    def submit(self, number: int) -> None:
        data = {name: str(value) for name, value in {**TINY, "seed": number}.items()}
        while not self.stop.is_set():
            try:
                response = httpx.post(
                    self.url + "/v1/jobs", files={"points": ("c.ply", cloud(number))}, data=data, timeout=15
                )
            except (httpx.ReadError, httpx.RemoteProtocolError, httpx.ReadTimeout):
                self.unknown_posts += 1  # sent, but no answer: a job may exist that nobody knows of
                time.sleep(0.5)
                continue
            except httpx.HTTPError:
                time.sleep(0.5)  # not connected: nothing was sent
                continue
            with self.lock:
                self.codes[response.status_code] += 1
            if response.status_code == 202:
                with self.lock:
                    self.jobs[response.json()["id"]] = Tracked()
                return
            time.sleep(0.5)  # 503 while Redis is down: try again

    def poll(self) -> None:
        """Every second, GET each unfinished job; every tenth round the finished ones too (they must stay so)."""
        rounds = 0
        while not self.stop.is_set():
            rounds += 1
            with self.lock:
                jobs = [
                    (job_id, job) for job_id, job in self.jobs.items() if job.status not in FINAL or rounds % 10 == 0
                ]
            for job_id, job in jobs:
                response = self.request("GET", f"/v1/jobs/{job_id}")
                if response is not None and response.status_code == 404:
                    job.vanished = True
                elif response is not None and response.status_code == 200:
                    self.observe(job, response.json())
            self.sample_rss()
            time.sleep(1.0)

    def observe(self, job: Tracked, view: dict) -> None:
        now = time.monotonic()
        progress = view.get("progress") or {}
        seen = (view["status"], view["attempts"], progress.get("stage"), progress.get("iteration"))
        if job.status == "running" and seen[0] == "running":
            self.longest_stall = max(self.longest_stall, now - job.changed)
        if seen != job.seen:
            job.seen, job.changed = seen, now
        job.status, job.attempts, job.error = view["status"], view["attempts"], view.get("error")
        job.vanished = False
        if job.status in FINAL:
            job.finals.add(job.status)

    def sample_rss(self) -> None:
        for api in self.children("uvicorn"):
            try:
                self.peak_rss = max(self.peak_rss, api.memory_info().rss)
            except psutil.Error:
                pass

    # --- the faults ----------------------------------------------------------------------------

    def inject(self) -> None:
        kind = self.random.choices(list(FAULTS), weights=list(FAULTS.values()))[0]
        if kind.startswith("worker"):
            workers = self.children("service.cli worker")
            if not workers:
                return
            victim = self.random.choice(workers)
            victim.send_signal(signal.SIGKILL if "KILL" in kind else signal.SIGTERM)
        elif kind.startswith("Redis"):
            redis = self.children("redis-server")
            if not redis:
                return
            if kind == "Redis SIGKILL":
                redis[0].kill()
            else:
                redis[0].suspend()
                time.sleep(self.random.uniform(1, 4))
                redis[0].resume()
        else:
            assert self.serve is not None
            self.serve.send_signal(signal.SIGKILL if "KILL" in kind else signal.SIGTERM)
            self.serve.wait(60)
            self.start_serve()
        self.faults[kind] += 1

    # --- the run -------------------------------------------------------------------------------

    def run(self) -> int:
        started = time.monotonic()
        self.start_serve()
        poller = threading.Thread(target=self.poll, daemon=True)
        poller.start()
        submitted = 0
        next_fault = time.monotonic() + self.random.uniform(2, 8)
        deadline = started + self.args.max_seconds
        while time.monotonic() < deadline and (
            submitted < self.args.jobs or sum(self.faults.values()) < self.args.faults
        ):
            with self.lock:
                unfinished = sum(job.status not in FINAL for job in self.jobs.values())
            if submitted < self.args.jobs and unfinished < self.args.backlog:
                self.submit(submitted)
                submitted += 1
            else:
                time.sleep(0.1)
            if time.monotonic() >= next_fault and sum(self.faults.values()) < self.args.faults:
                self.inject()
                next_fault = time.monotonic() + self.random.uniform(2, 8)
        # Faults over: every job must now reach a final state.
        settle = time.monotonic() + self.args.settle_seconds
        while time.monotonic() < settle:
            with self.lock:
                if all(job.status in FINAL for job in self.jobs.values()):
                    break
            time.sleep(1)
        time.sleep(2)  # one more round of polls of the finished jobs
        for job_id, job in list(self.jobs.items()):  # a last look at every job
            response = self.request("GET", f"/v1/jobs/{job_id}")
            if response is not None and response.status_code == 200:
                self.observe(job, response.json())
            elif response is not None and response.status_code == 404:
                job.vanished = True
        self.stop.set()
        poller.join(30)
        elapsed = time.monotonic() - started
        assert self.serve is not None
        self.serve.send_signal(signal.SIGTERM)
        self.serve.wait(60)
        lost = self.report(submitted, elapsed)
        shutil.rmtree(self.data, ignore_errors=True)
        return 1 if lost else 0

    def report(self, submitted: int, elapsed: float) -> int:
        succeeded_lines = Counter(re.findall(r"job (\S+) succeeded", self.log_path.read_text(errors="replace")))
        outcomes = Counter(job.status for job in self.jobs.values())
        reasons = Counter(
            re.sub(r"[0-9a-f]{6,}", "…", job.error or "")[:90] for job in self.jobs.values() if job.status == "failed"
        )
        lost = sum(job.vanished or job.status not in FINAL for job in self.jobs.values())
        duplicates = sum(len(job.finals) > 1 or succeeded_lines[job_id] > 1 for job_id, job in self.jobs.items())
        other_5xx = sum(count for code, count in self.codes.items() if code >= 500 and code != 503)
        retried = sum(job.attempts > 1 for job in self.jobs.values())
        rows = [
            ("seed", self.args.seed),
            ("run time", f"{elapsed:.0f} s"),
            ("jobs submitted (202)", submitted),
            ("succeeded", outcomes["succeeded"]),
            ("failed", outcomes["failed"]),
            *((f"failed: {reason}", count) for reason, count in reasons.items()),
            ("ran more than once (attempts > 1)", retried),
            ("lost (never final, or vanished)", lost),
            ("duplicates (ended twice)", duplicates),
            ("5xx answers other than 503", other_5xx),
            ("503 answers (Redis down or restarting)", self.codes[503]),
            ("POSTs without an answer (retried)", self.unknown_posts),
            ("faults injected", sum(self.faults.values())),
            *((f"fault: {kind}", count) for kind, count in sorted(self.faults.items())),
            ("longest time running without progress", f"{self.longest_stall:.1f} s"),
            ("API peak RSS", f"{self.peak_rss / 2**20:.0f} MB"),
        ]
        print("| | |\n|---|---|")
        for name, value in rows:
            print(f"| {name} | {value} |")
        return lost + duplicates + other_5xx


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--jobs", type=int, default=200, help="jobs to submit")
    parser.add_argument("--faults", type=int, default=30, help="faults to inject (at least)")
    parser.add_argument("--backlog", type=int, default=6, help="most unfinished jobs at a time")
    parser.add_argument("--max-seconds", type=float, default=900, help="stop submitting and injecting after this")
    parser.add_argument("--settle-seconds", type=float, default=180, help="time for the last jobs to finish")
    parser.add_argument("--port", type=int, default=8765)
    return Chaos(parser.parse_args()).run()


if __name__ == "__main__":
    sys.exit(main())
