"""worker.job: the rq job run in-process by a JobRunner against a real Redis (no rq worker, tiny fits).

What a job's record shows for each outcome, and that only the user's errors (no surface, an
expired input) become a user-facing failure; a bug keeps its traceback.
"""

from __future__ import annotations

import uuid

import pytest

from core import network
from core.params import FitParams
from tests.helpers import TINY, sphere
from worker.contract import OUTPUT_NAMES, SHUTDOWN, JobStatus, Stage, new_job_id
from worker.job import JobRunner, run_reconstruction
from worker.settings import Settings
from worker.store import JobStore

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(autouse=True)
def eager_kernels(monkeypatch):
    """Tiny fits: compiling their kernels would take longer than running them."""
    monkeypatch.setattr(network._kernels, "compiled", False)


@pytest.fixture
def runner(redis_server):
    run = f"test-{uuid.uuid4().hex[:12]}"
    redis = redis_server.client()
    settings = Settings(key_prefix=run, queue=run, job_ttl=60, progress_interval=0.05)
    yield JobRunner(JobStore(redis, settings), settings)
    redis.close()


def submit(runner: JobRunner, **params) -> str:
    job_id = new_job_id()
    runner.store.create(job_id, sphere(400), FitParams(**{**TINY, **params}))
    return job_id


def test_the_job_function_runs_only_inside_a_worker(runner):
    job_id = submit(runner)
    with pytest.raises(RuntimeError, match="inside an edgerecon worker"):
        run_reconstruction(job_id)
    assert runner.store.get(job_id).status == JobStatus.QUEUED
    with runner.serving():
        run_reconstruction(job_id)
    assert runner.store.get(job_id).status == JobStatus.SUCCEEDED


def test_a_job_runs_to_success_with_its_outputs_progress_and_summary(runner):
    job_id = submit(runner)
    seen_running: list[str | None] = []
    write = runner.store.set_progress
    runner.store.set_progress = lambda job, progress, attempt: (
        seen_running.append(runner.running_job) or write(job, progress, attempt)
    )
    runner.run(job_id, "worker-1")
    record = runner.store.get(job_id)
    assert record.status == JobStatus.SUCCEEDED and record.worker == "worker-1" and record.error is None
    assert record.progress.stage == Stage.EXTRACTING and "total" in record.progress.losses
    assert set(record.result) >= {"vertices", "faces", "watertight", "edge_points", "timings"}
    assert all(runner.store.output(job_id, name)[1] for name in OUTPUT_NAMES)
    assert seen_running and set(seen_running) == {job_id}  # the heartbeat's job while it ran...
    assert runner.running_job is None  # ...and none after


def test_a_job_canceled_while_queued_is_not_run(runner):
    job_id = submit(runner)
    runner.store.cancel(job_id)
    runner.run(job_id, "worker-1")
    record = runner.store.get(job_id)
    assert record.status == JobStatus.CANCELED and record.started_at is None


def test_an_expired_input_fails_the_job_with_a_reason_for_the_user(runner):
    job_id = submit(runner)
    runner.store.redis.delete(f"{runner.store.prefix}:job:{job_id}:points")
    runner.run(job_id, "worker-1")
    record = runner.store.get(job_id)
    assert record.status == JobStatus.FAILED and record.error == "the job's input has expired"


def test_a_fit_without_a_surface_fails_the_job_with_the_cores_message(runner, monkeypatch):
    import core.reconstruct
    from core.errors import EmptySurfaceError

    def no_surface(*args, **kwargs):
        raise EmptySurfaceError("the fitted function has no zero level set (simulated)")

    monkeypatch.setattr(core.reconstruct, "reconstruct", no_surface)
    job_id = submit(runner)
    runner.run(job_id, "worker-1")
    record = runner.store.get(job_id)
    assert record.status == JobStatus.FAILED
    assert record.error == "the fitted function has no zero level set (simulated)"


def test_a_bug_is_not_blamed_on_the_input_and_keeps_its_traceback(runner, monkeypatch):
    import core.reconstruct

    def broken(*args, **kwargs):
        raise KeyError("a bug (simulated)")

    monkeypatch.setattr(core.reconstruct, "reconstruct", broken)
    job_id = submit(runner)
    with pytest.raises(KeyError, match="a bug"):
        runner.run(job_id, "worker-1")
    record = runner.store.get(job_id)
    assert record.status == JobStatus.FAILED
    assert record.error == "the reconstruction failed: KeyError: 'a bug (simulated)'"


def test_a_shutdown_puts_the_running_job_back_in_the_queue_then_fails_it_on_its_last_attempt(runner):
    job_id = submit(runner, iterations=100_000)
    runner.shutdown.set()
    runner.run(job_id, "worker-1")
    record = runner.store.get(job_id)
    assert record.status == JobStatus.QUEUED and record.attempts == 1 and record.error is None
    assert runner.store.load_points(job_id) is not None  # kept for the next attempt
    runner.run(job_id, "worker-2")  # the last of EDGERECON_MAX_ATTEMPTS=2
    record = runner.store.get(job_id)
    assert record.status == JobStatus.FAILED and record.attempts == 2
    assert record.error == f"{SHUTDOWN}, after 2 attempts (the most allowed); submit the job again"


def test_a_users_error_is_never_retried_and_its_input_is_deleted(runner):
    job_id = submit(runner, resolution=32, iterations=1, width=16, depth=1, lambda3=0)
    runner.store.cancel(job_id)
    assert not runner.store.redis.exists(f"{runner.store.prefix}:job:{job_id}:points")
    failing = submit(runner)
    runner.store.redis.delete(f"{runner.store.prefix}:job:{failing}:points")
    runner.run(failing, "worker-1")
    record = runner.store.get(failing)
    assert record.status == JobStatus.FAILED and record.attempts == 1
    assert runner.store.queue.job_ids == [failing]  # only its first rq job (run here without rq): no retry


def test_a_cancel_while_running_stops_the_fit_at_its_next_progress_write(runner):
    job_id = submit(runner, iterations=100_000)
    write = runner.store.set_progress

    def cancel_at_the_tenth_step(job, progress, attempt):
        if progress.iteration >= 10:
            runner.store.cancel(job)
        return write(job, progress, attempt)

    runner.store.set_progress = cancel_at_the_tenth_step
    runner.run(job_id, "worker-1")
    record = runner.store.get(job_id)
    assert record.status == JobStatus.CANCELED and record.progress.iteration < 1000
    assert runner.store.output(job_id, "mesh.obj") == (JobStatus.CANCELED, None)
