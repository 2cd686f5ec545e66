"""Self-intersections of a triangle mesh: faces that pass through other faces of the same mesh.

Dual contouring with sharpened vertices can leave a few: where two sharpened vertices near an edge
take planes that cross, a face of one side pokes through a face of the other (5 to 97 faces on
the sample parts' fits, found by MeshLab). A mesh that passes through itself is no solid for a
printer or a Boolean operation, so ``core.dual`` takes such vertices back. Two triangles that share
no edge cross exactly when an edge of one passes through the other (not in its plane); that
test, on the pairs of faces near one another, is all this module does. Faces that share no vertex
count as crossing when they merely touch: the 8 decimals of an OBJ file turned such contacts into
crossings on three of twelve sample fits (MeshLab's check of the written file, docs/benchmarks.md).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from core.trees import kd_tree

_EPSILON = 1e-12
# Barycentric and along-the-edge margin: a crossing this near a triangle's boundary or an edge's end
# is a touch (two faces sharing a vertex meet there, to rounding), not a crossing.
_MARGIN = 1e-7
# Faces that share no vertex must not touch either: a vertex placed exactly on another face's edge
# (two sharpened vertices on one edge line) becomes a crossing once the coordinates are rounded,
# as a mesh file does (8 decimals in OBJ). Contact this near (barycentric, relative to the faces'
# size: about 6e-8 for a cell of 0.006) counts.
_TOUCH = 1e-5
_CHUNK = 8192  # faces of ``among`` tested at a time: a few hundred thousand candidate pairs
_UNCROSS_PASSES = 4  # rounds of putting back the moved vertices of faces that cross others


def crossing_faces(vertices: np.ndarray, faces: np.ndarray, among: np.ndarray) -> np.ndarray:
    """The faces of ``among`` (indices into ``faces`` (f, 3), on ``vertices`` (v, 3)) that cross
    another face of the mesh, one sharing no edge with them: a sorted index array.

    Candidates are the pairs whose bounding spheres (about each face's centroid) overlap; each
    is tested in both directions by ``edges_cross``."""
    among = np.unique(among)
    if len(among) == 0 or len(faces) < 2:
        return np.zeros(0, dtype=np.int64)
    corners = vertices[faces]
    centre = corners.mean(axis=1)
    radius = np.linalg.norm(corners - centre[:, None], axis=2).max(axis=1)
    tree = kd_tree(centre)
    chunks = [among[start : start + _CHUNK] for start in range(0, len(among), _CHUNK)]
    return np.unique(np.concatenate([_crossing(faces, corners, centre, radius, tree, chunk) for chunk in chunks]))


def uncrossed(vertices: np.ndarray, before: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``vertices`` (v, 3) with the moved ones (those not at ``before``) of faces that cross
    another face put back, until none does (``before``, as ``core.dual`` leaves it, crosses
    nowhere, so putting back every moved vertex of a crossing face ends it). What the steps after
    dual contouring (``core.creases``, ``core.corners``) do to a vertex they move too far."""
    vertices = vertices.copy()
    moved = np.flatnonzero((vertices != before).any(axis=1))
    for _ in range(_UNCROSS_PASSES):
        crossing = crossing_faces(vertices, faces, np.flatnonzero(np.isin(faces, moved).any(axis=1)))
        back = np.intersect1d(faces[crossing], moved)
        if len(back) == 0:
            break
        vertices[back] = before[back]
        moved = np.setdiff1d(moved, back)
    return vertices


def _crossing(
    faces: np.ndarray, corners: np.ndarray, centre: np.ndarray, radius: np.ndarray, tree: cKDTree, among: np.ndarray
) -> np.ndarray:
    """``crossing_faces`` for one chunk of ``among``, given the faces' corners, centroids, bounding
    radii and a k-d tree of the centroids."""
    near = tree.query_ball_point(centre[among], radius[among] + radius.max())
    first = np.repeat(among, [len(n) for n in near])
    second = np.concatenate([np.asarray(n, dtype=np.int64) for n in near])
    gap = centre[first] - centre[second]
    close = np.einsum("ij,ij->i", gap, gap) <= (radius[first] + radius[second]) ** 2
    first, second = first[close], second[close]
    # Faces sharing an edge meet along it (a fold between them is ``core.dual``'s unfolding's);
    # faces sharing one vertex may still cross, along a segment from it, which the edge opposite
    # the vertex shows.
    shared = (faces[first][:, :, None] == faces[second][:, None, :]).sum(axis=(1, 2))
    first, second, shared = first[shared < 2], second[shared < 2], shared[shared < 2]
    margin = np.where(shared == 0, -_TOUCH, _MARGIN)
    cross = edges_cross(corners[first], corners[second], margin) | edges_cross(corners[second], corners[first], margin)
    return first[cross]


def edges_cross(edges_of: np.ndarray, triangles: np.ndarray, margin: np.ndarray | float = _MARGIN) -> np.ndarray:
    """For each pair (row) of triangles (p, 3, 3) each, whether an edge of ``edges_of`` passes
    through the triangle of ``triangles`` (Möller and Trumbore's segment test): by more than
    ``margin`` (barycentric and along the edge; scalar or (p,)) inside both. A positive margin
    leaves out touching at an end or a boundary, a negative one counts contact that near; an edge
    in the triangle's plane never counts."""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    first, second = b - a, c - a
    result = np.zeros(len(triangles), dtype=bool)
    for start, end in ((0, 1), (1, 2), (2, 0)):
        origin, direction = edges_of[:, start], edges_of[:, end] - edges_of[:, start]
        p = np.cross(direction, second)
        determinant = np.einsum("ij,ij->i", first, p)
        usable = np.abs(determinant) > _EPSILON
        inverse = 1.0 / np.where(usable, determinant, 1.0)
        offset = origin - a
        u = np.einsum("ij,ij->i", offset, p) * inverse
        q = np.cross(offset, first)
        v = np.einsum("ij,ij->i", direction, q) * inverse
        t = np.einsum("ij,ij->i", second, q) * inverse
        inside = (u > margin) & (v > margin) & (u + v < 1 - margin)
        result |= usable & inside & (t > margin) & (t < 1 - margin)
    return result
