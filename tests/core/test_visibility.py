"""core.visibility: the directions in which a voxel sees the grid's boundary."""

from __future__ import annotations

import numpy as np
import pytest

from core.visibility import DIRECTIONS, escape_counts


def escape_counts_by_marching(blocked: np.ndarray) -> np.ndarray:
    """The slow, obviously right reference: march every ray voxel by voxel."""
    counts = np.zeros(blocked.shape, dtype=np.uint8)
    for voxel in np.ndindex(blocked.shape):
        for direction in DIRECTIONS:
            at = np.array(voxel) + direction
            while np.all(at >= 0) and np.all(at < blocked.shape) and not blocked[tuple(at)]:
                at += direction
            counts[voxel] += not (np.all(at >= 0) and np.all(at < blocked.shape))
    return counts


def test_there_are_26_directions_each_with_its_opposite():
    assert len(DIRECTIONS) == 26 and len(set(DIRECTIONS)) == 26
    assert all(tuple(-np.array(d)) in DIRECTIONS for d in DIRECTIONS)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_escape_counts_are_those_of_marching_every_ray_on_random_grids(seed):
    rng = np.random.default_rng(seed)
    blocked = rng.random((7, 9, 8)) < rng.uniform(0.05, 0.4)
    np.testing.assert_array_equal(escape_counts(blocked), escape_counts_by_marching(blocked))


def test_an_empty_grid_sees_out_every_way_and_a_closed_box_hides_its_inside():
    assert (escape_counts(np.zeros((5, 6, 7), dtype=bool)) == 26).all()
    blocked = np.zeros((12, 12, 12), dtype=bool)
    blocked[2:10, 2:10, 2:10] = True
    blocked[3:9, 3:9, 3:9] = False  # a hollow box, walls one voxel thick
    counts = escape_counts(blocked)
    assert (counts[3:9, 3:9, 3:9] == 0).all()
    assert (counts[1, 1, 1] == 26 - 1) and (counts[0] > 0).all()  # only the diagonal into the box is blocked
    blocked[2:10, 2:10, 9] = False  # take the lid off: the inside sees out through the top only
    counts = escape_counts(blocked)
    inside = counts[3:9, 3:9, 3:9]
    assert (inside >= 1).all() and (inside <= 9).all()  # never more than the 9 upward directions
    assert counts[5, 5, 8] == 9 and counts[5, 5, 3] == 1  # under the opening all 9, at the bottom straight up only
