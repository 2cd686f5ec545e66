"""Scores of a reconstruction against ground truth, as defined in the sample data's README.

Three outputs are scored, each by its own functions:

- the mesh: ``surface_distances`` gives the Chamfer and Hausdorff distances to the ground-truth
  mesh, from points sampled on both surfaces, measured to the other sample (``chamfer``,
  ``hausdorff``) and to the other mesh's triangles exactly (``chamfer_exact``,
  ``hausdorff_exact``; identical surfaces score 0). ``distance_to_mesh`` (a ``TriangleTree``
  of bounding boxes) is the exact point-to-mesh distance behind the latter.
- the normals: ``normal_errors`` gives the angle errors per input point, oriented and unoriented.
- the edge points: ``edge_scores`` (precision, recall, IoU against the ``is_edge`` labels) and
  ``edge_chamfer`` (the Edge Chamfer Distance to the ground-truth edge samples).

Each takes arrays (or anything with ``vertices`` and ``faces``), wherever they come from;
``evaluation.sample_data`` reads a shape folder of the sample data and scores a result against it
with these. All distances are Euclidean, not squared, in the units of the inputs. Only numpy and
scipy are used (no torch).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from core.trees import kd_tree

# Number of points sampled on each surface for the Chamfer and Hausdorff distances.
SURFACE_SAMPLES = 100_000
# At most about this many (point, box or triangle) pairs are held at once by distance_to_mesh,
# which bounds its memory (a few hundred bytes a pair).
MAX_PAIRS = 500_000
# TriangleTree first cuts triangles with an edge longer than this fraction of the mesh's
# bounding-box diagonal into pieces, so that their boxes are tight; at most MAX_PIECES pieces.
SPLIT_FRACTION = 1 / 32
MAX_PIECES = 4_000_000


def sample_surface(vertices: np.ndarray, faces: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """``count`` points drawn uniformly by area on a triangle mesh, as an (count, 3) float64 array.

    The same ``seed`` gives the same points (see ``sample_triangles``).
    """
    points, _, _ = sample_triangles(_corners(vertices, faces), count, np.random.default_rng(seed))
    return points


def sample_triangles(
    corners: np.ndarray, count: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``count`` points drawn uniformly by area on triangles given as (n, 3, 3) corners.

    A triangle is chosen with probability proportional to its area and the point is uniform
    inside it. Returns the points (count, 3), the index of each one's triangle, and its
    barycentric weights (count, 3) on the triangle's corners; nothing when the triangles have no area.
    """
    areas = triangle_areas(corners)
    if count <= 0 or areas.sum() <= 0.0:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros((0, 3))
    cumulative = np.cumsum(areas)
    chosen = np.searchsorted(cumulative, rng.random(count) * cumulative[-1], side="right")
    chosen = np.minimum(chosen, len(areas) - 1)
    # Uniform in the unit parallelogram, folded back into the triangle.
    u, v = rng.random((2, count))
    outside = u + v > 1.0
    u[outside], v[outside] = 1.0 - u[outside], 1.0 - v[outside]
    a, b, c = corners[chosen, 0], corners[chosen, 1], corners[chosen, 2]
    points = a + u[:, None] * (b - a) + v[:, None] * (c - a)
    return points, chosen, np.stack([1.0 - u - v, u, v], axis=1)


def triangle_areas(corners: np.ndarray) -> np.ndarray:
    """Areas of triangles given as an (n, 3, 3) array of corners."""
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return 0.5 * np.linalg.norm(cross, axis=1)


def point_triangle_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Exact distance from each point to the triangle (a, b, c) of the same row.

    All four arguments are (n, 3) arrays. The closest point is found by the Voronoi region of the
    triangle the point falls in (Ericson, "Real-Time Collision Detection", 5.1.5), vectorised:
    every region's answer is computed and the first region that holds the point is kept, in the
    order of Ericson's early returns. Degenerate triangles (repeated or collinear corners) are
    handled: their distance is the smallest distance to their three edges.
    """
    points, a, b, c = (np.asarray(x, dtype=np.float64) for x in (points, a, b, c))
    ab, ac = b - a, c - a
    ap, bp, cp = points - a, points - b, points - c
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2

    at_a = (d1 <= 0) & (d2 <= 0)
    at_b = (d3 >= 0) & (d4 <= d3)
    on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    at_c = (d6 >= 0) & (d5 <= d6)
    on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    on_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    regions = [at_a, at_b, on_ab, at_c, on_ac, on_bc]

    # Outside the triangle the nearest point is a + v * ab + w * ac on its boundary; the
    # denominators are |ab|², |ac|² and |bc|², which vanish only on degenerate triangles.
    along_ab = _ratio(d1, d1 - d3)
    along_ac = _ratio(d2, d2 - d6)
    along_bc = _ratio(d4 - d3, (d4 - d3) + (d5 - d6))
    v = np.select(regions, [0.0, 1.0, along_ab, 0.0, 0.0, 1.0 - along_bc], default=0.0)
    w = np.select(regions, [0.0, 0.0, 0.0, 1.0, along_ac, along_bc], default=0.0)
    distance = np.linalg.norm(points - a - v[:, None] * ab - w[:, None] * ac, axis=1)
    # Inside, the distance to the plane, which unlike the barycentric weights stays accurate on
    # slivers. On degenerate (zero-area, or nearly) triangles the region tests are unreliable;
    # there the nearest point lies on an edge: the smallest of the three segment distances.
    normal = np.cross(ab, ac)
    area_squared = _dot(normal, normal)  # (2 · area)²
    degenerate = area_squared <= 1e-12 * (_dot(ab, ab) + _dot(ac, ac)) ** 2
    inside = ~np.logical_or.reduce(regions) & ~degenerate
    distance[inside] = np.abs(_dot(ap[inside], normal[inside])) / np.sqrt(area_squared[inside])
    if degenerate.any():
        p, a, b, c = points[degenerate], a[degenerate], b[degenerate], c[degenerate]
        distance[degenerate] = np.minimum.reduce(
            [_segment_distance(p, a, b), _segment_distance(p, b, c), _segment_distance(p, c, a)]
        )
    return distance


def distance_to_mesh(
    points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, max_pairs: int = MAX_PAIRS
) -> np.ndarray:
    """Exact distance from each point to the nearest triangle of a mesh (unsigned), float64.

    The true minimum over all triangles, found with a ``TriangleTree``; build the tree once
    and call its ``distance`` to query the same mesh again. Without triangles, every distance
    is inf.
    """
    return TriangleTree(vertices, faces).distance(points, max_pairs=max_pairs)


class TriangleTree:
    """A hierarchy of axis-aligned bounding boxes over a mesh's triangles, for exact distances.

    Triangles with an edge longer than ``split_fraction`` of the mesh's bounding-box diagonal
    are first cut into pieces (the surface is unchanged), so that huge and thin triangles get
    tight boxes. The pieces are sorted along a Z-order curve of their centroids, which keeps neighbours in
    space close in the list. Level 0 holds the box of every piece and each level above the
    boxes of consecutive pairs of the level below, up to one box around everything.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, split_fraction: float = SPLIT_FRACTION):
        corners = _corners(vertices, faces)
        if len(corners):
            diagonal = float(np.linalg.norm(np.ptp(corners.reshape(-1, 3), axis=0)))
            corners = split_triangles(corners, split_fraction * diagonal)
            corners = corners[_z_order(corners.mean(axis=1))]
        self.a, self.b, self.c = (np.ascontiguousarray(corners[:, i]) for i in range(3))
        self.centroid_tree = kd_tree(corners.mean(axis=1)) if len(corners) else None
        # Levels are padded to an even length with empty boxes (low inf, high -inf), which are
        # infinitely far from every point.
        self.lows, self.highs = [corners.min(axis=1)], [corners.max(axis=1)]
        while len(self.lows[-1]) > 1:
            if len(self.lows[-1]) % 2:
                self.lows[-1] = np.vstack([self.lows[-1], np.full((1, 3), np.inf)])
                self.highs[-1] = np.vstack([self.highs[-1], np.full((1, 3), -np.inf)])
            low, high = self.lows[-1], self.highs[-1]
            self.lows.append(np.minimum(low[0::2], low[1::2]))
            self.highs.append(np.maximum(high[0::2], high[1::2]))

    def __len__(self) -> int:
        return len(self.a)

    def distance(self, points: np.ndarray, max_pairs: int = MAX_PAIRS) -> np.ndarray:
        """Exact distance from each of the (n, 3) points to the nearest triangle, float64.

        Each point starts with the distance to the piece whose centroid is nearest, an upper
        bound. Then the boxes are descended from the root, keeping the (point, box) pairs where
        the box is nearer than the point's best distance so far, and at level 0 the exact
        distance to each kept piece lowers the best. Pairs are processed in batches of at most
        ``max_pairs``, depth first, so memory stays bounded whatever the points.
        """
        return self._search(points, max_pairs, track=False)[0]

    def nearest(self, points: np.ndarray, max_pairs: int = MAX_PAIRS) -> tuple[np.ndarray, np.ndarray]:
        """The exact distance (n,) from each of the (n, 3) points to the nearest triangle, and the
        corners (n, 3, 3) of the piece of it that is nearest (in the triangle's plane, with its
        winding), found as ``distance`` finds the distance."""
        distance, piece = self._search(points, max_pairs, track=True)
        if self.centroid_tree is None:
            return distance, np.full((len(distance), 3, 3), np.nan)
        return distance, np.stack([self.a[piece], self.b[piece], self.c[piece]], axis=1)

    def _search(self, points: np.ndarray, max_pairs: int, track: bool) -> tuple[np.ndarray, np.ndarray]:
        """The best distance of each point and, if ``track``, the piece that gives it."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if self.centroid_tree is None or len(points) == 0:
            return np.full(len(points), np.inf), np.zeros(len(points), dtype=np.int64)
        _, nearest = self.centroid_tree.query(points)
        best = point_triangle_distance(points, self.a[nearest], self.b[nearest], self.c[nearest])
        piece = np.asarray(nearest, dtype=np.int64)
        batch = max(1, max_pairs // 2)  # a batch of pairs has at most twice as many children
        everything = np.arange(len(points))
        stack = _batches(everything, np.zeros_like(everything), len(self.lows) - 1, batch)
        while stack:
            point, box, level = stack.pop()
            if level == 0:
                exact = point_triangle_distance(points[point], self.a[box], self.b[box], self.c[box])
                if track:
                    # Each point's nearest piece of this batch: the first of its pairs by distance.
                    order = np.lexsort((exact, point))
                    _, first = np.unique(point[order], return_index=True)
                    chosen = order[first]
                    better = exact[chosen] < best[point[chosen]]
                    piece[point[chosen[better]]] = box[chosen[better]]
                np.minimum.at(best, point, exact)
                continue
            # The two children of every box, one level down; keep those that may hold a closer piece.
            point = np.repeat(point, 2)
            box = (2 * box[:, None] + np.array([0, 1])).ravel()
            level -= 1
            position = points[point]
            gap = np.maximum(self.lows[level][box] - position, position - self.highs[level][box])
            np.maximum(gap, 0.0, out=gap)
            near = _dot(gap, gap) < best[point] ** 2
            stack.extend(_batches(point[near], box[near], level, batch))
        return best, piece


def split_triangles(corners: np.ndarray, length: float, max_count: int = MAX_PIECES) -> np.ndarray:
    """Cut triangles, given as (n, 3, 3) corners, in two across their longest edge, again and
    again, until no edge is longer than ``length`` (or there are ``max_count`` pieces).

    The pieces cover exactly the same surface, so distances to it do not change.
    """
    finished = []
    count = len(corners)
    while len(corners):
        edges = np.linalg.norm(corners - np.roll(corners, -1, axis=1), axis=2)  # edge i: corner i to i + 1
        large = edges.max(axis=1) > length
        if count + large.sum() > max_count:
            break
        finished.append(corners[~large])
        corners, edges = corners[large], edges[large]
        count += len(corners)
        # Corners (o, p, q) with p q the longest edge, then halves (o, p, m) and (o, m, q).
        rows = np.arange(len(corners))
        longest = edges.argmax(axis=1)
        o = corners[rows, (longest + 2) % 3]
        p = corners[rows, longest]
        q = corners[rows, (longest + 1) % 3]
        m = (p + q) / 2
        corners = np.concatenate([np.stack([o, p, m], axis=1), np.stack([o, m, q], axis=1)])
    return np.concatenate(finished + [corners])


def surface_distances(
    mesh: Any, gt_mesh: Any, count: int = SURFACE_SAMPLES, seed: int = 0, exact: bool = True
) -> dict[str, float]:
    """Chamfer and Hausdorff distances between two triangle meshes (anything with ``vertices`` and
    ``faces``, such as ``trimesh.Trimesh``), as the sample data's README defines them.

    ``count`` points are sampled uniformly by area on each mesh (seeds ``seed`` and ``seed + 1``).
    ``chamfer`` is the average of the two mean distances (mesh samples to the nearest ground-truth
    sample and back) and ``hausdorff`` the largest of all of them. ``chamfer_exact`` and
    ``hausdorff_exact`` are the same with the exact distance from each sample to the other
    mesh's triangles: 0 for identical surfaces, while the sampled ones never go below them. With
    ``exact=False`` the exact pair is NaN and costs nothing. A mesh without area scores inf.
    """
    samples = sample_surface(mesh.vertices, mesh.faces, count, seed)
    gt_samples = sample_surface(gt_mesh.vertices, gt_mesh.faces, count, seed + 1)
    if len(samples) == 0 or len(gt_samples) == 0:
        return dict.fromkeys(["chamfer", "hausdorff", "chamfer_exact", "hausdorff_exact"], np.inf)
    to_gt, _ = kd_tree(gt_samples).query(samples)
    from_gt, _ = kd_tree(samples).query(gt_samples)
    scores = {"chamfer": _chamfer(to_gt, from_gt), "hausdorff": _hausdorff(to_gt, from_gt)}
    if exact:
        to_gt = distance_to_mesh(samples, gt_mesh.vertices, gt_mesh.faces)
        from_gt = distance_to_mesh(gt_samples, mesh.vertices, mesh.faces)
        scores.update(chamfer_exact=_chamfer(to_gt, from_gt), hausdorff_exact=_hausdorff(to_gt, from_gt))
    else:
        scores.update(chamfer_exact=np.nan, hausdorff_exact=np.nan)
    return scores


def normal_angles(normals: np.ndarray, gt_normals: np.ndarray) -> np.ndarray:
    """Oriented angle in degrees (0 to 180) between each predicted normal and its ground truth.

    Neither needs unit length. A predicted normal that is zero or has a NaN (missing) gives NaN.
    """
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    gt_normals = np.asarray(gt_normals, dtype=np.float64).reshape(-1, 3)
    if normals.shape != gt_normals.shape:
        raise ValueError(f"{len(normals)} predicted normals for {len(gt_normals)} points")
    # atan2(|n × g|, n · g) keeps its precision near 0 and 180 degrees, where arccos does not.
    sine = np.linalg.norm(np.cross(normals, gt_normals), axis=1)
    cosine = _dot(normals, gt_normals)
    angles = np.degrees(np.arctan2(sine, cosine))
    missing = ~np.isfinite(normals).all(axis=1) | ~normals.any(axis=1)
    angles[missing] = np.nan
    return angles


def normal_errors(normals: np.ndarray, gt_normals: np.ndarray) -> dict:
    """Angle errors in degrees of predicted normals against ground-truth (outward) normals.

    Returns the mean and median of the oriented error (0 to 180: the normal must point outward)
    and of the unoriented one (0 to 90: a normal and its opposite count as the same), the share
    of all points whose normal points inward (negative dot product with the ground truth), and
    the share of missing normals. A missing normal (zero, or with a NaN) counts as 90 degrees
    unoriented and 180 oriented, and not as pointing inward.
    """
    oriented = normal_angles(normals, gt_normals)
    missing = np.isnan(oriented)
    inward = oriented > 90.0  # the dot product is negative; NaN compares False
    unoriented = np.minimum(oriented, 180.0 - oriented)
    oriented[missing], unoriented[missing] = 180.0, 90.0
    return {
        "normal_mean_oriented": float(np.mean(oriented)),
        "normal_median_oriented": float(np.median(oriented)),
        "normal_mean_unoriented": float(np.mean(unoriented)),
        "normal_median_unoriented": float(np.median(unoriented)),
        "normal_inward_share": float(np.mean(inward)),
        "normal_missing_share": float(np.mean(missing)),
    }


def edge_mask(edges: np.ndarray, count: int) -> np.ndarray:
    """A boolean mask over ``count`` points from edge point indices or from a boolean mask."""
    edges = np.asarray(edges)
    if edges.dtype == bool:
        if edges.shape != (count,):
            raise ValueError(f"an edge mask of shape {edges.shape} for {count} points")
        return edges
    if edges.size and not np.issubdtype(edges.dtype, np.integer):
        raise ValueError(f"edge indices must be integers, got {edges.dtype}")
    indices = edges.astype(np.int64).ravel()
    if len(indices) and (indices.min() < 0 or indices.max() >= count):
        raise ValueError(f"edge indices must lie in [0, {count}), got {indices.min()} to {indices.max()}")
    mask = np.zeros(count, dtype=bool)
    mask[indices] = True
    return mask


def edge_scores(edges: np.ndarray, is_edge: np.ndarray) -> dict:
    """Precision, recall and IoU of the reported edge points against the ``is_edge`` labels.

    ``edges`` holds the indices of the reported points (repeats count once) or a boolean mask.
    When nothing is reported, precision is 0.0 (as are recall and IoU): a method that finds no
    edge on a shape that has some scores 0, rather than dropping out of an average. On a shape
    without true edge points, precision, recall and IoU are NaN and the score is
    ``edge_false_share``, the share of all points reported as edges (given on every shape: the
    share of points reported but not true edge points). The counts come along.
    """
    is_edge = np.asarray(is_edge, dtype=bool).ravel()
    reported = edge_mask(edges, len(is_edge))
    both = int(np.count_nonzero(reported & is_edge))
    either = int(np.count_nonzero(reported | is_edge))
    n_reported, n_true = int(np.count_nonzero(reported)), int(np.count_nonzero(is_edge))
    if n_true == 0:
        precision = recall = iou = np.nan
    else:
        precision = both / n_reported if n_reported else 0.0
        recall = both / n_true
        iou = both / either
    return {
        "edge_precision": precision,
        "edge_recall": recall,
        "edge_iou": iou,
        "edge_false_share": float(np.count_nonzero(reported & ~is_edge) / max(len(is_edge), 1)),
        "edge_reported": n_reported,
        "edge_true": n_true,
    }


def edge_chamfer(edge_points: np.ndarray, gt_edge_points: np.ndarray) -> float:
    """Edge Chamfer Distance: the average of the mean distance from each reported edge point to
    the nearest ground-truth edge sample and the mean distance from each ground-truth sample to
    the nearest reported point.

    When exactly one of the two sets is empty the distance is inf (the nearest point of an empty
    set is infinitely far: nothing reported on a shape with edges, or edges reported on a smooth
    shape). When both are empty it is NaN: a smooth shape with no edge reported, which the
    README does not score by ECD (see ``edge_false_share``).
    """
    edge_points = np.asarray(edge_points, dtype=np.float64).reshape(-1, 3)
    gt_edge_points = np.asarray(gt_edge_points, dtype=np.float64).reshape(-1, 3)
    if len(edge_points) == 0 and len(gt_edge_points) == 0:
        return np.nan
    if len(edge_points) == 0 or len(gt_edge_points) == 0:
        return np.inf
    to_gt, _ = kd_tree(gt_edge_points).query(edge_points)
    from_gt, _ = kd_tree(edge_points).query(gt_edge_points)
    return _chamfer(to_gt, from_gt)


def _batches(point: np.ndarray, box: np.ndarray, level: int, size: int) -> list[tuple]:
    """(point, box) pairs of one level of a TriangleTree, cut into batches of ``size``."""
    return [(point[i : i + size], box[i : i + size], level) for i in range(0, len(point), size)]


def _z_order(points: np.ndarray, bits: int = 10) -> np.ndarray:
    """The order of points along a Z-order (Morton) curve over their bounding box."""
    low = points.min(axis=0)
    size = max(float(np.ptp(points, axis=0).max()), np.finfo(float).tiny)
    cells = ((points - low) / size * (2**bits - 1)).astype(np.int64)
    code = np.zeros(len(points), dtype=np.int64)
    for bit in range(bits):
        for axis in range(3):
            code |= ((cells[:, axis] >> bit) & 1) << (3 * bit + axis)
    return np.argsort(code, kind="stable")


def _corners(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    return vertices[faces]


def _segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from each point to the segment (a, b) of the same row; a may equal b."""
    ab = b - a
    t = np.clip(_ratio(_dot(points - a, ab), _dot(ab, ab)), 0.0, 1.0)
    return np.linalg.norm(points - a - t[:, None] * ab, axis=1)


def _dot(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", x, y)


def _ratio(numerator: np.ndarray, denominator: np.ndarray) -> np.ndarray:
    """numerator / denominator, and 0 where the denominator is 0."""
    safe = np.where(denominator == 0, 1.0, denominator)
    return np.where(denominator == 0, 0.0, numerator / safe)


def _chamfer(forward: np.ndarray, backward: np.ndarray) -> float:
    return float((forward.mean() + backward.mean()) / 2)


def _hausdorff(forward: np.ndarray, backward: np.ndarray) -> float:
    return float(max(forward.max(), backward.max()))
