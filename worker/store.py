"""The jobs in Redis: their records, their input and outputs, and the state machine they move along.

A job is a hash (its record) plus compressed blobs (the input points and the three outputs), all
under ``{prefix}:job:{id}`` and expiring together ``job_ttl`` seconds after the job's last change.
Its status only moves along

    queued -> running -> succeeded | failed | canceled,      queued -> canceled,
    running -> queued (its worker died or was shut down, and it has attempts left)

and every move is one atomic "update the record if its status is one of ..." (a Lua script), so a
cancel, a crash verdict and a finishing worker cannot overwrite one another: the first one wins.
The same script counts the attempts (each move to ``running``) and deletes the input points when
the job ends, whichever way.

The rq job that carries a job to a worker has only the job's id as its argument (JSON serializer);
the parameters and points stay in the record and blobs. The first rq job has the job's id; a job
put back in the queue gets a fresh rq job (``{id}-{random}``) in the same transaction as the move,
so a queued record always has an rq job. A stale rq job is harmless: ``start`` runs only a queued
job, once.

At-least-once: while a worker runs a job, its heartbeat keeps ``{prefix}:job:{id}:alive`` alive
(``heartbeat_ttl`` seconds). A ``running`` job without that key belongs to a dead worker: when its
status is read, or in the API's periodic sweep (``recover_orphans``), it goes back to the queue if
it has run fewer than ``max_attempts`` times, and fails otherwise. rq's own abandoned-job handling
(its StartedJobRegistry cleanup) is not used: it runs in a worker's maintenance pass (every 10
minutes), when the rq job's own timeout (an hour) has passed, and knows nothing of our record.

Every write of a record is announced on the Redis channel ``{prefix}:job:{id}:changes`` (the new
status as the message), so that the API's event streams read the record when it changes instead of
polling it.

What /metrics reports is kept here too, so that every API process reports the same numbers:
``{prefix}:counts`` counts the jobs that ever entered each status (``queued`` is the number
submitted), moved by the same atomic writes; ``{prefix}:durations`` holds histograms of how long
jobs spent in each stage (``queued``, ``fitting``, ``extracting``), observed by the workers.
"""

from __future__ import annotations

import asyncio
import io
import json
import logging
import math
import secrets
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Any, cast

import numpy as np
from redis import Redis
from redis.asyncio import Redis as AsyncRedis
from redis.exceptions import OutOfMemoryError, RedisError, ResponseError
from rq import Queue
from rq.exceptions import NoSuchJobError
from rq.job import Job
from rq.serializers import JSONSerializer

from core.params import FitParams
from worker.connection import text
from worker.contract import JOB_FUNCTION, ORPHANED, OUTPUT_NAMES, JobRecord, JobStatus, Progress, Stage, is_job_id
from worker.errors import InputExpired, InvalidJobId, StoreFull
from worker.settings import Settings

log = logging.getLogger("edgerecon.store")

# KEYS[1] the record, KEYS[2] the set of running job ids, KEYS[3] the counts of statuses entered,
# KEYS[4] the input points, KEYS[5..] more keys of the job.
# ARGV[1] allowed statuses (space-separated), ARGV[2] job id, ARGV[3] ttl (0: leave expiries alone),
# ARGV[4] attempts limit (0: none), ARGV[5] the attempt the caller runs (0: any), ARGV[6..] field,
# value, ... to set (an empty value deletes the field). Returns {the status found ('': no record),
# 1 if the update was made else 0}; it is made if and only if that status is one of ARGV[1], the job
# has run fewer than ARGV[4] times (when ARGV[4] > 0) and its current attempt is ARGV[5] (when > 0:
# a worker presumed dead, whose job runs again elsewhere, cannot write), and then it is announced
# on KEYS[1] .. ':changes'. Each move to running is an attempt; a
# move back to queued is counted as 'requeued' (so 'queued' stays the number submitted); a move to
# a final status deletes the input points, which nothing needs any more.
_UPDATE_IF = """
local status = redis.call('HGET', KEYS[1], 'status')
if not status or not string.find(' ' .. ARGV[1] .. ' ', ' ' .. status .. ' ', 1, true) then
  return {status or '', 0}
end
local attempts = tonumber(redis.call('HGET', KEYS[1], 'attempts') or '0')
local limit, attempt = tonumber(ARGV[4]), tonumber(ARGV[5])
if (limit > 0 and attempts >= limit) or (attempt > 0 and attempts ~= attempt) then
  return {status, 0}
end
for i = 6, #ARGV, 2 do
  if ARGV[i + 1] == '' then
    redis.call('HDEL', KEYS[1], ARGV[i])
  else
    redis.call('HSET', KEYS[1], ARGV[i], ARGV[i + 1])
  end
end
local new = redis.call('HGET', KEYS[1], 'status')
if new == 'running' then
  redis.call('SADD', KEYS[2], ARGV[2])
else
  redis.call('SREM', KEYS[2], ARGV[2])
end
if new ~= status then
  if new == 'running' then redis.call('HINCRBY', KEYS[1], 'attempts', 1) end
  redis.call('HINCRBY', KEYS[3], new == 'queued' and 'requeued' or new, 1)
  if new == 'succeeded' or new == 'failed' or new == 'canceled' then redis.call('DEL', KEYS[4]) end
end
if tonumber(ARGV[3]) > 0 then
  for i = 1, #KEYS do
    if i ~= 2 and i ~= 3 then redis.call('EXPIRE', KEYS[i], ARGV[3]) end
  end
end
redis.call('PUBLISH', KEYS[1] .. ':changes', new)
return {status, 1}
"""


# New jobs are refused once Redis's memory in use would pass this share of its maxmemory: the rest
# is for the outputs of the jobs that run (noeviction: a write past maxmemory fails).
NEW_JOB_MEMORY_SHARE = 0.9

# A new job's input goes to Redis in parts of this many bytes, each a write of its own, and expires
# this many seconds after its first part until the transaction that creates the job.
WRITE_PART = 1 << 20
STAGING_TTL = 600

# Upper bounds (seconds) of the buckets of the stage-duration histograms; changing them restarts the histograms.
DURATION_BUCKETS = (0.5, 1, 2.5, 5, 10, 25, 50, 100, 250, 500, 1000, 2500, 5000)


@dataclass
class StageDurations:
    """One stage's histogram: how many durations fell at or below each bucket bound (cumulative,
    ``inf`` last), and their sum."""

    buckets: dict[float, int]
    sum: float

    @property
    def count(self) -> int:
        return self.buckets[math.inf]


@dataclass
class StoreStats:
    """What /metrics reads from the store at a scrape."""

    entered: dict[str, int]  # how many jobs ever entered each status (``queued``: submitted)
    queued: int  # jobs waiting in the queue now
    running: int  # jobs running now
    durations: dict[str, StageDurations]  # by stage: queued, fitting, extracting


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


def _pack(data: bytes, level: int = 6) -> bytes:
    return zlib.compress(data, level)


class _Deflating:
    """A write-only file that deflates what ``np.save`` writes into it, block by block, so that a
    large cloud is never held both as .npy bytes and compressed (the API's memory per upload)."""

    def __init__(self, level: int):
        self._deflate = zlib.compressobj(level)
        self.output = io.BytesIO()

    def write(self, data: bytes | memoryview) -> int:
        self.output.write(self._deflate.compress(data))
        return len(data)

    def close(self) -> memoryview:
        self.output.write(self._deflate.flush())
        return self.output.getbuffer()


def _pack_array(points: np.ndarray) -> memoryview:
    """``points`` as .npy, deflated at level 1: five times faster than 6 on coordinates, for a
    tenth more bytes; read only once."""
    sink = _Deflating(level=1)
    np.save(sink, points, allow_pickle=False)
    return sink.close()


class JobStore:
    """The jobs of one service (one key prefix and one queue) in one Redis."""

    def __init__(self, redis: Redis, settings: Settings, async_redis: AsyncRedis | None = None):
        self.redis = redis
        self.async_redis = async_redis  # the API's asyncio client, for get_async
        self.prefix = settings.key_prefix
        self.ttl = settings.job_ttl
        self.timeout = settings.job_timeout
        self.heartbeat_ttl = settings.heartbeat_ttl
        self.max_attempts = settings.max_attempts
        self.queue = Queue(settings.queue, connection=redis, serializer=JSONSerializer)
        self._update_if = redis.register_script(_UPDATE_IF)

    # --- keys ------------------------------------------------------------------------------------

    def _key(self, job_id: str, part: str = "") -> str:
        if not is_job_id(job_id):  # never build a key from unchecked input
            raise InvalidJobId(f"not a job id: {job_id!r}")
        return f"{self.prefix}:job:{job_id}" + (f":{part}" if part else "")

    def changes_channel(self, job_id: str) -> str:
        """The channel on which every write of the job's record is announced (the Lua script's
        ``KEYS[1] .. ':changes'``)."""
        return self._key(job_id, "changes")

    def _job_keys(self, job_id: str) -> list[str]:
        """The record, the running set, the counts, then every other key of the job (they expire together)."""
        blobs = [self._key(job_id, name) for name in ("points", *OUTPUT_NAMES)]
        return [self._key(job_id), f"{self.prefix}:running", f"{self.prefix}:counts", *blobs]

    def _update(
        self, job_id: str, allowed: tuple[JobStatus, ...], fields: Mapping[str, str], *, touch: bool
    ) -> JobStatus | None:
        """Set ``fields`` on the record if its status is in ``allowed``; return the status found.
        ``touch`` restarts the expiry of every key of the job."""
        return self._move(job_id, allowed, fields, touch=touch)[0]

    def _move(
        self,
        job_id: str,
        allowed: tuple[JobStatus, ...],
        fields: Mapping[str, str],
        *,
        touch: bool,
        attempts_below: int = 0,
        attempt: int = 0,
        client: Any = None,
    ) -> tuple[JobStatus | None, bool]:
        """``_update``, also only while the job has run fewer than ``attempts_below`` times (0: any)
        and is in its ``attempt``-th run (0: any); return the status found and whether the update
        was made. With ``client`` (a transaction) the script is only queued: the answer is None, False."""
        args: list[str | int] = [" ".join(allowed), job_id, self.ttl if touch else 0, attempts_below, attempt]
        for name, value in fields.items():
            args += [name, value]
        answer = self._update_if(keys=self._job_keys(job_id), args=args, client=client)
        if client is not None:
            return None, False
        found, made = answer
        return (JobStatus(text(found)) if found else None), bool(made)

    # --- the API's side ----------------------------------------------------------------------------

    def create(self, job_id: str, points: np.ndarray, params: FitParams) -> None:
        """Store the input of a new job (``_write_in_parts``), then its record and its rq job in one
        transaction; ``StoreFull`` (and no job) when Redis has no room for it."""
        self.redis.ping()  # a hung Redis fails here, before a write it might apply after the API answered 503
        packed = _pack_array(points)
        self._check_room(len(packed))
        record: dict[Any, Any] = {  # typed as redis-py's hset wants it
            "status": JobStatus.QUEUED.value,
            "params": params.model_dump_json(),
            "points": len(points),
            "created_at": _now(),
        }
        points_key = self._key(job_id, "points")
        try:
            self._write_in_parts(points_key, packed)
        except RedisError as error:
            self._forget(points_key)
            if isinstance(error, OutOfMemoryError):
                raise StoreFull(self._full_message()) from None
            raise
        with self.redis.pipeline() as pipe:
            pipe.watch(points_key)  # should the input expire before EXEC, the job is not created
            pipe.multi()  # MULTI/EXEC: all of it or nothing (and rq wants the transaction opened)
            pipe.expire(points_key, self.ttl)
            pipe.hset(self._key(job_id), mapping=record)
            pipe.expire(self._key(job_id), self.ttl)
            pipe.hincrby(f"{self.prefix}:counts", JobStatus.QUEUED.value, 1)
            self._enqueue(job_id, job_id, pipe)
            # Another error of EXEC (an answer lost) may come after Redis applied it: the input is
            # then the job's and stays; if not applied, it expires within STAGING_TTL.
            try:
                pipe.execute()
            except OutOfMemoryError:  # full since the check: the transaction was refused whole
                self._forget(points_key)
                raise StoreFull(self._full_message()) from None

    def _write_in_parts(self, key: str, blob: memoryview) -> None:
        """Store ``blob`` at ``key`` (expiring in ``STAGING_TTL`` s) in parts of ``WRITE_PART`` bytes.

        The API's client allows ``redis_socket_timeout`` for a whole write, and a busy Redis reads
        60 MB more slowly than that; each part is one write that fits the timeout, while a hung
        Redis still fails the first one that it does not read."""
        self.redis.set(key, blob[:WRITE_PART], ex=STAGING_TTL)
        for start in range(WRITE_PART, len(blob), WRITE_PART):
            self.redis.append(key, blob[start : start + WRITE_PART])

    def _forget(self, key: str) -> None:
        """Delete what a failed ``create`` stored, if Redis answers; else it expires on its own."""
        try:
            self.redis.delete(key)
        except RedisError:
            pass

    def _check_room(self, size: int) -> None:
        """Raise ``StoreFull`` unless ``size`` more bytes keep Redis under ``NEW_JOB_MEMORY_SHARE`` of its maxmemory."""
        try:
            memory = self.redis.info("memory")
        except ResponseError:  # INFO disabled (some managed Redis): Redis's own refusal still applies
            return
        limit, used = int(memory.get("maxmemory", 0)), int(memory.get("used_memory", 0))
        if limit and used + size > NEW_JOB_MEMORY_SHARE * limit:
            raise StoreFull(self._full_message(used, limit))

    @staticmethod
    def _full_message(used: int = 0, limit: int = 0) -> str:
        state = f" ({used / 2**20:.0f} of {limit / 2**20:.0f} MiB in use)" if limit else ""
        return (
            f"the job store (Redis) is full{state}: no new job is accepted until running jobs end and old"
            " ones expire; jobs already submitted, their status and their results are unaffected. Try again later"
        )

    def _enqueue(self, rq_id: str, job_id: str, pipe: Any) -> None:
        """Queue an rq job ``rq_id`` that runs job ``job_id``, in the transaction ``pipe``."""
        self.queue.enqueue_call(
            JOB_FUNCTION,
            args=(job_id,),
            job_id=rq_id,
            timeout=self.timeout,
            result_ttl=0,  # the outcome lives in the record; rq keeps only failures, for operators
            failure_ttl=self.ttl,
            pipeline=pipe,
        )

    def get(self, job_id: str) -> JobRecord | None:
        """The job's record (None if unknown or expired); requeues or fails it first if its worker died."""
        with self.redis.pipeline(transaction=False) as pipe:
            raw, pttl, alive = self._queue_read(pipe, job_id).execute()
        if self._orphaned(raw, alive) and self.release(job_id, ORPHANED) is not None:
            return self.get(job_id)
        return self._record(job_id, raw, pttl)

    async def get_async(self, job_id: str) -> JobRecord | None:
        """``get`` on the asyncio client: status polls, the API's busiest route, skip the thread pool."""
        assert self.async_redis is not None, "get_async needs the store's asyncio client"
        async with self.async_redis.pipeline(transaction=False) as pipe:
            raw, pttl, alive = await self._queue_read(pipe, job_id).execute()
        if self._orphaned(raw, alive) and await asyncio.to_thread(self.release, job_id, ORPHANED) is not None:
            return await self.get_async(job_id)
        return self._record(job_id, raw, pttl)

    def _queue_read(self, pipe: Any, job_id: str) -> Any:
        pipe.hgetall(self._key(job_id))
        pipe.pttl(self._key(job_id))
        pipe.exists(self._key(job_id, "alive"))
        return pipe

    @staticmethod
    def _orphaned(raw: dict[bytes, bytes], alive: int) -> bool:
        """Whether the record says running while no worker keeps the job alive."""
        return raw.get(b"status") == JobStatus.RUNNING.encode() and not alive

    @staticmethod
    def _record(job_id: str, raw: dict[bytes, bytes], pttl: int) -> JobRecord | None:
        if not raw:
            return None
        record = {key.decode(): value.decode() for key, value in raw.items()}
        return JobRecord(
            id=job_id,
            status=JobStatus(record["status"]),
            progress=Progress.model_validate_json(record["progress"]) if "progress" in record else None,
            params=FitParams.model_validate_json(record["params"]),
            points=int(record["points"]),
            created_at=datetime.fromisoformat(record["created_at"]),
            started_at=record.get("started_at"),
            ended_at=record.get("ended_at"),
            expires_at=datetime.now(UTC) + timedelta(milliseconds=pttl) if pttl > 0 else None,
            error=record.get("error"),
            result=json.loads(record["result"]) if "result" in record else None,
            worker=record.get("worker"),
            attempts=int(record.get("attempts", 0)),
        )

    def cancel(self, job_id: str) -> JobStatus | None:
        """Cancel a queued or running job; return the status it had (None if unknown).

        A queued job is also taken off the queue. A running one stops at its worker's next progress
        write, which finds the status changed."""
        found = self._update(
            job_id,
            (JobStatus.QUEUED, JobStatus.RUNNING),
            {"status": JobStatus.CANCELED.value, "ended_at": _now()},
            touch=True,
        )
        if found == JobStatus.QUEUED:
            try:
                Job.fetch(job_id, connection=self.redis, serializer=JSONSerializer).delete()
            except NoSuchJobError:  # a worker took it meanwhile: it will find the job canceled
                pass
        return found

    def output(self, job_id: str, name: str) -> tuple[JobStatus | None, bytes | None]:
        """The status of the job and, if it succeeded, the content of its output ``name``."""
        if name not in OUTPUT_NAMES:
            raise ValueError(f"no output called {name!r}")
        with self.redis.pipeline(transaction=False) as pipe:
            pipe.hget(self._key(job_id), "status")
            pipe.get(self._key(job_id, name))
            status, blob = pipe.execute()
        found = JobStatus(text(status)) if status else None
        if found != JobStatus.SUCCEEDED or blob is None:
            return found, None
        return found, zlib.decompress(blob)

    def recover_orphans(self) -> dict[str, JobStatus]:
        """Requeue (or fail, when it has no attempt left) every running job whose worker stopped
        signalling; return their ids and where each went."""
        running = [text(member) for member in self.redis.smembers(f"{self.prefix}:running")]
        running = [job_id for job_id in running if is_job_id(job_id)]
        if not running:
            return {}
        with self.redis.pipeline(transaction=False) as pipe:
            for job_id in running:
                pipe.exists(self._key(job_id, "alive"))
            alive = pipe.execute()
        recovered = {}
        for job_id in (job_id for job_id, ok in zip(running, alive) if not ok):
            if not self.redis.exists(self._key(job_id)):  # the record expired: forget it
                self.redis.srem(f"{self.prefix}:running", job_id)
                continue
            outcome = self.release(job_id, ORPHANED)
            if outcome is not None:
                recovered[job_id] = outcome
        return recovered

    def release(self, job_id: str, reason: str, attempt: int = 0) -> JobStatus | None:
        """Put a running job (in its ``attempt``-th run, if > 0) whose run was cut short (its worker
        died or is shutting down) back in the queue if it has run fewer than ``max_attempts`` times,
        else fail it with ``reason``; return the new status (None: nothing changed)."""
        fields = {"status": JobStatus.QUEUED.value, "progress": "", "worker": ""}
        with self.redis.pipeline() as pipe:
            pipe.multi()
            # The move and a fresh rq job, together; if the move is refused the rq job is stale and
            # the worker that takes it drops it (``start`` runs queued jobs only).
            self._move(
                job_id,
                (JobStatus.RUNNING,),
                fields,
                touch=True,
                attempts_below=self.max_attempts,
                attempt=attempt,
                client=pipe,
            )
            self._enqueue(f"{job_id}-{secrets.token_hex(4)}", job_id, pipe)
            answers = pipe.execute()
        found, made = answers[0]
        if made:
            log.warning("job %s back in the queue: %s", job_id, reason)
            return JobStatus.QUEUED
        if found and text(found) == JobStatus.RUNNING:  # no attempt left
            attempts = self.redis.hget(self._key(job_id), "attempts")
            tries = f"{int(attempts)} attempts" if attempts else "its attempts"
            if self.fail(job_id, f"{reason}, after {tries} (the most allowed); submit the job again", attempt):
                return JobStatus.FAILED
        return None

    # --- the worker's side -------------------------------------------------------------------------

    def start(self, job_id: str, worker: str) -> tuple[FitParams, int] | None:
        """Mark a queued job running on ``worker``; return its parameters and which attempt this is
        (1, 2, ...: the worker passes it to every later write), or None when it is no longer queued
        (canceled while it waited, already taken, or expired): then it must not run."""
        # The heartbeat key goes first, so a running job always has one while its worker lives.
        self.keep_alive(job_id, worker)
        fields = {
            "status": JobStatus.RUNNING.value,
            "started_at": _now(),
            "worker": worker,
            "progress": Progress(stage=Stage.STARTING, iteration=0, total=0).model_dump_json(),
        }
        if self._update(job_id, (JobStatus.QUEUED,), fields, touch=True) != JobStatus.QUEUED:
            return None
        params, created_at, attempts = self.redis.hmget(self._key(job_id), ["params", "created_at", "attempts"])
        if created_at and attempts == b"1":  # a job's wait in the queue, counted once
            waited = datetime.fromisoformat(fields["started_at"]) - datetime.fromisoformat(text(created_at))
            self.observe_durations({"queued": waited.total_seconds()})
        return (FitParams.model_validate_json(params), int(attempts or 0)) if params else None

    def keep_alive(self, job_id: str, worker: str) -> None:
        """The worker's heartbeat for a job it is running."""
        self.redis.set(self._key(job_id, "alive"), worker, ex=self.heartbeat_ttl)

    def load_points(self, job_id: str) -> np.ndarray:
        """The job's input cloud, (N, 3) float64."""
        blob = self.redis.get(self._key(job_id, "points"))
        if blob is None:
            raise InputExpired()
        points = np.load(io.BytesIO(zlib.decompress(cast(bytes, blob))), allow_pickle=False)
        return points.astype(np.float64, copy=False)  # the API stores float32 when that is exact

    def set_progress(self, job_id: str, progress: Progress, attempt: int = 0) -> bool:
        """Record the progress of a running job (a change: its keys' expiry restarts); False when it
        is no longer running, or no longer in ``attempt`` (canceled, requeued or failed by a crash
        verdict, expired): the worker should stop."""
        fields = {"progress": progress.model_dump_json()}
        return self._move(job_id, (JobStatus.RUNNING,), fields, touch=True, attempt=attempt)[1]

    def observe_durations(self, seconds: Mapping[str, float]) -> None:
        """Add each stage's duration to its histogram (``seconds``: stage to seconds). Best effort:
        a lost observation must not fail a job, so a Redis error is logged, not raised."""
        key = f"{self.prefix}:durations"
        try:
            with self.redis.pipeline() as pipe:
                for stage, value in seconds.items():
                    bound = next((bound for bound in DURATION_BUCKETS if value <= bound), math.inf)
                    pipe.hincrby(key, f"{stage}:le:{bound}", 1)
                    pipe.hincrbyfloat(key, f"{stage}:sum", value)
                pipe.execute()
        except RedisError as error:
            log.warning("durations %s not recorded: %s", dict(seconds), error)

    async def stats_async(self) -> StoreStats:
        """The counts, the queue's and running set's sizes and the stage histograms, in one round trip."""
        assert self.async_redis is not None, "stats_async needs the store's asyncio client"
        async with self.async_redis.pipeline(transaction=False) as pipe:
            pipe.hgetall(f"{self.prefix}:counts")
            pipe.llen(self.queue.key)
            pipe.scard(f"{self.prefix}:running")
            pipe.hgetall(f"{self.prefix}:durations")
            counts, queued, running, durations = await pipe.execute()
        return StoreStats(
            entered={text(status): int(count) for status, count in counts.items()},
            queued=queued,
            running=running,
            durations=_histograms({text(field): float(value) for field, value in durations.items()}),
        )

    def is_running(self, job_id: str, attempt: int = 0) -> bool:
        """Whether the job's status is still ``running`` (in its ``attempt``-th run, if > 0)."""
        status, attempts = self.redis.hmget(self._key(job_id), ["status", "attempts"])
        return status == JobStatus.RUNNING.encode() and (attempt == 0 or int(attempts or 0) == attempt)

    def succeed(self, job_id: str, outputs: Mapping[str, bytes], summary: Mapping[str, Any], attempt: int = 0) -> bool:
        """Store the outputs and mark the job succeeded, unless it stopped running (its ``attempt``) meanwhile."""
        if not self.is_running(job_id, attempt):  # finished already: a late write must not touch its outputs
            return False
        keys = [self._key(job_id, name) for name in OUTPUT_NAMES]
        with self.redis.pipeline() as pipe:
            for key, name in zip(keys, OUTPUT_NAMES):
                pipe.set(key, _pack(outputs[name]), ex=self.ttl)
            pipe.execute()
        fields = {"status": JobStatus.SUCCEEDED.value, "ended_at": _now(), "result": json.dumps(dict(summary))}
        found, made = self._move(job_id, (JobStatus.RUNNING,), fields, touch=True, attempt=attempt)
        if made:
            return True
        if found != JobStatus.SUCCEEDED:  # canceled or failed while they were written: they are not wanted
            self.redis.delete(*keys)  # (another attempt that succeeded wrote the same outputs: keep them)
        return False

    def fail(self, job_id: str, reason: str, attempt: int = 0) -> bool:
        """Mark a running job (in its ``attempt``-th run, if > 0) failed with a reason a user can
        read; False if it was not running (that attempt)."""
        return self._move(job_id, (JobStatus.RUNNING,), self._failure(reason), touch=True, attempt=attempt)[1]

    @staticmethod
    def _failure(reason: str) -> dict[str, str]:
        return {"status": JobStatus.FAILED.value, "ended_at": _now(), "error": reason}


def _histograms(fields: dict[str, float]) -> dict[str, StageDurations]:
    """The ``{prefix}:durations`` hash (``stage:le:bound`` counts per bucket, ``stage:sum``) as
    cumulative histograms by stage."""
    stages = sorted({name.split(":", 1)[0] for name in fields})
    histograms = {}
    for stage in stages:
        cumulative, buckets = 0, {}
        for bound in (*DURATION_BUCKETS, math.inf):
            cumulative += int(fields.get(f"{stage}:le:{bound}", 0))
            buckets[float(bound)] = cumulative
        histograms[stage] = StageDurations(buckets=buckets, sum=fields.get(f"{stage}:sum", 0.0))
    return histograms
