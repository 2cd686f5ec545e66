"""core.sampling's grid helpers for open clouds, against slow references and hand-made grids.

(The free-space map as a whole is tested with the fit, in test_fit.py.)"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from core.sampling import SLIVER_LENGTH, _across_own_walls, _geodesic_distance, _without_slivers
from core.visibility import DIRECTIONS


def geodesic_distance_by_dijkstra(mask: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """The slow, obviously right reference: Dijkstra over the graph of the mask's voxels, each
    joined to its 26 neighbours in the mask by the length of the step."""
    index = -np.ones(mask.shape, dtype=np.int64)
    cells = np.argwhere(mask)
    index[tuple(cells.T)] = np.arange(len(cells))
    rows, cols, lengths = [], [], []
    for step in DIRECTIONS:
        to = cells + step
        inside = np.all((to >= 0) & (to < mask.shape), axis=1)
        target = np.full(len(cells), -1)
        target[inside] = index[tuple(to[inside].T)]
        joined = target >= 0
        rows += [np.flatnonzero(joined)]
        cols += [target[joined]]
        lengths += [np.full(joined.sum(), np.linalg.norm(step))]
    graph = coo_matrix((np.concatenate(lengths), (np.concatenate(rows), np.concatenate(cols))), shape=(len(cells),) * 2)
    starts = index[seeds & mask]
    distance = np.full(mask.shape, np.inf)
    distance[tuple(cells.T)] = dijkstra(graph.tocsr(), indices=starts, min_only=True)
    return distance


@pytest.mark.parametrize(("seed", "density"), [(0, 0.6), (1, 0.75), (2, 0.9)])
def test_geodesic_distance_is_dijkstras_over_the_26_neighbours_on_random_grids(seed, density):
    rng = np.random.default_rng(seed)
    mask = rng.random((9, 8, 10)) < density
    mask[0] = False  # a box around the mask smaller than the grid
    seeds = rng.random(mask.shape) < 0.01
    expected = geodesic_distance_by_dijkstra(mask, seeds)
    assert np.isfinite(expected).sum() > 50  # seeds reach much of the mask
    np.testing.assert_allclose(_geodesic_distance(mask, seeds), expected, rtol=1e-9)


def test_geodesic_distance_without_a_seed_in_the_mask_is_infinite():
    mask = np.zeros((5, 5, 5), dtype=bool)
    mask[1:4, 1:4, 1:4] = True
    seeds = ~mask
    assert np.isinf(_geodesic_distance(mask, seeds)).all()


def grooved_region() -> tuple[np.ndarray, list[tuple[np.ndarray, ...]]]:
    """A region taken back as inside (bool grid), and the two sides of its walls' points: the
    inside (x 2-19), whose outer face (x 1) has outside space behind it, and a groove (x 24-29)
    across a wall (x 20-23) from it, joined to it round the wall's end (y 30-37)."""
    taken = np.zeros((40, 40, 12), dtype=bool)
    taken[2:20, 2:38, 2:10] = True  # the inside
    taken[24:30, 2:38, 2:10] = True  # the groove
    taken[20:24, 30:38, 2:10] = True  # round the wall's end
    y, z = (axis.ravel() for axis in np.meshgrid(np.arange(2, 38), np.arange(2, 10), indexing="ij"))
    outer = (np.full(len(y), 4), y, z), (np.full(len(y), 0), y, z)
    in_wall = y < 29
    wall = (np.full(in_wall.sum(), 18), y[in_wall], z[in_wall]), (np.full(in_wall.sum(), 25), y[in_wall], z[in_wall])
    sides = [
        tuple(np.concatenate([a, b]) for a, b in zip(outer[0], wall[0])),
        tuple(np.concatenate([a, b]) for a, b in zip(outer[1], wall[1])),
    ]
    return taken, sides


def test_a_groove_across_the_insides_own_wall_is_split_off_and_the_inside_kept():
    taken, sides = grooved_region()
    split = _across_own_walls(taken, ~taken, sides)
    assert split[24:30, 2:29, 2:10].all()  # the groove, up to the wall's end
    assert not split[2:16].any()  # the inside (by the way round, voxels go to the nearer growth)
    assert not (split & ~taken).any()


def test_a_region_without_walls_on_both_sides_loses_nothing():
    taken, sides = grooved_region()
    outer_only = [tuple(axis[: 36 * 8] for axis in side) for side in sides]  # the outer face's points
    assert not _across_own_walls(taken, ~taken, outer_only).any()
    swapped = sides[::-1]  # the same walls seen from their other sides
    np.testing.assert_array_equal(_across_own_walls(taken, ~taken, swapped), _across_own_walls(taken, ~taken, sides))


def test_a_line_of_inside_voxels_beside_the_inside_is_a_bores_stretch_and_left_unknown():
    """A bore closed at both ends by the shell leaves a line of inside voxels one across; a pocket of
    a few voxels, a sheet one voxel thick (a thin wall's inside) and the largest pocket, however
    thin, stay inside."""
    sign = np.ones((40, 40, 40), dtype=np.int8)
    sign[2:38, 2:38, 2:38] = 0  # the shell and what it encloses
    sign[5:20, 5:20, 5:20] = -1  # the part's own inside
    sign[25, 5 : 5 + SLIVER_LENGTH + 2, 25] = -1  # a bore's stretch
    sign[30:32, 5:7, 30] = -1  # four voxels
    sign[25:35, 25:35, 35] = -1  # a sheet
    result = _without_slivers(sign)
    changed = np.argwhere(result != sign)
    assert (result[25, 5 : 5 + SLIVER_LENGTH + 2, 25] == 0).all()
    assert len(changed) == SLIVER_LENGTH + 2
    thin = np.zeros_like(sign)
    thin[3, 3 : 3 + 2 * SLIVER_LENGTH, 3] = -1  # the largest pocket is the part's inside, a rod's
    thin[30, 3 : 3 + SLIVER_LENGTH, 30] = -1
    result = _without_slivers(thin)
    assert (result[3, 3 : 3 + 2 * SLIVER_LENGTH, 3] == -1).all() and (result[30] == 0).all()
