"""The sample shapes of ``../shared/data``: reading a shape folder, and scoring a result against it.

A shape folder holds the input clouds (``points*.ply``), their labels (``labels*.npz``: normals,
``is_edge``...), the ground-truth mesh (``gt.ply``) and samples along its sharp edges
(``edges_gt.npy``); that folder's README defines the scores, which ``evaluation.metrics``
computes from plain arrays.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from core.ply import read_points
from evaluation.metrics import SURFACE_SAMPLES, edge_chamfer, edge_mask, edge_scores, normal_errors, surface_distances


def labels_file(points_file: str) -> str:
    """The labels file that goes with an input file of a shape folder.

    ``points.ply`` and ``points_ascii.ply`` go with ``labels.npz``, ``points_4096.ply`` with
    ``labels_4096.npz``, ``points_noise010.ply`` with ``labels_noise010.npz``.
    """
    variant = Path(points_file).stem.removeprefix("points").removesuffix("_ascii")
    return f"labels{variant}.npz"


def load_points_and_labels(
    shape_dir: str | os.PathLike[str], points_file: str = "points.ply"
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The input points of a shape folder (float64, file order) and their labels (every array of
    the matching ``labels*.npz``: ``normals``, ``is_edge``, ``points_clean``, ...).

    Raises ValueError when the labels do not describe these points.
    """
    shape_dir = Path(shape_dir)
    points = read_points(shape_dir / points_file)
    with np.load(shape_dir / labels_file(points_file)) as archive:
        labels = {key: archive[key] for key in archive.files}
    if labels["points"].shape != points.shape or not np.allclose(labels["points"], points, atol=1e-6):
        raise ValueError(f"{labels_file(points_file)} does not hold the points of {points_file}")
    return points, labels


def evaluate_shape(
    mesh: Any,
    normals: np.ndarray,
    edges: np.ndarray,
    shape_dir: str | os.PathLike[str],
    points_file: str = "points.ply",
    count: int = SURFACE_SAMPLES,
    seed: int = 0,
) -> dict[str, float]:
    """Every score of one result on one shape folder of the sample data, in one flat dict.

    ``mesh`` is the reconstruction (``trimesh.Trimesh`` or anything with ``vertices`` and
    ``faces``), ``normals`` one normal per input point in file order, ``edges`` the indices of
    the input points reported as edges (or a boolean mask); their positions are the input
    points'. ``points_file`` names the input the result was computed from. The keys are those of
    ``surface_distances``, ``normal_errors`` and ``edge_scores``, plus ``ecd``.
    """
    import trimesh

    shape_dir = Path(shape_dir)
    points, labels = load_points_and_labels(shape_dir, points_file)
    gt_mesh = trimesh.load(shape_dir / "gt.ply", force="mesh", process=False)
    gt_edge_points = np.load(shape_dir / "edges_gt.npy")
    reported = edge_mask(edges, len(points))
    scores = surface_distances(mesh, gt_mesh, count=count, seed=seed)
    scores.update(normal_errors(normals, labels["normals"]))
    scores.update(edge_scores(reported, labels["is_edge"]))
    scores["ecd"] = edge_chamfer(points[reported], gt_edge_points)
    return scores
