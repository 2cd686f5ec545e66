"""evaluation.open_clouds: open variants of the sample shapes, scored against the whole true surface."""

import numpy as np

from evaluation.open_clouds import CUTS, OPEN_POINTS, Cut, Hole, kept_rows, write_open_variant
from evaluation.sample_data import load_points_and_labels


def test_kept_rows_are_the_points_on_the_kept_side_in_order():
    clean = np.array([[0.0, 0.0, 0.5], [0.0, 0.0, -0.5], [0.0, 0.0, 0.45], [0.0, 0.0, 0.46]])
    assert kept_rows(clean, Cut(axis=2, side=1, offset=0.45)).tolist() == [1, 2]
    assert kept_rows(clean, Cut(axis=2, side=-1, offset=-0.46)).tolist() == [0, 3]


def test_kept_rows_of_a_hole_are_the_points_outside_its_ball_in_order():
    clean = np.array([[0.0, 0.0, 0.5], [0.1, 0.0, 0.5], [0.3, 0.0, 0.5], [0.0, 0.0, 0.0]])
    assert kept_rows(clean, Hole(centre=(0.0, 0.0, 0.5), radius=0.2)).tolist() == [2, 3]


def test_open_cube_loses_its_top_face_and_keeps_labels_aligned(shared_data, tmp_path):
    points, labels = load_points_and_labels(shared_data / "cube")
    variant = write_open_variant(shared_data / "cube", tmp_path)
    open_points, open_labels = load_points_and_labels(variant, OPEN_POINTS)
    keep = kept_rows(labels["points_clean"], CUTS["cube"])
    # The cube's top face is a sixth of its area: about that share of the points is gone.
    assert 0.13 < 1 - len(open_points) / len(points) < 0.22
    assert np.allclose(open_points, points[keep], atol=1e-6)
    assert np.array_equal(open_labels["is_edge"], labels["is_edge"][keep])
    assert open_labels["points_clean"][:, 2].max() <= 0.45
    assert (variant / "gt.ply").read_bytes() == (shared_data / "cube" / "gt.ply").read_bytes()
