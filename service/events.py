"""Live progress: ``GET /v1/jobs/{id}/events``, a Server-Sent Events stream of the job.

The stream sends the job exactly as ``GET /v1/jobs/{id}`` shows it, as ``event: job``, when it
connects and at every change of status or progress; a comment line after
``EDGERECON_EVENT_KEEPALIVE`` seconds of silence, so that proxies keep the connection open; and it
ends after the job's final state (succeeded, failed, canceled), or when the job expires, Redis
fails or the client goes away.

It learns of changes from Redis pub/sub: the store announces every write of a job's record on the
job's channel (``worker.store``), and the stream reads the record when it hears one (about twice
a second while a job runs), instead of reading it on a timer whether it changed or not. A stream
holds one Redis connection of this API process and nothing of a worker; each process serves at
most ``EDGERECON_MAX_EVENT_STREAMS`` at once and answers 503 beyond, which the web page takes as
a cue to poll instead. FastAPI's own SSE support (``fastapi.sse``, FastAPI 0.135) does the
encoding; the API key is checked by ``service.middleware`` like on every ``/v1`` route.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterable, AsyncIterator, Callable
from typing import Annotated, Any

from fastapi import APIRouter, Depends, HTTPException, Request, Security
from fastapi.security import HTTPBearer
from fastapi.sse import EventSourceResponse, ServerSentEvent
from pydantic import BaseModel
from redis.exceptions import RedisError

from worker.contract import JobRecord, JobStatus, is_job_id
from worker.settings import Settings
from worker.store import JobStore

log = logging.getLogger("edgerecon.api")

FINAL = frozenset({JobStatus.SUCCEEDED, JobStatus.FAILED, JobStatus.CANCELED})


class LiveStreams:
    """How many event streams this process serves now (``edgerecon_event_streams`` in /metrics)."""

    count = 0


async def _admitted(job_id: str, request: Request) -> AsyncIterator[JobRecord]:
    """Admit a stream before it starts, so that refusals are plain answers: 404 for an unknown job,
    503 beyond the bound. Counts the stream while it lives (FastAPI leaves this after the stream)."""
    if not is_job_id(job_id):
        raise HTTPException(404, "no such job: job ids are 22 characters of A-Z, a-z, 0-9, '-' and '_'")
    settings: Settings = request.app.state.settings
    if LiveStreams.count >= settings.max_event_streams:
        detail = f"this API process serves {settings.max_event_streams} event streams already: poll GET /v1/jobs/{{id}}"
        raise HTTPException(503, detail, headers={"Retry-After": "10"})
    store: JobStore = request.app.state.store
    record = await store.get_async(job_id)
    if record is None:
        raise HTTPException(404, f"no job {job_id} (never submitted, or expired)")
    LiveStreams.count += 1
    try:
        yield record
    finally:
        LiveStreams.count -= 1


def events_router(view: Callable[[JobRecord], BaseModel]) -> APIRouter:
    """The events route; ``view`` turns a record into what ``GET /v1/jobs/{id}`` answers (the app's
    ``JobView.of``), so that both always say the same."""
    bearer = HTTPBearer(auto_error=False, description="required when EDGERECON_API_KEY is set")
    router = APIRouter(prefix="/v1", tags=["jobs"], dependencies=[Security(bearer)])
    responses: dict[int | str, dict[str, Any]] = {
        404: {"description": "unknown or expired job"},
        503: {"description": "too many event streams on this API process, or Redis is unavailable: poll instead"},
    }

    @router.get("/jobs/{job_id}/events", response_class=EventSourceResponse, responses=responses)
    async def job_events(
        request: Request, first: Annotated[JobRecord, Depends(_admitted)]
    ) -> AsyncIterable[ServerSentEvent]:
        """Server-Sent Events: ``event: job`` with the job (as ``GET /v1/jobs/{id}``) now and at every
        change of status or progress; keep-alive comments; the stream ends after the final state."""
        store: JobStore = request.app.state.store
        keepalive: float = request.app.state.settings.event_keepalive
        assert store.async_redis is not None
        changes = store.async_redis.pubsub()
        try:
            await changes.subscribe(store.changes_channel(first.id))
            record: JobRecord | None = await store.get_async(first.id)  # after subscribing: no change is missed
            sent = None
            while record is not None:
                if (record.status, record.progress) != sent:
                    yield ServerSentEvent(event="job", data=view(record))
                    sent = (record.status, record.progress)
                if record.status in FINAL:
                    return
                if await changes.get_message(timeout=keepalive) is None:  # any message: read the record
                    yield ServerSentEvent(comment="keep-alive")
                record = await store.get_async(first.id)
        except RedisError as error:  # the client sees the stream end early, and polls
            log.info("event stream of job %s ended: Redis failed: %s", first.id, error)
        finally:
            await asyncio.shield(changes.aclose())  # also when the stream is canceled: free the connection

    return router
