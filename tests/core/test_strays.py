"""core.strays: points far from every surface are found, and no point of a sampled surface is."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from core import strays as module
from core.strays import strays
from evaluation.metrics import distance_to_mesh
from evaluation.shapes import sample_shape
from tests.helpers import flooded


def by_hand(points: np.ndarray) -> np.ndarray:
    """The same test from all pairwise distances, sorted, read again without the strays found, and
    the small groups flooded one by one: the obviously right, slow reference."""
    stray = np.zeros(len(points), dtype=bool)
    for _ in range(module.PASSES):
        kept = np.flatnonzero(~stray)
        pairwise = np.linalg.norm(points[kept, None] - points[None, kept], axis=2)
        reach = np.sort(pairwise, axis=1)[:, module.NEIGHBOURS]
        typical = np.median(reach)
        nearest = np.argsort(pairwise, axis=1, kind="stable")
        around = np.array([np.median(reach[row[row != i][: module.NEIGHBOURS]]) for i, row in enumerate(nearest)])
        found = (reach > module.STRAY_RATIO * np.maximum(around, typical)) | (reach > module.FAR_RATIO * typical)
        stray[kept[found]] = True
    kept = np.flatnonzero(~stray)
    stray[kept[small_groups_by_hand(points[kept])]] = True
    return stray


def small_groups_by_hand(points: np.ndarray) -> np.ndarray:
    """Each distinct position linked to its NEIGHBOURS nearest others, both ways; a group flooded
    from each position in turn, small where it holds less than GROUP_SHARE of the points."""
    unique, inverse = np.unique(points, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    pairwise = np.linalg.norm(unique[:, None] - unique[None], axis=2)
    np.fill_diagonal(pairwise, np.inf)
    linked = [set() for _ in unique]
    for i, row in enumerate(np.argsort(pairwise, axis=1)[:, : module.NEIGHBOURS]):
        for j in row:
            linked[i].add(int(j))
            linked[int(j)].add(i)
    group = np.array(flooded(linked))
    counts = {g: int((group[inverse] == g).sum()) for g in set(group.tolist())}
    return np.array([counts[g] < module.GROUP_SHARE * len(points) for g in group[inverse]])


def with_strays(count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A noisy cube of 16,384 points (the sample data's) with ``count`` points drawn uniformly in
    its box grown by a tenth on every side after them; the cloud, whether each point is a stray,
    and each stray's distance from the cube's surface."""
    shape = sample_shape("cube", n_points=16_384, seed=seed)
    low, high = shape.points.min(axis=0), shape.points.max(axis=0)
    scattered = np.random.default_rng(seed).uniform(low - 0.1, high + 0.1, size=(count, 3))
    cloud = np.concatenate([shape.points, scattered])
    truth = np.arange(len(cloud)) >= len(shape.points)
    return cloud, truth, distance_to_mesh(scattered, shape.mesh.vertices, shape.mesh.faces)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_strays_match_the_test_made_by_hand_on_random_clouds(seed):
    rng = np.random.default_rng(seed)
    # A sheet of points and a few far off it, and a cloud of uniform noise.
    sheet = np.c_[rng.uniform(0, 1, (200, 2)), rng.normal(0, 0.005, 200)]
    far = rng.uniform(-1, 2, (10, 3))
    for points in (np.concatenate([sheet, far]), rng.uniform(0, 1, (150, 3))):
        assert np.array_equal(strays(points), by_hand(points))


@pytest.mark.parametrize("seed", [0, 1])
def test_strays_in_clumps_match_the_test_made_by_hand(seed):
    """A sheet of 3,000 points, clumps of 9 to 14 points off it and a stack of repeated points on it:
    the clumps are small groups (under 0.5 % of 3,034 points), the stack is no group of its own."""
    rng = np.random.default_rng(seed)
    sheet = np.c_[rng.uniform(0, 1, (3_000, 2)), rng.normal(0, 0.005, 3_000)]
    clumps = [rng.uniform(0, 1, 3) + [0, 0, 0.2] + rng.normal(0, 0.004, (count, 3)) for count in (9, 11, 14)]
    stack = np.repeat(sheet[:1], 12, axis=0)
    points = np.concatenate([sheet, *clumps, stack])
    found = strays(points)
    assert np.array_equal(found, by_hand(points))
    assert found[3_000:3_034].all() and not found[:3_000].any() and not found[3_034:].any()


@pytest.mark.parametrize("seed", [0, 1])
def test_strays_farther_from_a_cube_than_a_few_spacings_are_found_and_none_of_its_surface(seed):
    cloud, truth, distance = with_strays(160, seed)
    found = strays(cloud)
    assert not found[~truth].any()
    # The cube's spacing: its points' median distance to their eighth nearest neighbour (0.031).
    # A stray STRAY_RATIO spacings off the surface has its neighbours that much farther than theirs.
    spacing = np.median(cKDTree(cloud[~truth]).query(cloud[~truth], k=module.NEIGHBOURS + 1)[0][:, -1])
    assert 0.02 < spacing < 0.04
    assert found[truth][distance > 3.5 * spacing].all(), distance[~found[truth]].max() / spacing


@pytest.mark.parametrize("size", [9, 20, 80])
def test_clumps_of_strays_off_a_cube_are_found_and_none_of_its_surface(size):
    """Five clumps of ``size`` points each (spread 0.005 to 0.01, tighter than the cube's spacing),
    0.05 to 0.15 outside its faces: each point's nearest points are in its clump, so the test of
    the eighth neighbour passes them, and only their being a group apart finds them."""
    shape = sample_shape("cube", n_points=16_384, seed=0)
    rng = np.random.default_rng(size)
    low, high = shape.points.min(axis=0), shape.points.max(axis=0)
    clumps = []
    for spread in (0.005, 0.0075, 0.01, 0.005, 0.01):
        centre = rng.uniform(low, high)
        axis = rng.integers(3)
        centre[axis] = high[axis] + rng.uniform(0.05, 0.15)
        clumps.append(centre + rng.normal(0, spread, (size, 3)))
    cloud = np.concatenate([shape.points, *clumps])
    found = strays(cloud)
    assert found[16_384:].all() and not found[:16_384].any()
    assert not module._strays_among(cloud, 1)[16_384:].any()  # the neighbour test alone finds none of them


def test_a_cloud_eight_times_as_dense_at_one_end_keeps_every_point():
    shape = sample_shape("cube", n_points=16_384, seed=0)
    x = shape.points[:, 0]
    kept = np.random.default_rng(0).random(len(x)) < 0.12 + 0.88 * (x - x.min()) / np.ptp(x)
    assert not strays(shape.points[kept]).any()


def test_repeated_points_are_no_strays_and_neither_are_their_neighbours():
    points = sample_shape("sphere", n_points=2000, seed=0).points
    assert not strays(np.repeat(points, 10, axis=0)).any()
    assert not strays(np.concatenate([np.repeat(points[:1], 20, axis=0), points])).any()


@pytest.mark.parametrize("count", [0, 1, module.NEIGHBOURS + 1])
def test_a_cloud_too_small_to_tell_has_no_strays(count):
    assert strays(np.random.default_rng(0).uniform(size=(count, 3))).tolist() == [False] * count
