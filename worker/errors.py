"""The failures of the queue side that callers handle: each one a type of its own."""

from __future__ import annotations


class InvalidJobId(ValueError):
    """A string that is not a job id was about to become a Redis key."""


class StoreFull(Exception):
    """Redis is (nearly) at its ``maxmemory``: a new job is refused, so that the running ones can
    still store their results."""


class InputExpired(Exception):
    """The job's input cloud is no longer in Redis (it expired before a worker took the job)."""

    def __init__(self) -> None:
        super().__init__("the job's input has expired")
