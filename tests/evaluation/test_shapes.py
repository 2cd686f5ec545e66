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


def test_a_mesh_file_becomes_a_shape_folder_that_scores_its_own_surface_as_perfect(tmp_path):
    """``--mesh`` brings any model into the unit frame and writes the layout ``bench/run.py
    --data`` reads; the true surface and normals, scored against that folder, score zero error."""
    import trimesh

    from evaluation.sample_data import evaluate_shape, load_points_and_labels
    from evaluation.shapes import main

    box = trimesh.creation.box(extents=(4.0, 2.0, 1.0))
    box.apply_translation((10.0, -3.0, 2.0))
    box.invert()  # inward-facing, as a careless exporter might write it
    box.export(tmp_path / "part.stl")
    main(["--mesh", str(tmp_path / "part.stl"), "--points", "3000", "--folder", str(tmp_path / "part")])

    points, labels = load_points_and_labels(tmp_path / "part")
    gt = trimesh.load(tmp_path / "part" / "gt.ply", force="mesh")
    np.testing.assert_allclose(gt.extents, (1.0, 0.5, 0.25), atol=1e-9)
    assert gt.volume > 0 and points.shape == (3000, 3)
    np.testing.assert_allclose(np.abs(points).max(axis=0), (0.5, 0.25, 0.125), atol=0.03)
    scores = evaluate_shape(gt, labels["normals"], np.flatnonzero(labels["is_edge"]), tmp_path / "part")
    assert scores["chamfer_exact"] < 1e-6 and scores["normal_mean_oriented"] < 1e-3
    assert scores["edge_iou"] == 1.0 and 0.05 < labels["is_edge"].mean() < 0.2
    assert len(np.load(tmp_path / "part" / "edges_gt.npy")) > 0
