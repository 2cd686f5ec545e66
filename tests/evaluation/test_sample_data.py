"""evaluation.sample_data and the metrics on the sample shapes in ../shared/data (skipped without them)."""

import json
import shutil

import numpy as np
import pytest
import trimesh

from evaluation.metrics import edge_chamfer, edge_scores, normal_errors, surface_distances
from evaluation.sample_data import evaluate_shape, labels_file, load_points_and_labels

SHAPES = ["cube", "box_hole", "l_bracket", "sphere"]


@pytest.fixture
def data_dir(shared_data):
    """The sample shapes, which live next to the repository, not in it."""
    return shared_data


# --- shape folders ------------------------------------------------------------------------


def test_labels_files_of_the_variants():
    assert labels_file("points.ply") == "labels.npz"
    assert labels_file("points_ascii.ply") == "labels.npz"
    assert labels_file("points_4096.ply") == "labels_4096.npz"
    assert labels_file("points_noise010.ply") == "labels_noise010.npz"


@pytest.mark.parametrize("points_file, count", [("points_4096.ply", 4096), ("points_noise010.ply", 16384)])
def test_load_points_and_labels_of_the_variants(data_dir, points_file, count):
    points, labels = load_points_and_labels(data_dir / "box_hole", points_file)
    assert points.shape == (count, 3) and labels["is_edge"].shape == (count,)
    assert np.allclose(points, labels["points"], atol=1e-6)


def test_load_points_and_labels_refuses_labels_of_other_points(data_dir, tmp_path):
    shutil.copy(data_dir / "box_hole" / "points_noise010.ply", tmp_path / "points.ply")
    shutil.copy(data_dir / "box_hole" / "labels.npz", tmp_path / "labels.npz")
    with pytest.raises(ValueError):
        load_points_and_labels(tmp_path)


@pytest.mark.parametrize("shape", SHAPES)
def test_ground_truth_against_itself(data_dir, shape):
    gt = trimesh.load(data_dir / shape / "gt.ply", process=False)
    exact = surface_distances(gt, gt, count=10_000)
    assert exact["chamfer_exact"] < 1e-12 and exact["hausdorff_exact"] < 1e-12
    # The README: identical surfaces score a sampled d_C of about 0.002 to 0.004.
    sampled = surface_distances(gt, gt, exact=False)
    assert 0.001 < sampled["chamfer"] < 0.005


@pytest.mark.parametrize("shape", SHAPES)
def test_labels_against_themselves(data_dir, shape):
    points, labels = load_points_and_labels(data_dir / shape)
    assert all(value == 0 for value in normal_errors(labels["normals"], labels["normals"]).values())
    edges = edge_scores(np.flatnonzero(labels["is_edge"]), labels["is_edge"])
    gt_edges = np.load(data_dir / shape / "edges_gt.npy")
    if labels["is_edge"].any():
        assert (edges["edge_precision"], edges["edge_recall"], edges["edge_iou"]) == (1.0, 1.0, 1.0)
        # The README: a perfect classifier scores an ECD of about 0.008 to 0.010.
        assert 0.007 < edge_chamfer(points[labels["is_edge"]], gt_edges) < 0.011
    else:
        assert edges["edge_false_share"] == 0.0 and len(gt_edges) == 0


@pytest.mark.parametrize("shape", SHAPES)
def test_face_normals_differ_from_smooth_normals_as_the_metadata_says(data_dir, shape):
    _, labels = load_points_and_labels(data_dir / shape)
    meta = json.loads((data_dir / shape / "meta.json").read_text())
    errors = normal_errors(labels["normals_face"], labels["normals"])
    assert errors["normal_mean_unoriented"] == pytest.approx(meta["mean_face_vs_smooth_normal_deg"], abs=1e-3)


def test_evaluate_shape(data_dir):
    shape_dir = data_dir / "box_hole"
    _, labels = load_points_and_labels(shape_dir, "points_4096.ply")
    gt = trimesh.load(shape_dir / "gt.ply", process=False)
    edges = np.flatnonzero(labels["is_edge"])
    perfect = evaluate_shape(gt, labels["normals"], edges, shape_dir, "points_4096.ply", count=10_000)
    assert perfect["chamfer_exact"] < 1e-12 and perfect["normal_mean_oriented"] == 0
    assert perfect["edge_iou"] == 1.0 and 0.005 < perfect["ecd"] < 0.03
    assert perfect["edge_reported"] == labels["is_edge"].sum()

    shrunk = gt.copy()
    shrunk.vertices *= 0.9
    poor = evaluate_shape(shrunk, -labels["normals"], [], shape_dir, "points_4096.ply", count=10_000)
    assert 0.01 < poor["chamfer_exact"] < 0.05
    assert poor["normal_inward_share"] == 1.0 and poor["edge_precision"] == 0.0 and poor["ecd"] == np.inf
