"""The rq job: reconstruct one stored cloud, with progress, cancellation and a readable failure reason.

rq calls ``run_reconstruction(job_id)`` (enqueued by that name, ``worker.contract.JOB_FUNCTION``)
inside a worker process (``worker.process``) that has already imported torch. Everything about the
job is in Redis (``worker.store``): its parameters and points before, its outputs or its error
after. What the job needs from the process that runs it (the store, the settings, the shutdown
flag) is a ``JobRunner``, which that process makes current with ``JobRunner.serving``: rq calls
the job function by name, so it cannot be handed an object.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar

from redis.exceptions import RedisError
from rq import get_current_job
from rq.timeouts import JobTimeoutException

from core.errors import Cancelled, EdgereconError
from core.params import FitParams
from worker.contract import SHUTDOWN, Progress, Stage
from worker.errors import InputExpired
from worker.settings import Settings
from worker.store import JobStore

log = logging.getLogger("edgerecon.worker")

_current_runner: ContextVar[JobRunner] = ContextVar("edgerecon_job_runner")


def run_reconstruction(job_id: str) -> None:
    """Run job ``job_id`` if it is still queued; record its outputs, or why it failed."""
    try:
        runner = _current_runner.get()
    except LookupError:
        raise RuntimeError("run_reconstruction runs inside an edgerecon worker (JobRunner.serving)") from None
    current = get_current_job()
    worker = (current.worker_name if current else None) or f"pid-{os.getpid()}"
    runner.run(job_id, worker, int(current.timeout) if current and current.timeout else None)


class JobRunner:
    """Runs jobs in one worker process: ``running_job`` is the id of the job it runs now (which
    the worker's heartbeat keeps alive), ``shutdown`` the flag that stops it at its next step."""

    def __init__(self, store: JobStore, settings: Settings):
        self.store, self.settings = store, settings
        self.shutdown = threading.Event()
        self.running_job: str | None = None

    @contextmanager
    def serving(self) -> Iterator[JobRunner]:
        """Make this the runner of the rq jobs that this thread runs, while the block lasts."""
        token = _current_runner.set(self)
        try:
            yield self
        finally:
            _current_runner.reset(token)

    def run(self, job_id: str, worker: str, timeout: int | None = None) -> None:
        """Run job ``job_id`` on ``worker`` if it is still queued; ``timeout`` is its time limit, for the message."""
        self.running_job = job_id
        try:
            started = self.store.start(job_id, worker)
            if started is None:
                log.info("job %s is no longer queued (canceled, taken or expired): not run", job_id)
                return
            params, attempt = started
            self._reconstruct(job_id, params, attempt, timeout)
        finally:
            self.running_job = None

    def _reconstruct(self, job_id: str, params: FitParams, attempt: int, timeout: int | None) -> None:
        """Run the ``attempt``-th run of the job; every write names the attempt, so that a run the
        service has given up on (its heartbeat lapsed, the job runs again elsewhere) changes nothing."""
        from core.reconstruct import reconstruct  # torch: only ever imported in worker processes

        store = self.store
        control = _JobControl(store, job_id, attempt, self.settings.progress_interval, self.shutdown)
        try:
            points = store.load_points(job_id)
            result = reconstruct(points, params, progress=control.progress, should_cancel=control.should_cancel)
            summary = result.summary()
            if store.succeed(job_id, result.outputs(), summary, attempt):
                log.info("job %s succeeded: %s", job_id, summary)
                store.observe_durations(
                    {"fitting": result.timings["fit_seconds"], "extracting": result.timings["extract_seconds"]}
                )
        except Cancelled:
            if self.shutdown.is_set():  # the job is not at fault: another worker runs it (attempts allowing)
                store.release(job_id, SHUTDOWN, attempt)
            log.info("job %s stopped: %s", job_id, "worker shutting down" if self.shutdown.is_set() else "canceled")
        except (EdgereconError, InputExpired) as error:  # the user's input: no surface, input expired...
            store.fail(job_id, str(error), attempt)
        except JobTimeoutException:
            store.fail(job_id, f"the job ran longer than its time limit of {timeout} s", attempt)
            raise
        except (KeyboardInterrupt, SystemExit):  # the worker's cold shutdown
            store.release(job_id, SHUTDOWN, attempt)
            raise
        except BaseException as error:  # a bug or the machine (MemoryError...): keep the traceback in rq
            store.fail(job_id, f"the reconstruction failed: {type(error).__name__}: {error}", attempt)
            raise


class _JobControl:
    """The progress callback and cancel check of one running job.

    Progress is written at most once per ``interval`` seconds (plus the first and last steps and
    each new stage), and each write is conditional on the job still running. ``should_cancel``,
    which core polls before every fitting step and every chunk of extraction, reads the status
    itself when no write has for ``interval`` seconds. So a cancel, a crash verdict or the
    worker's shutdown stops the job within about one interval, whatever stage it is in.
    """

    def __init__(self, store: JobStore, job_id: str, attempt: int, interval: float, shutdown: threading.Event):
        self.store, self.job_id, self.attempt, self.interval, self.shutdown = store, job_id, attempt, interval, shutdown
        self.last_write = -math.inf
        self.last_check = time.monotonic()
        self.losses: dict[str, float | None] | None = None
        self.stopped = False

    def progress(self, update: Progress) -> None:
        now = time.monotonic()
        milestone = update.stage != Stage.FITTING or update.iteration in (1, update.total)
        if now - self.last_write < self.interval and not milestone:
            return
        self.last_write = self.last_check = now
        if update.losses:  # extraction reports none: keep showing the last ones
            self.losses = {name: _finite(value) for name, value in update.losses.items()}
        report = update.model_copy(update={"losses": self.losses, "edge_share": _finite(update.edge_share)})
        if not self.store.set_progress(self.job_id, report, self.attempt):
            self.stopped = True

    def should_cancel(self) -> bool:
        if self.stopped or self.shutdown.is_set():
            return True
        now = time.monotonic()
        if now - self.last_check >= self.interval:
            self.last_check = now
            try:
                self.stopped = not self.store.is_running(self.job_id, self.attempt)
            except RedisError as error:  # Redis unreachable: keep working, check again later
                log.warning("job %s: status check failed: %s", self.job_id, error)
        return self.stopped


def _finite(value: float | None) -> float | None:
    """``value`` to 6 significant digits, or None for None, NaN and infinities (not valid JSON)."""
    return float(f"{value:.6g}") if value is not None and math.isfinite(value) else None
