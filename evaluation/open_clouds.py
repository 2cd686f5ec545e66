"""Open variants of the sample shapes: a cloud that does not enclose its volume everywhere.

A scan of a part standing on a table misses its base; a sampled part can miss a face; a scanner
cannot see into a pocket's corner. Such a cloud is made here from a shape folder of
``../shared/data`` by deleting every point whose clean position lies beyond a plane (a ``Cut``)
or within a ball (a ``Hole``), so the result is scored against the same ground truth: the mesh
must follow the points and close the gap, and the part of the true surface that has no points
left counts against it (a fair price: the gap's true surface is the one a user wants).

    >>> variant_dir = write_open_variant(Path("../shared/data/cube"), Path("/tmp/open"))
    >>> evaluate_shape(mesh, normals, edges, variant_dir, points_file=OPEN_POINTS)
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from evaluation.sample_data import labels_file, load_points_and_labels
from evaluation.shapes import write_ply

OPEN_POINTS = "points_open.ply"


class Cut(NamedTuple):
    """Delete the points with ``side * clean[:, axis] > offset`` (side +1 or -1)."""

    axis: int
    side: int
    offset: float


class Hole(NamedTuple):
    """Delete the points within ``radius`` of ``centre``: a hole in a scan."""

    centre: tuple[float, float, float]
    radius: float


# One cut per shape, each removing a face or the end of a part: the top of the cube (20 % of its
# points), a cap of the sphere, the end of the bracket's long leg, the base of the box with a
# through-hole (the hole then joins the inside to the opening, the hardest case here), and the
# bases of the real part idler_riser (30 % of its points; its three holes join the inside to the
# opening) and of the thin flange (43 %: a plate scanned lying on a table, its holes open below),
# a corner of the wedge's base, along its length (the slot along its base then joins the inside
# past the opening), and a hole in the wall and floor of octagon_pocket's pocket (1 %, but the
# pocket then joins the inside).
CUTS: dict[str, Cut | Hole] = {
    "cube": Cut(axis=2, side=1, offset=0.45),
    "sphere": Cut(axis=2, side=1, offset=0.35),
    "l_bracket": Cut(axis=0, side=1, offset=0.45),
    "box_hole": Cut(axis=2, side=-1, offset=0.2),
    "idler_riser": Cut(axis=2, side=-1, offset=0.08),
    "flange": Cut(axis=2, side=-1, offset=0.02),
    "wedge": Cut(axis=0, side=-1, offset=0.203),
    "octagon_pocket": Hole(centre=(0.3, 0.0, 0.0), radius=0.15),
}


def kept_rows(clean_points: np.ndarray, cut: Cut | Hole) -> np.ndarray:
    """Indices (K,) of the rows of ``clean_points`` (N, 3) that ``cut`` keeps, in order."""
    if isinstance(cut, Hole):
        return np.flatnonzero(np.linalg.norm(clean_points - cut.centre, axis=1) > cut.radius)
    return np.flatnonzero(cut.side * clean_points[:, cut.axis] <= cut.offset)


def write_open_variant(shape_dir: Path, out_root: Path, cut: Cut | Hole | None = None) -> Path:
    """Write the open variant of ``shape_dir`` (its ``CUTS`` entry unless ``cut`` is given) as a
    shape folder ``out_root/<shape>``: ``points_open.ply``, its labels (every per-point array
    subset to the kept points) and the shape's own ``gt.ply`` and ``edges_gt.npy``. Returns that
    folder.
    """
    cut = cut or CUTS[shape_dir.name]
    points, labels = load_points_and_labels(shape_dir, "points.ply")
    keep = kept_rows(labels["points_clean"], cut)
    out = out_root / shape_dir.name
    out.mkdir(parents=True, exist_ok=True)
    write_ply(out / OPEN_POINTS, points[keep])
    per_point: dict[str, Any] = {key: _subset(value, keep, len(points)) for key, value in labels.items()}
    np.savez(out / labels_file(OPEN_POINTS), **per_point)
    for name in ("gt.ply", "edges_gt.npy"):
        shutil.copyfile(shape_dir / name, out / name)
    return out


def _subset(value: np.ndarray, keep: np.ndarray, count: int) -> np.ndarray:
    """``value[keep]`` for a per-point array (first axis ``count``); any other array as it is."""
    return value[keep] if value.ndim and len(value) == count else value
