"""The job contract shared by the API and the workers: statuses, progress, outputs, the job record.

No torch here (the API imports it). ``Stage`` and ``Progress`` are core's own models, which the
fit reports, the worker stores and the API returns unchanged; ``OUTPUT_NAMES`` are core's files.
"""

from __future__ import annotations

import re
import secrets
from datetime import datetime
from enum import StrEnum
from typing import Any

from pydantic import BaseModel, Field

from core.outputs import OUTPUT_NAMES
from core.params import FitParams
from core.progress import Progress, Stage

__all__ = [
    "JOB_FUNCTION",
    "ORPHANED",
    "OUTPUT_NAMES",
    "SHUTDOWN",
    "JobRecord",
    "JobStatus",
    "Progress",
    "Stage",
    "is_job_id",
    "new_job_id",
]

# The rq job, by name: the API enqueues it without importing the worker's code (or torch).
JOB_FUNCTION = "worker.job.run_reconstruction"


_JOB_ID = re.compile(r"[A-Za-z0-9_-]{22}")


def new_job_id() -> str:
    """A fresh job id: 128 random bits, URL-safe (22 characters)."""
    return secrets.token_urlsafe(16)


def is_job_id(text: str) -> bool:
    """Whether ``text`` has the shape of a job id (checked before any key is built from it)."""
    return _JOB_ID.fullmatch(text) is not None


class JobStatus(StrEnum):
    """Where a job is. It only moves along queued -> running -> succeeded | failed | canceled,
    and queued -> canceled (``worker.store``)."""

    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELED = "canceled"


# Why a job's run was cut short when the reason is the service's, not the input's: the job goes back
# to the queue, or when it has no attempt left fails with this (and the count) as its ``error``.
ORPHANED = "the worker running this job stopped unexpectedly (crashed or was killed)"
SHUTDOWN = "the worker was shut down while running this job"


class JobRecord(BaseModel):
    """A job as the store keeps it."""

    id: str
    status: JobStatus
    progress: Progress | None = None
    params: FitParams
    points: int = Field(description="number of points in the uploaded cloud")
    created_at: datetime
    started_at: datetime | None = None
    ended_at: datetime | None = None
    expires_at: datetime | None = Field(None, description="when the job and its outputs will be deleted")
    error: str | None = Field(None, description="why the job failed")
    result: dict[str, Any] | None = Field(
        None, description="vertex and face counts, edge point count, timings (succeeded jobs)"
    )
    worker: str | None = Field(None, description="the worker that took the job")
    attempts: int = Field(
        0,
        description="how many times a worker started the job: one whose worker died or was shut down runs again,"
        " up to EDGERECON_MAX_ATTEMPTS times",
    )
