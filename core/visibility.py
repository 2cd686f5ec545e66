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

# The 26 directions to a voxel's neighbours (13 lines, both ways): DIRECTIONS[25 - i] is the
# opposite of DIRECTIONS[i].
DIRECTIONS = tuple(d for d in itertools.product((-1, 0, 1), repeat=3) if d != (0, 0, 0))


def escape_bits(blocked: np.ndarray) -> np.ndarray:
    """(n0, n1, n2) uint32: bit i of a voxel is set when the ray from it along ``DIRECTIONS[i]``
    (stepping one voxel at a time) leaves the grid without entering a voxel of ``blocked`` (a
    (n0, n1, n2) bool array; the voxel itself does not count). One word per voxel keeps every
    direction for ``escape_counts`` and ``tunnels`` at a sixth of the memory of 26 bool grids."""
    bits = np.zeros(blocked.shape, dtype=np.uint32)
    for i, direction in enumerate(DIRECTIONS):
        bits |= _escapes(blocked, direction).astype(np.uint32) << np.uint32(i)
    return bits


def escape_counts(bits: np.ndarray) -> np.ndarray:
    """(n0, n1, n2) uint8: in how many directions each voxel sees out, from ``escape_bits``."""
    return np.bitwise_count(bits).astype(np.uint8)


def tunnels(bits: np.ndarray) -> np.ndarray:
    """(n0, n1, n2) bool, from ``escape_bits``: the voxels that see out both ways along one of the
    13 lines of ``DIRECTIONS`` and in none of the directions square to it: the space of a bore
    open at both ends, walled in all round. The inside of an open part sees out through its
    opening only; the layer of it level with the opening's rim, which sees out sideways over the
    rim both ways, sees out upwards too, so it is no tunnel."""
    inside = np.zeros(bits.shape, dtype=bool)
    for line, direction in enumerate(DIRECTIONS[: len(DIRECTIONS) // 2]):  # the rest are opposites
        both_ways = np.uint32((1 << line) | (1 << (len(DIRECTIONS) - 1 - line)))
        square = np.uint32(sum(1 << i for i, other in enumerate(DIRECTIONS) if np.dot(other, direction) == 0))
        inside |= ((bits & both_ways) == both_ways) & ((bits & square) == 0)
    return inside


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
