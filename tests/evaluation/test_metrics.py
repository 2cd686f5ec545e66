"""evaluation.metrics: analytic cases and brute force (the sample shapes are in test_sample_data.py)."""

import numpy as np
import pytest
import trimesh
from scipy.integrate import dblquad

from evaluation.metrics import (
    TriangleTree,
    distance_to_mesh,
    edge_chamfer,
    edge_scores,
    normal_errors,
    point_triangle_distance,
    sample_surface,
    split_triangles,
    surface_distances,
    triangle_areas,
)

# --- exact point-to-triangle and point-to-mesh distances --------------------------------------


def reference_distance(points, a, b, c):
    """Point-triangle distance by another route than Ericson's regions: the distance to the plane
    when the projection falls inside the triangle, else the nearest of the three edges.
    Broadcasts, so that points[:, None] against triangles[None] gives every pair."""

    def segment(p, s, t):
        st = t - s
        length = (st * st).sum(-1)
        u = np.clip(((p - s) * st).sum(-1) / np.where(length > 0, length, 1), 0, 1)
        return np.linalg.norm(p - s - u[..., None] * st, axis=-1)

    edges = np.minimum(np.minimum(segment(points, a, b), segment(points, b, c)), segment(points, c, a))
    normal = np.cross(b - a, c - a)
    norm = np.linalg.norm(normal, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = normal / norm[..., None]
        height = ((points - a) * unit).sum(-1)
        foot = points - height[..., None] * unit
        # Degenerate triangles (zero area, up to rounding) are their edges.
        inside = norm > 1e-6 * ((b - a) ** 2 + (c - a) ** 2).sum(-1)
        for s, t in ((a, b), (b, c), (c, a)):
            inside = inside & ((np.cross(t - s, foot - s) * normal).sum(-1) >= 0)
    return np.where(inside, np.abs(height), edges)


def random_triangles(rng, count):
    """Random triangles, a fifth of them degenerate in one of several ways."""
    a, b, c = rng.normal(size=(3, count, 3))
    k = count // 20
    b[:k] = a[:k]  # two corners equal
    c[k : 2 * k] = b[k : 2 * k]
    c[2 * k : 3 * k] = a[2 * k : 3 * k] + 0.3 * (b[2 * k : 3 * k] - a[2 * k : 3 * k])  # collinear, inside
    c[3 * k : 4 * k] = a[3 * k : 4 * k] + 1.7 * (b[3 * k : 4 * k] - a[3 * k : 4 * k])  # collinear, beyond
    b[4 * k : 5 * k] = c[4 * k : 5 * k] = a[4 * k : 5 * k]  # a single point
    return a, b, c


def test_point_triangle_distance_matches_reference():
    rng = np.random.default_rng(0)
    a, b, c = random_triangles(rng, 20_000)
    points = rng.normal(size=(20_000, 3)) * 2
    expected = reference_distance(points, a, b, c)
    assert np.allclose(point_triangle_distance(points, a, b, c), expected, rtol=1e-12, atol=1e-12)
    # Far away, the same up to rounding.
    far = points * 1e3
    assert np.allclose(point_triangle_distance(far, a, b, c), reference_distance(far, a, b, c), rtol=1e-12)


def test_point_triangle_distance_is_zero_on_the_triangle():
    rng = np.random.default_rng(1)
    a, b, c = rng.normal(size=(3, 5000, 3))
    u, v = rng.random((2, 5000))
    u, v = np.where(u + v > 1, 1 - u, u), np.where(u + v > 1, 1 - v, v)
    on_surface = a + u[:, None] * (b - a) + v[:, None] * (c - a)
    on_edge = a + u[:, None] * (b - a)
    for points in (on_surface, on_edge, a, b, c, (b + c) / 2):
        assert point_triangle_distance(points, a, b, c).max() < 1e-12


def test_point_triangle_distance_known_values():
    a, b, c = np.array([[0.0, 0, 0]]), np.array([[1.0, 0, 0]]), np.array([[0.0, 1, 0]])
    cases = {
        (0.2, 0.2, 0.5): 0.5,  # above the inside
        (-1.0, -1.0, 0.0): np.sqrt(2),  # beyond corner a
        (0.5, -2.0, 0.0): 2.0,  # beyond edge ab
        (1.0, 1.0, 0.0): np.sqrt(0.5),  # beyond edge bc
        (3.0, 0.0, 4.0): np.sqrt(4 + 16),  # beyond corner b, off the plane
    }
    for point, expected in cases.items():
        assert point_triangle_distance(np.array([point]), a, b, c)[0] == pytest.approx(expected, abs=1e-15)


@pytest.mark.parametrize("max_pairs", [500_000, 50])
def test_distance_to_mesh_matches_brute_force(max_pairs):
    rng = np.random.default_rng(2)
    a, b, c = random_triangles(rng, 300)
    vertices = np.concatenate([a, b, c])
    faces = np.arange(900).reshape(3, 300).T
    u, v = rng.random((2, 300)) / 2
    points = np.concatenate(
        [
            rng.normal(size=(1000, 3)),  # near and among the triangles
            vertices,  # at vertices
            (a + b) / 2,  # on edges
            a + u[:, None] * (b - a) + v[:, None] * (c - a),  # on triangles
            rng.normal(size=(100, 3)) * 100,  # far away
        ]
    )
    expected = reference_distance(points[:, None], a[None], b[None], c[None]).min(axis=1)
    distance = distance_to_mesh(points, vertices, faces, max_pairs=max_pairs)
    assert np.allclose(distance, expected, rtol=1e-12, atol=1e-13)


@pytest.mark.parametrize("max_pairs", [500_000, 50])
def test_nearest_piece_lies_in_the_brute_force_nearest_triangle(max_pairs):
    rng = np.random.default_rng(6)
    a, b, c = (corners[50:] for corners in random_triangles(rng, 200))  # the degenerate ones have no normal
    vertices, faces = np.concatenate([a, b, c]), np.arange(450).reshape(3, 150).T
    points = rng.normal(size=(2000, 3))
    all_distances = reference_distance(points[:, None], a[None], b[None], c[None])
    ranked = np.sort(all_distances, axis=1)
    clear = ranked[:, 1] - ranked[:, 0] > 1e-9  # a unique nearest triangle
    expected = np.cross(b - a, c - a)[all_distances.argmin(axis=1)]
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    distance, corners = TriangleTree(vertices, faces).nearest(points, max_pairs=max_pairs)
    assert np.allclose(distance, ranked[:, 0], rtol=1e-12, atol=1e-13)
    assert np.allclose(point_triangle_distance(points, *(corners[:, i] for i in range(3))), distance, atol=1e-13)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    assert clear.mean() > 0.95
    np.testing.assert_allclose(normal[clear], expected[clear], atol=1e-9)


def test_distance_to_mesh_with_many_equally_near_triangles():
    # Near the centre of a tessellated sphere every triangle is nearly as close as the nearest.
    sphere = trimesh.creation.icosphere(subdivisions=2)
    rng = np.random.default_rng(3)
    points = np.concatenate([rng.normal(size=(200, 3)) * 1e-3, rng.normal(size=(200, 3))])
    corners = sphere.triangles
    expected = reference_distance(points[:, None], *(corners[None, :, i] for i in range(3))).min(axis=1)
    distance = distance_to_mesh(points, sphere.vertices, sphere.faces)
    assert np.allclose(distance, expected, rtol=1e-12, atol=1e-14)


def box_distance(points, half=0.5):
    """Unsigned distance to the surface of the cube [-half, half]³."""
    q = np.abs(points) - half
    outside = np.linalg.norm(np.maximum(q, 0), axis=1)
    return np.abs(outside + np.minimum(q.max(axis=1), 0))


def test_distance_to_mesh_of_a_cube_mixing_huge_and_tiny_triangles():
    cube = trimesh.creation.box()
    for _ in range(5):  # only the two triangles of one face get small, again and again
        cube = cube.subdivide(face_index=np.flatnonzero(cube.triangles_center[:, 2] > 0.49))
    assert triangle_areas(cube.triangles).max() / triangle_areas(cube.triangles).min() > 1000
    rng = np.random.default_rng(4)
    points = np.concatenate([rng.uniform(-1, 1, size=(5000, 3)), rng.uniform(-0.5, 0.5, size=(2000, 3))])
    points[-1000:, 2] = 0.5  # on the finely cut face
    assert np.allclose(distance_to_mesh(points, cube.vertices, cube.faces), box_distance(points), atol=1e-12)


def test_distance_to_mesh_without_triangles():
    distance = distance_to_mesh(np.zeros((3, 3)), np.zeros((0, 3)), np.zeros((0, 3), dtype=int))
    assert distance.shape == (3,) and np.isinf(distance).all()


def test_split_triangles_keeps_the_surface():
    rng = np.random.default_rng(5)
    corners = np.stack(random_triangles(rng, 100), axis=1)
    pieces = split_triangles(corners, 0.1)
    edges = np.linalg.norm(pieces - np.roll(pieces, -1, axis=1), axis=2)
    assert edges.max() <= 0.1
    assert triangle_areas(pieces).sum() == pytest.approx(triangle_areas(corners).sum(), rel=1e-12)
    points = rng.normal(size=(300, 3))
    original = reference_distance(points[:, None], *(corners[None, :, i] for i in range(3))).min(axis=1)
    cut = distance_to_mesh(points, pieces.reshape(-1, 3), np.arange(3 * len(pieces)).reshape(-1, 3))
    assert np.allclose(cut, original, atol=1e-12)


# --- sampling, Chamfer and Hausdorff distances ------------------------------------------------


def test_sample_surface_is_uniform_by_area_and_reproducible():
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0], [3, 0, 0], [0, 1, 0]]) + [0, 0, 5]
    faces = np.array([[0, 1, 2], [3, 4, 5]])  # areas 0.5 and 1.5
    points = sample_surface(vertices, faces, 40_000, seed=7)
    assert np.array_equal(points, sample_surface(vertices, faces, 40_000, seed=7))
    assert not np.array_equal(points, sample_surface(vertices, faces, 40_000, seed=8))
    assert distance_to_mesh(points, vertices, faces).max() < 1e-12
    # The first triangle (a quarter of the area) lies inside the second: a point lands in the
    # first triangle's region with chance 1/4 + 3/4 * (0.5 / 1.5) = 1/2.
    in_first = (points[:, 0] + points[:, 1] <= 1).mean()
    assert in_first == pytest.approx(0.5, abs=0.01)


def test_identical_cubes_score_zero_exactly():
    cube = trimesh.creation.box()
    scores = surface_distances(cube, cube.copy(), count=20_000)
    assert scores["chamfer_exact"] < 1e-15 and scores["hausdorff_exact"] < 1e-15
    # Independent samples of one surface are some way apart.
    assert 0.002 < scores["chamfer"] < 0.02 and scores["hausdorff"] < 0.1


def test_cube_against_a_larger_concentric_cube():
    inner, outer = trimesh.creation.box(extents=(1, 1, 1)), trimesh.creation.box(extents=(1.2, 1.2, 1.2))
    scores = surface_distances(outer, inner, count=20_000)
    # Every point of the inner cube is 0.1 from the outer one. A point of an outer face is
    # sqrt(0.1² + s² + t²) from the inner cube, s and t being how far it lies beyond the inner
    # face's edges; mean over one outer face (area 1.44): centre 1 x 1, four strips, four corners.
    strip = 1.0 * (0.1 * np.sqrt(0.02) + 0.01 * np.arcsinh(1.0)) / 2  # ∫_0^0.1 sqrt(0.01 + s²) ds
    corner, _ = dblquad(lambda s, t: np.sqrt(0.01 + s**2 + t**2), 0, 0.1, 0, 0.1)
    outer_mean = (0.1 + 4 * strip + 4 * corner) / 1.44
    assert scores["chamfer_exact"] == pytest.approx((0.1 + outer_mean) / 2, abs=5e-4)
    assert 0.16 < scores["hausdorff_exact"] <= 0.1 * np.sqrt(3) + 1e-12
    # A sample's nearest sample is never nearer than the surface it was drawn on.
    assert scores["chamfer"] >= scores["chamfer_exact"]
    assert scores["hausdorff"] >= scores["hausdorff_exact"]


def test_surface_distances_of_an_empty_mesh_are_infinite():
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=int))
    scores = surface_distances(empty, trimesh.creation.box(), count=1000)
    assert all(np.isinf(value) for value in scores.values())


def test_surface_distances_can_skip_the_exact_pair():
    cube = trimesh.creation.box()
    scores = surface_distances(cube, cube, count=1000, exact=False)
    assert np.isnan(scores["chamfer_exact"]) and np.isnan(scores["hausdorff_exact"])
    assert scores["chamfer"] > 0


# --- normals ----------------------------------------------------------------------------------


def test_normal_errors_of_known_angles():
    rng = np.random.default_rng(6)
    gt = rng.normal(size=(1000, 3))
    gt /= np.linalg.norm(gt, axis=1, keepdims=True)
    assert all(value == 0 for value in normal_errors(gt, gt).values())
    longer = normal_errors(gt * 3.0, gt)  # length does not matter
    assert all(value == pytest.approx(0, abs=1e-9) for value in longer.values())
    flipped = normal_errors(-gt, gt)
    assert flipped["normal_mean_oriented"] == pytest.approx(180)
    assert flipped["normal_median_oriented"] == pytest.approx(180)
    assert flipped["normal_mean_unoriented"] == pytest.approx(0, abs=1e-9)
    assert flipped["normal_inward_share"] == 1.0

    angles = np.radians([10.0, 30.0, 120.0, 170.0])
    predicted = np.stack([np.sin(angles), np.zeros(4), np.cos(angles)], axis=1)
    errors = normal_errors(predicted, np.tile([0.0, 0.0, 1.0], (4, 1)))
    assert errors["normal_mean_oriented"] == pytest.approx((10 + 30 + 120 + 170) / 4)
    assert errors["normal_median_oriented"] == pytest.approx((30 + 120) / 2)
    assert errors["normal_mean_unoriented"] == pytest.approx((10 + 30 + 60 + 10) / 4)
    assert errors["normal_median_unoriented"] == pytest.approx((10 + 30) / 2)
    assert errors["normal_inward_share"] == 0.5


def test_missing_normals_count_as_90_and_180_degrees_but_not_inward():
    predicted = np.array([[0.0, 0, 1], [0, 0, 0], [np.nan, 0, 1], [0, 0, -1]])
    errors = normal_errors(predicted, np.tile([0.0, 0.0, 1.0], (4, 1)))
    assert errors["normal_mean_oriented"] == pytest.approx((0 + 180 + 180 + 180) / 4)
    assert errors["normal_median_oriented"] == pytest.approx(180)
    assert errors["normal_mean_unoriented"] == pytest.approx((0 + 90 + 90 + 0) / 4)
    assert errors["normal_inward_share"] == 0.25
    assert errors["normal_missing_share"] == 0.5


def test_normal_errors_need_one_normal_per_point():
    with pytest.raises(ValueError):
        normal_errors(np.ones((3, 3)), np.ones((4, 3)))


# --- edge points ------------------------------------------------------------------------------

IS_EDGE = np.array([True, True, True, False, False, False])
REPORTED = np.array([True, True, False, True, False, False])  # points 0, 1 and 3


@pytest.mark.parametrize("reported", [[0, 1, 3], [3, 0, 1, 1], REPORTED])
def test_edge_scores_of_a_small_label_set(reported):
    scores = edge_scores(reported, IS_EDGE)
    assert scores["edge_precision"] == pytest.approx(2 / 3)
    assert scores["edge_recall"] == pytest.approx(2 / 3)
    assert scores["edge_iou"] == pytest.approx(2 / 4)
    assert scores["edge_false_share"] == pytest.approx(1 / 6)
    assert (scores["edge_reported"], scores["edge_true"]) == (3, 3)


def test_edge_scores_when_everything_or_nothing_is_reported():
    everything = edge_scores(np.arange(6), IS_EDGE)
    assert (everything["edge_precision"], everything["edge_recall"], everything["edge_iou"]) == (0.5, 1, 0.5)
    nothing = edge_scores([], IS_EDGE)
    assert (nothing["edge_precision"], nothing["edge_recall"], nothing["edge_iou"]) == (0.0, 0.0, 0.0)
    exact = edge_scores(IS_EDGE, IS_EDGE)
    assert (exact["edge_precision"], exact["edge_recall"], exact["edge_iou"]) == (1.0, 1.0, 1.0)


def test_edge_scores_on_a_smooth_shape():
    smooth = np.zeros(6, dtype=bool)
    scores = edge_scores([2, 4], smooth)
    assert np.isnan([scores["edge_precision"], scores["edge_recall"], scores["edge_iou"]]).all()
    assert scores["edge_false_share"] == pytest.approx(2 / 6)
    assert edge_scores([], smooth)["edge_false_share"] == 0.0


@pytest.mark.parametrize("reported", [[6], [-1], [0.5], np.ones(5, dtype=bool)])
def test_edge_scores_reject_bad_indices(reported):
    with pytest.raises(ValueError):
        edge_scores(reported, IS_EDGE)


def test_edge_chamfer_of_known_point_sets():
    assert edge_chamfer([[0.0, 0, 0]], [[1.0, 0, 0], [0, 2, 0]]) == pytest.approx((1 + (1 + 2) / 2) / 2)
    line = np.stack([np.linspace(0, 1, 11), np.zeros(11), np.zeros(11)], axis=1)
    assert edge_chamfer(line, line) == 0.0
    assert edge_chamfer(line + [0, 0.01, 0], line) == pytest.approx(0.01)
    # Half the line reported: the other five points are 0.1 to 0.5 away from the nearest reported point.
    assert edge_chamfer(line[:6], line) == pytest.approx((0 + np.arange(1, 6).sum() * 0.1 / 11) / 2)


def test_edge_chamfer_with_an_empty_set():
    line = np.stack([np.linspace(0, 1, 11), np.zeros(11), np.zeros(11)], axis=1)
    assert edge_chamfer(np.zeros((0, 3)), line) == np.inf
    assert edge_chamfer(line, np.zeros((0, 3))) == np.inf
    assert np.isnan(edge_chamfer(np.zeros((0, 3)), np.zeros((0, 3))))
