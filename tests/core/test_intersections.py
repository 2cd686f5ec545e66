"""core.intersections against a slow, obviously right reference, and core.dual's use of it."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import trimesh

from core.dual import _uncross
from core.intersections import crossing_faces, edges_cross, uncrossed


def reference_edges_cross(edges_of: np.ndarray, triangle: np.ndarray) -> bool:
    """Whether an edge of the triangle ``edges_of`` (3, 3) passes through ``triangle`` (3, 3):
    solve origin + t·direction = a + u·(b - a) + v·(c - a) for (t, u, v), one edge at a time."""
    a, b, c = triangle
    for start, end in ((0, 1), (1, 2), (2, 0)):
        origin, direction = edges_of[start], edges_of[end] - edges_of[start]
        system = np.stack([direction, a - b, a - c], axis=1)
        if abs(np.linalg.det(system)) < 1e-12:
            continue
        t, u, v = np.linalg.solve(system, a - origin)
        if 1e-7 < t < 1 - 1e-7 and u > 1e-7 and v > 1e-7 and u + v < 1 - 1e-7:
            return True
    return False


@pytest.mark.parametrize("seed", range(3))
def test_edges_cross_matches_the_reference_on_random_triangles(seed):
    rng = np.random.default_rng(seed)
    first, second = rng.uniform(-1, 1, (2, 2000, 3, 3))
    expected = np.array([reference_edges_cross(p, q) for p, q in zip(first, second)])
    assert 0.05 < expected.mean() < 0.95  # both kinds are there
    np.testing.assert_array_equal(edges_cross(first, second), expected)


def test_two_triangles_through_each_other_cross_and_ones_sharing_a_vertex_do_not():
    flat = np.array([[-1.0, -1, 0], [1, -1, 0], [0, 1, 0]])
    upright = np.array([[0.0, 0, -0.3], [0, 0, 0.3], [0.2, 0.5, 0]])  # pierces flat's middle
    hinged = np.array([[0.0, 2, 1], [0.5, 2, -1]])  # with flat's top corner: meets flat only there
    above = flat + [0, 0, 0.5]
    vertices = np.concatenate([flat, upright, hinged, above])
    faces = np.array([[0, 1, 2], [3, 4, 5], [2, 6, 7], [8, 9, 10]])
    np.testing.assert_array_equal(crossing_faces(vertices, faces, np.arange(4)), [0, 1])
    np.testing.assert_array_equal(crossing_faces(vertices, faces, np.array([2, 3])), [])


def test_faces_sharing_no_vertex_may_not_touch_even_to_rounding():
    """A vertex on another face's edge (two sharpened vertices on one edge line) pokes through once
    a mesh file rounds it, so contact counts as crossing, up to the rounding of 8 decimals."""
    flat = np.array([[-1.0, -1, 0], [1, -1, 0], [0, 1, 0]])
    foot = np.array([[0.3, -1.0, 0.0], [0.3, -1.5, 0.5], [0.5, -1.5, 0.6]])  # its corner on flat's edge
    for lift, touches in ((0.0, True), (-2e-8, True), (2e-8, True), (-1e-3, False), (1e-3, False)):
        vertices = np.concatenate([flat, foot + [0, 0, lift]])
        found = crossing_faces(vertices, np.arange(6).reshape(2, 3), np.arange(2))
        np.testing.assert_array_equal(found, [0, 1] if touches else [], err_msg=f"foot lifted by {lift}")
    # The same contact through a shared vertex is the mesh's own joint.
    shared = np.concatenate([flat, foot[1:]])
    assert len(crossing_faces(shared, np.array([[0, 1, 2], [1, 3, 4]]), np.arange(2))) == 0


def test_crossing_faces_matches_the_reference_on_a_crumpled_sphere():
    sphere = trimesh.creation.icosphere(subdivisions=2)
    vertices = sphere.vertices + np.random.default_rng(4).normal(0, 0.15, sphere.vertices.shape)
    faces = sphere.faces
    expected = set()
    for i, j in itertools.combinations(range(len(faces)), 2):
        if len(set(faces[i]) & set(faces[j])) >= 2:
            continue  # neighbours across an edge meet along it
        p, q = vertices[faces[i]], vertices[faces[j]]
        if reference_edges_cross(p, q) or reference_edges_cross(q, p):
            expected |= {i, j}
    assert len(expected) > 10
    found = crossing_faces(vertices, faces, np.arange(len(faces)))
    np.testing.assert_array_equal(found, sorted(expected))
    some = np.arange(0, len(faces), 3)
    np.testing.assert_array_equal(crossing_faces(vertices, faces, some), sorted(expected & set(some.tolist())))


def test_a_sharpened_vertex_pushed_through_the_mesh_is_put_back():
    sphere = trimesh.creation.icosphere(subdivisions=2)
    fallback = sphere.vertices.copy()
    pushed = fallback.copy()
    pushed[0] = -1.3 * fallback[0]  # through the far side of the sphere
    sharpened = np.zeros(len(fallback), dtype=bool)
    sharpened[0] = True
    every = np.arange(len(sphere.faces))
    assert len(crossing_faces(pushed, sphere.faces, every)) > 0
    uncrossed = _uncross(pushed, fallback, sphere.faces, sharpened)
    assert len(crossing_faces(uncrossed, sphere.faces, every)) == 0
    np.testing.assert_array_equal(uncrossed[1:], fallback[1:])
    # Taken back along its move, by halves, as far as it has to go (here half of it).
    way, went = fallback[0] - pushed[0], uncrossed[0] - pushed[0]
    assert np.linalg.norm(np.cross(way, went)) < 1e-12
    assert 0.5 <= went @ way / (way @ way) <= 1
    # An unsharpened vertex is not the sharpening's to put back.
    np.testing.assert_array_equal(_uncross(pushed, fallback, sphere.faces, ~sharpened), pushed)


def test_a_moved_vertex_whose_face_then_crosses_another_goes_back():
    sphere = trimesh.creation.icosphere(subdivisions=2)
    before = sphere.vertices
    moved = before.copy()
    moved[0] = -1.3 * before[0]  # through the far side of the sphere
    moved[5] = 1.02 * before[5]  # a little outwards: no face crosses
    every = np.arange(len(sphere.faces))
    assert len(crossing_faces(moved, sphere.faces, every)) > 0
    kept = uncrossed(moved, before, sphere.faces)
    assert len(crossing_faces(kept, sphere.faces, every)) == 0
    np.testing.assert_array_equal(kept[0], before[0])
    np.testing.assert_array_equal(kept[5], moved[5])
