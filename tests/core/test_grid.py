"""core.grid: the sampled grid both extractions read."""

from __future__ import annotations

import numpy as np
from skimage.measure import marching_cubes

from core.grid import Grid


def _box_on_nodes() -> Grid:
    """The L∞ distance to a cube of half-size 0.25 on a grid of cell 0.05: the cube's faces pass
    through nodes, where f is exactly 0."""
    axis = np.arange(-8, 9) * 0.05
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    values = (np.maximum(np.maximum(np.abs(x), np.abs(y)), np.abs(z)) - 0.25).astype(np.float32)
    values[np.abs(values) < 1e-6] = 0.0
    return Grid(values=values, origin=np.full(3, -0.4), cell=0.05)


def _zero_area_faces(values: np.ndarray) -> int:
    vertices, faces, _, _ = marching_cubes(values, 0.0)
    corners = vertices[faces]
    area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1) / 2
    return int((area < 1e-9).sum())


def test_values_off_zero_keep_marching_cubes_from_faces_of_no_area():
    """Exact zeros at nodes give marching cubes triangles with two vertices on one node (the public
    gear assembly's fallback mesh: 13 such faces, 11 faces touching others); off zero, none."""
    grid = _box_on_nodes()
    assert (grid.values == 0).sum() > 100
    assert _zero_area_faces(grid.values) > 0
    assert _zero_area_faces(grid.values_off_zero()) == 0


def test_values_off_zero_move_only_the_values_near_zero_and_keep_their_side():
    rng = np.random.default_rng(0)
    values = rng.normal(0, 1e-3, (9, 9, 9)).astype(np.float32)
    values[0, 0, 0] = 0.0
    grid = Grid(values=values, origin=np.zeros(3), cell=0.5)  # 0.001 cells: 5e-4
    moved = grid.values_off_zero()
    near = np.abs(values) < 5e-4
    assert near.sum() > 100
    assert (np.abs(moved) >= np.float32(5e-4)).all()
    np.testing.assert_array_equal(moved[~near], values[~near])
    assert (np.sign(moved[near & (values != 0)]) == np.sign(values[near & (values != 0)])).all()
    assert moved[0, 0, 0] > 0  # an exact zero counts as outside
