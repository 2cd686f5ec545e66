"""The fitting loop: an ImplicitNetwork fitted to one cloud in the unit frame."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from typing import cast

import numpy as np
import torch
from torch import Tensor

from core.errors import CancelCheck, check_cancel
from core.losses import eikonal_loss, free_space_loss, laplacian_loss, normal_loss, vanish_loss
from core.network import (
    ImplicitNetwork,
    compile_whole,
    eager_kernels,
    finish_warming_kernels,
    warm_kernels_in_background,
)
from core.params import FitParams
from core.progress import Progress, ProgressCallback, Stage
from core.sampling import (
    FreeSpace,
    build_tree,
    draw_batch,
    neighbour_distances,
    noise_width,
    plane_normals,
    subsample_rows,
)
from core.trees import nearest_others

# The most input points a fit draws its batches from. 1,800 steps of 512 to 1,024 points see each
# of 131,072 points 9 times; beyond that, more points only add set-up (neighbour queries at every
# point: 24 s at 1 M) and slower steps (a deeper tree for every sample), not information (the
# cube at 100 k and at 1 M points scored alike).
FIT_POINTS = 131_072


# The share of the steps that carry the normal term. It decides the topology early (which small
# holes open: a plug across one contradicts the normals of its wall) and is then dropped, since
# the cloud's planes average the two faces at every edge: with it to the end the cube's d_H was
# 0.0142 (0.0145 for three quarters of the steps), with it for half 0.0101 (0.0098 without it).
NORMAL_TERM_SHARE = 0.5

# The share of the steps that draw half of ``batch_points``. A step of 512 points cost 22 ms against
# 50 ms for 1,024 (the smaller working set stays in cache), so the fit took 0.7 of the time; the
# last quarter, which settles the surface into the noise, takes the whole batch: with 512 points
# to the end, d_C rose on five shapes of seven (l_bracket 0.0010 to 0.0013, wedge 0.0013 to 0.0018).
HALF_BATCH_SHARE = 0.75
# Clouds with fewer points keep the whole batch throughout: box_hole's 4,096-point variant lost with
# the half batch (exact d_C 0.0016 to 0.0023, seed 1: 0.0025 to 0.0052), its 16,384 points did not.
HALF_BATCH_MIN_POINTS = 8192

# The first steps of every fit run the eager kernels while the compiled ones are made in the
# background (``warm_kernels_in_background``): 5-9 s to load from the disk cache, 30 s or more
# after an install, before which the first step waited (a fit's whole steps, three shapes: 8-10 s
# from the disk cache on a Xeon with AMX, 0.7 s where the process compiled them before). The two
# threads share the interpreter's lock, so each runs at half its pace or less: with 100 eager
# steps a warm-cache fit reached step 200 5-7 s later than without the thread, with 20 about 1.4 s
# later (docs/benchmarks.md); the fit waits at this step for what is left of the compile. Every
# fit switches at the same step, whether or not its process had compiled before, so that a seed
# gives the same fit.
EAGER_STEPS = 20

# The points whose median of f sets the fitted level (``centre_level``), drawn from the cloud: the
# median of this many is the whole cloud's to within a hundredth of the noise's width.
LEVEL_POINTS = 16_384


def fit_rows(count: int, seed: int) -> np.ndarray:
    """The rows of a cloud of ``count`` points that a fit uses, in order: all of them up to
    ``FIT_POINTS``, else ``FIT_POINTS`` of them drawn at random, the same for the same seed."""
    return subsample_rows(count, FIT_POINTS, seed)


def fit(
    points: np.ndarray,
    params: FitParams,
    progress: ProgressCallback | None = None,
    should_cancel: CancelCheck | None = None,
) -> ImplicitNetwork:
    """Fit f to ``points`` (N, 3), already in the unit frame; return the trained network.

    A cloud of more than ``FIT_POINTS`` points is fitted to that many of them (``fit_rows``). The
    normal term (``lambda4``) covers the first ``NORMAL_TERM_SHARE`` of the steps.
    Each step draws ``batch_points`` input points (half as many in the first ``HALF_BATCH_SHARE``
    of the steps, for a cloud of at least ``HALF_BATCH_MIN_POINTS``) and their eikonal samples
    (``draw_batch``; a ``residual_share`` of the points in proportion to their |f| when last
    drawn), computes ``step_loss`` and takes one Adam step, with the learning rate decaying
    geometrically. The first ``EAGER_STEPS`` steps run the eager kernels while the compiled ones are
    made in a background thread; where the batch is ``batch_points`` (a cloud of at least that
    many), the later steps are compiled whole, once for each shape they take (``step_loss``).
    With ``encoding="auto"`` the network starts without Fourier features and, in a fit of at least
    ``CHECKED_ITERATIONS`` steps whose residuals at its ``CHECK_SHARE`` (each counted no further
    than its neighbours', so that strays do not count) have a heavier tail than noise
    (``residual_tail`` above ``TAIL_LIMIT``, or reaching past ``NOISE_TAIL_LIMIT`` times the
    cloud's noise width) that reaches past ``MISS_FLOOR`` and the points' spacing, starts again
    with ``features`` of them: the same fit as ``encoding="always"``, after those extra steps.
    Last, f is shifted so that its median at the points is 0 (``centre_level``).
    ``should_cancel`` is polled every step, and often during the set-up before the first (the
    neighbour queries and the free-space map take seconds); when it returns True, ``Cancelled``
    is raised.
    """
    points = points[fit_rows(len(points), params.seed)]
    cloud = torch.as_tensor(points, dtype=torch.float32)
    setup = _set_up(points, params, should_cancel)
    level_rows = subsample_rows(len(cloud), LEVEL_POINTS, params.seed)
    level_points = cloud[torch.as_tensor(level_rows)]
    features = params.features if params.encoding == "always" else 0
    check = None
    if params.encoding == "auto" and params.features > 0 and params.iterations >= CHECKED_ITERATIONS:
        floor = max(MISS_FLOOR, setup.spacing)
        neighbours = torch.as_tensor(nearest_others(points[level_rows], SUPPORT_NEIGHBOURS, torch.get_num_threads()))
        check = _Check(round(CHECK_SHARE * params.iterations), level_points, neighbours, floor, setup.noise)
    model = _train(cloud, setup, params, features, progress, should_cancel, check)
    if model is None:
        assert check is not None
        again = _offset(progress, check.step) if progress is not None else None
        model = _train(cloud, setup, params, params.features, again, should_cancel)
        assert model is not None
    centre_level(model, level_points)
    return model


# The share of the steps after which ``encoding="auto"`` reads the residuals. By then every sample
# CAD shape's fit is down to its noise (below), featuretype's counterbores are capped for good, and
# a restart costs half a fit. At a sixth of the steps (300 of 1,800) the fits' tails had not
# settled: featuretype's 99th percentile was 3.9-4.6 medians at three seeds, a CAD block's up to 4.0.
CHECK_SHARE = 0.5

# The fewest steps of a fit that ``encoding="auto"`` checks: the limit below was set on fits of the
# default 1,800 steps, and shorter ones are still above the noise at half of them (a 150-step fit of
# the cube passed it).
CHECKED_ITERATIONS = 1800

# ``residual_tail`` above which the fit starts again with Fourier features. Noise that is normal
# along the surface gives 4.88 (3.29 σ over 0.674 σ). Halfway through default fits of the nine
# sample shapes, their variants and eleven public CAD parts and scans (docs/benchmarks.md), the
# clouds a plain fit follows gave 4.13-5.35 on an AMD EPYC; featuretype 6.10-6.38, a housing with
# 24 holes 7.56-7.66, the teapot 5.78-6.93, an angled block 5.56-6.26. On a Xeon with AMX the
# teapot gave 5.65 and clouds of 4,096 points 5.34-5.67, which the floor below tells apart.
TAIL_LIMIT = 5.5
# ... and the 99.9th percentile of |f - median f| that must pass this too (unit frame: three cells
# of the default grid). A cloud without noise has a tail of the fit's own rounding at every edge
# (the cube's ratio 7.2), but it reaches only 0.008-0.013, which the mesh barely shows, and
# the features gave such clouds no better surface (docs/benchmarks.md): not worth half a fit more.
# The percentile must also pass the points' spacing (``_SetUp.spacing``): a sparse cloud's fit rounds
# its edges over more of a tail (box_hole's 4,096 points 5.56-5.59, a cube's 5.67, reaching
# 0.020-0.023, under their spacing of 0.032-0.040), and there the features made every CAD block
# worse (box_hole's exact d_H 0.0133 -> 0.0250), while the shapes they help reach past it
# (featuretype's 4,096 points 0.040 against 0.024).
MISS_FLOOR = 0.02
# ... or the 99.9th percentile over the cloud's own noise width (``core.sampling.noise_width``) above
# this, which also restarts the fit. The ratio above is taken over the fit's median residual, which a
# fit that is rough everywhere raises with its tail: featuretype's plain fits read 5.12 at seed 0 on
# an AMD EPYC and 5.40 on a Xeon with AMX, under the limit, with 3 % of their normals flipped and
# exact d_H 0.049-0.051 against Poisson's 0.032 (with the features 0.028). Over the noise width,
# halfway through default fits on an AMD EPYC (docs/benchmarks.md), 44 clouds a plain fit follows
# (the nine sample shapes at seeds 0 and 1, box_hole's 4,096-point and noise-0.010 clouds, the eight
# open variants, the twelve parts of bench/parts.py, six public models with the bunny scan) read
# 3.22-4.53; featuretype 5.44, 6.78 and 7.02 at seeds 0 to 2, and the two public parts the tail
# rule restarts 5.63 and 7.45. (Noise alone: 3.29 σ over a width of 0.82-0.88 σ, about 3.9.)
NOISE_TAIL_LIMIT = 5.0

# A residual counts towards the tail only as far as the ``SUPPORT_RANK``-th largest of its
# ``SUPPORT_NEIGHBOURS`` nearest points' residuals: a missed feature (a capped counterbore) is many
# points together, all missed, while a stray return near the surface is a point alone among points
# the fit follows, which features would not fit either. Counted one by one, the strays within a few
# spacings of the faces (0.35 % of the points of box_hole's and l_bracket's clouds with 1 % strays,
# docs/benchmarks.md) reached 9-17 noise widths and restarted the fit, 2.4-4 times as long; counted
# so, 2.5-2.8. Three, so that two or three strays side by side still count as strays. The limits
# above were set on residuals counted one by one (the readings quoted there), and each residual can
# only come down, so a fit that did not restart then does not now; halfway (AMD EPYC, seed 0) the
# sample shapes read 2.6-3.1 noise widths instead of 3.9-4.3, the bunny scan 3.29 (4.54),
# featuretype 5.50 and 5.36 at seeds 0 and 1 (6.31, 5.94 one by one), the housing and the angled
# block 7.14 and 5.70 (7.38, 6.39): the same restarts.
SUPPORT_NEIGHBOURS = 8
SUPPORT_RANK = 3


@dataclass(frozen=True)
class _Check:
    """When ``_train`` reads the residuals (the step), where (the points, (n, 3), with the rows of
    each one's nearest others, (n, ``SUPPORT_NEIGHBOURS``)), how far their tail must reach for a
    restart (the floor, unit frame), and the cloud's noise width."""

    step: int
    points: Tensor
    neighbours: Tensor
    floor: float
    noise: float

    def misses(self, tail: float, reach: float) -> bool:
        """Whether residuals with this ``tail`` and ``reach`` (``residual_tail``) show points the fit
        misses: a tail past ``TAIL_LIMIT``, or a reach past ``NOISE_TAIL_LIMIT`` noise widths, that
        reaches past the floor."""
        return (tail > TAIL_LIMIT or reach > NOISE_TAIL_LIMIT * self.noise) and reach > self.floor


@dataclass(frozen=True)
class _SetUp:
    """What every step of a fit reads besides the network: the points' local scales (n,), the
    free-space map, and the normal term's normals with whether each is oriented; and the points'
    spacing (the median distance to the fourth nearest point), below which ``encoding="auto"``
    takes no residual for a miss, and their noise width (``noise_width``), its other scale."""

    scales: Tensor
    free_space: FreeSpace | None
    cloud_normals: tuple[Tensor, Tensor] | None
    spacing: float
    noise: float


def _set_up(points: np.ndarray, params: FitParams, should_cancel: CancelCheck | None) -> _SetUp:
    # One tree and one pass of neighbour queries serve the local scales and the free-space map.
    tree = build_tree(points, should_cancel)
    distances = neighbour_distances(tree, points, [1, 4, min(50, len(points) - 1)], should_cancel)
    scales = torch.as_tensor(distances[:, 2], dtype=torch.float32)
    # The cloud's own (unoriented) normals: the free-space map's walls for an open cloud, and the
    # normal term's targets.
    planes = None
    if params.lambda3 > 0 or params.lambda4 > 0:
        planes = plane_normals(points, params.seed, should_cancel, tree=tree)
    free_space = None
    if params.lambda3 > 0:
        free_space = FreeSpace(points, tree=tree, spacing=distances[:, :2], normals=planes, should_cancel=should_cancel)
    # The normal term's normals, oriented where the free-space map tells, and whether they are.
    cloud_normals = None
    if planes is not None and params.lambda4 > 0:
        sides = free_space.outward(points, planes) if free_space is not None else np.zeros(len(points), np.int8)
        oriented = torch.as_tensor(planes * np.where(sides == 0, 1, sides)[:, None], dtype=torch.float32)
        cloud_normals = (oriented, torch.as_tensor(sides != 0))
    spacing = float(np.median(distances[:, 1]))
    return _SetUp(scales, free_space, cloud_normals, spacing, noise_width(points, spacing, params.seed, tree))


def _train(
    cloud: Tensor,
    setup: _SetUp,
    params: FitParams,
    features: int,
    progress: ProgressCallback | None,
    should_cancel: CancelCheck | None,
    check: _Check | None = None,
) -> ImplicitNetwork | None:
    """A network with ``features`` Fourier features, trained on ``cloud`` (n, 3) for
    ``params.iterations`` steps; None when ``check`` finds at its step that the fit misses points
    (``_Check.misses``; the steps after it are not taken)."""
    generator = torch.Generator().manual_seed(params.seed)
    with torch.random.fork_rng(devices=[]):  # nn.Linear's own initialisation draws from torch's global generator
        model = ImplicitNetwork(
            params.width, params.depth, params.beta, generator=generator, features=features, frequency=params.frequency
        )
    matmul_dtype = matmul_dtype_for(params.precision)
    batch_size = min(params.batch_points, len(cloud))
    early_size = max(batch_size // 2, 1) if len(cloud) >= HALF_BATCH_MIN_POINTS else batch_size

    # fused: one kernel for all of Adam's updates instead of a dozen operations per tensor (a step
    # 7 % faster); tests/core/test_fit.py checks it against the plain loop.
    optimizer = torch.optim.Adam(model.parameters(), lr=params.learning_rate, fused=True)
    decay = (params.final_learning_rate / params.learning_rate) ** (1.0 / max(params.iterations - 1, 1))
    schedule = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=decay)

    # Each point's |f| when it was last drawn; 1 (far above any fitted residual) until then, so the
    # first weighted draws go to the points not yet seen.
    residuals = torch.ones(len(cloud))

    # The steps are compiled whole where their shapes are the defaults' (a cloud of at least a
    # batch): a smaller cloud's batch is its own size, each a compile of its own.
    whole = batch_size == params.batch_points

    def shape(iteration: int) -> tuple[int, bool]:
        """The step's batch size and whether it carries the normal term."""
        size = batch_size if iteration > HALF_BATCH_SHARE * params.iterations else early_size
        return size, setup.cloud_normals is not None and iteration <= NORMAL_TERM_SHARE * params.iterations

    def inputs(
        size: int, with_normals: bool, draws: torch.Generator, weights: Tensor | None
    ) -> tuple[Tensor, Tensor, Tensor, tuple[Tensor, Tensor] | None]:
        """A step's batch, eikonal samples, the batch's rows and their normals (or None)."""
        batch, samples, rows = draw_batch(cloud, setup.scales, size, draws, weights, params.residual_share)
        batch_normals = None
        if with_normals:
            assert setup.cloud_normals is not None
            batch_normals = (setup.cloud_normals[0][rows], setup.cloud_normals[1][rows])
        return batch, samples, rows, batch_normals

    def take_step(iteration: int) -> None:
        check_cancel(should_cancel)
        batch, samples, rows, batch_normals = inputs(*shape(iteration), generator, residuals)
        loss, terms, edges, batch_residuals = step_loss(
            model, batch, samples, params, setup.free_space, matmul_dtype, batch_normals, whole
        )
        residuals[rows] = batch_residuals

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

    def too_far(iteration: int) -> bool:
        if check is None or iteration != check.step:
            return False
        return check.misses(*residual_tail(model, check.points, check.neighbours))

    def warm_steps(network: ImplicitNetwork) -> None:
        """A step of each shape the fit's compiled steps take, on ``network`` (a copy)."""
        draws = torch.Generator().manual_seed(params.seed)
        for step_shape in sorted({shape(i) for i in range(EAGER_STEPS + 1, params.iterations + 1)}):
            batch, samples, _, batch_normals = inputs(*step_shape, draws, None)  # the same shapes
            loss = step_loss(network, batch, samples, params, setup.free_space, matmul_dtype, batch_normals, True)[0]
            loss.backward()

    warm_kernels_in_background(model, matmul_dtype, params.lambda2 > 0, warm_steps if whole else None)
    try:
        with eager_kernels():
            for iteration in range(1, min(EAGER_STEPS, params.iterations) + 1):
                take_step(iteration)
                if too_far(iteration):
                    return None
    finally:  # a cancelled fit leaves no compiler thread behind to race the next import or the exit
        finish_warming_kernels()
    for iteration in range(EAGER_STEPS + 1, params.iterations + 1):
        take_step(iteration)
        if too_far(iteration):
            return None
    return model


def _offset(progress: ProgressCallback, steps: int) -> ProgressCallback:
    """``progress`` with ``steps`` more done and to do: a fit started again reports the steps
    it already took, so that its progress never goes back."""

    def report(update: Progress) -> None:
        progress(update.model_copy(update={"iteration": update.iteration + steps, "total": update.total + steps}))

    return report


@torch.no_grad()
def residual_tail(model: Callable[[Tensor], Tensor], points: Tensor, neighbours: Tensor) -> tuple[float, float]:
    """How far the largest residuals at ``points`` (n, 3) reach beyond the typical one, the
    99.9th percentile of |f - median f| over its median, and that percentile itself; each residual
    taken no larger than the ``SUPPORT_RANK``-th largest of its neighbours' (``neighbours``, (n, k)
    rows of ``points``), so that points missed alone (strays) do not count.

    Where f follows the points to their noise, this is the noise's own ratio (about 2.6 for noise
    that is normal along the surface, 4.88 with each residual counted alone); points that f does
    not reach together (a pocket it caps, a rib it rounds off) lengthen the tail. The ratio is the
    noise's scale-free: a cloud twice as noisy gives the same one.
    """
    f = model(points)
    residual = (f - f.median()).abs()
    rank = min(SUPPORT_RANK, neighbours.shape[1])
    support = residual[neighbours].topk(rank, dim=1).values[:, -1] if rank > 0 else residual
    high = torch.quantile(torch.minimum(residual, support), 0.999).item()
    typical = torch.quantile(residual, 0.5).item()
    return high / max(typical, 1e-12), high


@torch.no_grad()
def centre_level(model: ImplicitNetwork, points: Tensor) -> float:
    """Shift f by a constant so that its median at ``points`` (n, 3) is 0; return the shift.

    The vanish term's mean |f| is least, over shifts of f, where the median of f at the points is 0,
    but it is flat within the noise, so the other terms can leave a whole surface offset: a fit of
    box_hole's 4,096 points came out inflated by one noise width (the median of f at its points
    -0.0043, the mesh's volume 0.0047 times its area too large). Shifting f's last bias by the
    median puts the surface back in the middle of the points; a good fit moves by a few ten-thousandths.
    """
    median = float(model(points).median())
    last = cast(torch.nn.Linear, model.layers[-1])
    last.bias.sub_(median)
    return median


def step_loss(
    model: ImplicitNetwork,
    batch: Tensor,
    samples: Tensor,
    params: FitParams,
    free_space: FreeSpace | None = None,
    matmul_dtype: torch.dtype | None = None,
    normals: tuple[Tensor, Tensor] | None = None,
    whole: bool = False,
) -> tuple[Tensor, dict[str, Tensor], Tensor, Tensor]:
    """The loss of one step, its terms, the batch's edge mask (DES) and |f| at the batch's points
    (detached: the residuals that weight the next draws).

    ``batch`` holds input points, ``samples`` the eikonal samples (near the points, then uniform in
    the box). One pass of the network gives f and ∇f everywhere and Δf at the batch; the eikonal
    and free-space terms cover the samples (the eikonal term the batch too). The free-space term
    needs the near samples: a membrane across a small hole (the L-bracket's) is met by a uniform
    sample a few times per thousand steps, by the near samples every step. ``normals`` are the
    cloud's normals at the batch's points and whether each is oriented, for the normal term (None:
    no such term). ``whole``: the step after the free-space map's lookup is compiled whole
    (``compile_whole``) for these shapes; the same loss to rounding.
    """
    space = None
    if free_space is not None:
        distance, sign = free_space.distance_and_sign(samples)
        space = (distance, sign, torch.tensor(free_space.margin))
    # The weights as a tensor, so that a compiled step is one graph for every value of them.
    weights = torch.tensor(
        [params.lambda1, params.lambda2, params.tau, params.penalty_scale, params.lambda4, params.lambda3]
    )
    which = _Terms(params.lambda2 > 0, params.edge_sampling, params.laplacian_penalty)
    terms_of = _whole_step_terms if whole else _step_terms
    return terms_of(model, batch, samples, which, weights, space, matmul_dtype, normals)


@dataclass(frozen=True)
class _Terms:
    """Which terms a step has and how (what a compiled step's graph depends on, besides shapes)."""

    laplacian: bool
    edge_sampling: bool
    penalty: str


def _step_terms(
    model: ImplicitNetwork,
    batch: Tensor,
    samples: Tensor,
    which: _Terms,
    weights: Tensor,
    space: tuple[Tensor, Tensor, Tensor] | None,
    matmul_dtype: torch.dtype | None,
    normals: tuple[Tensor, Tensor] | None,
) -> tuple[Tensor, dict[str, Tensor], Tensor, Tensor]:
    """``step_loss`` given the free-space map's distance, sign (at the samples) and margin, and
    ``weights`` (6,): λ1, λ2, τ, the penalty's scale, λ4, λ3."""
    lambda1, lambda2, tau, scale, lambda4, lambda3 = weights.unbind()
    n = len(batch)
    f, grad, lap = model.derivatives(torch.cat([batch, samples]), n if which.laplacian else 0, matmul_dtype)
    terms = {"vanish": vanish_loss(f[:n]), "eikonal": eikonal_loss(grad)}
    loss = terms["vanish"] + lambda1 * terms["eikonal"]
    edges = torch.zeros(0, dtype=torch.bool)
    if lap is not None:
        terms["laplacian"], edges = laplacian_loss(lap, tau, which.edge_sampling, which.penalty, scale)
        loss = loss + lambda2 * terms["laplacian"]
    if normals is not None:
        terms["normal"] = normal_loss(grad[:n], *normals, edges)
        loss = loss + lambda4 * terms["normal"]
    if space is not None:
        terms["free_space"] = free_space_loss(f[n:], *space)
        loss = loss + lambda3 * terms["free_space"]
    return loss, terms, edges, f[:n].detach().abs()


_whole_step_terms = compile_whole(_step_terms)


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
