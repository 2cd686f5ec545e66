"""How much of the sky a voxel sees: the directions in which a ray leaves the grid unblocked.

An open cloud (a scan whose base was never scanned, a part with an unsampled face) lets the
free-space map's flood fill run from the box's boundary into the solid, so the inside is labelled
outside. What still tells the two apart is visibility: empty space outside a part sees the box's
boundary in most of the 26 grid directions, the inside of an open part only through its opening.
``core.sampling.FreeSpace`` uses this, with the walls' normals, to take such regions back.
"""

from __future__ import annotations

import itertools

import numpy as np

# The 26 directions to a voxel's neighbours (13 lines, both ways).
DIRECTIONS = tuple(d for d in itertools.product((-1, 0, 1), repeat=3) if d != (0, 0, 0))


def escape_counts(blocked: np.ndarray) -> np.ndarray:
    """(n0, n1, n2) uint8: for each voxel, in how many of the 26 ``DIRECTIONS`` the ray from it
    (stepping one voxel along the direction at a time) leaves the grid without entering a voxel of
    ``blocked`` (a (n0, n1, n2) bool array; the voxel itself does not count)."""
    counts = np.zeros(blocked.shape, dtype=np.uint8)
    for direction in DIRECTIONS:
        counts += _escapes(blocked, direction)
    return counts


def sees_through(blocked: np.ndarray) -> np.ndarray:
    """(n0, n1, n2) bool: the voxels whose rays leave the grid unblocked both ways along one of the
    13 lines of ``DIRECTIONS``: the space of a tunnel open at both ends (a through-hole), which the
    inside of an open part, seeing out only through its opening, is not."""
    through = np.zeros(blocked.shape, dtype=bool)
    for direction in DIRECTIONS[: len(DIRECTIONS) // 2]:  # the other half are their opposites
        opposite = tuple(-step for step in direction)
        through |= _escapes(blocked, direction) & _escapes(blocked, opposite)
    return through


def _escapes(blocked: np.ndarray, direction: tuple[int, ...]) -> np.ndarray:
    """(n0, n1, n2) bool: whether the ray from each voxel along ``direction`` leaves the grid
    without entering a voxel of ``blocked``.

    One sweep, a slice at a time: a voxel's ray is blocked when its next voxel is blocked or that
    voxel's ray is, so each direction costs one pass over the grid (26 of them: 0.1 s at 90³).
    """
    axis = max(i for i in range(3) if direction[i] != 0)  # sweep along an axis the ray advances on
    order = [i for i in range(3) if i != axis] + [axis]
    grid = np.ascontiguousarray(np.moveaxis(np.transpose(blocked, order), 2, 0))  # slices first
    step = direction[axis]
    (source0, target0), (source1, target1) = (_overlap(grid.shape[k + 1], direction[order[k]]) for k in (0, 1))
    hit = np.zeros_like(grid)  # hit[i]: the ray from each voxel of slice i meets a blocked voxel
    ahead = np.empty_like(grid[0])
    for i in range(grid.shape[0] - 2, -1, -1) if step > 0 else range(1, grid.shape[0]):
        np.logical_or(grid[i + step], hit[i + step], out=ahead)
        hit[i][target0, target1] = ahead[source0, source1]  # past the edge: left the grid, not blocked
    return ~np.transpose(np.moveaxis(hit, 0, 2), np.argsort(order))


def _overlap(size: int, shift: int) -> tuple[slice, slice]:
    """The slices (source, target) of an axis of ``size`` read at offset ``shift``:
    out[target] = plane[source] means out[j] = plane[j + shift] wherever both exist."""
    return slice(max(shift, 0), size + min(shift, 0)), slice(max(-shift, 0), size + min(-shift, 0))
