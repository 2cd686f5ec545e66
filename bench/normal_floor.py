"""The lowest normal error any method can score that gives each input point the normal of a face
chosen from its position: the ground truth's own faces, chosen by nearness.

Each noisy input point of a shape folder takes the normal of the triangle of ``gt.ply`` nearest to
it (exact point-to-triangle distance; a tie, beyond a convex edge, goes to the face whose plane is
farther, the likelier one). Where that triangle lies on the point's own surface (its
normal within ``SAME_SURFACE`` degrees of the point's ``normals_face`` label: a neighbouring facet of
the same cylinder, say), the point counts as assigned correctly and takes its label normal. Every
error left is a point that the noise carried nearer to another face than to its own, where no
method reading positions can tell which face it came from. The scores are those of
``evaluation.metrics.normal_errors``, so the table sits beside bench/run.py's normal columns.

    .venv/bin/python bench/normal_floor.py                  # every shape of ../shared/data
    .venv/bin/python bench/normal_floor.py --shapes l_bracket,wedge
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from core.features import unit  # noqa: E402
from evaluation.metrics import TriangleTree, normal_errors, point_triangle_distance  # noqa: E402
from evaluation.sample_data import load_points_and_labels  # noqa: E402

SAME_SURFACE = 10.0  # degrees: facets of one tessellated smooth surface; sharp edges are 35 or more


def floor_normals(shape_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """The floor's normals for the points of ``shape_dir``, and the labelled normals (both (n, 3))."""
    points, labels = load_points_and_labels(shape_dir)
    gt = trimesh.load(shape_dir / "gt.ply", force="mesh", process=False)
    distance, corners = TriangleTree(gt.vertices, gt.faces).nearest(points)
    nearest = unit(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]))
    own = np.einsum("ij,ij->i", nearest, labels["normals_face"]) > np.cos(np.radians(SAME_SURFACE))
    # A point beyond a convex edge is equally near both faces (its nearest point is on the edge).
    # Then the face whose plane is farther is the likelier origin: the noise must have carried the
    # point past the other face's edge along that face, and a Gaussian's tail beyond a distance
    # falls off faster than its density there (Mills' ratio), so it goes to its own face exactly
    # when its own plane is the farther one.
    mine = gt.triangles[labels["face_index"]]
    tied = ~own & (point_triangle_distance(points, *(mine[:, i] for i in range(3))) <= distance + 1e-9)
    own_plane = np.abs(np.einsum("ij,ij->i", labels["normals_face"], points - mine[:, 0]))
    other_plane = np.abs(np.einsum("ij,ij->i", nearest, points - corners[:, 0]))
    own |= tied & (own_plane >= other_plane)
    return np.where(own[:, None], labels["normals"], nearest), labels["normals"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    parser.add_argument("--shapes", help="comma-separated folder names (default: every shape)")
    args = parser.parse_args()
    if not args.data.is_dir():
        sys.exit(f"normal_floor: {args.data} is missing (the sample shapes of ../shared/data)")
    names = args.shapes.split(",") if args.shapes else sorted(p.parent.name for p in args.data.glob("*/gt.ply"))
    print("| shape | floor: normals mean | median | pointing inward | points nearer another face |")
    print("|---|---|---|---|---|")
    for name in names:
        normals, truth = floor_normals(args.data / name)
        scores = normal_errors(normals, truth)
        moved = float(np.mean(np.einsum("ij,ij->i", normals, truth) < np.cos(np.radians(SAME_SURFACE))))
        print(
            f"| {name} | {scores['normal_mean_oriented']:.2f}° | {scores['normal_median_oriented']:.2f}° "
            f"| {100 * scores['normal_inward_share']:.2f} % | {100 * moved:.1f} % |",
            flush=True,
        )


if __name__ == "__main__":
    main()
