"""What a reconstruction reports while it runs (no torch here).

One model for everyone: core's progress callback receives a ``Progress``, the worker stores it
in the job's record, and the API returns it as the job's ``progress``.
"""

from __future__ import annotations

from collections.abc import Callable
from enum import StrEnum

from pydantic import BaseModel, Field


class Stage(StrEnum):
    """Where a reconstruction is: the worker has taken it, the network is being fitted, or the
    mesh, normals and edges are being extracted from it."""

    STARTING = "starting"
    FITTING = "fitting"
    EXTRACTING = "extracting"


class Progress(BaseModel):
    """The latest step of a reconstruction."""

    stage: Stage = Field(description="starting, fitting or extracting")
    iteration: int
    total: int
    losses: dict[str, float | None] | None = Field(
        None, description="latest loss terms: total, vanish, eikonal, laplacian (null: not finite)"
    )
    edge_share: float | None = Field(None, description="share of the batch left out of the Laplacian term (DES)")


ProgressCallback = Callable[[Progress], None]
