"""The rq job: reconstruct one stored cloud, with progress, cancellation and a readable failure reason.

rq calls ``run_reconstruction(job_id)`` inside a worker process (``worker.main``) that has already
imported torch. Everything about the job is in Redis (``service.store``): its parameters and points
before, and its outputs or its error after.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from functools import lru_cache

from redis.exceptions import RedisError
from rq import get_current_job
from rq.timeouts import JobTimeoutException

from core.errors import Cancelled, EdgereconError
from service.settings import get_settings
from service.store import Store, connect

log = logging.getLogger("edgerecon.worker")

SHUTDOWN = "the worker was shut down while running this job; submit the job again"

# Set by the worker's SIGINT/SIGTERM handler: the running job stops at its next step.
shutdown_requested = threading.Event()
# The job this process is running, which the worker's heartbeat thread keeps alive.
running_job: str | None = None


@lru_cache
def get_store() -> Store:
    """This process's store, from the environment's settings."""
    settings = get_settings()
    return Store(connect(settings.redis_url), settings)


def run_reconstruction(job_id: str) -> None:
    """Run job ``job_id`` if it is still queued; record its outputs, or why it failed."""
    global running_job
    store = get_store()
    current = get_current_job()
    worker = (current.worker_name if current else None) or f"pid-{os.getpid()}"
    running_job = job_id
    try:
        params = store.start(job_id, worker)
        if params is None:
            log.info("job %s is no longer queued (canceled or expired): not run", job_id)
            return
        _reconstruct(store, job_id, params, current.timeout if current else None)
    finally:
        running_job = None


def _reconstruct(store: Store, job_id: str, params, timeout: int | None) -> None:
    from core.reconstruct import reconstruct  # torch: only ever imported in worker processes

    control = _JobControl(store, job_id, get_settings().progress_interval)
    try:
        points = store.load_points(job_id)
        result = reconstruct(points, params, progress=control.progress, should_cancel=control.should_cancel)
        if store.succeed(job_id, result.outputs(), result.summary()):
            log.info("job %s succeeded: %s", job_id, result.summary())
    except Cancelled:
        if shutdown_requested.is_set():
            store.fail(job_id, SHUTDOWN)
        log.info("job %s stopped: %s", job_id, "worker shutting down" if shutdown_requested.is_set() else "canceled")
    except (EdgereconError, LookupError) as error:  # the user's input: no surface, input expired...
        store.fail(job_id, str(error))
    except JobTimeoutException:
        store.fail(job_id, f"the job ran longer than its time limit of {timeout} s")
        raise
    except (KeyboardInterrupt, SystemExit):  # the worker's cold shutdown
        store.fail(job_id, SHUTDOWN)
        raise
    except BaseException as error:  # a bug or the machine (MemoryError...): keep the traceback in rq
        store.fail(job_id, f"the reconstruction failed: {type(error).__name__}: {error}")
        raise


class _JobControl:
    """The progress callback and cancel check of one running job.

    Progress is written at most once per ``interval`` seconds (plus the first and last steps and
    each new stage), and each write is conditional on the job still running. ``should_cancel``,
    which core polls before every fitting step and every chunk of extraction, reads the status
    itself when no write has for ``interval`` seconds. So a cancel, a crash verdict or the
    worker's shutdown stops the job within about one interval, whatever stage it is in.
    """

    def __init__(self, store: Store, job_id: str, interval: float):
        self.store, self.job_id, self.interval = store, job_id, interval
        self.last_write = -math.inf
        self.last_check = time.monotonic()
        self.losses: dict = {}
        self.stopped = False

    def progress(self, update) -> None:
        now = time.monotonic()
        milestone = update.stage != "fitting" or update.iteration in (1, update.total)
        if now - self.last_write < self.interval and not milestone:
            return
        self.last_write = self.last_check = now
        if update.losses:  # extraction reports none: keep showing the last ones
            self.losses = {name: _finite(value) for name, value in update.losses.items()}
        report = {
            "stage": update.stage,
            "iteration": update.iteration,
            "total": update.total,
            "losses": self.losses,
            "edge_share": _finite(update.edge_share),
        }
        if not self.store.set_progress(self.job_id, report):
            self.stopped = True

    def should_cancel(self) -> bool:
        if self.stopped or shutdown_requested.is_set():
            return True
        now = time.monotonic()
        if now - self.last_check >= self.interval:
            self.last_check = now
            try:
                self.stopped = not self.store.is_running(self.job_id)
            except RedisError as error:  # Redis unreachable: keep working, check again later
                log.warning("job %s: status check failed: %s", self.job_id, error)
        return self.stopped


def _finite(value: float) -> float | None:
    """``value`` to 6 significant digits, or None for NaN and infinities (not valid JSON)."""
    return float(f"{value:.6g}") if math.isfinite(value) else None
