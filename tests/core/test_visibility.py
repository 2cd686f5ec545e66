"""core.visibility: the directions in which a voxel sees the grid's boundary."""

from __future__ import annotations

import numpy as np
import pytest

from core.visibility import DIRECTIONS, escape_bits, escape_counts, tunnels


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


def tunnels_by_marching(blocked: np.ndarray) -> np.ndarray:
    """Out both ways along a line, and blocked every way square to it."""
    inside = np.zeros(blocked.shape, dtype=bool)
    for voxel in np.ndindex(blocked.shape):
        for line in DIRECTIONS:
            opposite = tuple(-np.array(line))
            square = [d for d in DIRECTIONS if np.dot(d, line) == 0]
            inside[voxel] |= (
                escapes_by_marching(blocked, voxel, line)
                and escapes_by_marching(blocked, voxel, opposite)
                and not any(escapes_by_marching(blocked, voxel, d) for d in square)
            )
    return inside


def test_there_are_26_directions_each_with_its_opposite_at_the_mirrored_index():
    assert len(DIRECTIONS) == 26 and len(set(DIRECTIONS)) == 26
    assert all(DIRECTIONS[25 - i] == tuple(-np.array(d)) for i, d in enumerate(DIRECTIONS))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_escape_counts_are_those_of_marching_every_ray_on_random_grids(seed):
    rng = np.random.default_rng(seed)
    blocked = rng.random((7, 9, 8)) < rng.uniform(0.05, 0.4)
    np.testing.assert_array_equal(escape_counts(escape_bits(blocked)), escape_counts_by_marching(blocked))


@pytest.mark.parametrize("seed", [0, 1])
def test_escape_bits_are_the_rays_of_marching_one_bit_per_direction(seed):
    blocked = np.random.default_rng(seed).random((6, 7, 5)) < 0.3
    bits = escape_bits(blocked)
    for i, direction in enumerate(DIRECTIONS):
        expected = [escapes_by_marching(blocked, voxel, direction) for voxel in np.ndindex(blocked.shape)]
        np.testing.assert_array_equal((bits >> i & 1).astype(bool).ravel(), expected)


@pytest.mark.parametrize(("seed", "density"), [(0, 0.5), (1, 0.6), (2, 0.7)])
def test_tunnels_are_those_of_marching_every_line_on_random_grids(seed, density):
    blocked = np.random.default_rng(seed).random((10, 9, 11)) < density
    expected = tunnels_by_marching(blocked)
    assert 0 < expected.sum() < (~blocked).sum()  # both answers occur among the free voxels
    np.testing.assert_array_equal(tunnels(escape_bits(blocked)), expected)


def test_a_bore_is_a_tunnel_and_neither_a_cup_nor_the_rim_of_an_open_box_is():
    blocked = np.zeros((12, 12, 14), dtype=bool)
    blocked[2:10, 2:10, 2:12] = True
    blocked[4:8, 4:8, :] = False  # a square bore along z, through the block
    assert tunnels(escape_bits(blocked))[4:8, 4:8, 2:12].all()
    blocked[4:8, 4:8, 2] = True  # close its bottom: a cup, open at the top only
    assert not tunnels(escape_bits(blocked))[4:8, 4:8, 3:12].any()
    box = np.zeros((12, 12, 12), dtype=bool)
    box[2:10, 2:10, 2:9] = True
    box[3:9, 3:9, 3:9] = False  # a box without its lid; its rim at z = 8
    free = ~box
    rim_layer = escape_bits(box)[3:9, 3:9, 9]  # level with nothing: sees out sideways both ways, and up
    assert free[3:9, 3:9, 3:12].all() and not tunnels(escape_bits(box))[3:9, 3:9, 3:12].any()
    assert (escape_counts(rim_layer) > 9).all()


def test_an_empty_grid_sees_out_every_way_and_a_closed_box_hides_its_inside():
    assert (escape_counts(escape_bits(np.zeros((5, 6, 7), dtype=bool))) == 26).all()
    blocked = np.zeros((12, 12, 12), dtype=bool)
    blocked[2:10, 2:10, 2:10] = True
    blocked[3:9, 3:9, 3:9] = False  # a hollow box, walls one voxel thick
    counts = escape_counts(escape_bits(blocked))
    assert (counts[3:9, 3:9, 3:9] == 0).all()
    assert (counts[1, 1, 1] == 26 - 1) and (counts[0] > 0).all()  # only the diagonal into the box is blocked
    blocked[2:10, 2:10, 9] = False  # take the lid off: the inside sees out through the top only
    counts = escape_counts(escape_bits(blocked))
    inside = counts[3:9, 3:9, 3:9]
    assert (inside >= 1).all() and (inside <= 9).all()  # never more than the 9 upward directions
    assert counts[5, 5, 8] == 9 and counts[5, 5, 3] == 1  # under the opening all 9, at the bottom straight up only
