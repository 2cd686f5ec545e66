"""core.corners: corners found where three faces' edges meet, and the mesh's rounding put back on them."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import trimesh

from core.corners import (
    BEYOND_REACH,
    SNAP_RADIUS,
    Corner,
    _beyond_onto_faces,
    _corner_of_points,
    _onto_faces,
    _refitted,
    corners,
    extend_to_corners,
    snap_corners,
)
from core.curves import Curve, edge_curves
from core.dual import dual_contour
from core.extract import sample_grid
from core.features import unit
from core.intersections import crossing_faces
from evaluation.metrics import distance_to_mesh, sample_surface
from tests.core.test_dual import HALF, HIGH, IDENTITY, LOW, ROTATION, box, box_mesh, gradient

JOIN = 0.05
APEX = np.array([0.1, 0.2, 0.3])
X, Y, Z = np.eye(3)


def edge(direction: np.ndarray, left: np.ndarray, right: np.ndarray, convex: bool = True, start: float = 0.03) -> Curve:
    """A straight curve leaving APEX along ``direction``, from ``start`` to 0.2 away, sampled every
    0.005, with the given side normals."""
    t = np.arange(start, 0.2 + 1e-9, 0.005)[:, None]
    count = len(t)
    return Curve(APEX + t * direction, np.tile(left, (count, 1)), np.tile(right, (count, 1)), 90.0, convex)


def closed(curve: Curve) -> Curve:
    """``curve`` with its first sample repeated at its end: a loop."""
    return Curve(
        *(np.vstack([a, a[:1]]) for a in (curve.points, curve.left, curve.right)), curve.dihedral, curve.convex
    )


def cube_corner(convex: bool = True) -> list[Curve]:
    """The three edges of a box's corner at APEX (faces x, y and z = APEX's), each stopping 0.03
    short of it, as the extraction leaves them."""
    return [edge(-X, Y, Z, convex), edge(-Y, Z, X, convex), edge(-Z, X, Y, convex)]


def test_three_edges_ending_near_one_point_meet_at_their_faces_corner():
    (corner,) = corners(cube_corner(), JOIN)
    np.testing.assert_allclose(corner.point, APEX, atol=1e-12)
    # The planes face so that the solid of a convex corner is inside all three.
    assert (corner.normals @ (APEX - 0.01) <= corner.offsets).all()
    assert not (corner.normals @ (APEX + 0.01) <= corner.offsets).any()


def test_a_concave_corner_has_its_planes_turned_to_the_empty_side():
    (corner,) = corners(cube_corner(convex=False), JOIN)
    np.testing.assert_allclose(corner.point, APEX, atol=1e-12)
    assert (corner.normals @ (APEX + 0.01) <= corner.offsets).all()


def saddle(odd_convex: bool = False) -> list[Curve]:
    """The end (y = APEX's) of a bar with a step cut along it, at APEX: the step's wall (x = APEX's)
    meets its floor (z = APEX's) on a concave edge, and the end face the two on convex edges; from
    APEX the solid is (x <= 0 or z <= 0) and y <= 0. With ``odd_convex`` the same surface turned
    inside out: the faces' normals turned, the edges' kinds swapped. Each edge stops 0.03 short of
    APEX."""
    sign = -1.0 if odd_convex else 1.0
    return [
        edge(-Y, sign * X, sign * Z, convex=odd_convex),
        edge(Z, sign * X, sign * Y, convex=not odd_convex),
        edge(X, sign * Z, sign * Y, convex=not odd_convex),
    ]


@pytest.mark.parametrize("odd_convex", [False, True])
def test_a_saddle_where_a_concave_edge_meets_two_convex_ones_is_a_corner(odd_convex):
    (corner,) = corners(saddle(odd_convex), JOIN)
    np.testing.assert_allclose(corner.point, APEX, atol=1e-12)
    # The end face is the one apart: its two edges are alike.
    assert corner.apart is not None and abs(corner.normals[corner.apart] @ Y) > 0.999
    # Its region is the solid where the odd edge is concave, the empty space where it is convex:
    # the bar's solid both times (turned inside out, that is the empty space), here tried 0.01 off
    # every face on either side.
    offsets = np.array([[-1, -1, 1], [1, -1, -1], [-1, -1, -1], [1, -1, 1], [-1, 1, -1], [1, 1, 1]]) * 0.01
    bar = ((offsets[:, 0] <= 0) | (offsets[:, 2] <= 0)) & (offsets[:, 1] <= 0)
    np.testing.assert_array_equal(corner.region(corner.inside(APEX + offsets)), bar)


def step_faces(rng: np.random.Generator, count: int = 600) -> np.ndarray:
    """Points (about 3 * count / 2, 3) with noise 0.002 on the three faces of ``saddle``'s step
    within 0.15 of APEX: the wall (x = 0, z > 0), the floor (z = 0, x > 0), both for y < 0, and the
    end face (y = 0) where x < 0 or z < 0, all from APEX."""
    u, v = rng.uniform(-0.15, 0.15, (2, 3, count))
    wall = np.stack([0 * u[0], -np.abs(u[0]), np.abs(v[0])], 1)
    floor = np.stack([np.abs(u[1]), -np.abs(v[1]), 0 * u[1]], 1)
    end = np.stack([u[2], 0 * u[2], v[2]], 1)
    end = end[(end[:, 0] < 0) | (end[:, 2] < 0)]
    faces = np.concatenate([wall, floor, end])
    return APEX + faces + rng.normal(0.0, 0.002, faces.shape)


def test_a_saddle_is_kept_only_where_its_planes_refit_to_the_points():
    # On a small hole's rim, strips of the wall between the fit's creases pass for two faces of a
    # saddle in the curves; the points there do not lie on such planes.
    rng = np.random.default_rng(0)
    on_faces = step_faces(rng)
    (corner,) = corners(saddle(), JOIN, on_faces, np.zeros_like(on_faces))
    np.testing.assert_allclose(corner.point, APEX, atol=0.002)
    elsewhere = APEX + rng.normal(0.0, 0.002, (900, 3)) + [0.5, 0.5, 0.5]  # no face of it near
    assert corners(saddle(), JOIN, elsewhere, np.zeros_like(elsewhere)) == []


def test_a_point_by_a_saddle_goes_onto_the_nearest_of_its_faces():
    (corner,) = corners(saddle(), JOIN)
    # In the solid by the wall's convex edge with the end face, nearer the end face: onto it, not
    # onto the wall's plane, which runs inside the solid there (below the step's floor).
    inside = APEX + np.array([-0.004, -0.002, -0.05])
    np.testing.assert_allclose(_onto_faces(inside, corner), APEX + [-0.004, 0.0, -0.05], atol=1e-12)
    # In the step's empty corner by its concave edge, nearer the floor: onto the floor.
    slot = APEX + np.array([0.006, -0.05, 0.002])
    np.testing.assert_allclose(_onto_faces(slot, corner), APEX + [0.006, -0.05, 0.0], atol=1e-12)
    # Beyond the end face, over the step: onto the wall's edge with the end face, the nearest.
    out = APEX + np.array([0.003, 0.003, 0.02])
    np.testing.assert_allclose(_onto_faces(out, corner), APEX + [0.0, 0.0, 0.02], atol=1e-12)


SLOT_CENTRE, SLOT_HALF = np.array([0.0, 0.0, -HALF[2]]), np.array([HALF[0] + 0.1, 0.08, 0.1])
# Where the slot's walls meet its top at the bar's two ends.
SADDLES = np.array([[x * HALF[0], y * SLOT_HALF[1], SLOT_HALF[2] - HALF[2]] for x in (-1, 1) for y in (-1, 1)])


def slotted(x: np.ndarray) -> np.ndarray:
    """The box with a slot 0.16 wide and 0.1 deep cut along x through its base (as the wedge's):
    at each end of the slot its concave edges meet the end face's convex ones, four saddles."""
    return np.maximum(box(x), -box(x - SLOT_CENTRE, SLOT_HALF))


@functools.cache
def slotted_bar() -> tuple[trimesh.Trimesh, list[Curve]]:
    """The slotted bar dual-contoured with sharpening at 160 cells, and its curves."""
    grid = sample_grid(slotted, 160, LOW, HIGH)
    mesh = dual_contour(grid, slotted, lambda x: (slotted(x), gradient(slotted, x)), sharpen=True)
    return mesh, edge_curves(mesh, 30.0, 0.02, 0.005)


def test_a_slotted_bars_saddles_are_found_and_vertices_pushed_off_them_go_back():
    mesh, curves = slotted_bar()
    saddles = [corner for corner in corners(curves, JOIN) if corner.apart is not None]
    assert len(saddles) == 4
    assert max(np.linalg.norm(SADDLES - corner.point, axis=1).min() for corner in saddles) < 0.002
    # The vertices within 0.04 of one saddle pushed by up to 0.017 along one diagonal, into the
    # slot and past the end face, up to 0.01 off its faces (into the solid by the slot's top): those
    # go back onto its faces, half or a quarter of the way where a face would fold (as at a convex
    # corner, test_vertices_pushed_past_a_corners_faces_go_back_onto_them).
    reach = np.linalg.norm(mesh.vertices - SADDLES[3], axis=1)
    pushed = mesh.copy()
    direction = unit(np.array([[1.0, -1.0, -1.0]]))
    pushed.vertices = mesh.vertices + 0.017 * np.clip(1.0 - reach / 0.04, 0.0, None)[:, None] * direction
    snapped, _ = snap_corners(pushed, curves, JOIN)
    before, after = np.abs(slotted(pushed.vertices)), np.abs(slotted(snapped.vertices))
    assert before.max() > 0.0095 and np.count_nonzero(before > 0.002) > 80
    assert after.max() < 0.0051 and np.count_nonzero(after > 0.002) <= 15
    assert len(crossing_faces(snapped.vertices, snapped.faces, np.arange(len(snapped.faces)))) == 0


def test_the_ends_along_an_edge_shorter_than_twice_the_join_are_read_one_by_one():
    # The saddle above with a top face 0.1 over the step's floor: the wall meets it and the end
    # face at a convex corner, TOP, at the wall's other end. The wall's edge with the end face
    # comes out in two pieces, whose ends link both corners' ends into one group; its centre, half
    # way up the wall, sees the floor's and the top's edges alike and no corner.
    top = APEX + 0.1 * Z
    notch, _, floor_end = saddle()  # the wall's edge with the end face in pieces instead
    pieces = [
        Curve(APEX + t[:, None] * Z, np.tile(X, (len(t), 1)), np.tile(Y, (len(t), 1)), 90.0, True)
        for t in (np.arange(0.03, 0.045 + 1e-9, 0.005), np.arange(0.055, 0.07 + 1e-9, 0.005))
    ]
    top_edges = [
        Curve(top - t[:, None] * axis, np.tile(Z, (len(t), 1)), np.tile(side, (len(t), 1)), 90.0, True)
        for axis, side in ((X, Y), (Y, X))
        for t in [np.arange(0.03, 0.2 + 1e-9, 0.005)]
    ]
    found = corners([notch, floor_end, *pieces, *top_edges], JOIN)
    points = sorted((tuple(corner.point), corner.apart is not None) for corner in found)
    assert len(points) == 2
    np.testing.assert_allclose(points[0][0], APEX, atol=1e-12)
    np.testing.assert_allclose(points[1][0], top, atol=1e-12)
    assert [saddle_ for _, saddle_ in points] == [True, False]


def test_no_corner_where_the_ends_lie_farther_apart_than_the_join():
    curves = [edge(-X, Y, Z, start=0.03), edge(-Y, Z, X, start=0.09), edge(-Z, X, Y, start=0.09)]
    assert corners(curves, JOIN) == []


def test_two_pieces_of_one_edge_are_no_corner():
    curves = [edge(-X, Y, Z, start=0.03), edge(X, Y, Z, start=0.03)]  # the same line, two faces
    assert corners(curves, JOIN) == []


def test_a_holes_rim_broken_in_two_is_no_corner():
    # The rim of a hole of radius 0.05 in a plate's top: the wall's normal turns all round, so its
    # samples fall into several sets of normals, but every edge among them joins the top to the
    # wall; no three faces meet pairwise.
    angle = np.linspace(0.2, 2 * np.pi - 0.2, 120)
    radial = np.stack([np.cos(angle), np.sin(angle), np.zeros_like(angle)], axis=1)
    points = 0.05 * radial
    pieces = [slice(0, 60), slice(60, 120)]
    curves = [Curve(points[p], -radial[p], np.tile(Z, (len(angle[p]), 1)), 90.0, True) for p in pieces]
    assert corners(curves, JOIN) == []


def test_ends_chained_round_a_ring_wider_than_the_reach_are_no_corner():
    # Sixteen short curves whose ends lie 0.04 apart round a ring of radius 0.1: one group of ends
    # whose centre (the ring's) is farther than CORNER_REACH from every sample.
    curves = []
    for angle in np.arange(16) * 2 * np.pi / 16:
        out = np.array([np.cos(angle), np.sin(angle), 0.0])
        points = np.outer([0.1, 0.105, 0.11], out)
        curves.append(Curve(points, np.tile(Z, (3, 1)), np.tile(out, (3, 1)), 90.0, True))
    assert corners(curves, JOIN) == []


def test_loops_have_no_ends():
    assert corners([], JOIN) == []
    loop = closed(edge(-X, Y, Z))
    assert corners([loop, loop], JOIN) == []


def cross(mesh: trimesh.Trimesh) -> np.ndarray:
    """Each face's (f, 3) unnormalised normal."""
    corner = mesh.vertices[mesh.faces]
    return np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])


def test_curves_are_carried_on_to_the_corner_their_faces_meet_at():
    curves = cube_corner()
    stray = edge(X, Y, -Y, start=0.02)  # ends as near, but its faces are not the corner's
    extended = extend_to_corners([*curves, stray], corners(curves, JOIN), JOIN, 0.005)
    for before, after in zip(curves, extended[:3]):
        np.testing.assert_allclose(after.points[0], APEX, atol=1e-12)  # each started 0.03 short
        np.testing.assert_array_equal(after.points[-len(before.points) :], before.points)
        assert np.linalg.norm(np.diff(after.points, axis=0), axis=1).max() <= 0.005 + 1e-12
        assert len(after.left) == len(after.right) == len(after.points)
        np.testing.assert_array_equal(after.left[0], before.left[0])
    np.testing.assert_array_equal(extended[3].points, stray.points)
    loop = closed(edge(-X, Y, Z))
    (kept,) = extend_to_corners([loop], corners(curves, JOIN), JOIN, 0.005)
    np.testing.assert_array_equal(kept.points, loop.points)


@functools.cache
def rounded_box(rotation_name: str, radius: float) -> tuple[trimesh.Trimesh, list[Curve], trimesh.Trimesh]:
    """A box rounded by ``radius`` (as a fit rounds one), dual-contoured with sharpening at 160
    cells, its curves, and the true box."""
    rotation = {"aligned": IDENTITY, "rotated": ROTATION}[rotation_name]
    f = functools.partial(box, rotation=rotation, radius=radius)
    grid = sample_grid(f, 160, LOW, HIGH)
    mesh = dual_contour(grid, f, lambda x: (f(x), gradient(f, x)), sharpen=True)
    return mesh, edge_curves(mesh, 30.0, 0.02, 0.005), box_mesh(rotation)


@pytest.mark.parametrize("rotation", ["aligned", "rotated"])
def test_the_corners_found_on_a_rounded_box_are_its_corners(rotation):
    # Rounded by 0.03, wider than the sharpening brings back: the curves stop short of the corners.
    _, curves, truth = rounded_box(rotation, 0.03)
    found = np.array([corner.point for corner in corners(curves, JOIN)])
    assert len(found) >= 7  # of 8 (the rotated box's curves miss one)
    to_truth = np.linalg.norm(found[:, None] - truth.vertices[None], axis=2).min(axis=1)
    assert to_truth.max() < 0.003
    assert len(np.unique(np.round(found, 2), axis=0)) == len(found)  # one per corner


def test_snapping_puts_a_rounded_boxs_corners_back_on_the_mesh():
    mesh, curves, truth = rounded_box("aligned", 0.03)
    before = distance_to_mesh(truth.vertices, mesh.vertices, mesh.faces)
    snapped, found = snap_corners(mesh, curves, JOIN)
    after = distance_to_mesh(truth.vertices, snapped.vertices, snapped.faces)
    assert len(found) == 8
    assert before.min() > 0.011  # about 0.73 r of the rounding: the sharpening does not put them back
    assert after.max() < 0.002
    np.testing.assert_array_equal(snapped.faces, mesh.faces)
    assert snapped.is_watertight and snapped.is_winding_consistent and snapped.volume > 0
    # The faces kept their side: none turned over against the unsnapped mesh (whose dual
    # contouring leaves a few slivers of no area, which have no side).
    before, after = cross(mesh), cross(snapped)
    sided = np.linalg.norm(before, axis=1) > 0
    assert (np.einsum("ij,ij->i", before[sided], after[sided]) > 0).all()
    # Away from the corners (farther than BEYOND_REACH, within which vertices beyond a corner's
    # faces go onto them) nothing moved.
    far = np.linalg.norm(mesh.vertices[:, None] - truth.vertices[None], axis=2).min(axis=1) > BEYOND_REACH + 0.005
    np.testing.assert_array_equal(snapped.vertices[far], mesh.vertices[far])
    # No face goes through or touches another, in memory or as an OBJ file writes it.
    for vertices in (snapped.vertices, np.round(snapped.vertices, 8)):
        assert len(crossing_faces(vertices, snapped.faces, np.arange(len(snapped.faces)))) == 0


def test_a_rounded_boxs_curves_reach_its_corners():
    # Its twelve edges are 6.0 long; their curves (faces at 90 degrees; the rest are creases of the
    # rounded corners' own facets) stop short of every corner until carried on.
    _, curves, truth = rounded_box("aligned", 0.03)
    extended = extend_to_corners(curves, corners(curves, JOIN), JOIN, 0.005)

    def edges_length(some: list[Curve]) -> float:
        return sum(curve.length for curve in some if abs(curve.dihedral - 90) < 10)

    assert edges_length(curves) < 5.4 and edges_length(extended) == pytest.approx(6.0, abs=0.01)
    ends = np.array([end for curve in extended for end in (curve.points[0], curve.points[-1])])
    at_corners = np.linalg.norm(ends[:, None] - truth.vertices[None], axis=2).min(axis=1) < 0.002
    assert np.count_nonzero(at_corners) == 24  # three edges at each of the eight corners


def test_a_sharp_boxs_mesh_stays_where_it_is():
    # Dual contouring of the exact box already has its corners: whatever is found is a true corner,
    # and only vertices near the corners move, by a quarter of a cell at most (0.0017: a corner's
    # own vertex onto the exact corner), those off the corner's faces by far less.
    mesh, curves, truth = rounded_box("aligned", 0.0)
    snapped, found = snap_corners(mesh, curves, JOIN)
    for corner in found:
        assert np.linalg.norm(truth.vertices - corner.point, axis=1).min() < 0.001
    move = np.linalg.norm(snapped.vertices - mesh.vertices, axis=1)
    assert move.max() < 0.26 * 1.1 / 160
    to_corner = np.linalg.norm(snapped.vertices[:, None] - truth.vertices[None], axis=2).min(axis=1)
    # Within SNAP_RADIUS of a corner found (which is within 0.001 of a true one), or within
    # BEYOND_REACH and off a face by a hair (a seventh of a cell at most).
    assert (to_corner[move > 0] <= BEYOND_REACH + 0.001).all()
    assert move[to_corner > SNAP_RADIUS + 0.001].max() < 0.001
    assert distance_to_mesh(truth.vertices, snapped.vertices, snapped.faces).max() < 0.001


@pytest.mark.parametrize("convex", [True, False])
def test_vertices_pushed_past_a_corners_faces_go_back_onto_them(convex):
    # The sharp box, or the same surface turned inside out (a pocket's concave corners), with the
    # vertices around its corner at HALF pushed out along the diagonal by up to 0.01, as the
    # sharpening pushed them at octagon_pocket's pocket corners: out of the solid of the convex
    # corner, into that of the concave one. Several go onto the corner's point or its edges, and
    # the faces between them would collapse, so those go back only half or a quarter of the way.
    mesh, _, truth = rounded_box("aligned", 0.0)
    if not convex:
        mesh = trimesh.Trimesh(mesh.vertices, mesh.faces[:, ::-1], process=False)
    curves = edge_curves(mesh, 30.0, 0.02, 0.005)
    assert all(curve.convex == convex for curve in curves)
    reach = np.linalg.norm(mesh.vertices - HALF, axis=1)
    pushed = mesh.copy()
    pushed.vertices = mesh.vertices + 0.01 * np.clip(1.0 - reach / 0.04, 0.0, None)[:, None] * unit(HALF[None])
    before = distance_to_mesh(pushed.vertices, truth.vertices, truth.faces)
    snapped, found = snap_corners(pushed, curves, JOIN)
    after = distance_to_mesh(snapped.vertices, truth.vertices, truth.faces)
    assert before.max() > 0.0095 and np.count_nonzero(before > 0.002) > 30
    assert after.max() < 0.0051 and np.count_nonzero(after > 0.002) <= 12
    assert any(np.linalg.norm(corner.point - HALF) < 0.001 for corner in found)
    # The faces kept their side (but slivers of dual contouring of a thousandth of a cell's area, which
    # a vertex put back by the crossing check can turn), and none goes through or touches another.
    sided = np.linalg.norm(cross(pushed), axis=1) > 1e-7
    assert (np.einsum("ij,ij->i", cross(pushed)[sided], cross(snapped)[sided]) > 0).all()
    assert len(crossing_faces(snapped.vertices, snapped.faces, np.arange(len(snapped.faces)))) == 0


def test_the_points_keep_most_vertices_on_the_surface_where_a_corners_planes_are_off():
    # The sharp box's corner at HALF, its planes tilted by 8 degrees (as a small facet's curves
    # can give them): part of the true faces lies beyond them. Without the input points 74 of those
    # vertices go onto the tilted planes, more than 0.002 off the surface; with points on the true
    # box a move must bring a vertex nearer them, which the mean distance to 16 of them tells
    # but along an edge, where it is shortest a little inside (6 went).
    mesh, _, truth = rounded_box("aligned", 0.0)
    normals = np.array([tilted(X, Y, 8.0), tilted(Y, Z, 8.0), tilted(Z, X, 8.0)])
    off = Corner(HALF, normals, normals @ HALF)
    blind = _beyond_onto_faces(np.asarray(mesh.vertices), mesh.faces, [off], JOIN)
    points = sample_surface(truth.vertices, truth.faces, 20_000, 0)
    kept = _beyond_onto_faces(np.asarray(mesh.vertices), mesh.faces, [off], JOIN, points)
    off_blind = distance_to_mesh(blind, truth.vertices, truth.faces)
    off_kept = distance_to_mesh(kept, truth.vertices, truth.faces)
    assert np.count_nonzero(off_blind > 0.002) > 50
    assert np.count_nonzero(off_kept > 0.002) <= 10
    assert off_kept.max() < 0.004 < off_blind.max()


def noisy_points(mesh: trimesh.Trimesh, count: int = 16_384, noise: float = 0.005, seed: int = 0) -> np.ndarray:
    """``count`` points drawn uniformly on ``mesh``'s surface, with Gaussian noise of ``noise`` per
    coordinate, as the sample data are made."""
    points = sample_surface(mesh.vertices, mesh.faces, count, seed)
    return points + np.random.default_rng(seed).normal(0.0, noise, points.shape)


def tilted(normal: np.ndarray, axis: np.ndarray, degrees: float) -> np.ndarray:
    """``normal`` turned by ``degrees`` about ``axis``."""
    return trimesh.transformations.rotation_matrix(np.radians(degrees), axis)[:3, :3] @ normal


def test_planes_tilted_by_the_rounding_are_refitted_to_the_points_of_their_faces():
    # The corner of the box at HALF (faces x, y, z = HALF's), read from planes each tilted by 8
    # degrees and 0.008 off, as the side normals of a knot of short curves give them.
    truth = box_mesh()
    normals = np.array([tilted(X, Y, 8.0), tilted(Y, Z, -8.0), tilted(Z, X, 8.0)])
    offsets = normals @ HALF + np.array([0.008, -0.008, 0.008])
    off = Corner(np.linalg.solve(normals, offsets), normals, offsets)
    assert np.linalg.norm(off.point - HALF) > 0.01
    refitted = _refitted(off, noisy_points(truth), JOIN)
    assert np.linalg.norm(refitted.point - HALF) < 0.003
    assert np.degrees(np.arccos(np.einsum("ij,ij->i", refitted.normals, np.eye(3)))).max() < 2.0  # of the faces'
    # Oriented as before (the side the fit rounds it from), and through the corner it gives.
    assert (np.einsum("ij,ij->i", refitted.normals, normals) > 0).all()
    np.testing.assert_allclose(refitted.normals @ refitted.point, refitted.offsets, atol=1e-12)


def test_a_concave_corners_planes_are_refitted_on_the_empty_side():
    # A pocket's corner at the origin: its floor z = 0 and walls x = 0 and y = 0 bound the empty
    # quarter x, y < 0, z > 0, so its planes face the empty side (n.x <= offset there), as
    # _meeting_point orients them; each read tilted by 8 degrees and 0.008 off, as at
    # octagon_pocket's pocket corners.
    rng = np.random.default_rng(1)
    u, v = rng.uniform(0.0, 0.2, (2, 3, 1500))
    faces = [
        np.stack([-u[0], -v[0], 0 * u[0]], 1),
        np.stack([0 * u[1], -v[1], u[1]], 1),
        np.stack([-u[2], 0 * u[2], v[2]], 1),
    ]
    points = np.concatenate(faces) + rng.normal(0.0, 0.005, (4500, 3))
    normals = np.array([tilted(-Z, X, 8.0), tilted(X, Y, -8.0), tilted(Y, Z, 8.0)])
    offsets = np.array([0.008, -0.008, 0.008])
    off = Corner(np.linalg.solve(normals, offsets), normals, offsets)
    assert np.linalg.norm(off.point) > 0.01
    refitted = _refitted(off, points, JOIN)
    assert np.linalg.norm(refitted.point) < 0.003
    assert np.degrees(np.arccos(np.einsum("ij,ij->i", refitted.normals, np.array([-Z, X, Y])))).max() < 2.0


def test_a_corner_with_a_face_the_points_do_not_show_is_kept():
    # Points on two of the corner's faces only (its z face left unsampled, as an open cloud's).
    truth = box_mesh()
    points = noisy_points(truth)
    points = points[points[:, 2] < HALF[2] - 0.03]
    corner = Corner(HALF + 0.004, np.eye(3), HALF + 0.004)
    assert _refitted(corner, points, JOIN) is corner


def test_snapping_with_the_points_puts_a_rounded_boxs_corners_back_as_well():
    # Its curves already give the corners to within 0.003 (the test above): read from the noisy
    # points of the faces instead, they stay within the noise.
    mesh, curves, truth = rounded_box("aligned", 0.03)
    snapped, found = snap_corners(mesh, curves, JOIN, noisy_points(truth))
    assert len(found) == 8
    to_truth = np.linalg.norm(np.array([c.point for c in found])[:, None] - truth.vertices[None], axis=2).min(axis=1)
    assert to_truth.max() < 0.005
    assert distance_to_mesh(truth.vertices, snapped.vertices, snapped.faces).max() < 0.005
    assert snapped.is_watertight and snapped.is_winding_consistent and snapped.volume > 0
    assert len(crossing_faces(snapped.vertices, snapped.faces, np.arange(len(snapped.faces)))) == 0


# A wedge whose ridge (x = 0, z = 0.5, |y| <= 0.3) is as acute as the sample wedge's: its two
# slanted faces meet at 26 degrees through the solid.
WEDGE = trimesh.convex.convex_hull(
    np.array([[x, y, z] for y in (-0.3, 0.3) for x, z in ((-0.233, -0.5), (0.233, -0.5), (0.0, 0.5))])
)
TIP = np.array([0.0, -0.3, 0.5])


def fit_normals(mesh: trimesh.Trimesh, points: np.ndarray, rounding: float = 0.01) -> np.ndarray:
    """Unit normals (n, 3) at ``points`` as a fit that rounds ``mesh``'s edges gives them: the
    normal of the plane of ``mesh`` nearest to each point, and within ``rounding`` of two planes,
    their mean."""
    normals, offsets = mesh.face_normals, np.einsum("ij,ij->i", mesh.face_normals, mesh.triangles[:, 0])
    distance = np.abs(points @ normals.T - offsets)  # (n, f): to each face's plane
    order = np.argsort(distance, axis=1)
    first = normals[order[:, 0]]
    second = normals[order[:, 1]]
    same_plane = np.einsum("ij,ij->i", first, second) > 1 - 1e-9
    rounded = ~same_plane & (distance[np.arange(len(points)), order[:, 1]] < rounding)
    blended = first + np.where(rounded[:, None], second, 0.0)
    return blended / np.linalg.norm(blended, axis=1, keepdims=True)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_an_acute_ridges_tip_is_found_from_the_points_of_its_faces(seed):
    # Read from around the ends of the ridge's curves, which the extraction stops 0.03 or more short.
    points = noisy_points(WEDGE, seed=seed)
    centre = TIP + np.array([0.0, 0.04, -0.08])
    corner = _corner_of_points(centre, centre[None], points, fit_normals(WEDGE, points))
    assert corner is not None
    assert np.linalg.norm(corner.point - TIP) < 0.008
    true_normals = WEDGE.face_normals[
        np.abs(WEDGE.face_normals @ TIP - np.einsum("ij,ij->i", WEDGE.face_normals, WEDGE.triangles[:, 0])) < 1e-9
    ]
    angles = np.degrees(np.arccos(np.clip(corner.normals @ np.unique(np.round(true_normals, 9), axis=0).T, -1, 1)))
    # Each plane one of the tip's three faces' (the end face, a thin triangle there, has few points).
    assert (angles.min(axis=1) < 4.0).all()
    # A convex corner: its planes face out, the solid inside all three.
    assert (corner.normals @ WEDGE.center_mass < corner.offsets).all()
    np.testing.assert_allclose(corner.normals @ corner.point, corner.offsets, atol=1e-12)


def test_a_ridge_whose_curves_show_two_faces_gets_its_tip_from_the_points():
    # The acute ridge comes out as two creases a strip apart (the strip's normal between the
    # slanted faces'), stopping 0.03 short of the tip; the end face's edges are not found.
    slant_left, slant_right = unit(np.array([[-1.0, 0.0, 0.233], [1.0, 0.0, 0.233]]))
    strip = unit((slant_left + slant_right)[None])[0]
    y = np.arange(-0.27, 0.0, 0.005)[:, None]
    ridge = [
        Curve(np.hstack([x + 0 * y, y, 0.49 + 0 * y]), np.tile(a, (len(y), 1)), np.tile(b, (len(y), 1)), 75.0, True)
        for x, a, b in ((-0.002, slant_left, strip), (0.002, strip, slant_right))
    ]
    assert corners(ridge, JOIN) == []
    points = noisy_points(WEDGE)
    (corner,) = corners(ridge, JOIN, points, fit_normals(WEDGE, points))
    # Read around the ends' centre, high on the ridge, where the end face is a thin triangle of
    # few points: its plane comes out a few degrees off, and the tip about 0.01 inside it.
    assert np.linalg.norm(corner.point - TIP) < 0.015


def test_no_corner_from_the_points_where_convex_and_concave_edges_meet():
    # The end (y = 0) of an L-shaped bar: its inner, concave edge (wall x = 0 over floor z = 0)
    # meets the end face's two convex edges at the origin, a saddle.
    rng = np.random.default_rng(0)
    u, v = rng.uniform(0.0, 0.3, (2, 3000))
    wall = np.stack([0 * u[:1000], v[:1000], u[:1000]], 1)
    floor = np.stack([u[1000:2000], v[1000:2000], 0 * u[1000:2000]], 1)
    end = np.stack([u[2000:] - 0.15, 0 * u[2000:], v[2000:] - 0.15], 1)
    end = end[(end[:, 0] < 0) | (end[:, 2] < 0)]
    points = np.concatenate([wall, floor, end]) + rng.normal(0.0, 0.005, (len(wall) + len(floor) + len(end), 3))
    normals = np.concatenate([np.tile(X, (len(wall), 1)), np.tile(Z, (len(floor), 1)), np.tile(-Y, (len(end), 1))])
    centre = np.array([0.02, 0.02, 0.02])
    assert _corner_of_points(centre, centre[None], points, normals) is None


def box_corner_faces(rng: np.random.Generator) -> list[np.ndarray]:
    """Points (320, 3) drawn uniformly on each of the three faces x, y and z = 0 of a box's corner
    at the origin, each 0.2 across (the box on the negative side), without noise."""
    u, v = rng.uniform(-0.2, 0.0, (2, 3, 320))
    return [
        np.stack([0 * u[0], u[0], v[0]], 1),
        np.stack([u[1], 0 * u[1], v[1]], 1),
        np.stack([u[2], v[2], 0 * u[2]], 1),
    ]


def test_of_the_faces_the_points_show_those_meeting_nearest_the_curves_ends_make_the_corner():
    # A box's corner at the origin (faces x, y, z = 0, each 0.2 across), and within the reach a
    # larger face of another part, z = -0.3 facing down: more points than any of the corner's.
    rng = np.random.default_rng(0)
    faces = box_corner_faces(rng)
    big = np.hstack([rng.uniform(-0.4, 0.4, (2, 5000)).T, np.full((5000, 1), -0.3)])
    points = np.concatenate([*faces, big]) + rng.normal(0.0, 0.005, (960 + 5000, 3))
    normals = np.concatenate([np.tile(X, (320, 1)), np.tile(Y, (320, 1)), np.tile(Z, (320, 1)), np.tile(-Z, (5000, 1))])
    ends = np.array([[-0.03, 0.0, 0.0], [0.0, -0.03, 0.0], [0.0, 0.0, -0.03]])
    corner = _corner_of_points(ends.mean(axis=0), ends, points, normals)
    assert corner is not None
    assert np.linalg.norm(corner.point) < 0.004
    assert (corner.normals @ np.full(3, -0.05) < corner.offsets).all()  # the box's inside, inside all three


def pocket_corner(count: int = 900, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Noisy points (n, 3) on the three faces of a square pocket's floor corner at the origin (the
    pocket x < 0, y < 0, z > 0: the floor z = 0 and the walls x = 0 and y = 0, each 0.25 across),
    and the unit normals a fit gives them (out of the solid, into the pocket)."""
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(0.0, 0.25, (2, 3, count))
    faces = [
        np.stack([-u[0], -v[0], 0 * u[0]], 1),
        np.stack([0 * u[1], -u[1], v[1]], 1),
        np.stack([-u[2], 0 * u[2], v[2]], 1),
    ]
    points = np.concatenate(faces) + rng.normal(0.0, 0.005, (3 * count, 3))
    normals = np.concatenate([np.tile(Z, (count, 1)), np.tile(-X, (count, 1)), np.tile(-Y, (count, 1))])
    return points, normals


def round_the_corner(radius: float) -> Curve:
    """The pocket's floor edges (``pocket_corner``) as one concave curve that runs from 0.15 along
    the wall y = 0 round the corner on an arc of ``radius`` and 0.15 along the wall x = 0, every
    0.005 or less, as the extraction leaves it where the walls' upright edge stops short of the floor."""
    straight = np.linspace(-0.15, -radius, int(np.ceil((0.15 - radius) / 0.005)) + 1)
    angle = np.linspace(np.pi / 2, 0.0, int(np.ceil(radius * np.pi / 2 / 0.005)) + 1)[1:-1]
    points = np.concatenate(
        [
            np.stack([straight, 0 * straight, 0 * straight], 1),
            np.stack([radius * (np.cos(angle) - 1), radius * (np.sin(angle) - 1), 0 * angle], 1),
            np.stack([0 * straight, straight[::-1], 0 * straight], 1),
        ]
    )
    wall = np.concatenate(
        [
            np.tile(-Y, (len(straight), 1)),
            -np.stack([np.cos(angle), np.sin(angle), 0 * angle], 1),
            np.tile(-X, (len(straight), 1)),
        ]
    )
    return Curve(points, np.tile(Z, (len(points), 1)), wall, 90.0, False)


def upright_edge() -> Curve:
    """The pocket's upright edge (``pocket_corner``: walls x = 0 and y = 0), from 0.08 above its
    floor up to 0.2, as the extraction leaves it when it stops short of the floor."""
    z = np.arange(0.08, 0.2 + 1e-9, 0.005)
    return Curve(np.outer(z, Z), np.tile(-X, (len(z), 1)), np.tile(-Y, (len(z), 1)), 90.0, False)


@pytest.mark.parametrize("radius", [0.02, 0.04])
def test_a_corner_a_curve_runs_round_is_found_from_the_points_of_its_faces(radius):
    curves = [round_the_corner(radius), upright_edge()]
    assert corners(curves, JOIN) == []  # no ends near it, and without the points nothing to read
    points, normals = pocket_corner()
    (corner,) = corners(curves, JOIN, points, normals)
    assert np.linalg.norm(corner.point) < 0.004
    # A concave corner: its planes face the solid, the pocket inside all three.
    assert (corner.normals @ np.array([-0.05, -0.05, 0.05]) < corner.offsets).all()
    assert not (corner.normals @ np.array([0.05, 0.05, -0.05]) < corner.offsets).any()
    # Without the upright edge among the curves, nothing shows the points' third edge is one.
    assert corners(curves[:1], JOIN, points, normals) == []


def off_the_floor_edges(points: np.ndarray) -> np.ndarray:
    """How far each of ``points`` (m, 3) lies from the pocket's two floor edges (``pocket_corner``:
    the lines y = z = 0 for x <= 0 and x = z = 0 for y <= 0), (m,)."""
    along_x = np.hypot(points[:, 1], points[:, 2]) + np.maximum(points[:, 0], 0.0)
    along_y = np.hypot(points[:, 0], points[:, 2]) + np.maximum(points[:, 1], 0.0)
    return np.minimum(along_x, along_y)


def test_a_curve_that_runs_round_a_corner_is_cut_there_and_its_pieces_carried_on_to_it():
    curve = round_the_corner(0.04)
    assert off_the_floor_edges(curve.points).max() > 0.01  # the arc, 0.0117 off at its middle
    points, normals = pocket_corner()
    found = corners([curve, upright_edge()], JOIN, points, normals)
    pieces = extend_to_corners([curve], found, JOIN, 0.005)
    assert len(pieces) == 2
    for piece in pieces:
        assert off_the_floor_edges(piece.points).max() < 0.004  # the corner's own offset
        assert np.linalg.norm(np.diff(piece.points, axis=0), axis=1).max() <= 0.005 + 1e-12
        assert len(piece.left) == len(piece.right) == len(piece.points)
    ends = np.array([pieces[0].points[-1], pieces[1].points[0]])
    np.testing.assert_allclose(ends, [found[0].point, found[0].point], atol=1e-12)
    # A curve that passes the corner on other faces (a parallel edge 0.03 above) is not cut.
    passing = Curve(curve.points + [0.0, 0.0, 0.03], np.tile(-X, (len(curve.points), 1)), curve.right, 90.0, True)
    (kept,) = extend_to_corners([passing], found, JOIN, 0.005)
    np.testing.assert_array_equal(kept.points, passing.points)


def test_a_holes_rim_is_no_corner_for_the_points_either():
    # A hole of radius 0.04 through a plate's top (z = 0): the rim's curve turns all the way round,
    # and the points show the top and the hole's wall, a cylinder, not three faces.
    rng = np.random.default_rng(0)
    radius = 0.04
    top = rng.uniform(-0.25, 0.25, (6000, 2))
    top = top[np.linalg.norm(top, axis=1) > radius]
    angle, depth = rng.uniform(0.0, 2 * np.pi, 1500), rng.uniform(-0.1, 0.0, 1500)
    around = np.stack([np.cos(angle), np.sin(angle), 0 * angle], 1)
    points = np.concatenate([np.hstack([top, np.zeros((len(top), 1))]), radius * around + depth[:, None] * Z])
    points += rng.normal(0.0, 0.005, points.shape)
    normals = np.concatenate([np.tile(Z, (len(top), 1)), -around])
    rim_angle = np.linspace(0.0, 2 * np.pi, 51)
    rim_around = np.stack([np.cos(rim_angle), np.sin(rim_angle), 0 * rim_angle], 1)
    rim_around[-1] = rim_around[0]
    rim = Curve(radius * rim_around, np.tile(Z, (51, 1)), -rim_around, 90.0, True)
    assert corners([rim], JOIN, points, normals) == []
    # Nor broken into three pieces, whose ends meet.
    pieces = [
        Curve(rim.points[a : b + 1], rim.left[a : b + 1], rim.right[a : b + 1], 90.0, True)
        for a, b in ((0, 17), (17, 34), (34, 50))
    ]
    assert corners(pieces, JOIN, points, normals) == []


def test_a_corner_crowded_out_of_the_wide_reach_by_larger_faces_is_read_nearer_its_curves_ends():
    # A box's corner at the origin (faces x, y, z = 0, each 0.2 across) whose three edges stop 0.03
    # short of it, with the side normals a rounding gives them near a corner (no three faces among
    # them); within the points' wide reach, six larger faces of other parts, turned other ways:
    # the corner's own faces are not among the largest groups there.
    rng = np.random.default_rng(0)
    faces = box_corner_faces(rng)
    others, other_normals = [], []
    for direction in ([1, 1, 0], [1, -1, 0], [-1, 1, 0], [1, 0, 1], [0, 1, 1], [-1, 0, 1]):
        normal = unit(np.array([direction], dtype=float))[0]
        across = unit(np.cross(normal, [0.3, 0.5, 0.8])[None])[0]
        up = np.cross(normal, across)
        a, b = rng.uniform(-0.12, 0.12, (2, 700))
        others.append(0.26 * normal + a[:, None] * across + b[:, None] * up)
        other_normals.append(np.tile(normal, (700, 1)))
    points = np.concatenate([*faces, *others]) + rng.normal(0.0, 0.005, (960 + 4200, 3))
    normals = np.concatenate([np.tile(X, (320, 1)), np.tile(Y, (320, 1)), np.tile(Z, (320, 1)), *other_normals])
    rounded = unit(np.array([[1.0, 1.0, 1.0]]))[0]
    curves = [edge(-X, rounded, Y), edge(-Y, rounded, Z), edge(-Z, rounded, X)]
    for curve in curves:
        curve.points = curve.points - APEX
    assert corners(curves, JOIN) == []  # the curves' normals show no three faces
    (corner,) = corners(curves, JOIN, points, normals)
    assert np.linalg.norm(corner.point) < 0.004


def test_a_shafts_rim_in_pieces_is_no_corner_though_strips_of_its_wall_pass_for_faces():
    # A round shaft of radius 0.16 along x, ending at x = 0, as noisy points; its rim comes out as
    # eight curves with gaps of 0.02 between them. Read near, two strips of the wall and the end
    # face meet at a point by the rim, but no crease runs along the wall between the strips.
    rng = np.random.default_rng(0)
    radius = 0.16
    disc = rng.uniform(-radius, radius, (4000, 2))
    disc = disc[np.linalg.norm(disc, axis=1) < radius]
    angle, depth = rng.uniform(0.0, 2 * np.pi, 6000), rng.uniform(-0.3, 0.0, 6000)
    around = np.stack([0 * angle, np.cos(angle), np.sin(angle)], 1)
    points = np.concatenate([np.hstack([np.zeros((len(disc), 1)), disc]), radius * around + depth[:, None] * X])
    points += rng.normal(0.0, 0.005, points.shape)
    normals = np.concatenate([np.tile(X, (len(disc), 1)), around])
    pieces = []
    for start in np.arange(8) * np.pi / 4:
        rim_angle = np.linspace(start, start + np.pi / 4 - 0.02 / radius, 25)
        rim_around = np.stack([0 * rim_angle, np.cos(rim_angle), np.sin(rim_angle)], 1)
        pieces.append(Curve(radius * rim_around, np.tile(X, (25, 1)), rim_around, 90.0, True))
    assert corners(pieces, JOIN, points, normals) == []
