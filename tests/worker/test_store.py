"""worker.store.JobStore: the job state machine, in-process against a real redis-server.

Every move of queued -> running -> succeeded | failed | canceled (and queued -> canceled), what
each refuses, and the races between the API, a worker and the crash verdict: the first write wins,
and a late write from a worker whose job moved on changes nothing.
"""

from __future__ import annotations

import asyncio
import importlib
import socket
import threading
import time
import uuid

import numpy as np
import pytest
from redis.asyncio import Redis as AsyncRedis
from redis.exceptions import RedisError
from rq.job import Job
from rq.serializers import JSONSerializer

from core.params import FitParams
from tests.helpers import sphere
from worker.connection import connect
from worker.contract import JOB_FUNCTION, ORPHANED, OUTPUT_NAMES, JobStatus, Progress, Stage, new_job_id
from worker.errors import InputExpired, InvalidJobId, StoreFull
from worker.redis_server import RedisServer
from worker.settings import Settings
from worker.store import JobStore

TTL = 60
OUTPUTS = {name: f"the content of {name}".encode() for name in OUTPUT_NAMES}
SUMMARY = {"vertices": 8, "faces": 12, "watertight": True, "edge_points": 3, "timings": {"fit_seconds": 1.5}}
PARAMS = FitParams(iterations=30, tau=15)
FITTING = Progress(stage=Stage.FITTING, iteration=3, total=30, losses={"total": 0.5, "eikonal": None}, edge_share=0.1)


@pytest.fixture
def settings() -> Settings:
    run = f"test-{uuid.uuid4().hex[:12]}"
    return Settings(key_prefix=run, queue=run, job_ttl=TTL, heartbeat_ttl=5)


@pytest.fixture
def store(redis_server, settings):
    redis = redis_server.client()
    yield JobStore(redis, settings)
    redis.close()


def new_job(store: JobStore, points: np.ndarray | None = None) -> str:
    job_id = new_job_id()
    store.create(job_id, sphere(300) if points is None else points, PARAMS)
    return job_id


def running_job(store: JobStore, worker: str = "worker-1") -> str:
    job_id = new_job(store)
    assert store.start(job_id, worker) == (PARAMS, 1)
    return job_id


def settings_of(store: JobStore) -> Settings:
    return Settings(key_prefix=store.prefix, queue=store.queue.name, job_ttl=TTL, heartbeat_ttl=5)


def status(store: JobStore, job_id: str) -> JobStatus | None:
    record = store.get(job_id)
    return record.status if record else None


def kept_outputs(store: JobStore, job_id: str) -> list[str]:
    return [name for name in OUTPUT_NAMES if store.redis.exists(f"{store.prefix}:job:{job_id}:{name}")]


def is_in_running_set(store: JobStore, job_id: str) -> bool:
    return bool(store.redis.sismember(f"{store.prefix}:running", job_id))


def kill_worker_of(store: JobStore, job_id: str) -> None:
    """What a SIGKILLed worker leaves: its heartbeat for the job lapses."""
    store.redis.delete(f"{store.prefix}:job:{job_id}:alive")


# --- every transition ----------------------------------------------------------------------------


def test_a_new_job_is_queued_with_its_input_and_parameters(store):
    points = sphere(300, seed=4)
    job_id = new_job(store, points)
    record = store.get(job_id)
    assert record is not None
    assert (record.id, record.status, record.params, record.points) == (job_id, JobStatus.QUEUED, PARAMS, 300)
    assert record.progress is None and record.started_at is None and record.ended_at is None
    assert record.error is None and record.result is None and record.worker is None
    assert record.created_at.tzinfo is not None and record.expires_at is not None
    assert 0 < (record.expires_at - record.created_at).total_seconds() <= TTL + 1
    np.testing.assert_array_equal(store.load_points(job_id), points)


def test_a_new_job_is_enqueued_for_the_job_function_by_name_with_only_its_id(store):
    job_id = new_job(store)
    assert store.queue.job_ids == [job_id]
    job = Job.fetch(job_id, connection=store.redis, serializer=JSONSerializer)  # JSON: never a pickle
    assert job.func_name == JOB_FUNCTION and list(job.args) == [job_id] and not job.kwargs
    from worker.job import run_reconstruction

    module, _, name = JOB_FUNCTION.rpartition(".")
    assert getattr(importlib.import_module(module), name) is run_reconstruction


def test_start_moves_a_queued_job_to_running_and_returns_its_parameters(store):
    job_id = new_job(store)
    assert store.start(job_id, "worker-1") == (PARAMS, 1)
    record = store.get(job_id)
    assert record.status == JobStatus.RUNNING and record.worker == "worker-1" and record.started_at
    assert record.progress == Progress(stage=Stage.STARTING, iteration=0, total=0)
    assert is_in_running_set(store, job_id) and store.is_running(job_id)
    assert store.redis.get(f"{store.prefix}:job:{job_id}:alive") == b"worker-1"  # its heartbeat


def test_a_job_starts_only_once(store):
    job_id = running_job(store, "worker-1")
    started_at = store.get(job_id).started_at
    assert store.start(job_id, "worker-2") is None
    record = store.get(job_id)
    assert record.worker == "worker-1" and record.started_at == started_at


def test_progress_of_a_running_job_is_recorded_and_restarts_every_expiry(store):
    job_id = running_job(store)
    for key in store.redis.keys(f"{store.prefix}:job:{job_id}*"):
        store.redis.expire(key, 5)
    assert store.set_progress(job_id, FITTING)
    assert store.get(job_id).progress == FITTING
    ttls = [store.redis.ttl(f"{store.prefix}:job:{job_id}{part}") for part in ("", ":points")]
    assert all(TTL - 2 <= ttl <= TTL for ttl in ttls), ttls


def test_succeed_stores_the_outputs_and_the_summary(store):
    job_id = running_job(store)
    assert store.succeed(job_id, OUTPUTS, SUMMARY)
    record = store.get(job_id)
    assert record.status == JobStatus.SUCCEEDED and record.ended_at and record.result == SUMMARY
    assert record.error is None
    for name in OUTPUT_NAMES:
        assert store.output(job_id, name) == (JobStatus.SUCCEEDED, OUTPUTS[name])
    assert not is_in_running_set(store, job_id) and not store.is_running(job_id)


def test_every_write_of_a_record_is_announced_on_its_channel_with_the_new_status(store):
    job_id = new_job(store)
    with store.redis.pubsub(ignore_subscribe_messages=True) as changes:
        changes.subscribe(store.changes_channel(job_id))
        store.start(job_id, "worker-1")
        store.set_progress(job_id, FITTING)
        store.cancel(job_id)
        assert not store.set_progress(job_id, FITTING)  # refused: announces nothing
        heard, deadline = [], time.monotonic() + 2
        while time.monotonic() < deadline:  # whatever arrives within 2 s
            if message := changes.get_message(timeout=0.1):
                heard.append(message["data"].decode())
    assert heard == ["running", "running", "canceled"]


def test_the_counts_of_statuses_entered_and_the_stage_histograms_follow_the_transitions(store, redis_server):
    succeeded, canceled, refused = running_job(store), new_job(store), running_job(store)
    store.succeed(succeeded, OUTPUTS, SUMMARY)
    store.cancel(canceled)
    store.fail(refused, "no surface")
    store.cancel(canceled), store.succeed(refused, OUTPUTS, SUMMARY)  # refused moves count nothing
    store.observe_durations({"fitting": 3.0, "extracting": 0.2})
    store.observe_durations({"fitting": 7000.0})

    async def read():
        async with AsyncRedis.from_url(redis_server.url) as client:
            return await JobStore(store.redis, settings_of(store), client).stats_async()

    stats = asyncio.run(read())
    assert stats.entered == {"queued": 3, "running": 2, "succeeded": 1, "canceled": 1, "failed": 1}
    assert stats.running == 0  # (stats.queued is rq's queue, which no worker pops here: see tests/service)
    fitting = stats.durations["fitting"]
    assert fitting.count == 2 and fitting.sum == 7003.0
    assert (fitting.buckets[2.5], fitting.buckets[5.0], fitting.buckets[5000.0]) == (0, 1, 1)  # cumulative
    assert stats.durations["extracting"].buckets[0.5] == 1
    assert stats.durations["queued"].count == 2  # observed by start, for the two jobs that started


def test_every_key_of_a_job_expires_together(store):
    job_id = running_job(store)
    store.set_progress(job_id, FITTING)
    ttls = [store.redis.ttl(f"{store.prefix}:job:{job_id}{part}") for part in ("", ":points")]
    assert all(0 < ttl <= TTL for ttl in ttls) and max(ttls) - min(ttls) <= 1, ttls
    store.succeed(job_id, OUTPUTS, SUMMARY)  # the input is deleted; the outputs expire with the record
    parts = ("", *(f":{name}" for name in OUTPUT_NAMES))
    ttls = [store.redis.ttl(f"{store.prefix}:job:{job_id}{part}") for part in parts]
    assert all(0 < ttl <= TTL for ttl in ttls) and max(ttls) - min(ttls) <= 1, ttls


def test_fail_records_a_reason_the_user_can_read(store):
    job_id = running_job(store)
    assert store.fail(job_id, "there is no surface")
    record = store.get(job_id)
    assert record.status == JobStatus.FAILED and record.error == "there is no surface" and record.ended_at
    assert not is_in_running_set(store, job_id)


def test_cancel_of_a_queued_job_takes_it_off_the_queue(store):
    job_id = new_job(store)
    assert store.cancel(job_id) == JobStatus.QUEUED
    record = store.get(job_id)
    assert record.status == JobStatus.CANCELED and record.ended_at and record.started_at is None
    assert store.queue.job_ids == [] and not Job.exists(job_id, connection=store.redis)


def test_cancel_of_a_running_job_makes_its_next_progress_write_fail(store):
    job_id = running_job(store)
    assert store.cancel(job_id) == JobStatus.RUNNING
    assert status(store, job_id) == JobStatus.CANCELED
    assert not store.set_progress(job_id, FITTING) and not store.is_running(job_id)
    assert store.get(job_id).progress.stage == Stage.STARTING  # the refused write left no trace
    assert not is_in_running_set(store, job_id)


@pytest.mark.parametrize("final", [JobStatus.SUCCEEDED, JobStatus.FAILED, JobStatus.CANCELED])
def test_a_finished_job_does_not_move_again(store, final):
    job_id = running_job(store)
    {
        JobStatus.SUCCEEDED: lambda: store.succeed(job_id, OUTPUTS, SUMMARY),
        JobStatus.FAILED: lambda: store.fail(job_id, "first reason"),
        JobStatus.CANCELED: lambda: store.cancel(job_id),
    }[final]()
    before = store.get(job_id)
    assert store.cancel(job_id) == final  # canceling a canceled job answers "canceled", changes nothing
    assert store.start(job_id, "worker-2") is None
    assert not store.set_progress(job_id, FITTING)
    assert not store.fail(job_id, "second reason")
    assert not store.succeed(job_id, OUTPUTS, SUMMARY)
    after = store.get(job_id)
    assert after.model_dump(exclude={"expires_at"}) == before.model_dump(exclude={"expires_at"})
    assert kept_outputs(store, job_id) == (list(OUTPUT_NAMES) if final == JobStatus.SUCCEEDED else [])


def test_outputs_are_withheld_until_the_job_succeeds(store):
    job_id = new_job(store)
    assert store.output(job_id, "mesh.obj") == (JobStatus.QUEUED, None)
    store.start(job_id, "worker-1")
    assert store.output(job_id, "mesh.obj") == (JobStatus.RUNNING, None)
    with pytest.raises(ValueError, match="no output"):
        store.output(job_id, "points")


def test_an_unknown_job_has_no_record_and_nothing_to_cancel(store):
    unknown = "A" * 22
    assert store.get(unknown) is None and store.cancel(unknown) is None
    assert store.output(unknown, "mesh.obj") == (None, None)
    assert store.start(unknown, "worker-1") is None and not store.set_progress(unknown, FITTING)
    assert store.redis.keys(f"{store.prefix}:job:{unknown}") == []


@pytest.mark.parametrize("bad", ["abc", "A" * 23, "../../etc/passwd", "A" * 21 + "*"])
def test_a_malformed_id_never_becomes_a_key(store, bad):
    for call in (store.get, store.cancel, store.load_points, lambda job_id: store.start(job_id, "w")):
        with pytest.raises(InvalidJobId):
            call(bad)
    assert store.redis.keys(f"{store.prefix}:*") == []


def test_an_expired_input_is_a_typed_error(store):
    job_id = new_job(store)
    store.redis.delete(f"{store.prefix}:job:{job_id}:points")
    with pytest.raises(InputExpired, match="input has expired"):
        store.load_points(job_id)


class _ThrottledRelay:
    """A TCP relay to Redis on ``port`` that passes at most ``rate`` bytes per second towards it:
    a slow link, or a Redis that reads slowly. Its ``url`` is what clients connect to."""

    def __init__(self, port: int, rate: float):
        self.port, self.rate = port, rate
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 16)  # little held in buffers

    def __enter__(self) -> str:
        threading.Thread(target=self._accept, daemon=True).start()
        return f"redis://127.0.0.1:{self.listener.getsockname()[1]}/0"

    def __exit__(self, *exc) -> None:
        self.listener.close()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:  # closed
                return
            upstream = socket.create_connection(("127.0.0.1", self.port))
            threading.Thread(target=self._pass, args=(client, upstream, self.rate), daemon=True).start()
            threading.Thread(target=self._pass, args=(upstream, client, 0), daemon=True).start()

    @staticmethod
    def _pass(source: socket.socket, sink: socket.socket, rate: float) -> None:
        with source, sink:
            try:
                while data := source.recv(1 << 16):
                    sink.sendall(data)
                    if rate:
                        time.sleep(len(data) / rate)
            except OSError:  # the other side closed
                pass


def test_a_large_input_is_stored_over_a_link_too_slow_to_send_it_within_one_socket_timeout(redis_server, settings):
    """The API's client gives Redis 0.5 s per answer; a 12 MB input over a 4 MB/s link takes 3 s.

    A busy machine's Redis reads that slowly (CI: a 60 MB upload answered 503 "Timeout writing to
    socket"): the input goes in parts that each fit the timeout, and the job exists only once all
    of it is stored."""
    points = np.random.default_rng(0).normal(size=(500_000, 3))  # 12 MB, deflate cannot shrink it
    with _ThrottledRelay(redis_server.port, rate=4 << 20) as url:
        redis = connect(url, fail_fast=True, socket_timeout=0.5)
        store = JobStore(redis, settings)
        job_id = new_job(store, points)
        np.testing.assert_array_equal(store.load_points(job_id), points)
        assert store.get(job_id).status == JobStatus.QUEUED and store.queue.job_ids == [job_id]
        redis.close()


def test_an_input_redis_does_not_take_in_time_creates_no_job(redis_server, settings):
    """A write that times out is a RedisError (the API's 503) and leaves no record and no queued job;
    a part that Redis reads later expires with its staging time."""
    direct = JobStore(redis_server.client(), settings)
    with _ThrottledRelay(redis_server.port, rate=100_000) as url:
        store = JobStore(connect(url, fail_fast=True, socket_timeout=0.5), settings)
        job_id, began = new_job_id(), time.monotonic()
        with pytest.raises(RedisError, match="Timeout"):
            store.create(job_id, np.random.default_rng(0).normal(size=(100_000, 3)), PARAMS)
        assert time.monotonic() - began < 5
        assert direct.get(job_id) is None and direct.queue.job_ids == []
        assert direct.redis.ttl(f"{store.prefix}:job:{job_id}:points") in (-2, *range(1, 601))
        store.redis.close()
    direct.redis.close()


def test_an_input_that_fills_redis_midway_is_store_full_and_leaves_nothing(tmp_path, settings, monkeypatch):
    """Redis refuses a part (noeviction, maxmemory 4 MB, a 12 MB input; the check of room before
    is skipped, as when another upload filled Redis since): StoreFull, no job, no part left."""
    server = RedisServer(tmp_path, maxmemory=4 << 20).start()
    try:
        store = JobStore(server.client(), settings)
        monkeypatch.setattr(store, "_check_room", lambda size: None)
        job_id = new_job_id()
        with pytest.raises(StoreFull):
            store.create(job_id, np.random.default_rng(0).normal(size=(500_000, 3)), PARAMS)
        assert store.get(job_id) is None and store.queue.job_ids == []
        assert store.redis.keys(f"{store.prefix}:job:*") == []
        store.redis.close()
    finally:
        server.stop()


# --- races -----------------------------------------------------------------------------------------


def test_cancel_before_start_means_the_job_never_runs(store):
    job_id = new_job(store)
    store.cancel(job_id)
    assert store.start(job_id, "worker-1") is None
    record = store.get(job_id)
    assert record.status == JobStatus.CANCELED and record.started_at is None and record.progress is None


def test_start_before_cancel_then_the_worker_stops_and_its_outputs_are_dropped(store):
    job_id = running_job(store)
    assert store.cancel(job_id) == JobStatus.RUNNING
    assert not store.set_progress(job_id, FITTING)
    assert not store.succeed(job_id, OUTPUTS, SUMMARY)
    record = store.get(job_id)
    assert record.status == JobStatus.CANCELED and record.result is None
    assert kept_outputs(store, job_id) == []


def test_succeed_before_cancel_keeps_the_result(store):
    job_id = running_job(store)
    assert store.succeed(job_id, OUTPUTS, SUMMARY)
    assert store.cancel(job_id) == JobStatus.SUCCEEDED
    assert status(store, job_id) == JobStatus.SUCCEEDED and kept_outputs(store, job_id) == list(OUTPUT_NAMES)


def test_cancel_and_succeed_at_once_leave_one_consistent_outcome(store):
    """Many jobs, each canceled by one thread while another finishes it: whichever write came first
    decides, and the answers, the status and the kept outputs always agree."""
    jobs = [running_job(store) for _ in range(40)]
    canceled: dict[str, JobStatus | None] = {}
    succeeded: dict[str, bool] = {}
    start = threading.Barrier(2)

    def cancel_all():
        start.wait()
        for job_id in jobs:
            canceled[job_id] = store.cancel(job_id)

    def succeed_all():
        start.wait()
        for job_id in reversed(jobs):
            succeeded[job_id] = store.succeed(job_id, OUTPUTS, SUMMARY)

    threads = [threading.Thread(target=cancel_all), threading.Thread(target=succeed_all)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(30)
    for job_id in jobs:
        if succeeded[job_id]:
            assert canceled[job_id] == JobStatus.SUCCEEDED and status(store, job_id) == JobStatus.SUCCEEDED
            assert kept_outputs(store, job_id) == list(OUTPUT_NAMES)
        else:
            assert canceled[job_id] == JobStatus.RUNNING and status(store, job_id) == JobStatus.CANCELED
            assert kept_outputs(store, job_id) == []


def rq_jobs_for(store: JobStore, job_id: str) -> list[str]:
    """The ids of the rq jobs in the queue that would run job ``job_id``."""
    return [
        rq_id
        for rq_id in store.queue.job_ids
        if list(Job.fetch(rq_id, connection=store.redis, serializer=JSONSerializer).args) == [job_id]
    ]


def test_reading_a_job_whose_worker_died_puts_it_back_in_the_queue_with_its_input(store):
    job_id = running_job(store)
    store.queue.empty()  # the worker had taken its rq job
    kill_worker_of(store, job_id)
    record = store.get(job_id)
    assert record.status == JobStatus.QUEUED and record.attempts == 1 and record.error is None
    assert record.progress is None and record.worker is None and not is_in_running_set(store, job_id)
    assert len(rq_jobs_for(store, job_id)) == 1  # in the same transaction as the move
    assert store.load_points(job_id) is not None
    assert store.start(job_id, "worker-2") == (PARAMS, 2)
    assert store.get(job_id).attempts == 2


def test_a_job_whose_worker_died_on_its_last_attempt_fails_with_the_reason_and_count(store):
    job_id = running_job(store)
    for attempt in (1, 2):
        kill_worker_of(store, job_id)
        record = store.get(job_id)
        if attempt == 1:
            assert record.status == JobStatus.QUEUED
            assert store.start(job_id, "worker-2") == (PARAMS, 2)
    assert record.status == JobStatus.FAILED and record.ended_at and record.attempts == 2
    assert record.error == f"{ORPHANED}, after 2 attempts (the most allowed); submit the job again"
    assert not store.redis.exists(f"{store.prefix}:job:{job_id}:points")  # ended: its input is gone
    counts = {key.decode(): int(value) for key, value in store.redis.hgetall(f"{store.prefix}:counts").items()}
    assert counts == {"queued": 1, "running": 2, "requeued": 1, "failed": 1}  # queued: submitted once


def test_reading_asynchronously_requeues_an_orphan_too(store, redis_server):
    job_id = running_job(store)
    kill_worker_of(store, job_id)

    async def read():
        async with AsyncRedis.from_url(redis_server.url) as client:
            return await JobStore(store.redis, settings_of(store), client).get_async(job_id)

    record = asyncio.run(read())
    assert record.status == JobStatus.QUEUED and record.attempts == 1
    assert status(store, job_id) == JobStatus.QUEUED


def test_the_sweep_requeues_only_the_jobs_whose_worker_died(store):
    alive, dead = running_job(store, "worker-1"), running_job(store, "worker-2")
    kill_worker_of(store, dead)
    assert store.recover_orphans() == {dead: JobStatus.QUEUED}
    assert status(store, dead) == JobStatus.QUEUED and status(store, alive) == JobStatus.RUNNING
    assert store.recover_orphans() == {}


def test_the_sweep_forgets_running_jobs_whose_record_expired(store):
    job_id = running_job(store)
    store.redis.delete(f"{store.prefix}:job:{job_id}", f"{store.prefix}:job:{job_id}:alive")
    assert store.recover_orphans() == {}
    assert not is_in_running_set(store, job_id)


def test_a_late_write_from_a_worker_presumed_dead_changes_nothing_even_once_the_job_runs_again(store):
    """The worker was only presumed dead (its heartbeat lapsed, say a long pause, or Redis hung):
    once its job is requeued and taken by another worker, its progress, result or failure (of
    attempt 1) arrive too late and are dropped, so the job runs to one outcome only."""
    job_id = running_job(store)
    kill_worker_of(store, job_id)
    assert store.recover_orphans() == {job_id: JobStatus.QUEUED}
    assert store.start(job_id, "worker-2") == (PARAMS, 2)
    assert not store.set_progress(job_id, FITTING, attempt=1) and not store.is_running(job_id, attempt=1)
    assert not store.succeed(job_id, OUTPUTS, SUMMARY, attempt=1)
    assert not store.fail(job_id, "the worker's own reason", attempt=1)
    assert store.release(job_id, "shut down", attempt=1) is None
    assert store.get(job_id).status == JobStatus.RUNNING and kept_outputs(store, job_id) == []
    assert store.set_progress(job_id, FITTING, attempt=2) and store.succeed(job_id, OUTPUTS, SUMMARY, attempt=2)
    assert not store.succeed(job_id, OUTPUTS, SUMMARY, attempt=1)
    record = store.get(job_id)
    assert record.status == JobStatus.SUCCEEDED and record.result == SUMMARY
    assert kept_outputs(store, job_id) == list(OUTPUT_NAMES)


def test_the_input_is_deleted_as_soon_as_the_job_ends_whichever_way(store):
    ended = {}
    for how in ("succeed", "fail", "cancel running", "cancel queued"):
        job_id = new_job(store) if how == "cancel queued" else running_job(store)
        if how == "succeed":
            store.succeed(job_id, OUTPUTS, SUMMARY)
        elif how == "fail":
            store.fail(job_id, "no surface")
        else:
            store.cancel(job_id)
        ended[how] = bool(store.redis.exists(f"{store.prefix}:job:{job_id}:points"))
    assert ended == dict.fromkeys(ended, False)
