"""evaluation.shapes: the synthetic shapes with their ground truth, and the example cloud they made."""

from __future__ import annotations

import numpy as np
import pytest

from core.ply import read_points
from evaluation.metrics import distance_to_mesh
from evaluation.shapes import sample_shape, write_ply
from tests.helpers import EXAMPLE_CLOUD as EXAMPLE


def test_example_cloud_is_what_the_readme_says():
    assert EXAMPLE.stat().st_size < 200_000
    assert EXAMPLE.read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\nelement vertex 6000\n")
    points = read_points(EXAMPLE)
    assert points.shape == (6000, 3)
    assert np.allclose(points.min(axis=0), -0.5, atol=0.03) and np.allclose(points.max(axis=0), 0.5, atol=0.03)


def test_example_cloud_is_reproducible(tmp_path):
    write_ply(tmp_path / "cube.ply", sample_shape("cube", n_points=6000, noise=0.005, seed=0).points)
    assert (tmp_path / "cube.ply").read_bytes() == EXAMPLE.read_bytes()


@pytest.mark.parametrize("name", ["cube", "box", "l_shape", "cylinder", "sphere", "bumps"])
def test_shapes_ground_truth_is_consistent(name):
    """The synthetic shapes: unit frame, labels as ../shared/data defines them."""
    shape = sample_shape(name, n_points=4000, seed=3)
    mesh = shape.mesh
    assert mesh.is_watertight and mesh.volume > 0
    np.testing.assert_allclose(mesh.bounds.sum(axis=0), 0.0, atol=1e-12)
    assert mesh.extents.max() == pytest.approx(1.0)
    assert shape.points.shape == shape.clean_points.shape == shape.normals.shape == (4000, 3)
    assert distance_to_mesh(shape.clean_points[:500], mesh.vertices, mesh.faces).max() < 1e-9
    noise = shape.points - shape.clean_points
    assert noise.std() == pytest.approx(0.005, rel=0.05) and abs(noise.mean()) < 5e-4
    np.testing.assert_allclose(np.linalg.norm(shape.normals, axis=1), 1.0, atol=1e-12)
    # Outward: the normal agrees with the (outward) face it was drawn from, to within the faceting
    # (on the narrowest bump of ``bumps`` neighbouring faces are up to 27° apart).
    face = mesh.face_normals[shape.face_index]
    faceting = 15 if name == "bumps" else 5
    assert ((shape.normals * face).sum(axis=1) > np.cos(np.radians(faceting))).all()
    assert np.array_equal(shape.is_edge, shape.edge_dist <= 0.01)
    if name in ("sphere", "bumps"):
        assert not shape.is_edge.any() and np.isinf(shape.edge_dist).all() and len(shape.edge_samples) == 0
    else:
        assert 0.02 < shape.is_edge.mean() < 0.12
        # every edge sample lies on the boundary between two faces: on the mesh, near no face interior
        assert distance_to_mesh(shape.edge_samples[::50], mesh.vertices, mesh.faces).max() < 1e-9
    again = sample_shape(name, n_points=4000, seed=3)
    assert np.array_equal(again.points, shape.points)
    assert not np.array_equal(sample_shape(name, n_points=4000, seed=4).points, shape.points)


def test_shapes_match_the_shared_cube(shared_data):
    shape = sample_shape("cube", n_points=16_384, seed=0)
    labels = np.load(shared_data / "cube" / "labels.npz")
    edges = np.load(shared_data / "cube" / "edges_gt.npy")
    assert shape.is_edge.mean() == pytest.approx(labels["is_edge"].mean(), abs=0.005)
    assert len(shape.edge_samples) == len(edges)
    ordered = lambda a: a[np.lexsort(np.round(a, 6).T)]  # noqa: E731
    np.testing.assert_allclose(ordered(shape.edge_samples), ordered(edges.astype(np.float64)), atol=1e-6)
