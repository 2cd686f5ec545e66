"""The worker process (``edgerecon worker``): one rq SimpleWorker that owns torch, and a heartbeat thread.

Why a SimpleWorker, which runs each job in the worker process itself, rather than rq's default
Worker, which forks a "work horse" per job: torch's OpenMP thread pool is not fork-safe, and a
work horse forked before torch is loaded would pay the torch import and the torch.compile warm-up
(seconds) on every job. So each worker process imports torch once, sets its thread count, compiles
the kernels on a tiny warm-up fit, and then runs jobs one after another. What the forking Worker
gave for free is rebuilt on the job's record (``worker.store``):

- cancel: the job's progress writes (a few per second) find the status changed to ``canceled`` and
  core stops at its next step;
- crash: the heartbeat thread keeps ``{prefix}:job:{id}:alive`` alive while a job runs; if the
  process dies (SIGKILL, OOM), the key expires after ``heartbeat_ttl`` seconds and the API fails the
  job (when its status is read, and in its periodic sweep);
- shutdown: the first SIGINT/SIGTERM stops the running job at its next step (it fails with "the
  worker was shut down"), then the worker exits; a second signal exits at once (rq's cold shutdown).

A worker uses ``Settings.torch_threads()`` torch threads: ``EDGERECON_WORKER_THREADS``, or by default
every core (``edgerecon serve --workers N`` sets cores // N for each). Scale by running more worker
processes: one per core with ``EDGERECON_WORKER_THREADS=1``, or fewer with more threads each.
Workers lower their CPU priority (``EDGERECON_WORKER_NICE``, +10 by default) so that on shared
cores the API's status polls stay fast while fits run.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
from types import FrameType
from typing import Any, NoReturn

from redis.exceptions import RedisError
from rq.serializers import JSONSerializer
from rq.worker import SimpleWorker

from worker.connection import connect
from worker.job import JobRunner
from worker.registry import WorkerRegistry
from worker.settings import Settings, get_settings
from worker.store import JobStore

log = logging.getLogger("edgerecon.worker")


class FitWorker(SimpleWorker):
    """A SimpleWorker whose first SIGINT/SIGTERM also stops the running job at its next step."""

    PUBSUB_POLL_SECONDS = 1.0

    def __init__(self, *args: Any, runner: JobRunner, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.runner = runner

    def subscribe(self) -> None:
        """rq's subscription to its command channel, polled every second instead of every 60 s.

        Why: at shutdown rq unsubscribes and then stops the listener thread, and redis-py 8 joins that
        thread with no time limit. When the thread has read the unsubscribe reply before the stop, it
        waits for a new subscription for its whole poll period, and so did the worker's exit (the
        service's stop took 15 s, its kill, on a busy machine)."""
        self.log.info("Worker %s: subscribing to channel %s", self.name, self.pubsub_channel_name)
        self.pubsub = self.connection.pubsub()
        self.pubsub.subscribe(**{self.pubsub_channel_name: self.handle_payload})
        self.pubsub_thread = self.pubsub.run_in_thread(  # type: ignore[assignment]  # rq types it None
            sleep_time=self.PUBSUB_POLL_SECONDS, daemon=True, exception_handler=self._pubsub_exception_handler
        )

    def request_stop(self, signum: int, frame: FrameType | None) -> None:
        self.runner.shutdown.set()
        super().request_stop(signum, frame)


class Heartbeat(threading.Thread):
    """Every ``period`` seconds: announce the worker, and keep the job its runner runs (if any) alive."""

    def __init__(self, registry: WorkerRegistry, runner: JobRunner, worker_name: str, period: float):
        super().__init__(name="edgerecon-heartbeat", daemon=True)
        self.registry, self.runner, self.worker_name, self.period = registry, runner, worker_name, period
        self.stopping = threading.Event()

    def run(self) -> None:
        while not self.stopping.is_set():
            try:
                self.registry.beat(self.worker_name)
                job_id = self.runner.running_job
                if job_id:
                    self.runner.store.keep_alive(job_id, self.worker_name)
            except RedisError as error:
                log.warning("heartbeat failed: %s", error)
            self.stopping.wait(self.period)

    def stop(self) -> None:
        self.stopping.set()
        self.join()
        try:
            self.registry.withdraw(self.worker_name)
        except RedisError:
            pass


def main() -> int:
    """Run one worker against REDIS_URL until SIGINT/SIGTERM; the process ends here (``_exit_now``)."""
    settings = get_settings()
    if not settings.redis_url:
        print("edgerecon worker: REDIS_URL is not set; point it at the Redis the API uses", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    # Fits are batch work: when they share cores with the API, its status polls should win.
    os.nice(settings.worker_nice)
    try:
        prepare_torch(settings)
    except KeyboardInterrupt:
        return 130
    redis = connect(settings.redis_url)
    runner = JobRunner(JobStore(redis, settings), settings)
    worker = FitWorker([runner.store.queue], connection=redis, serializer=JSONSerializer, runner=runner)
    heartbeat = Heartbeat(WorkerRegistry(redis, settings), runner, worker.name, period=settings.heartbeat_ttl / 3)
    heartbeat.start()
    code = 0
    try:
        with runner.serving():
            worker.work(logging_level="INFO")
    except RedisError as error:  # Redis went away during the stop (its job is requeued by the API's sweep)
        log.error("stopping without Redis: %s", error)
        code = 1
    finally:
        heartbeat.stop()
    _exit_now(code)


def _exit_now(code: int) -> NoReturn:
    """End the process without the interpreter's teardown, once logs are flushed.

    Why: with torch loaded, the teardown's garbage collection takes about 1 s of CPU, and a worker
    at niceness 10 on a busy machine got so little of it that its exit took 15 s after its job
    was already back in the queue. Nothing else is left to write: jobs and outputs are in Redis."""
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def prepare_torch(settings: Settings) -> None:
    """Import torch and core once, configure them, and (optionally) compile on a tiny fit."""
    from core.runtime import configure

    configure(compile=settings.compile, threads=settings.torch_threads())
    import torch

    if settings.worker_warmup:
        log.info("warming up (torch.compile of the network's kernels)...")
        warm_kernels()
    log.info("torch ready: %d thread(s)", torch.get_num_threads())


def warm_kernels() -> None:
    """Compile every kernel a job calls: two-step fits of a tiny cloud (the kernels compiled for
    dynamic shapes, and the extraction's), then the first compiled steps of default fits of a
    cloud of ``HALF_BATCH_MIN_POINTS`` (the steps compiled whole for a default job's shapes); one of
    each network a job may train, without Fourier features and with them (a fit that starts
    again). The worker runs it at its start, the Dockerfile at the image's build."""
    from core.errors import Cancelled, EdgereconError
    from core.fit import EAGER_STEPS, HALF_BATCH_MIN_POINTS, fit
    from core.params import FitParams
    from core.progress import Progress
    from core.reconstruct import reconstruct
    from evaluation.shapes import sample_shape

    points = sample_shape("sphere", n_points=400).points
    dense = sample_shape("sphere", n_points=HALF_BATCH_MIN_POINTS).points
    steps: list[int] = []

    def record(update: Progress) -> None:
        steps.append(update.iteration)

    for encoding in ("never", "always"):
        try:
            reconstruct(points, FitParams(iterations=2, resolution=32, encoding=encoding))
        except EdgereconError as error:  # two steps may leave no surface: the kernels are compiled anyway
            log.info("warm-up fit: %s", error)
        steps.clear()
        try:  # the first compiled step waits for every shape's compile, then the fit stops
            fit(dense, FitParams(encoding=encoding), record, lambda: len(steps) > EAGER_STEPS)
        except Cancelled:
            pass


if __name__ == "__main__":
    sys.exit(main())
