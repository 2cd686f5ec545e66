"""core.creases: crease vertices and edge curves moved onto the edge of planes refitted to the points."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from core.creases import (
    ACROSS_REACH,
    ALONG_EDGE,
    HEDGE,
    HELD_GAP,
    MAX_MOVE,
    MAX_RADIUS,
    NORMAL_REACH,
    READ_HEDGE,
    _circle,
    _crease_sides,
    normals_on_faces,
    onto_refitted,
)
from core.curves import Curve, edge_curves
from core.dual import dual_contour
from core.extract import sample_grid
from core.intersections import crossing_faces
from evaluation.metrics import normal_angles
from tests.core.test_dual import HALF, HIGH, LOW, box_mesh, cylinder, gradient

NOISE = 0.005
X, Y, Z = np.eye(3)
# The box of tests.core.test_dual with its +x face turned by TILT about y (through the face's
# centre): what a fit that tilts a face leaves; its +x face's edges at z = ±0.2 lie 0.014 off.
TILT = np.radians(4.0)


def _tilted_box(x: np.ndarray) -> np.ndarray:
    """Signed distance-like function (max of plane distances) of the box with its +x face tilted."""
    planes = [(-X, HALF[0]), (Y, HALF[1]), (-Y, HALF[1]), (Z, HALF[2]), (-Z, HALF[2])]
    tilted = np.array([np.cos(TILT), 0.0, np.sin(TILT)])
    planes.append((tilted, HALF[0] * np.cos(TILT)))
    return np.max([x @ normal - offset for normal, offset in planes], axis=0)


@functools.cache
def tilted_box_mesh() -> trimesh.Trimesh:
    grid = sample_grid(_tilted_box, 64, LOW, HIGH)
    return dual_contour(grid, _tilted_box, lambda x: (_tilted_box(x), gradient(_tilted_box, x)))


def noisy_samples(mesh: trimesh.Trimesh, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points drawn on ``mesh`` with Gaussian noise of NOISE, and the normals (n, 3) of
    the faces they were drawn from (standing in for a fit's normals)."""
    points, faces = trimesh.sample.sample_surface(mesh, count, seed=seed)
    rng = np.random.default_rng(seed)
    return points + rng.normal(0.0, NOISE, points.shape), mesh.face_normals[faces]


def distance_to_box_edges(points: np.ndarray) -> np.ndarray:
    """Distance (n,) from ``points`` to the nearest of the true box's twelve edges."""
    truth = box_mesh()
    edges = truth.face_adjacency_edges[truth.face_adjacency_angles > np.radians(30)]
    a, b = truth.vertices[edges[:, 0]], truth.vertices[edges[:, 1]]
    t = np.clip(np.einsum("pej,ej->pe", points[:, None] - a[None], b - a) / np.einsum("ej,ej->e", b - a, b - a), 0, 1)
    return np.linalg.norm(points[:, None] - (a[None] + t[:, :, None] * (b - a)[None]), axis=2).min(axis=1)


def test_crease_vertices_a_tilted_face_put_off_their_edges_go_back_onto_the_true_edges():
    mesh = tilted_box_mesh()
    points, normals = noisy_samples(box_mesh(), 16384)
    vertex, _, _, _ = _crease_sides(mesh, 30.0)
    before = mesh.vertices[vertex]
    # Along the tilted face's edges at z = ±0.2, away from the corners: 0.014 off at the face's edges.
    far_from_corners = np.abs(before[:, 1]) < HALF[1] - 0.06
    off = far_from_corners & (before[:, 0] > 0.25) & (np.abs(before[:, 2]) > 0.15)
    assert off.sum() >= 20 and np.median(distance_to_box_edges(before[off])) > 0.008

    moved, _ = onto_refitted(mesh, [], 30.0, points, normals)

    after = moved.vertices[vertex]
    assert np.median(distance_to_box_edges(after[off])) < 0.002
    # Near the corners some refits are refused (fewer points on the corner's side); none goes farther
    # off than the refit's own error (vertices exact on the other edges move by up to 0.0025).
    assert np.mean(distance_to_box_edges(after[off]) < 0.004) > 0.9
    assert (distance_to_box_edges(after) <= np.maximum(distance_to_box_edges(before), 0.003)).all()
    # Only two-face crease vertices move, and no farther than MAX_MOVE.
    unmoved = np.setdiff1d(np.arange(len(mesh.vertices)), vertex)
    np.testing.assert_array_equal(moved.vertices[unmoved], mesh.vertices[unmoved])
    assert np.linalg.norm(after - before, axis=1).max() <= MAX_MOVE + 1e-12
    # No face turns over or crosses another.
    assert (np.einsum("ij,ij->i", moved.face_normals, mesh.face_normals) > 0).all()
    assert len(crossing_faces(moved.vertices, moved.faces, np.arange(len(moved.faces)))) == 0


def test_a_dense_cloud_is_read_through_a_draw_of_its_points(monkeypatch):
    # At most CLOUD_POINTS points are searched (the cost of a million-point cloud stays that of a
    # small one), and the draw still brings the tilted face's crease vertices back.
    from core import creases

    searched: list[int] = []
    real_tree = creases.kd_tree

    def kd_tree(points):
        searched.append(len(points))
        return real_tree(points)

    monkeypatch.setattr(creases, "kd_tree", kd_tree)
    monkeypatch.setattr(creases, "CLOUD_POINTS", 8192)
    mesh = tilted_box_mesh()
    points, normals = noisy_samples(box_mesh(), 16384)
    vertex, _, _, _ = _crease_sides(mesh, 30.0)
    before = mesh.vertices[vertex]
    off = (np.abs(before[:, 1]) < HALF[1] - 0.06) & (before[:, 0] > 0.25) & (np.abs(before[:, 2]) > 0.15)

    moved, _ = onto_refitted(mesh, [], 30.0, points, normals)

    assert searched == [8192]
    assert np.median(distance_to_box_edges(moved.vertices[vertex][off])) < 0.002


def test_a_corner_where_three_faces_meet_is_not_a_crease_between_two():
    mesh = tilted_box_mesh()
    vertex, side_a, side_b, convex = _crease_sides(mesh, 30.0)
    corners = trimesh.creation.box(2 * HALF).vertices
    near_corner = np.linalg.norm(mesh.vertices[vertex][:, None] - corners[None], axis=2).min(axis=1) < 0.005
    assert not near_corner.any()
    # Along the edges the two faces are two of the box's six, at 90 degrees (the tilted one within 4).
    along = (np.abs(mesh.vertices[vertex]) < HALF - 0.05).sum(axis=1) == 1
    assert along.sum() > 100
    assert np.abs(np.einsum("ij,ij->i", side_a[along], side_b[along])).max() < np.sin(np.radians(5))
    assert convex.all()


def rim_distance(vertices: np.ndarray) -> np.ndarray:
    """Distance (n,) from ``vertices`` to the rims of the cylinder of tests.core.test_dual."""
    return np.hypot(np.hypot(vertices[:, 0], vertices[:, 1]) - 0.25, np.abs(vertices[:, 2]) - 0.2)


def test_a_curved_faces_rim_mostly_stays_where_it_is():
    # The rims of a cylinder of radius 0.25, exact on the mesh: a plane fitted to its wall meets the
    # cap off the rim. The halves of the wall's points either side of a vertex give planes turned by
    # about 4 degrees, so most refits are refused; the few that pass stay within 0.004 of the rim.
    grid = sample_grid(cylinder, 64, LOW, HIGH)
    mesh = dual_contour(grid, cylinder, lambda x: (cylinder(x), gradient(cylinder, x)))
    points, normals = noisy_samples(trimesh.creation.cylinder(radius=0.25, height=0.4, sections=512), 16384)
    vertex, _, _, _ = _crease_sides(mesh, 30.0)
    assert len(vertex) > 100 and rim_distance(mesh.vertices[vertex]).max() < 0.001

    moved, _ = onto_refitted(mesh, [], 30.0, points, normals)

    changed = (moved.vertices != mesh.vertices).any(axis=1)
    assert changed.sum() <= 0.15 * len(vertex)
    assert rim_distance(moved.vertices[vertex]).max() < 0.004


def straight_curve(
    start: np.ndarray, direction: np.ndarray, left: np.ndarray, right: np.ndarray, convex: bool
) -> Curve:
    """A curve from ``start`` along ``direction``, 0.4 long, sampled every 0.005."""
    t = np.arange(0.0, 0.4 + 1e-9, 0.005)[:, None]
    count = len(t)
    return Curve(start + t * direction, np.tile(left, (count, 1)), np.tile(right, (count, 1)), 90.0, convex)


def face_points(rng: np.random.Generator, origin: np.ndarray, across: np.ndarray, count: int) -> np.ndarray:
    """``count`` points on the face from ``origin`` spanned by ``across`` (2, 3): 0.5 along the
    first, 0.9 along the second."""
    return origin + rng.uniform(0, 1, (count, 2)) * [0.5, 0.9] @ across


def floor_and_wall(seed: int, convex: bool) -> tuple[np.ndarray, np.ndarray, np.random.Generator]:
    """Two faces meeting along the y axis, 8,000 points on each, before noise: the floor z = 0
    (outward +z) and the wall x = 0 (outward +x). Convex: the floor runs to -x and the wall down -z
    (the solid is x < 0, z < 0); concave (an L's inner corner): the floor runs to +x and the wall up
    +z (the solid is all but x > 0, z > 0). With the generator, for the noise."""
    rng = np.random.default_rng(seed)
    sense = -1.0 if convex else 1.0
    floor = face_points(rng, np.array([0.0, -0.45, 0.0]), np.array([sense * X, Y]), 8000)
    wall = face_points(rng, np.array([0.0, -0.45, 0.0]), np.array([sense * Z, Y]), 8000)
    return floor, wall, rng


@pytest.mark.parametrize("convex", [True, False])
def test_a_curve_off_its_edge_goes_onto_the_edge_of_its_faces(convex):
    floor, wall, rng = floor_and_wall(1, convex)
    sense = -1.0 if convex else 1.0
    points = np.vstack([floor, wall]) + rng.normal(0.0, NOISE, (16000, 3))
    normals = np.vstack([np.tile(Z, (8000, 1)), np.tile(X, (8000, 1))])
    # The curve 0.008 off the edge: into empty space at a convex edge, into the solid at a concave one.
    off = sense * -0.008 * (X + Z) / np.sqrt(2)
    curve = straight_curve(np.array([0.0, -0.2, 0.0]) + off, Y, Z, X, convex)

    _, (moved,) = onto_refitted(trimesh.Trimesh(), [curve], 30.0, points, normals)

    assert np.linalg.norm(curve.points[:, [0, 2]], axis=1).min() > 0.0079
    distance = np.linalg.norm(moved.points[:, [0, 2]], axis=1)
    assert np.median(distance) < 0.001 and distance.max() < 0.003  # against noise of 0.005
    np.testing.assert_allclose(moved.points[:, 1], curve.points[:, 1], atol=0.002)
    assert moved.convex == convex and np.array_equal(moved.left, curve.left)


def test_a_curve_with_too_few_points_beside_it_stays():
    curve = straight_curve(np.zeros(3), Y, Z, X, True)
    points = np.array([[0.1, 0.0, 0.0]] * 5)
    _, (same,) = onto_refitted(trimesh.Trimesh(), [curve], 30.0, points, np.tile(Z, (5, 1)))
    np.testing.assert_array_equal(same.points, curve.points)
    assert onto_refitted(trimesh.Trimesh(), [], 30.0, points, np.tile(Z, (5, 1)))[1] == []


@pytest.mark.parametrize("convex", [True, False])
def test_points_beside_an_edge_take_their_faces_normal_and_those_nearer_it_the_nearer_faces_turned_short_of_inward(
    convex,
):
    # The floor and wall, the curve on their edge; the fit's normals lean towards the other face's
    # near the edge, as a fit that rounds it does (convex or concave): by 27 degrees at the edge,
    # 10 at 0.03 from it, 2 at 0.08.
    floor, wall, rng = floor_and_wall(2, convex)
    truth = np.vstack([np.tile(Z, (8000, 1)), np.tile(X, (8000, 1))])
    from_edge = np.concatenate([np.abs(floor[:, 0]), np.abs(wall[:, 2])])  # along the face
    lean = 0.5 * np.exp(-from_edge / 0.03)[:, None]
    fitted = truth + lean * truth[::-1]  # the floor's lean towards +x, the wall's towards +z
    fitted /= np.linalg.norm(fitted, axis=1, keepdims=True)
    points = np.vstack([floor, wall]) + rng.normal(0.0, NOISE, (16000, 3))
    curve = straight_curve(np.array([0.0, -0.2, 0.0]), Y, Z, X, convex)
    middle = np.abs(points[:, 1]) < 0.15
    beside = middle & (from_edge > 0.03) & (from_edge < NORMAL_REACH - 0.01)
    assert normal_angles(fitted[beside], truth[beside]).mean() > 2.0

    result = normals_on_faces(points, fitted, [curve])

    replaced = (result != fitted).any(axis=1)
    assert replaced[beside].mean() > 0.9
    assert normal_angles(result[beside], truth[beside]).mean() < 1.0  # the refitted planes' own error, about 0.4
    # Nearer the edge each point takes a face's normal turned HEDGE towards the other's (the faces
    # are 90 degrees apart): its own face's, or the other's where noise carried it nearer that one,
    # and then still HEDGE short of pointing inward. On the whole the nearer face is the better guess.
    near_edge = middle & (from_edge < 0.02)
    assert near_edge.sum() > 150 and replaced[near_edge].mean() > 0.95
    error = normal_angles(result[near_edge], truth[near_edge])
    assert error.max() < 90.0 - HEDGE / 2
    turned = error[replaced[near_edge]]
    assert np.mean((turned < HEDGE + 1.5) | (turned > 90.0 - HEDGE - 1.5)) > 0.95
    assert error.mean() < normal_angles(fitted[near_edge], truth[near_edge]).mean() - 3.0
    # No point out of reach is touched.
    out_of_reach = np.linalg.norm(points[:, None] - curve.points[None], axis=2).min(axis=1) > NORMAL_REACH
    assert out_of_reach.sum() > 1000 and not replaced[out_of_reach].any()


def test_a_point_beside_an_obtuse_edge_is_told_its_face_by_where_the_faces_end_not_by_their_planes():
    # Two faces meeting at 135 degrees along the y axis (normals 45 degrees apart): the floor z = 0
    # running to -x, and a face running down from the edge at 45 degrees. The floor's plane runs on
    # past the edge right beside the sloping face, so a point of the sloping face near the edge is
    # near the floor's plane as well; the floor itself ends at the edge.
    rng = np.random.default_rng(4)
    down = (X - Z) / np.sqrt(2)
    slope_normal = (X + Z) / np.sqrt(2)
    floor = face_points(rng, np.array([0.0, -0.45, 0.0]), np.array([-X, Y]), 8000)
    slope = face_points(rng, np.array([0.0, -0.45, 0.0]), np.array([down, Y]), 8000)
    truth = np.vstack([np.tile(Z, (8000, 1)), np.tile(slope_normal, (8000, 1))])
    from_edge = np.concatenate([np.abs(floor[:, 0]), slope @ down])
    points = np.vstack([floor, slope]) + rng.normal(0.0, NOISE, (16000, 3))
    fitted = truth + 0.3 * np.exp(-from_edge / 0.03)[:, None] * truth[::-1]  # rounded towards the other face
    fitted /= np.linalg.norm(fitted, axis=1, keepdims=True)
    curve = straight_curve(np.array([0.0, -0.2, 0.0]), Y, Z, slope_normal, True)

    result = normals_on_faces(points, fitted, [curve])

    # From 0.004 to 0.012 off the edge along its face, nine in ten points take their own face's
    # normal (the nearer plane: seven in ten); the rest the other's, 45 degrees off, never inward.
    band = (np.abs(points[:, 1]) < 0.18) & (from_edge > 0.004) & (from_edge < 0.012)
    error = normal_angles(result[band], truth[band])
    assert band.sum() > 60
    assert np.mean(error < 2.0) > 0.85
    assert error.max() < 47.0


def test_points_nearer_a_curve_whose_refit_failed_than_one_where_it_held_keep_the_fits_normals():
    # The convex edge of the test above, and a second curve on the floor 0.06 from it whose other
    # face has no points (so its refit fails): a floor point beside that curve is within reach of
    # the edge's planes, but it lies by another feature than that edge, and keeps its normal.
    floor, wall, rng = floor_and_wall(3, True)
    points = np.vstack([floor, wall]) + rng.normal(0.0, NOISE, (16000, 3))
    tilted = np.array([0.05, 0.0, 1.0]) / np.hypot(0.05, 1.0)  # 2.9 degrees off, across the edges
    fitted = np.vstack([np.tile(tilted, (8000, 1)), np.tile(X, (8000, 1))])
    edge = straight_curve(np.array([0.0, -0.2, 0.0]), Y, Z, X, True)
    elsewhere = straight_curve(np.array([-0.06, -0.2, 0.0]), Y, Z, -X, True)

    result = normals_on_faces(points, fitted, [edge, elsewhere])

    replaced = (result != fitted).any(axis=1)
    middle = np.abs(points[:, 1]) < 0.15
    by_elsewhere = middle & (np.abs(points[:, 0] + 0.06) < 0.01) & (np.abs(points[:, 2]) < 0.01)
    # Floor points nearer the edge than the other curve, or farther by less than HELD_GAP (0.02)
    # and clear of the wall's plane, take the floor's.
    by_edge = middle & (points[:, 0] > -0.06 + HELD_GAP / 2 + 0.01) & (points[:, 0] < -0.022) & (points[:, 2] < 0.01)
    assert by_elsewhere.sum() > 50 and not replaced[by_elsewhere].any()
    assert by_edge.sum() > 50 and replaced[by_edge].mean() > 0.8


def test_points_beside_a_curved_faces_rim_keep_the_fits_normals():
    # A cylinder's rims: a plane fitted to the wall's points is the wall's normal at one place only.
    # Most refits are refused (the wall's points either side along the rim fit planes turned from
    # each other); where one holds, its wall plane is turned along the rim by up to 6 degrees, and
    # a point whose normal leans along the edge by more than ALONG_EDGE keeps it. Given exact
    # normals, none clear of the rim is made worse by more than that and the refitted planes'
    # noise; nearer the rim, where noise may have carried a point nearer the other face, none is
    # given a normal that points inward.
    grid = sample_grid(cylinder, 64, LOW, HIGH)
    mesh = dual_contour(grid, cylinder, lambda x: (cylinder(x), gradient(cylinder, x)))
    curves = edge_curves(mesh, 30.0, 0.02, 0.005)
    assert len(curves) == 2 and all(curve.closed for curve in curves)
    exact = trimesh.creation.cylinder(radius=0.25, height=0.4, sections=512)
    points, normals = noisy_samples(exact, 16384)

    result = normals_on_faces(points, normals, curves)

    error = normal_angles(result, normals)
    to_rim = np.hypot(np.hypot(points[:, 0], points[:, 1]) - 0.25, np.abs(points[:, 2]) - 0.2)
    clear = to_rim > 0.03
    assert error[clear].max() < ALONG_EDGE + 1.0
    assert error.max() < 90.0 - HEDGE / 2
    assert np.median(error[error > 0]) < 1.0


def disc_rim(count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, Curve]:
    """A sector (1 radian) of a disc of radius 0.5 about (3, 0, 0), before noise: ``count`` points
    on its top z = 0 (outward +z) beyond radius 0.2 and as many on its wall down to z = -0.3
    (outward along the radius); their true normals (2 count, 3), their distances from the rim along
    their face (2 count,), and the rim's curve (convex), sampled every 0.005."""
    centre, radius = np.array([3.0, 0.0, 0.0]), 0.5
    top_angle, wall_angle = rng.uniform(-0.5, 0.5, count), rng.uniform(-0.5, 0.5, count)
    top_radius = np.sqrt(rng.uniform(0.2**2, radius**2, count))
    depth = rng.uniform(0.0, 0.3, count)
    top = centre + np.stack([top_radius * np.cos(top_angle), top_radius * np.sin(top_angle), np.zeros(count)], axis=1)
    outward = np.stack([np.cos(wall_angle), np.sin(wall_angle), np.zeros(count)], axis=1)
    wall = centre + radius * outward - depth[:, None] * Z
    truth = np.vstack([np.tile(Z, (count, 1)), outward])
    from_rim = np.concatenate([radius - top_radius, depth])
    along = np.arange(-0.5, 0.5, 0.005 / radius)
    rim_outward = np.stack([np.cos(along), np.sin(along), np.zeros(len(along))], axis=1)
    curve = Curve(centre + radius * rim_outward, np.tile(Z, (len(along), 1)), rim_outward, 90.0, True)
    return np.vstack([top, wall]), truth, from_rim, curve


def test_points_beside_a_rim_too_wide_to_refit_take_their_faces_normal_read_across_it():
    # A disc's rim of radius 0.5 (wider than MAX_RADIUS: no circle is refitted; its wall curves
    # along the rim: no plane is) beside the convex edge of the tests above, whose refit holds and
    # gives the cloud's noise width. The fit's normals lean towards the other face's near both
    # edges, as a fit that rounds them does: halfway (45 degrees) at the edge, 8 at 0.03 from it.
    floor, wall, rng = floor_and_wall(5, True)
    disc, disc_truth, disc_from_rim, rim = disc_rim(6000, rng)
    assert np.linalg.norm(rim.points[0] - rim.points[-1]) > 0.4 and 0.5 > MAX_RADIUS
    truth = np.vstack([np.tile(Z, (8000, 1)), np.tile(X, (8000, 1)), disc_truth])
    from_edge = np.concatenate([np.abs(floor[:, 0]), np.abs(wall[:, 2]), disc_from_rim])
    other = np.vstack([np.tile(X, (8000, 1)), np.tile(Z, (8000, 1)), disc_truth[6000:], np.tile(Z, (6000, 1))])
    fitted = truth + np.exp(-from_edge / 0.015)[:, None] * other
    fitted /= np.linalg.norm(fitted, axis=1, keepdims=True)
    points = np.vstack([floor, wall, disc]) + rng.normal(0.0, NOISE, (len(truth), 3))
    edge = straight_curve(np.array([0.0, -0.2, 0.0]), Y, Z, X, True)

    result = normals_on_faces(points, fitted, [edge, rim])

    on_disc = np.arange(len(points)) >= 16000
    middle = on_disc & (np.abs(np.arctan2(points[:, 1], points[:, 0] - 3.0)) < 0.35)
    # Off the rim along their face, most take their face's normal as the fit has it 0.04 across,
    # past most of its rounding (within 3 degrees; turned to READ_HEDGE short of square with the
    # other face's where within CLEAR noise widths of it): half the fit's error or less, where it
    # leaned 18 degrees.
    beside = middle & (from_edge > 0.01) & (from_edge < ACROSS_REACH - 0.005)
    error, before = normal_angles(result[beside], truth[beside]), normal_angles(fitted[beside], truth[beside])
    assert beside.sum() > 100 and before.mean() > 15.0
    assert (result[beside] != fitted[beside]).any(axis=1).mean() > 0.8
    assert error.mean() < before.mean() / 2
    # None points inward, nearer the rim either (there its nearer face's is turned as far).
    assert normal_angles(result[on_disc], truth[on_disc]).max() < 90.0 - READ_HEDGE / 2
    # Out of every curve's reach, none moves.
    far = on_disc & (from_edge > NORMAL_REACH + 0.02)
    assert far.sum() > 1000 and (result[far] == fitted[far]).all()


def test_without_curves_or_points_to_refit_the_normals_are_the_fits():
    normals = np.tile(Z, (5, 1))
    points = np.array([[0.1, 0.0, 0.0]] * 5)
    assert normals_on_faces(points, normals, []) is normals
    curve = straight_curve(np.zeros(3), Y, Z, X, True)
    np.testing.assert_array_equal(normals_on_faces(points, normals, [curve]), normals)


def test_a_circle_is_fitted_exactly_and_a_line_is_no_circle():
    rng = np.random.default_rng(3)
    centres, radii = rng.uniform(-0.3, 0.3, (20, 2)), rng.uniform(0.02, 0.2, 20)
    angles = rng.uniform(0, 1, (20, 40)) * rng.uniform(0.5, 2 * np.pi, (20, 1))  # arcs of 30° to the whole circle
    x = centres[:, :1] + radii[:, None] * np.cos(angles)
    y = centres[:, 1:] + radii[:, None] * np.sin(angles)
    chosen = rng.uniform(0, 1, (20, 40)) < 0.8  # each row's own subset

    centre_x, centre_y, radius = _circle(x, y, chosen)

    np.testing.assert_allclose(centre_x, centres[:, 0], atol=1e-9)
    np.testing.assert_allclose(centre_y, centres[:, 1], atol=1e-9)
    np.testing.assert_allclose(radius, radii, atol=1e-9)
    t = rng.uniform(-0.2, 0.2, (2, 40))
    _, _, straight = _circle(t, 0.5 * t + 0.1, np.ones((2, 40), dtype=bool))
    assert (straight > 1e3).all()
    _, _, too_few = _circle(x[:1, :2], y[:1, :2], np.ones((1, 2), dtype=bool))
    assert np.isinf(too_few).all()


# A plate 0.1 thick with a hole of radius 0.1 along z through it. The fitted surface the mesh is
# contoured from has the hole's wall bulging into the hole near its top rim, by up to BULGE, as a
# fit's rounding leaves it (l_bracket's holes).
PLATE, HOLE, BULGE = np.array([0.35, 0.35, 0.05]), 0.1, 0.012


def _bulged_plate(x: np.ndarray) -> np.ndarray:
    """A distance-like function (max of the box's and the hole's) of the plate whose hole narrows
    by BULGE at its top rim, fading over 0.04 down the wall."""
    radius = HOLE - BULGE * np.exp(-(((PLATE[2] - x[:, 2]) / 0.04) ** 2))
    return np.maximum(np.abs(x) - PLATE, radius[:, None] - np.hypot(x[:, 0], x[:, 1])[:, None]).max(axis=1)


def plate_samples(count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points on the true plate with its hole (by area), with noise NOISE, and their true
    unit normals."""
    rng = np.random.default_rng(seed)
    areas = {"caps": 2 * (4 * PLATE[0] * PLATE[1] - np.pi * HOLE**2), "wall": 2 * np.pi * HOLE * 2 * PLATE[2]}
    areas["sides"] = 4 * 2 * PLATE[0] * 2 * PLATE[2]
    total = sum(areas.values())
    parts = []
    caps = rng.uniform(-1, 1, (4 * count, 2)) * PLATE[:2]
    caps = caps[np.hypot(caps[:, 0], caps[:, 1]) > HOLE][: round(count * areas["caps"] / total)]
    up = rng.uniform(0, 1, len(caps)) < 0.5
    parts.append((np.c_[caps, np.where(up, PLATE[2], -PLATE[2])], np.c_[0 * caps, np.where(up, 1.0, -1.0)]))
    turn = rng.uniform(0, 2 * np.pi, round(count * areas["wall"] / total))
    height = rng.uniform(-PLATE[2], PLATE[2], len(turn))
    parts.append(
        (np.c_[HOLE * np.cos(turn), HOLE * np.sin(turn), height], np.c_[-np.cos(turn), -np.sin(turn), 0 * turn])
    )
    sides = count - len(caps) - len(turn)
    side = rng.integers(0, 4, sides)
    along, height = rng.uniform(-1, 1, sides) * PLATE[0], rng.uniform(-PLATE[2], PLATE[2], sides)
    normal = np.array([X, -X, Y, -Y])[side]
    spots = normal * PLATE[0] + np.c_[normal[:, 1], normal[:, 0], 0 * along] * along[:, None] + Z * height[:, None]
    parts.append((spots, normal))
    points, normals = (np.concatenate(part) for part in zip(*parts, strict=True))
    return points + rng.normal(0.0, NOISE, points.shape), normals


def distance_to_hole(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (n,) from ``vertices`` to the top rim of the true hole, and to its wall."""
    radial = np.hypot(vertices[:, 0], vertices[:, 1])
    return np.hypot(radial - HOLE, vertices[:, 2] - PLATE[2]), np.abs(radial - HOLE)


def test_a_holes_rim_and_wall_pushed_into_it_by_the_fit_go_back_onto_the_cylinder_of_its_points():
    grid = sample_grid(_bulged_plate, 96, LOW, HIGH)
    mesh = dual_contour(grid, _bulged_plate, lambda x: (_bulged_plate(x), gradient(_bulged_plate, x)))
    points, normals = plate_samples(16384)
    vertex, _, _, _ = _crease_sides(mesh, 30.0)
    before = mesh.vertices
    to_rim, to_wall = distance_to_hole(before)
    rim = vertex[to_rim[vertex] < 0.02]
    # Near the top: the wall's vertices from 0.005 to 0.02 under the rim (within WALL_REACH of it).
    depth = PLATE[2] - before[:, 2]
    wall = np.flatnonzero((depth > 0.005) & (depth < 0.02) & (np.hypot(before[:, 0], before[:, 1]) < HOLE + 0.005))
    assert len(rim) > 30 and np.median(to_rim[rim]) > 0.008
    assert len(wall) > 40 and np.median(to_wall[wall]) > 0.006

    moved, _ = onto_refitted(mesh, [], 30.0, points, normals)

    to_rim, to_wall = distance_to_hole(moved.vertices)
    assert np.median(to_rim[rim]) < 0.002 and np.mean(to_rim[rim] < 0.004) > 0.9
    assert np.median(to_wall[wall]) < 0.002 and np.mean(to_wall[wall] < 0.004) > 0.9

    # The bottom rim, where the fit was not off, stays on it; no face turns over or crosses another.
    def to_bottom(vertices: np.ndarray) -> np.ndarray:
        return np.hypot(np.hypot(vertices[:, 0], vertices[:, 1]) - HOLE, vertices[:, 2] + PLATE[2])

    bottom = vertex[to_bottom(before[vertex]) < 0.01]
    assert len(bottom) > 10
    assert (to_bottom(moved.vertices[bottom]) <= np.maximum(to_bottom(before[bottom]), 0.003)).all()
    faces = np.flatnonzero(mesh.area_faces > 0)  # the contouring leaves a few faces of no area here
    assert (np.einsum("ij,ij->i", moved.face_normals[faces], mesh.face_normals[faces]) > 0).all()
    assert len(crossing_faces(moved.vertices, moved.faces, np.arange(len(moved.faces)))) == 0


def test_points_beside_a_holes_rim_take_the_normal_of_the_plate_or_of_its_wall():
    # The fit's normals near the top rim lean 20 degrees towards the other face on either side, as a
    # rounding leaves them; the points there take their face's normal, as those beside a straight
    # edge do, from where they lie clearly nearer one face than the other (CLEAR noise widths:
    # about 0.02 from the rim here).
    grid = sample_grid(_bulged_plate, 96, LOW, HIGH)
    mesh = dual_contour(grid, _bulged_plate, lambda x: (_bulged_plate(x), gradient(_bulged_plate, x)))
    points, truth = plate_samples(16384)
    mesh, curves = onto_refitted(mesh, edge_curves(mesh, 30.0, 0.02, 0.005), 30.0, points, truth)
    to_rim, _ = distance_to_hole(points)
    band = (to_rim > 0.025) & (to_rim < 0.05)
    radial = np.c_[points[:, :2], 0 * points[:, 2]] / np.hypot(points[:, 0], points[:, 1])[:, None]
    on_wall = np.abs(truth[:, 2]) < 0.5
    towards_other = np.where(on_wall[:, None], Z, -radial)  # from the wall up, from the top into the hole
    lean = np.radians(20.0) * band
    fit = truth * np.cos(lean)[:, None] + towards_other * np.sin(lean)[:, None]
    assert np.mean(normal_angles(fit[band], truth[band])) > 19.0

    result = normals_on_faces(points, fit, curves)

    # Against the normal of the true surface where it is nearest each noisy point (on the wall the
    # true normal of a point's own place is up to a few degrees off that: its noise along the wall
    # over the radius, 0.005 / 0.1).
    nearest = np.where(on_wall[:, None], -radial, Z)
    error = normal_angles(result, nearest)
    assert band.sum() > 300 and np.mean(error[band] < 2.0) > 0.9
    far = cKDTree(np.concatenate([curve.points for curve in curves])).query(points)[0] > NORMAL_REACH
    assert far.sum() > 1000
    np.testing.assert_array_equal(result[far], fit[far])
