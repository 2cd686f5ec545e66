"""Where the fit looks besides the input points: eikonal samples, and what is known of empty space."""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import TypeVar

import numpy as np
import torch
from scipy import ndimage
from scipy.spatial import cKDTree
from torch import Tensor

from core.errors import CancelCheck, check_cancel
from core.trees import kd_tree
from core.visibility import escape_bits, escape_counts, tunnels

# The shape fills [-0.5, 0.5]^3 in the unit frame; uniform samples cover a slightly larger box.
BOX_HALF_SIZE = 0.6
# Points per neighbour query: about 0.2 s at k = 51 on one core, so a cancel is seen promptly, and
# the distances of one chunk (not of 5 M points times 51 neighbours, 2 GB) are all that is held.
QUERY_CHUNK = 16_384
# At most this many voxels along the free-space grid's side: 256³ bytes per grid. Finer grids
# (from the spacing of a cloud of millions of points) cost gigabytes and tens of seconds in
# calls that cannot be interrupted, and the sign is unknown near the points anyway.
MAX_GRID_CELLS = 256
# The cloud's own normals (the normal term): planes through each point's 16 nearest points, at the
# density of 16,384 points (the sample shapes'), where a plane spans about 0.02 and averages the noise
# of 16 points; 8 neighbours gave noisier planes, 32 wider ones that bend over small holes.
PLANE_NEIGHBOURS = 16
PLANE_POINTS = 16_384
# The spacing at which ``noise_width`` fits its planes: a denser cloud is subsampled to it. Where the
# noise is as wide as the spacing the width reads less than the noise (a public part whose points lie
# 0.0064 apart: 0.59 σ at its own spacing, 0.82 σ at this one; the sample shapes lie 0.013-0.021 apart).
NOISE_SPACING = 0.012
# How far to each side of a point (in free-space voxels) its normal's orientation is read: past the
# shell of dilated voxels around the points, whose sign is unknown (on the sample shapes: 94 to 100 %
# of the points of the CAD parts oriented, 81 % of featuretype's, nearly all wrong ones on edges).
ORIENT_VOXELS = 3
# Open clouds (the free-space map's flood fill leaks in through an unsampled face): an empty
# region is a candidate for the inside of an open part when none of its voxels sees the box's
# boundary in more than OPEN_ESCAPE_MAX of the 26 grid directions. On the sample shapes, empty space
# outside a part sees it in 9 to 26 (mostly 17 or more), the inside of a cube whose top was not
# sampled in at most 9; pockets and bores of closed parts see little too, and the walls' votes
# tell them apart. A region is taken back as inside when at least OPEN_MIN_VOTES wall points, and
# OPEN_VOTE_RATIO times as many as say otherwise, have open outside space behind them. A
# through-bore is a region of its own: it sees out both ways along its axis and nowhere else, which
# the inside of an open part, seeing out only through its opening, cannot.
OPEN_ESCAPE_MAX = 11
OPEN_MIN_VOTES = 32
OPEN_VOTE_RATIO = 3
# A region taken back can hold outside space too, joined to the inside past the opening (a groove
# of the part): space across one of the region's own walls from the inside, yet reached from the
# inside's walls only by a path round, longer by more than OPEN_DETOUR_VOXELS (the two sides of a
# wall are 2 * ORIENT_VOXELS apart straight through it).
OPEN_DETOUR_VOXELS = 4 * ORIENT_VOXELS
# A stretch of a bore that the dilated shell closed at both ends, left unknown rather than inside
# (``_without_slivers``): an enclosed pocket of the fill at most SLIVER_DEPTH voxels deep (1: one
# voxel across; about 1.41: two, diagonally), at least SLIVER_LENGTH voxels long and at most
# SLIVER_WIDTH wide (along its principal axes). A shaft's bore of radius 0.035 (3.3 voxels) left
# stretches 12 to 33 voxels long, and the fit held the bore solid along its thin end. Shorter or
# wider pockets stay inside: idler_riser's pockets of one and five voxels lie inside its solid,
# and its fits lost 0.0005 to 0.0071 of exact d_H at three seeds without them (docs/benchmarks.md).
SLIVER_DEPTH = 1.5
SLIVER_LENGTH = 8
SLIVER_WIDTH = 4
# Seconds between cancel checks while a call that cannot be interrupted runs in a thread.
_POLL_SECONDS = 0.05

T = TypeVar("T")


def polled(work: Callable[[], T], should_cancel: CancelCheck | None) -> T:
    """``work()``, run in a thread while ``should_cancel`` is polled: for a long call into C that
    releases the GIL (a k-d tree's build: 1.5 s at 5 M points). On a cancel ``Cancelled`` is raised
    at once and the thread is left to finish on its own."""
    if should_cancel is None:
        return work()
    outcome: list[T] = []
    failure: list[BaseException] = []

    def run() -> None:
        try:
            outcome.append(work())
        except BaseException as error:  # handed to the caller below
            failure.append(error)

    thread = threading.Thread(target=run, name="edgerecon-setup", daemon=True)
    thread.start()
    while thread.is_alive():
        check_cancel(should_cancel)
        thread.join(_POLL_SECONDS)
    if failure:
        raise failure[0]
    return outcome[0]


def build_tree(points: np.ndarray, should_cancel: CancelCheck | None = None) -> cKDTree:
    """The k-d tree of ``points``, built while ``should_cancel`` is polled.

    Balanced (median splits): it builds in 0.56 s at 1 M points where a sliding-midpoint tree takes
    0.39 s, but it finds the nearest point of a sample far from the cloud five times faster (12 ms
    against 62 ms for the 128 uniform samples of a step at 1 M points; the same at 16 k), and every
    step asks that of the free-space term. Both give the same, exact distances."""
    return polled(lambda: kd_tree(points), should_cancel)


def neighbour_distances(
    tree: cKDTree, points: np.ndarray, ranks: Sequence[int], should_cancel: CancelCheck | None = None
) -> np.ndarray:
    """(N, len(ranks)): the distance from each point to its ``rank``-th nearest input point (rank 0
    is the point itself), queried ``QUERY_CHUNK`` points at a time with ``should_cancel`` polled
    before each, on torch's threads: at 1 M points these queries are most of the set-up."""
    k = max(ranks) + 1
    distances = np.empty((len(points), len(ranks)))
    workers = torch.get_num_threads()  # the cores this process may use (core.runtime.configure)
    for start in range(0, len(points), QUERY_CHUNK):
        check_cancel(should_cancel)
        found, _ = tree.query(points[start : start + QUERY_CHUNK], k=k, workers=workers)
        distances[start : start + QUERY_CHUNK] = found[:, list(ranks)]
    return distances


def local_scales(
    points: np.ndarray, neighbour: int = 50, tree: cKDTree | None = None, should_cancel: CancelCheck | None = None
) -> np.ndarray:
    """Per-point distance to the ``neighbour``-th nearest input point (IGR's local noise scale)."""
    tree = tree if tree is not None else build_tree(points, should_cancel)
    k = min(neighbour, len(points) - 1)
    return neighbour_distances(tree, points, [k], should_cancel)[:, 0]


def eikonal_samples(batch: Tensor, scales: Tensor, n_uniform: int, generator: torch.Generator) -> Tensor:
    """The batch points moved by Gaussian noise of their local scale, then ``n_uniform`` points
    drawn uniformly in the box (last)."""
    near = batch + torch.randn(batch.shape, generator=generator, dtype=batch.dtype) * scales[:, None]
    box = (torch.rand((n_uniform, 3), generator=generator, dtype=batch.dtype) * 2 - 1) * BOX_HALF_SIZE
    return torch.cat([near, box])


def draw_batch(
    cloud: Tensor,
    scales: Tensor,
    size: int,
    generator: torch.Generator,
    residuals: Tensor | None = None,
    residual_share: float = 0.0,
) -> tuple[Tensor, Tensor, Tensor]:
    """One step's inputs: ``size`` input points drawn at random, their eikonal samples (near the
    first half of them, then ``size // 8`` uniform in the box), and the rows of the points drawn.

    With ``residuals`` (N,), each input point's last |f|, the last ``round(size * residual_share)``
    points are drawn again in proportion to them (with replacement), after the eikonal samples:
    the steps go where the surface does not yet pass through the points (a small hole, a thin
    rib) instead of to the faces already fitted to the noise, and the eikonal samples keep their
    uniform cover. With none, the draws are the uniform ones alone.
    """
    index = torch.randint(len(cloud), (size,), generator=generator)
    near = index[: max(size // 2, 1)]
    samples = eikonal_samples(cloud[near], scales[near], max(size // 8, 1), generator)
    weighted = round(size * residual_share)
    if residuals is not None and weighted:
        index[size - weighted :] = torch.multinomial(residuals, weighted, replacement=True, generator=generator)
    return cloud[index], samples, index


def subsample_rows(count: int, limit: int, seed: int) -> np.ndarray:
    """The rows of ``count`` points to keep, in order: all of them up to ``limit``, else ``limit``
    of them drawn at random, the same for the same seed."""
    if count <= limit:
        return np.arange(count)
    return np.sort(np.random.default_rng(seed).choice(count, limit, replace=False))


def plane_normals(
    points: np.ndarray,
    seed: int = 0,
    should_cancel: CancelCheck | None = None,
    tree: cKDTree | None = None,
) -> np.ndarray:
    """Unoriented unit normals (N, 3): for each point, the normal of the plane through the
    ``PLANE_NEIGHBOURS`` nearest points (the least principal direction of their spread).

    The planes are fitted at the density of ``PLANE_POINTS`` points (a seeded subsample of a larger
    cloud, each point taking the normal of its nearest subsample point), so that a plane spans the
    same area, and averages away the same noise, however dense the cloud. ``tree``, the k-d tree of
    ``points``, may be given when the caller has it; it serves when there is no subsample.
    """
    sample = points
    if len(points) > PLANE_POINTS:
        sample = points[subsample_rows(len(points), PLANE_POINTS, seed)]
        tree = None
    tree = tree if tree is not None else build_tree(sample, should_cancel)
    normals = _neighbour_planes(sample, tree)[1][:, :, 0]
    if sample is points:
        return normals
    workers = torch.get_num_threads()
    nearest = np.empty(len(points), dtype=np.int64)
    chunk = 8 * QUERY_CHUNK  # k = 1: a fraction of the time of the neighbour queries' chunks
    for start in range(0, len(points), chunk):
        check_cancel(should_cancel)
        _, nearest[start : start + chunk] = tree.query(points[start : start + chunk], workers=workers)
    return normals[nearest]


def noise_width(points: np.ndarray, spacing: float, seed: int = 0, tree: cKDTree | None = None) -> float:
    """The cloud's noise width: the median, over the planes through each point's ``PLANE_NEIGHBOURS``
    nearest points, of their RMS distance from it; fitted at a spacing of at least ``NOISE_SPACING``
    (``spacing``: the cloud's median distance to its fourth nearest point; a denser cloud is
    subsampled, seeded).

    The cloud's own scale for how far a fit's residuals may reach (``core.fit``). For noise of width
    σ along a flat face, well under the spacing, it is 0.88 σ (a plane through 16 points takes up 3
    of their degrees of freedom); noise as wide as the spacing reads less, since the nearest points
    in space are then those nearest the plane; curvature within a plane's span reads more.
    ``tree``, the k-d tree of ``points``, may be given when the caller has it; it serves when there
    is no subsample.
    """
    sample = points
    if spacing < NOISE_SPACING:
        count = max(PLANE_NEIGHBOURS, round(len(points) * (spacing / NOISE_SPACING) ** 2))
        sample = points[subsample_rows(len(points), count, seed)]
        tree = None
    spreads = _neighbour_planes(sample, tree if tree is not None else build_tree(sample))[0][:, 0]
    return float(np.median(np.sqrt(np.maximum(spreads, 0.0) / min(PLANE_NEIGHBOURS, len(sample)))))


def _neighbour_planes(sample: np.ndarray, tree: cKDTree) -> tuple[np.ndarray, np.ndarray]:
    """The planes through each point's ``PLANE_NEIGHBOURS`` nearest points of ``sample`` (n, 3),
    ``tree`` its k-d tree: the spread of those points along the principal directions, least first
    (n, 3; sums of squares about their mean), and the directions (n, 3, 3; columns)."""
    _, rows = tree.query(sample, k=min(PLANE_NEIGHBOURS, len(sample)), workers=torch.get_num_threads())
    around = sample[rows] - sample[rows].mean(axis=1, keepdims=True)
    spreads, directions = np.linalg.eigh(np.einsum("nki,nkj->nij", around, around))
    return spreads, directions


class FreeSpace:
    """What the cloud says about empty space, for the free-space term.

    ``distance`` is the distance from a sample to the nearest input point: a surface through the
    points is at least that far away, give or take ``margin`` (noise and sampling gaps). Where it
    can, ``sign`` also tells inside (-1) from outside (+1): the input points are voxelised, the
    voxels dilated by one so that the sampling gaps close, and the empty voxels that cannot be
    reached from the box's boundary are inside, but for lines of them one or two voxels across,
    the stretches of a narrow bore that the dilation closed (``_without_slivers``). Near the points
    (the dilated voxels) and for clouds that do not enclose a volume, the sign is unknown (0).

    An open cloud lets the fill run into the solid. Given the points' unoriented ``normals``
    (``plane_normals``), regions of that kind are found and taken back as inside (``_close_openings``):
    empty space that sees little of the box's boundary, whose walls have open outside space behind
    them, less any through-bore or groove of the part joined to it. A closed cloud's map is left as
    the fill made it.

    ``tree`` and ``spacing`` (the distances to the 1st and 4th nearest neighbours) may be given
    when the caller has them; ``should_cancel`` is polled throughout.
    """

    def __init__(
        self,
        points: np.ndarray,
        *,
        tree: cKDTree | None = None,
        spacing: np.ndarray | None = None,
        normals: np.ndarray | None = None,
        should_cancel: CancelCheck | None = None,
    ):
        self.tree = tree if tree is not None else build_tree(points, should_cancel)
        if spacing is None:
            spacing = neighbour_distances(self.tree, points, [1, 4], should_cancel)
        self.margin = float(2 * np.median(spacing[:, 0]))
        self.voxel = max(float(np.median(spacing[:, 1])), 2 * BOX_HALF_SIZE / MAX_GRID_CELLS)
        cells = int(np.ceil(2 * BOX_HALF_SIZE / self.voxel))
        shell = np.zeros((cells,) * 3, dtype=bool)
        shell[self._cells(points)] = True
        check_cancel(should_cancel)
        shell = polled(lambda: ndimage.binary_dilation(shell, structure=np.ones((3, 3, 3), dtype=bool)), should_cancel)
        enclosed = polled(lambda: ndimage.binary_fill_holes(shell), should_cancel)
        sign = np.where(enclosed, 0, 1).astype(np.int8)
        sign[enclosed & ~shell] = -1
        sign = _without_slivers(sign)
        if normals is not None:
            check_cancel(should_cancel)
            sign = self._close_openings(sign, points, normals)
        self.sign_grid = torch.as_tensor(sign)

    def _close_openings(self, sign: np.ndarray, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """``sign`` (cells³, int8) with the inside of an open part, which the fill reached through
        an unsampled face, marked inside (-1).

        Candidates are the connected regions of reachable voxels that see the box's boundary in at
        most ``OPEN_ESCAPE_MAX`` directions (``core.visibility.escape_counts``). Each wall point
        votes for the region on one side of it (``ORIENT_VOXELS`` voxels along its normal): inside
        when open outside space (reachable, not a candidate) lies on its other side, outside when
        the solid (-1) does. A pocket in a closed part has the solid behind its walls; the inside
        of an open box has the outside behind them. A region taken back loses what lies across its
        own walls from the inside (``_across_own_walls``).

        A through-bore is a region of its own (``_candidate_regions``).
        """
        step = ORIENT_VOXELS * self.voxel
        sides = [self._cells(points + step * normals), self._cells(points - step * normals)]
        regions, count = _candidate_regions(sign, sides)
        if count == 0:
            return sign
        inside_votes = np.zeros(count + 1, dtype=np.int64)
        outside_votes = np.zeros(count + 1, dtype=np.int64)
        for here, there in (sides, sides[::-1]):
            region, other_sign, other_region = regions[here], sign[there], regions[there]
            inside_votes += np.bincount(region[(other_sign == 1) & (other_region == 0)], minlength=count + 1)
            outside_votes += np.bincount(region[other_sign == -1], minlength=count + 1)
        inside = (inside_votes >= OPEN_MIN_VOTES) & (inside_votes >= OPEN_VOTE_RATIO * outside_votes)
        inside[0] = False  # label 0: not a candidate
        taken = inside[regions]
        if taken.any():
            taken &= ~_across_own_walls(taken, sign == 1, sides)
        repaired = sign.copy()
        repaired[taken] = -1
        return repaired

    def _cells(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The index of the free-space voxel of each of ``points`` (N, 3), clamped to the grid."""
        cells = int(np.ceil(2 * BOX_HALF_SIZE / self.voxel))
        index = np.clip(((points + BOX_HALF_SIZE) / self.voxel).astype(int), 0, cells - 1)
        return index[:, 0], index[:, 1], index[:, 2]

    def outward(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Which way each unoriented normal (N, 3) at ``points`` (N, 3) points out of the solid
        (N,): +1 along it, -1 against it, 0 unknown. Read from the signs ``ORIENT_VOXELS`` voxels
        to either side, past the dilated shell around the points: +1 where the side ahead is
        outside or the side behind inside, and nothing says the reverse (on a thin plate both
        sides are outside, and the answer is 0)."""
        step = ORIENT_VOXELS * self.voxel
        cloud, along = torch.as_tensor(points, dtype=torch.float32), torch.as_tensor(normals, dtype=torch.float32)
        _, ahead = self.distance_and_sign(cloud + step * along)
        _, behind = self.distance_and_sign(cloud - step * along)
        out = (ahead > 0) | (behind < 0)
        into = (ahead < 0) | (behind > 0)
        return (out & ~into).numpy().astype(np.int8) - (into & ~out).numpy().astype(np.int8)

    def distance_and_sign(self, samples: Tensor) -> tuple[Tensor, Tensor]:
        """The distance from each sample to the nearest input point, and its sign (-1, 0 or +1)."""
        distance = torch.as_tensor(self.tree.query(samples.numpy(), k=1)[0], dtype=samples.dtype)
        index = tuple(torch.as_tensor(axis) for axis in self._cells(samples.numpy()))
        sign = self.sign_grid[index].to(samples.dtype)
        return distance, sign


def _without_slivers(sign: np.ndarray) -> np.ndarray:
    """``sign`` (cells³, int8) with each inside pocket but the largest that is a line of voxels (at
    most ``SLIVER_DEPTH`` deep, at least ``SLIVER_LENGTH`` long, at most ``SLIVER_WIDTH`` wide) set
    to unknown (0).

    The shell's dilation closes a bore narrower than about seven voxels in places, and the fill
    takes the stretches between for inside; the fit then holds the bore solid against its own
    points, and orients their normals into it. Unknown, the points decide.
    """
    inside = sign == -1
    labels, count = ndimage.label(inside, structure=np.ones((3, 3, 3), dtype=bool))
    if count < 2:
        return sign
    index = np.arange(1, count + 1)
    largest = int(np.argmax(ndimage.sum(inside, labels, index))) + 1
    unknown = np.zeros(count + 1, dtype=bool)
    for label, box in zip(index, ndimage.find_objects(labels), strict=True):
        if label == largest:
            continue
        # The pocket in its box with a margin of one voxel (never past the grid: the fill's inside
        # does not reach its boundary), so that the depth is read off the pocket alone: the
        # distance transform of a whole grid of 256³ voxels took seconds.
        margin = tuple(slice(max(axis.start - 1, 0), axis.stop + 1) for axis in box)
        pocket = labels[margin] == label
        length, width = _extents(np.argwhere(pocket).astype(np.float64))
        if length >= SLIVER_LENGTH and width <= SLIVER_WIDTH:
            unknown[label] = ndimage.distance_transform_edt(pocket).max() <= SLIVER_DEPTH
    if not unknown.any():
        return sign
    return np.where(unknown[labels], np.int8(0), sign)


def _extents(cells: np.ndarray) -> tuple[float, float]:
    """The length and width of a set of voxels (n, 3): the extent of their centres along their
    first and second principal axes, plus one voxel."""
    if len(cells) < 2:
        return 1.0, 1.0
    centred = cells - cells.mean(axis=0)
    _, axes = np.linalg.eigh(centred.T @ centred)
    along = centred @ axes[:, ::-1][:, :2]
    length, width = np.ptp(along, axis=0) + 1.0
    return float(length), float(width)


def _candidate_regions(
    sign: np.ndarray, sides: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]]
) -> tuple[np.ndarray, int]:
    """The candidates of ``_close_openings`` (reachable voxels that see the box's boundary in at
    most ``OPEN_ESCAPE_MAX`` directions) labelled by connected region, 1 to count (0: none), with
    every bore a region of its own: (labels like ``sign``, count).

    A bore is a region of tunnel voxels (``core.visibility.tunnels``) and their neighbours (the
    voxels along its noisy walls see out along no line) that at least ``OPEN_MIN_VOTES`` wall
    points line (a side of theirs lies in it). A through-bore of a part whose base is open sees
    little sky and joins the inside under the opening; as one region it was taken back with the
    inside (box_hole without its base: 7,616 voxels of its bore; its wall's normals flipped). On
    its own it has the inside behind its walls, which casts no vote, and stays outside. Tunnel
    voxels that no wall lines are a line of sight between two openings of one cavity (a cube
    scanned with holes in two faces): they stay with the cavity.
    """
    escapes = escape_bits(sign == 0)
    candidates = (sign == 1) & (escape_counts(escapes) <= OPEN_ESCAPE_MAX)
    cube = np.ones((3, 3, 3), dtype=bool)
    walled_in, walled_count = ndimage.label(candidates & ndimage.binary_dilation(tunnels(escapes)), structure=cube)
    lined = np.zeros(walled_count + 1, dtype=np.int64)
    for side in sides:
        lined += np.bincount(walled_in[side], minlength=walled_count + 1)
    lined[0] = 0
    bores = (lined >= OPEN_MIN_VOTES)[walled_in]
    regions, count = ndimage.label(candidates & ~bores, structure=cube)
    bore_regions, bore_count = ndimage.label(bores, structure=cube)
    regions[bores] = bore_regions[bores] + count
    return regions, count + bore_count


def _across_own_walls(
    taken: np.ndarray, outside: np.ndarray, sides: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]]
) -> np.ndarray:
    """The part of ``taken`` (bool grid: the regions taken back as inside) that is outside space
    joined to the inside past the opening, such as a groove of the part: bool, like ``taken``.

    ``sides`` holds the voxels on the two sides of every wall point (``_close_openings``). The
    inside is grown from the taken side of the walls with outside space (``outside`` and not
    taken) behind them, by distance within ``taken``. A wall with taken space on both sides, one
    side farther than ``OPEN_DETOUR_VOXELS`` beyond the other, seeds the farther side as outside;
    each taken voxel then goes to the nearer of the two growths. Without walls that have taken
    space on both sides (most open clouds) nothing is grown: a growth costs about a second per
    million voxels.
    """
    here, there = sides
    if not (taken[here] & taken[there]).any():
        return np.zeros(taken.shape, dtype=bool)
    inside_seeds = np.zeros(taken.shape, dtype=bool)
    for here, there in (sides, sides[::-1]):
        open_behind = taken[here] & outside[there] & ~taken[there]
        inside_seeds[tuple(axis[open_behind] for axis in here)] = True
    from_inside = _geodesic_distance(taken, inside_seeds)
    outside_seeds = np.zeros(taken.shape, dtype=bool)
    for here, there in (sides, sides[::-1]):
        round_about = taken[here] & taken[there] & (from_inside[here] > from_inside[there] + OPEN_DETOUR_VOXELS)
        outside_seeds[tuple(axis[round_about] for axis in here)] = True
    if not outside_seeds.any():
        return outside_seeds
    return _geodesic_distance(taken, outside_seeds) < from_inside


def _geodesic_distance(mask: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """(n0, n1, n2) float64: the length (in voxels) of the shortest path from a voxel of ``seeds``
    to each voxel of ``mask`` through ``mask``, in steps to any of the 26 neighbours; inf off
    ``mask`` and where no seed is reached. skimage's minimum-cost paths, on the box around ``mask``.
    """
    from skimage.graph import MCP_Geometric  # here: most fits never need it, and workers import this module

    distance = np.full(mask.shape, np.inf)
    starts = seeds & mask
    if not starts.any():
        return distance
    box = ndimage.find_objects(mask.astype(np.uint8))[0]
    costs = np.where(mask[box], 1.0, np.inf)
    found, _ = MCP_Geometric(costs, fully_connected=True).find_costs(np.argwhere(starts[box]))
    distance[box] = np.where(mask[box], found, np.inf)
    return distance
