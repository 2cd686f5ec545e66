"""The fitting loop: an ImplicitNetwork fitted to one cloud in the unit frame."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import torch
from torch import Tensor

from core.errors import CancelCheck, check_cancel
from core.losses import eikonal_loss, free_space_loss, laplacian_loss, vanish_loss
from core.network import ImplicitNetwork
from core.params import FitParams
from core.progress import Progress, ProgressCallback, Stage
from core.sampling import FreeSpace, build_tree, draw_batch, neighbour_distances

# The most input points a fit draws its batches from. 1,800 steps of 1,024 points see each of
# 131,072 points 14 times; beyond that, more points only add set-up (neighbour queries at every
# point: 24 s at 1 M) and slower steps (a deeper tree for every sample), not information (the
# cube at 100 k and at 1 M points scored alike).
FIT_POINTS = 131_072


def fit_rows(count: int, seed: int) -> np.ndarray:
    """The rows of a cloud of ``count`` points that a fit uses, in order: all of them up to
    ``FIT_POINTS``, else ``FIT_POINTS`` of them drawn at random, the same for the same seed."""
    if count <= FIT_POINTS:
        return np.arange(count)
    return np.sort(np.random.default_rng(seed).choice(count, FIT_POINTS, replace=False))


def fit(
    points: np.ndarray,
    params: FitParams,
    progress: ProgressCallback | None = None,
    should_cancel: CancelCheck | None = None,
) -> ImplicitNetwork:
    """Fit f to ``points`` (N, 3), already in the unit frame; return the trained network.

    A cloud of more than ``FIT_POINTS`` points is fitted to that many of them (``fit_rows``).
    Each step draws ``batch_points`` input points and their eikonal samples (``draw_batch``),
    computes ``step_loss`` and takes one Adam step, with the learning rate decaying geometrically.
    ``should_cancel`` is polled every step, and often during the set-up before the first (the
    neighbour queries and the free-space map take seconds); when it returns True, ``Cancelled``
    is raised.
    """
    generator = torch.Generator().manual_seed(params.seed)
    with torch.random.fork_rng(devices=[]):  # nn.Linear's own initialisation draws from torch's global generator
        model = ImplicitNetwork(params.width, params.depth, params.beta, generator=generator)
    points = points[fit_rows(len(points), params.seed)]
    cloud = torch.as_tensor(points, dtype=torch.float32)
    # One tree and one pass of neighbour queries serve the local scales and the free-space map.
    tree = build_tree(points, should_cancel)
    distances = neighbour_distances(tree, points, [1, 4, min(50, len(points) - 1)], should_cancel)
    scales = torch.as_tensor(distances[:, 2], dtype=torch.float32)
    free_space = None
    if params.lambda3 > 0:
        free_space = FreeSpace(points, tree=tree, spacing=distances[:, :2], should_cancel=should_cancel)
    matmul_dtype = matmul_dtype_for(params.precision)
    batch_size = min(params.batch_points, len(cloud))

    optimizer = torch.optim.Adam(model.parameters(), lr=params.learning_rate)
    decay = (params.final_learning_rate / params.learning_rate) ** (1.0 / max(params.iterations - 1, 1))
    schedule = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=decay)

    for iteration in range(1, params.iterations + 1):
        check_cancel(should_cancel)
        batch, samples = draw_batch(cloud, scales, batch_size, generator)
        loss, terms, edges = step_loss(model, batch, samples, params, free_space, matmul_dtype)

        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        schedule.step()

        if progress is not None:
            losses = {"total": loss.item(), **{name: value.item() for name, value in terms.items()}}
            edge_share = edges.float().mean().item() if edges.numel() else 0.0
            progress(
                Progress(
                    stage=Stage.FITTING,
                    iteration=iteration,
                    total=params.iterations,
                    losses=losses,
                    edge_share=edge_share,
                )
            )
    return model


def step_loss(
    model: ImplicitNetwork,
    batch: Tensor,
    samples: Tensor,
    params: FitParams,
    free_space: FreeSpace | None = None,
    matmul_dtype: torch.dtype | None = None,
) -> tuple[Tensor, dict[str, Tensor], Tensor]:
    """The loss of one step, its terms, and the batch's edge mask (DES).

    ``batch`` holds input points, ``samples`` the eikonal samples (near the points, then uniform in
    the box). One pass of the network gives f and ∇f everywhere and Δf at the batch; the eikonal
    and free-space terms cover the samples (the eikonal term the batch too). The free-space term
    needs the near samples: a membrane across a small hole (the L-bracket's) is met by a uniform
    sample a few times per thousand steps, by the near samples every step.
    """
    n = len(batch)
    laplacian_rows = n if params.lambda2 > 0 else 0
    f, grad, lap = model.derivatives(torch.cat([batch, samples]), laplacian_rows, matmul_dtype)
    terms = {"vanish": vanish_loss(f[:n]), "eikonal": eikonal_loss(grad)}
    loss = terms["vanish"] + params.lambda1 * terms["eikonal"]
    edges = torch.zeros(0, dtype=torch.bool)
    if lap is not None:
        terms["laplacian"], edges = laplacian_loss(
            lap, params.tau, params.edge_sampling, params.laplacian_penalty, params.penalty_scale
        )
        loss = loss + params.lambda2 * terms["laplacian"]
    if free_space is not None:
        distance, sign = free_space.distance_and_sign(samples)
        terms["free_space"] = free_space_loss(f[n:], distance, sign, free_space.margin)
        loss = loss + params.lambda3 * terms["free_space"]
    return loss, terms, edges


def matmul_dtype_for(precision: str) -> torch.dtype | None:
    """The dtype of the training's matrix products: bfloat16 when asked, or when ``"auto"`` and
    the CPU multiplies bfloat16 natively (AMX or AVX512-BF16); None means float32."""
    if precision == "bfloat16" or (precision == "auto" and _cpu_has_bfloat16()):
        return torch.bfloat16
    return None


@lru_cache(maxsize=1)
def _cpu_has_bfloat16() -> bool:
    try:
        with open("/proc/cpuinfo") as info:
            flags = info.read()
    except OSError:
        return False
    return " amx_bf16" in flags or " avx512_bf16" in flags
