"""core.dual and core.curves on analytic shapes whose sharp edges and corners are known exactly.

f is a signed distance (a box, a rotated box, a cylinder) or an intersection of half-spaces (a
wedge with a 50° ridge), with ∇f by central differences (exact to about 1e-9 here). The grid has
64 cells across 1.1, so a cell is about 0.017.
"""

from __future__ import annotations

import functools
import itertools

import numpy as np
import pytest
import trimesh
from skimage.measure import marching_cubes

from core import features
from core.curves import _along, distance_to_curves, edge_curves
from core.dual import dual_contour
from core.extract import sample_grid
from core.intersections import crossing_faces
from evaluation.metrics import distance_to_mesh, surface_distances

RESOLUTION = 64
CELL = 1.1 / RESOLUTION
HALF = np.array([0.3, 0.25, 0.2])
ROTATION = trimesh.transformations.rotation_matrix(0.3, [1, 2, 3])[:3, :3]
LOW, HIGH = np.full(3, -0.4), np.full(3, 0.4)


IDENTITY = np.eye(3)


def box(x: np.ndarray, half: np.ndarray = HALF, rotation: np.ndarray = IDENTITY, radius: float = 0.0) -> np.ndarray:
    """Signed distance to a box (rounded by ``radius``), turned by ``rotation``."""
    q = np.abs(x @ rotation) - (half - radius)
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0) - radius


def cylinder(x: np.ndarray) -> np.ndarray:
    """Signed distance to a cylinder of radius 0.25 and height 0.4 along z."""
    d = np.stack([np.linalg.norm(x[:, :2], axis=1) - 0.25, np.abs(x[:, 2]) - 0.2], axis=1)
    return np.linalg.norm(np.maximum(d, 0), axis=1) + np.minimum(d.max(axis=1), 0)


WEDGE_PLANES = [  # (unit normal, offset): a prism along x whose ridge angle is 50°
    (np.array([0.0, np.cos(np.radians(25)), np.sin(np.radians(25))]), 0.12),
    (np.array([0.0, -np.cos(np.radians(25)), np.sin(np.radians(25))]), 0.12),
    (np.array([0.0, 0.0, -1.0]), 0.2),
    (np.array([1.0, 0.0, 0.0]), 0.3),
    (np.array([-1.0, 0.0, 0.0]), 0.3),
]


def wedge(x: np.ndarray) -> np.ndarray:
    """The intersection of the half-spaces of WEDGE_PLANES (max of plane distances)."""
    return np.max([x @ n - d for n, d in WEDGE_PLANES], axis=0)


def wedge_mesh() -> trimesh.Trimesh:
    corners = []
    for i, j, k in itertools.combinations(range(5), 3):
        normals = np.array([WEDGE_PLANES[m][0] for m in (i, j, k)])
        if abs(np.linalg.det(normals)) > 1e-9:
            point = np.linalg.solve(normals, [WEDGE_PLANES[m][1] for m in (i, j, k)])
            if wedge(point[None])[0] <= 1e-9:
                corners.append(point)
    return trimesh.convex.convex_hull(np.array(corners))


def gradient(f, x: np.ndarray, step: float = 1e-6) -> np.ndarray:
    return np.stack([(f(x + step * e) - f(x - step * e)) / (2 * step) for e in np.eye(3)], axis=1)


@functools.cache
def contour(name: str, sharpen: bool = False) -> trimesh.Trimesh:
    """Plain dual contouring: f is exact here, so its own tangent planes meet on the edges (the
    side planes are for a fitted f, which rounds them: test_sharpening_restores_...)."""
    f = SHAPES[name][0]
    grid = sample_grid(f, RESOLUTION, LOW, HIGH)
    return dual_contour(grid, f, lambda x: (f(x), gradient(f, x)), sharpen=sharpen)


def box_mesh(rotation: np.ndarray = IDENTITY) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(2 * HALF)
    mesh.vertices = mesh.vertices @ rotation.T
    return mesh


def _cylinder_mesh() -> trimesh.Trimesh:
    return trimesh.creation.cylinder(radius=0.25, height=0.4, sections=512)


SHAPES = {
    "box": (box, box_mesh),
    "rotated box": (functools.partial(box, rotation=ROTATION), functools.partial(box_mesh, ROTATION)),
    "wedge": (wedge, wedge_mesh),
    "cylinder": (cylinder, _cylinder_mesh),
}


@pytest.mark.parametrize("name", list(SHAPES))
def test_dual_contouring_is_a_closed_outward_manifold(name):
    mesh = contour(name)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0
    assert mesh.volume == pytest.approx(SHAPES[name][1]().volume, rel=0.01)


@pytest.mark.parametrize("name", ["box", "rotated box", "wedge", "cylinder"])
def test_dual_contouring_keeps_sharp_edges_and_corners_within_a_fraction_of_a_cell(name):
    truth = SHAPES[name][1]()
    distances = surface_distances(contour(name), truth, count=20_000)
    # Marching cubes cuts each 90° corner by up to a cell (0.017); the cylinder's facets (512
    # around) are within 2e-5 of the true cylinder. What is left is where a face spans a bend.
    assert distances["hausdorff_exact"] < 0.25 * CELL
    assert distances["chamfer_exact"] < 0.01 * CELL
    assert np.abs(SHAPES[name][0](contour(name).vertices)).max() < 0.1 * CELL


@pytest.mark.parametrize("name", ["box", "rotated box", "wedge"])
def test_every_corner_of_a_polytope_gets_a_vertex(name):
    truth, mesh = SHAPES[name][1](), contour(name)
    nearest = np.linalg.norm(truth.vertices[:, None] - mesh.vertices[None], axis=2).min(axis=1)
    assert nearest.max() < 0.2 * CELL


def _along_edges_away_from_corners(truth: trimesh.Trimesh) -> np.ndarray:
    """Points (n, 3) every 1/400 of each sharp edge of the polytope ``truth``, those 0.03 or more
    from every corner (where a rounding cuts the corner itself)."""
    segments = truth.vertices[truth.face_adjacency_edges[truth.face_adjacency_angles > 1.0]]
    t = np.linspace(0, 1, 400)[:, None]
    on_edges = np.concatenate([a + t * (b - a) for a, b in segments])
    away = np.min([np.linalg.norm(on_edges - corner, axis=1) for corner in truth.vertices], axis=0) >= 0.03
    return on_edges[away]


def test_sharpening_restores_the_edges_a_fit_rounds():
    # A box rounded by 0.01, as a fitted network rounds its edges, against the sharp box: the side
    # planes move the rounded band's vertices onto the sharp edges (its corners stay cut).
    rounded = functools.partial(box, radius=0.01)
    grid = sample_grid(rounded, 160, LOW, HIGH)
    field = lambda x: (rounded(x), gradient(rounded, x))  # noqa: E731
    plain_mesh = dual_contour(grid, rounded, field, sharpen=False)
    sharp_mesh = dual_contour(grid, rounded, field, sharpen=True)
    plain = surface_distances(plain_mesh, box_mesh(), count=20_000)
    sharp = surface_distances(sharp_mesh, box_mesh(), count=20_000)
    assert sharp["chamfer_exact"] < 0.1 * plain["chamfer_exact"]
    assert sharp_mesh.is_watertight and sharp_mesh.is_winding_consistent
    # Along the 12 edges, 0.03 or more from a corner: the rounding leaves them 0.41 r = 0.004 away.
    truth = box_mesh()
    on_edges = _along_edges_away_from_corners(truth)
    for mesh, bound in ((plain_mesh, (0.003, np.inf)), (sharp_mesh, (0.0, 0.001))):
        gap = distance_to_mesh(on_edges, mesh.vertices, mesh.faces)
        assert bound[0] <= np.percentile(gap, 99) < bound[1]


def test_a_thin_plates_edges_are_sharpened_though_its_wall_is_narrower_than_the_walk():
    # A plate 0.05 thick rounded by 0.012: a walk down its wall from one edge's band reaches the
    # other edge's rounding before one and a half SIDE_STEP, so its far reading is not flat; the
    # wall is read nearer (features._WINDOWS). Read only at SIDE_STEP, the edges kept their
    # rounding (99th percentile 0.0050 from the mesh) and the band's creases gave 8.5 of curves.
    half = np.array([0.3, 0.25, 0.025])
    rounded = functools.partial(box, half=half, radius=0.012)
    grid = sample_grid(rounded, 160, LOW, HIGH)
    mesh = dual_contour(grid, rounded, lambda x: (rounded(x), gradient(rounded, x)))
    truth = trimesh.creation.box(2 * half)
    on_edges = _along_edges_away_from_corners(truth)
    assert np.percentile(distance_to_mesh(on_edges, mesh.vertices, mesh.faces), 99) < 0.001
    # The twelve edges are 4.6 long; each curve stops short of the corners.
    assert 4.3 < sum(curve.length for curve in edge_curves(mesh, 30.0, 0.02, 0.005)) < 4.6
    assert mesh.is_watertight and mesh.is_winding_consistent


def test_the_two_sides_of_a_thin_wall_read_across_its_rounded_end_are_not_an_edges_faces():
    # A wall 0.03 thick whose end a fit rounds into a dome 0.01 high: a walk from the dome reaches
    # both sides within SIDE_STEP, flat and facing opposite ways. They meet nowhere near: 265
    # crossings took them as an edge's faces, and on a fitted U-channel such planes, mixed with
    # the dome's own, put its wall tops 0.025 above the truth (docs/benchmarks.md).
    half, dome = 0.015, 0.01

    def wall(x: np.ndarray) -> np.ndarray:
        cap = half * np.hypot(x[:, 1] / half, np.maximum(x[:, 2] - 0.2 + dome, 0) / dome) - half
        return np.maximum.reduce([np.abs(x[:, 0]) - 0.3, cap, -x[:, 2] - 0.2])

    grid = sample_grid(wall, 160, LOW, HIGH)
    crossings = grid.position(marching_cubes(grid.values_off_zero(), 0.0)[0])
    normals = features.unit(gradient(wall, crossings))
    planes = features.side_planes(crossings, normals, lambda x: (wall(x), gradient(wall, x)))
    turning = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", planes.normals_a, planes.normals_b), -1, 1)))
    assert planes.edge.sum() > 500  # the wall's other ends: its edges at the box's faces
    assert turning[planes.edge].max() <= features.MAX_EDGE_TURNING


SHAFT_RADIUS, FLAT_HEIGHT = 0.15, 0.1  # the flat's edges: y = ±0.1118, z = 0.1; faces 48° apart


def flatted_shaft(x: np.ndarray, rounding: float) -> np.ndarray:
    """A shaft along x of radius 0.15 with a flat at z = 0.1, the flat's edges rounded over about
    ``rounding`` (a polynomial smooth maximum), as a fit rounds them."""
    shaft, flat = np.hypot(x[:, 1], x[:, 2]) - SHAFT_RADIUS, x[:, 2] - FLAT_HEIGHT
    blend = np.maximum(rounding - np.abs(shaft - flat), 0) / rounding
    return np.maximum(np.maximum(shaft, flat) + blend**2 * rounding / 4, np.abs(x[:, 0]) - 0.3)


@pytest.mark.parametrize("rounding", [0.01, 0.02])
def test_a_flat_on_a_shaft_is_sharpened_though_the_shaft_beside_it_curves(rounding):
    # The walk across the flat's edge reads the flat on one side and the shaft, turning 7° every
    # step, on the other: no flat face there, so the edge was left rounded (0.0028 and 0.0055 from
    # the mesh) and had no curve. The shaft's tangent plane where it meets the flat is its plane.
    f = functools.partial(flatted_shaft, rounding=rounding)
    grid = sample_grid(f, 160, LOW, HIGH)
    mesh = dual_contour(grid, f, lambda x: (f(x), gradient(f, x)))
    edge_y = np.sqrt(SHAFT_RADIUS**2 - FLAT_HEIGHT**2)
    along = np.linspace(-0.2, 0.2, 100)
    for side in (1, -1):
        line = np.stack([along, np.full(100, side * edge_y), np.full(100, FLAT_HEIGHT)], axis=1)
        assert np.percentile(distance_to_mesh(line, mesh.vertices, mesh.faces), 99) < 0.001
        on_edge = [
            curve
            for curve in edge_curves(mesh, 30.0, 0.02, 0.005)
            if np.abs(curve.points - [0, side * edge_y, FLAT_HEIGHT])[:, 1:].max() < 0.005
        ]
        assert 0.5 < sum(curve.length for curve in on_edge) < 0.61  # 0.6 from end to end
        assert all(abs(curve.dihedral - 132) < 4 and curve.convex for curve in on_edge)
    assert mesh.is_watertight and mesh.is_winding_consistent


def test_a_curved_sides_plane_is_its_tangent_where_it_meets_the_flat_side():
    # A walk over a circle of radius 0.1 (centre at the origin, in the plane z = 0) away from the
    # line y = 0.06 that a flat side lies on: the side meets it at x = 0.08, where its normal is
    # (0.8, 0.6, 0). With the steady turn taken out, the walk's normals are all the start's.
    radius, step = 0.1, 1.5 * features.SIDE_STEP / features._WALK_STEPS
    start_angle = np.arcsin(0.06 / radius) - 0.002 / radius  # 0.002 along the circle past the edge
    angles = start_angle - step * np.arange(1, features._WALK_STEPS + 1) / radius
    normals = np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], axis=1)[None]
    points = radius * normals
    start = radius * np.array([[np.cos(start_angle), np.sin(start_angle), 0.0]])
    flat_point, flat_normal = np.array([[0, 0.06, 0]]), np.array([[0, 1.0, 0]])
    point, normal, unbent, found = features._curved_side(points, normals, start, flat_point, flat_normal)
    assert found.all()
    assert point[0] == pytest.approx([0.08, 0.06, 0], abs=1e-9)
    assert normal[0] == pytest.approx([0.8, 0.6, 0], abs=1e-9)
    assert np.abs(unbent[0] - start / radius).max() < 1e-9


def test_a_wall_read_nearer_its_edge_must_turn_on_as_a_plates_does():
    # Across a plate's edge: top (+z), then its wall (+x), then the bottom (-z) beyond the wall's
    # other edge; a stair's step turns back instead (tread, riser, next tread).
    up, out, down = np.array([[0.0, 0, 1]]), np.array([[1.0, 0, 0]]), np.array([[0.0, 0, -1]])
    nearer, first = np.array([3]), np.array([features._WINDOWS[0][0]])
    assert features._wall_turns_on(nearer, up, out, down).all()
    assert not features._wall_turns_on(nearer, up, out, up).any()
    assert features._wall_turns_on(first, up, out, up).all()


@pytest.mark.parametrize("rotation", [IDENTITY, ROTATION], ids=["aligned", "rotated"])
def test_sharpening_brings_the_mesh_back_to_the_corners_a_fit_rounds(rotation):
    # A box rounded by 0.02 keeps its corners 0.73 r = 0.0146 from the rounding. Each crossing's
    # vertex goes onto the plane of the face it lies nearer, so a corner's patch, with crossings
    # near three faces, lands on the corner; fitting both planes of every crossing put it on one
    # of the corner's edges instead (0.011 from the corner, rotated 0.0125).
    rounded = functools.partial(box, rotation=rotation, radius=0.02)
    grid = sample_grid(rounded, 160, LOW, HIGH)
    mesh = dual_contour(grid, rounded, lambda x: (rounded(x), gradient(rounded, x)), sharpen=True)
    truth = box_mesh(rotation)
    assert distance_to_mesh(truth.vertices, mesh.vertices, mesh.faces).max() < 0.6 * 0.73 * 0.02
    assert mesh.is_watertight and mesh.is_winding_consistent


@pytest.mark.parametrize(
    "rotation, radius", [(IDENTITY, 0.01), (ROTATION, 0.02), (ROTATION, 0.03)], ids=["aligned", "rotated", "rounder"]
)
def test_a_sharpened_mesh_does_not_cross_itself_once_written_to_eight_decimals(rotation, radius):
    # Sharpened vertices on one edge line can lie exactly on another face's edge; a mesh file's
    # rounding (OBJ: 8 decimals) then pushed 4, 16 and 7 faces through others. Contact between
    # faces that share no vertex now counts as crossing (core.intersections), and is parted.
    rounded = functools.partial(box, rotation=rotation, radius=radius)
    grid = sample_grid(rounded, 160, LOW, HIGH)
    mesh = dual_contour(grid, rounded, lambda x: (rounded(x), gradient(rounded, x)), sharpen=True)
    every = np.arange(len(mesh.faces))
    assert len(crossing_faces(np.round(mesh.vertices, 8), mesh.faces, every)) == 0
    assert len(crossing_faces(mesh.vertices.astype(np.float32).astype(np.float64), mesh.faces, every)) == 0


@pytest.mark.parametrize("radius, edges", [(0.015, True), (0.03, True), (0.04, False), (0.05, False)])
def test_a_rounding_as_narrow_as_a_fits_is_an_edge_and_a_wider_bend_is_not(radius, edges):
    # A fit rounds a sharp edge over a band 0.02 to 0.035 wide (a box rounded by 0.015 to 0.03);
    # a bend of radius 0.04 or more with flat faces beside it (a smooth part, the bump of a scan)
    # keeps its curve: without features.BAND_WIDTH both of these got edge curves.
    rounded = functools.partial(box, radius=radius)
    grid = sample_grid(rounded, 160, LOW, HIGH)
    mesh = dual_contour(grid, rounded, lambda x: (rounded(x), gradient(rounded, x)))
    length = sum(curve.length for curve in edge_curves(mesh, 30.0, 0.02, 0.005))
    # The box's twelve edges are 6.0 long; each curve stops short of the corners.
    assert 5.0 < length < 6.0 if edges else length == 0


def test_band_width_of_a_steady_turn_is_four_fifths_of_its_band():
    # Normals turning at a steady rate by 60° between s = -0.02 and 0.02, read every 0.01 from
    # -0.06 to 0.06, flat beyond: from 10 % to 90 % of the turn is 0.8 of the band's 0.04.
    s = np.arange(-6, 7) * 0.01
    angle = np.radians(60) * np.clip((s + 0.02) / 0.04, 0, 1)
    profile = np.stack([np.zeros_like(s), np.sin(angle), np.cos(angle)], axis=1)[None]
    assert features.band_width(profile, 0.01) == pytest.approx([0.032], abs=1e-12)
    assert features.band_width(profile[:, ::-1], 0.01) == pytest.approx([0.032], abs=1e-12)


def test_sharpening_leaves_a_smooth_surface_alone():
    sphere = lambda x: np.linalg.norm(x, axis=1) - 0.3  # noqa: E731
    grid = sample_grid(sphere, RESOLUTION, LOW, HIGH)
    mesh = dual_contour(grid, sphere, lambda x: (sphere(x), gradient(sphere, x)))
    radii = np.linalg.norm(mesh.vertices, axis=1)
    assert np.abs(radii - 0.3).max() < 0.002
    assert edge_curves(mesh, 30.0, 0.02, 0.005) == []


def test_the_curves_of_a_box_are_its_twelve_edges():
    curves = edge_curves(contour("box"), 30.0, 0.02, 0.005)
    assert len(curves) == 12
    assert sorted(round(c.length, 2) for c in curves) == pytest.approx([0.4] * 4 + [0.5] * 4 + [0.6] * 4, abs=0.02)
    for curve in curves:
        assert curve.convex
        assert curve.dihedral == pytest.approx(90, abs=3)
        assert np.abs(box(curve.points)).max() < 0.05 * CELL  # on the box ...
        on_faces = np.sum(np.abs(np.abs(curve.points) - HALF) < 0.1 * CELL, axis=1)
        assert (on_faces >= 2).all()  # ... on two faces at once: on an edge
        assert np.linalg.norm(np.diff(curve.points, axis=0), axis=1).max() <= 0.005 + 1e-9


def _distance_along_faces_by_hand(points: np.ndarray, curves: list, within: float) -> np.ndarray:
    """distance_to_curves point by point: the nearest of all dense samples of all curves, its
    segment's direction and faces, the offset less its parts along the direction (unless it points
    past the curve's end from its end) and off the nearer face; inf beyond ``within`` along the
    face or twice ``within`` away; nan where two samples are nearest (a corner where curves end
    together), which the two ways may break differently."""
    samples, directions, lefts, rights, ends = [], [], [], [], []
    for curve in curves:
        dense, step = _along(curve.points, 0.001)
        for i, (sample, k) in enumerate(zip(dense, step)):
            segment = curve.points[k + 1] - curve.points[k]
            samples.append(sample)
            directions.append(segment / np.linalg.norm(segment))
            lefts.append(curve.left[k])
            rights.append(curve.right[k])
            ends.append(-1 if i == 0 else 1 if i == len(dense) - 1 else 0)
    samples = np.array(samples)
    distances = []
    for point in points:
        away = np.linalg.norm(samples - point, axis=1)
        j, second = np.argsort(away)[:2]
        offset = point - samples[j]
        if away[second] - away[j] < 1e-9:
            distances.append(np.nan)
            continue
        if np.linalg.norm(offset) > 2 * within:
            distances.append(np.inf)
            continue
        along_curve = np.dot(offset, directions[j])
        if along_curve * ends[j] <= 0:
            offset = offset - along_curve * directions[j]
        off_face = min(abs(np.dot(offset, lefts[j])), abs(np.dot(offset, rights[j])))
        along = np.sqrt(max(np.dot(offset, offset) - off_face**2, 0.0))
        distances.append(along if along <= within else np.inf)
    return np.array(distances)


@pytest.mark.parametrize("workers", [1, 2])
def test_distance_to_curves_is_the_distance_along_the_nearer_face_up_to_the_bound(workers):
    curves = edge_curves(contour("box"), 30.0, 0.02, 0.005)
    points = np.random.default_rng(5).uniform(-0.35, 0.35, (1500, 3))
    by_hand = _distance_along_faces_by_hand(points, curves, 0.05)
    untied = ~np.isnan(by_hand)
    assert untied.mean() > 0.95
    assert 0.1 < np.isfinite(by_hand).mean() < 0.8
    bounded = distance_to_curves(points, curves, 0.005, 0.05, workers)
    np.testing.assert_allclose(bounded[untied], by_hand[untied], atol=1e-12)
    unbounded = distance_to_curves(points, curves, 0.005)
    near = np.isfinite(by_hand)
    np.testing.assert_allclose(unbounded[near], by_hand[near], atol=1e-12)
    assert np.isfinite(unbounded).all()
    assert np.isinf(distance_to_curves(points, [], 0.005)).all()


def test_a_point_moved_off_its_face_is_as_far_from_the_edge_as_where_it_was_sampled():
    """Points on the box's faces at a known distance from an edge (away from the corners), moved
    off their face by up to 0.008 (noise of the sample data's size): their distance along the
    face is the one they were sampled at, where the straight distance to the edge is not. A point
    moved off its face by more than it lies from the edge is nearer the other face's plane, and is
    read on that face: as far from the edge as it was moved."""
    curves = edge_curves(contour("box"), 30.0, 0.02, 0.005)
    rng = np.random.default_rng(9)
    count = 2000
    along_edge = rng.uniform(-0.5, 0.5, count) * HALF[2]  # edges along z, the middle half
    sampled_at = rng.uniform(0.0, 0.03, count)
    off = rng.uniform(-0.008, 0.008, count)
    on_x_face = rng.random(count) < 0.5
    # The edge x = HALF[0], y = HALF[1]: on the face x = HALF[0], y runs in from the edge; and the other way round.
    x = np.where(on_x_face, HALF[0] + off, HALF[0] - sampled_at)
    y = np.where(on_x_face, HALF[1] - sampled_at, HALF[1] + off)
    points = np.stack([x, y, along_edge], axis=1)
    distance = distance_to_curves(points, curves, 0.005, 0.05)
    on_its_face = np.abs(off) < sampled_at
    assert 0.6 < on_its_face.mean() < 0.9
    np.testing.assert_allclose(distance[on_its_face], sampled_at[on_its_face], atol=0.1 * CELL)
    np.testing.assert_allclose(distance, np.maximum(sampled_at, np.abs(off)), atol=0.1 * CELL)
    straight = np.hypot(sampled_at, off)
    assert np.abs(straight - sampled_at)[on_its_face].max() > 0.1 * CELL  # the straight distance would fail


def test_the_curves_of_a_wedge_follow_its_nine_edges_including_the_acute_ridge():
    curves = edge_curves(contour("wedge"), 30.0, 0.02, 0.005)
    truth = wedge_mesh()
    sharp = truth.face_adjacency_angles > np.radians(30)
    segments = truth.vertices[truth.face_adjacency_edges[sharp]]
    assert len(segments) == 9
    on_edges = np.concatenate([a + np.linspace(0, 1, 200)[:, None] * (b - a) for a, b in segments])
    samples = np.concatenate([c.points for c in curves])
    to_curves = np.linalg.norm(on_edges[:, None] - samples[None], axis=2).min(axis=1)
    assert to_curves.max() < 0.2 * CELL  # every edge is found ...
    to_edges = np.linalg.norm(samples[:, None] - on_edges[None], axis=2).min(axis=1)
    assert to_edges.max() < 0.2 * CELL  # ... and nothing else
    assert all(c.convex for c in curves)


def test_a_concave_edge_is_reported_as_concave():
    def l_shape(x):
        return np.minimum(
            box(x - [0, 0, -0.1], np.array([0.3, 0.25, 0.1])), box(x - [-0.15, 0, 0], np.array([0.15, 0.25, 0.2]))
        )

    grid = sample_grid(l_shape, RESOLUTION, LOW, HIGH)
    mesh = dual_contour(grid, l_shape, lambda x: (l_shape(x), gradient(l_shape, x)), sharpen=False)
    curves = edge_curves(mesh, 30.0, 0.02, 0.005)
    concave = [c for c in curves if not c.convex]
    assert len(concave) == 1
    assert concave[0].length == pytest.approx(0.5, abs=0.02)
    assert concave[0].dihedral == pytest.approx(90, abs=2)


def test_edges_json_lists_each_curve_in_order_with_its_angle_and_side():
    import json

    from core.reconstruct import Reconstruction

    mesh = contour("box")
    curves = edge_curves(mesh, 30.0, 0.02, 0.005)
    points = mesh.vertices[:10]
    result = Reconstruction(
        mesh=mesh,
        normals=np.zeros((10, 3)),
        edge_indices=np.array([1, 2]),
        edge_points=points[[1, 2]],
        edge_laplacian=np.array([40.0, 50.0]),
        tau=30.0,
        points=points,
        curves=curves,
    )
    edges = json.loads(result.edges_json())
    assert set(edges) == {"tau", "count", "indices", "points", "laplacian", "curves"}
    assert len(edges["curves"]) == 12 and result.summary()["edge_curves"] == 12
    for written, curve in zip(edges["curves"], curves):
        assert set(written) == {"points", "dihedral", "convex"}
        np.testing.assert_allclose(written["points"], curve.points, atol=1e-6)
        assert written["dihedral"] == pytest.approx(90, abs=3) and written["convex"] is True


def test_folded_vertices_are_a_sharp_folds_and_a_thin_walls_two_sides_and_nothing_on_a_plain_box():
    """What ``_uncross`` tests besides the vertices it moved (a public tray 0.01 thick kept 6
    crossing faces at its rim, all of vertices within 0.16 cells of their means): the vertices of
    a fold sharper than 60° and those facing another side within reach."""
    from core.dual import _folded

    # A sheet folded back on itself: two triangles on an edge along x, their half-planes 30° apart
    # (normals 150° apart).
    angle = np.radians(30)
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, np.cos(angle), np.sin(angle)]], dtype=float)
    folded = _folded(vertices, np.array([[0, 1, 2], [1, 0, 3]]), reach=0.01)
    np.testing.assert_array_equal(folded, [True, True, False, False])
    # A right angle is no fold, and far vertices are not facing.
    vertices[3] = [0.5, 0, 1]
    assert not _folded(vertices, np.array([[0, 1, 2], [1, 0, 3]]), reach=0.01).any()
    # A slab 0.004 thick: its two big faces face each other within reach; a box is left alone.
    slab = trimesh.creation.box([0.4, 0.4, 0.004])
    slab = slab.subdivide().subdivide()
    inner = (np.abs(slab.vertices[:, :2]) < 0.19).all(axis=1)
    assert inner.sum() >= 10 and _folded(slab.vertices, slab.faces, reach=0.01)[inner].all()
    plain = trimesh.creation.box([0.4, 0.4, 0.4]).subdivide().subdivide()
    assert not _folded(plain.vertices, plain.faces, reach=0.01).any()
