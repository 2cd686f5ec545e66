"""The configuration of the service and of ``edgerecon fit``, read from the environment (pydantic-settings).

Every setting is ``EDGERECON_<NAME>`` (e.g. ``EDGERECON_JOB_TTL=3600``) except the Redis address,
which is the conventional ``REDIS_URL``. Empty variables count as unset. The API, the workers,
``edgerecon serve`` and ``edgerecon fit`` all read these settings at their start and pass them
down, so one environment configures everything; nothing below the entry points reads the
environment.
"""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path

from pydantic import AliasChoices, Field, SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict

from core.ply import MAX_POINTS, MIN_POINTS


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="EDGERECON_", env_ignore_empty=True, frozen=True)

    redis_url: str | None = Field(
        None,
        validation_alias=AliasChoices("REDIS_URL", "EDGERECON_REDIS_URL"),
        description="redis://host:port/db or unix:///path; unset: `edgerecon serve` starts its own Redis",
    )
    api_key: SecretStr | None = Field(None, description="when set, every /v1 route needs 'Authorization: Bearer <key>'")

    # `edgerecon serve`'s own Redis (when REDIS_URL is unset).
    data_dir: Path | None = Field(
        None,
        description="folder of the embedded Redis's data (append-only file); unset: $XDG_DATA_HOME/edgerecon,"
        " else ~/.local/share/edgerecon",
    )
    redis_maxmemory: int = Field(
        1024**3,
        ge=0,
        description="memory limit of the embedded Redis in bytes (0: none); when it is nearly full, new jobs get 507",
    )

    # Limits on what a user may send.
    max_upload_bytes: int = Field(
        64 * 1024 * 1024, ge=1024, description="largest request body, checked while it streams in"
    )
    min_points: int = Field(MIN_POINTS, ge=1, description="fewest points a cloud may have")
    max_points: int = Field(MAX_POINTS, ge=1, description="most points a cloud may have")
    max_uploads: int = Field(
        16, ge=1, description="uploads one API process receives and checks at once (each spools to disk); 503 beyond"
    )
    max_parsing: int = Field(
        2, ge=1, description="uploads one API process parses and stores at once (each costs CPU and memory); 503 beyond"
    )
    body_idle_timeout: float = Field(
        30.0, gt=0, description="seconds an upload may send nothing before it is dropped with 408"
    )

    # The API's Redis clients: a hung or lost Redis must turn into a prompt 503, not a hung request.
    redis_connect_timeout: float = Field(
        0.5, gt=0, le=30, description="seconds the API waits to connect to Redis before answering 503"
    )
    redis_socket_timeout: float = Field(
        0.5, gt=0, le=30, description="seconds the API waits for an answer of Redis before answering 503"
    )

    # Lifetimes.
    job_ttl: int = Field(
        24 * 3600, ge=1, description="seconds a job, its input and its results are kept after its last change"
    )
    job_timeout: int = Field(3600, ge=1, description="seconds a job may run before the worker stops it (failed)")
    heartbeat_ttl: int = Field(
        30, ge=2, description="a running job whose worker has not signalled for this many seconds is requeued or failed"
    )
    max_attempts: int = Field(
        2,
        ge=1,
        le=100,
        description="times a job may start: one whose worker dies or is shut down runs again until then, then fails",
    )
    sweep_interval: float = Field(10.0, gt=0, description="seconds between the API's checks for jobs of dead workers")
    progress_interval: float = Field(
        0.5, gt=0, description="seconds between a worker's progress writes (which also pick up cancellation)"
    )

    # Where things live in Redis: change them to run several services on one Redis.
    queue: str = Field("edgerecon", pattern=r"^[A-Za-z0-9_.-]+$", description="rq queue name")
    key_prefix: str = Field("edgerecon", pattern=r"^[A-Za-z0-9_.-]+$", description="prefix of every job key")

    # The worker process.
    worker_threads: int | None = Field(
        None,
        ge=1,
        le=256,
        description="torch threads per worker process; unset: the cores, shared among `edgerecon serve`'s workers",
    )
    worker_nice: int = Field(
        10, ge=0, le=19, description="added niceness of worker processes, so fits yield the CPU to the API's requests"
    )
    worker_warmup: bool = Field(
        True, description="fit a tiny cloud at worker start so the first job pays no compile time"
    )

    # The fitting core, in workers and in `edgerecon fit` (core.runtime.configure).
    compile: bool = Field(
        True, description="compile the network's kernels with torch.compile (0: run them eagerly, no compile time)"
    )

    # Live progress (GET /v1/jobs/{id}/events), per API process.
    max_event_streams: int = Field(
        100,
        ge=0,
        description="event streams one API process serves at once (each holds a Redis connection); 503 beyond",
    )
    event_keepalive: float = Field(
        10.0,
        gt=0,
        le=15,
        description="seconds of silence after which an event stream sends a keep-alive comment (FastAPI pings at 15)",
    )

    # Metrics (GET /metrics).
    metrics_need_api_key: bool = Field(
        False, description="whether GET /metrics needs the API key (when one is set); off: scrapers need no secret"
    )

    def data_path(self) -> Path:
        """Where the embedded Redis keeps its data: ``data_dir``, or the user's data folder (XDG),
        never a temporary one, so that jobs outlive a restart."""
        if self.data_dir is not None:
            return self.data_dir
        xdg = os.environ.get("XDG_DATA_HOME")
        return (Path(xdg) if xdg else Path.home() / ".local" / "share") / "edgerecon"

    def torch_threads(self, workers: int = 1) -> int:
        """Torch threads for each of ``workers`` worker processes on this machine: ``worker_threads``
        if set, else the cores this process may use shared among them, so that a lone job on an idle
        machine uses all of it and several workers do not oversubscribe it."""
        if self.worker_threads is not None:
            return self.worker_threads
        return max(1, len(os.sched_getaffinity(0)) // max(1, workers))


@lru_cache
def get_settings() -> Settings:
    """The settings of this process, read once."""
    return Settings()
