"""The parameters of a reconstruction, with their bounds and defaults (no torch here)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator


class FitParams(BaseModel):
    """Everything a fit and its extraction depend on.

    The loss is ``L_vanish + lambda1 * L_eikonal + lambda2 * L_laplacian + lambda3 * L_free_space
    + lambda4 * L_normal``
    (see ``core.losses``). ``L_laplacian`` is the *mean* penalty of Δf over the non-edge points of
    the batch (the paper writes a sum; a mean keeps ``lambda2`` independent of the number of
    points). ``tau`` and every length are in the normalised frame, where the cloud is centred and
    its largest bounding-box extent is 1.

    The defaults are the measured best on the sample shapes (docs/benchmarks.md); they depart
    from the paper's (quadratic penalty, ``lambda2`` 0.001, ``tau`` 20), which round every edge,
    and add a free-space term. The paper's variant stays selectable.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    iterations: int = Field(1800, ge=1, le=100_000, description="optimisation steps")
    lambda1: float = Field(0.1, ge=0, le=1000, description="weight of the eikonal term")
    lambda2: float = Field(
        1e-4, ge=0, le=1000, description="weight of the Laplacian term (0: plain IGR; the paper: 0.001)"
    )
    tau: float = Field(
        30.0,
        gt=0,
        le=1e6,
        description="|Δf| threshold: dynamic edge sampling in the fit; edge points of the mc extraction (paper: 20)",
    )
    edge_sampling: bool = Field(
        True, description="dynamic edge sampling: leave points with |Δf| >= tau out of the Laplacian term"
    )
    laplacian_penalty: Literal["robust", "quadratic"] = Field(
        "robust",
        description="penalty of Δf: robust (Geman-McClure, levels off at penalty_scale²) or the paper's quadratic",
    )
    penalty_scale: float = Field(5.0, gt=0, le=1e4, description="|Δf| where the robust penalty levels off")
    lambda3: float = Field(
        1.0,
        ge=0,
        le=1000,
        description="weight of the free-space term, which keeps the surface out of empty space (0: off)",
    )
    lambda4: float = Field(
        0.5,
        ge=0,
        le=1000,
        description="weight of the normal term: ∇f at each point across the plane of its nearest points (0: off)",
    )
    extraction: Literal["sharp", "mc"] = Field(
        "sharp",
        description="mesh extraction: sharp (dual contouring, vertices on edges and corners) or mc (marching cubes)",
    )
    edge_angle: float = Field(
        30.0,
        gt=0,
        lt=180,
        description="sharp extraction: faces whose normals differ by more degrees meet at an edge curve",
    )
    edge_width: float = Field(
        0.0125,
        gt=0,
        le=0.2,
        description=(
            "sharp extraction: input points this near an edge curve, along their face, are edge points"
            " (normalised frame)"
        ),
    )
    resolution: int = Field(160, ge=32, le=512, description="marching-cubes grid cells along the largest extent")
    seed: int = Field(0, ge=0, le=2**31 - 1, description="random seed of initialisation and sampling")
    width: int = Field(256, ge=16, le=1024, description="hidden units per layer")
    depth: int = Field(4, ge=1, le=12, description="hidden layers")
    features: int = Field(
        32,
        ge=0,
        le=256,
        description="random Fourier features of x that the network reads when it reads them (see encoding; 0: none)",
    )
    frequency: float = Field(
        2.0, gt=0, le=64, description="spread of the Fourier features' frequencies (cycles per unit, normalised frame)"
    )
    encoding: Literal["auto", "always", "never"] = Field(
        "auto",
        description=(
            "when the network reads the Fourier features: auto starts without them and starts again with them"
            " where the residuals halfway have a heavier tail than noise (a pocket capped, detail missed)"
        ),
    )
    beta: float = Field(200.0, gt=0, le=1e4, description="softplus sharpness (IGR uses 100)")
    batch_points: int = Field(1024, ge=64, le=65_536, description="input points per step")
    residual_share: float = Field(
        0.5,
        ge=0,
        le=1,
        description="share of each step's input points drawn in proportion to their last |f| (the rest uniformly)",
    )
    learning_rate: float = Field(5e-3, gt=0, le=1.0, description="initial Adam learning rate")
    precision: Literal["auto", "float32", "bfloat16"] = Field(
        "auto", description="matrix products in training: bfloat16 where the CPU has it natively (auto), or float32"
    )
    final_learning_rate: float = Field(
        1e-4, gt=0, le=1.0, description="learning rate at the last step (geometric decay)"
    )

    @field_validator("*", mode="before")
    @classmethod
    def _no_booleans_for_numbers(cls, value: Any, info: ValidationInfo) -> Any:
        # pydantic's lax mode reads True as 1; a form or JSON client sending a boolean for a
        # number has made a mistake worth reporting.
        if isinstance(value, bool) and cls.model_fields[str(info.field_name)].annotation is not bool:
            raise ValueError("expected a number, not a boolean")
        return value
