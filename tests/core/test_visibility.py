"""core.visibility: the directions in which a voxel sees the grid's boundary."""

from __future__ import annotations

import numpy as np
import pytest

from core.visibility import DIRECTIONS, escape_counts, sees_through


def escapes_by_marching(blocked: np.ndarray, voxel: tuple[int, ...], direction: tuple[int, ...]) -> bool:
    """The slow, obviously right reference: march the ray voxel by voxel."""
    at = np.array(voxel) + direction
    while np.all(at >= 0) and np.all(at < blocked.shape) and not blocked[tuple(at)]:
        at += direction
    return not (np.all(at >= 0) and np.all(at < blocked.shape))


def escape_counts_by_marching(blocked: np.ndarray) -> np.ndarray:
    counts = np.zeros(blocked.shape, dtype=np.uint8)
    for voxel in np.ndindex(blocked.shape):
        counts[voxel] = sum(escapes_by_marching(blocked, voxel, direction) for direction in DIRECTIONS)
    return counts


def sees_through_by_marching(blocked: np.ndarray) -> np.ndarray:
    through = np.zeros(blocked.shape, dtype=bool)
    for voxel in np.ndindex(blocked.shape):
        through[voxel] = any(
            escapes_by_marching(blocked, voxel, d) and escapes_by_marching(blocked, voxel, tuple(-np.array(d)))
            for d in DIRECTIONS
        )
    return through


def test_there_are_26_directions_each_with_its_opposite():
    assert len(DIRECTIONS) == 26 and len(set(DIRECTIONS)) == 26
    assert all(tuple(-np.array(d)) in DIRECTIONS for d in DIRECTIONS)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_escape_counts_are_those_of_marching_every_ray_on_random_grids(seed):
    rng = np.random.default_rng(seed)
    blocked = rng.random((7, 9, 8)) < rng.uniform(0.05, 0.4)
    np.testing.assert_array_equal(escape_counts(blocked), escape_counts_by_marching(blocked))


@pytest.mark.parametrize(("seed", "density"), [(0, 0.3), (1, 0.4), (2, 0.5)])
def test_sees_through_is_marching_both_ways_along_a_line_on_random_grids(seed, density):
    blocked = np.random.default_rng(seed).random((10, 9, 11)) < density
    expected = sees_through_by_marching(blocked)
    assert 0 < expected.sum() < expected.size  # both answers occur
    np.testing.assert_array_equal(sees_through(blocked), expected)


def test_a_tube_is_seen_through_and_a_cup_is_not():
    blocked = np.zeros((12, 12, 14), dtype=bool)
    blocked[2:10, 2:10, 2:12] = True
    blocked[4:8, 4:8, :] = False  # a square bore along z, through the block
    assert sees_through(blocked)[4:8, 4:8, 2:12].all()
    blocked[4:8, 4:8, 2] = True  # close its bottom: a cup, open at the top only
    assert not sees_through(blocked)[4:8, 4:8, 3:12].any()


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
