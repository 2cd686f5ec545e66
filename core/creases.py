"""Creases: the mesh's sharp edges and the edge curves moved onto planes fitted to the input points.

Dual contouring (``core.dual``) puts a crease vertex where the planes of f's faces beside the edge
meet, read a walk away from it. Where the fit tilts a face near the edge (most of all near a corner,
where a third face's rounding bends it) those planes meet off the true edge: on seed-0 fits of the
sample parts the edge curves lay a median 0.0024 to 0.0033 from the true edges, and some crease
vertices of l_bracket 0.014 beyond them, its Hausdorff distance (docs/benchmarks.md). The input
points say where the faces are. For each crease vertex or curve sample, each face's plane is fitted
again to the input points around it that lie near that plane, on the face's side of the other plane
(off the rounding) and whose fit normal is the face's, and the point goes onto the line where the two
refitted planes meet. A refit is not used where it would move the point far, turn a plane far, fit
one face much more loosely than the other, or where a face is curved (a disc's rim, a hole's wall:
the planes of the points on either side along the edge differ), since a plane fitted to a curved
face meets the other off the edge.

The same planes give the normals of the input points beside an edge (``normals_on_faces``): ∇f
there leans towards the other face over the band the fit rounds, and the refitted plane is the
face the point lies on.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from core.curves import Curve
from core.features import face_normals, unit
from core.intersections import uncrossed
from core.sampling import subsample_rows
from core.trees import kd_tree

# Unit frame: the input points read around a crease. The faces' points are averaged along the edge
# as well as across it: at 0.08 a refit moved l_bracket's curves no nearer the true edges, at 0.15
# and 0.2 their median distance went from 0.0029 to 0.0014 and 0.0016 (docs/benchmarks.md).
REACH = 0.2
MAX_POINTS = 512  # of those, at most about this many (evenly in input order): the cost stays bounded on dense clouds
BAND = 0.02  # unit frame: points this near a face's plane may be its points (four times the sample data's noise)
OFF_EDGE = 0.01  # unit frame: and this far from the edge along the face (off the rounding)
# Degrees: a point's fit normal this near its face's (and a crease vertex's edges' faces this near
# one another, or it is a corner's). At 15 the refit planes of the flange's rim, a cylinder of
# radius 0.5, took in its curve and its curves went 0.0033 -> 0.0039 from the true edges.
SAME_FACE = 8.0
STRAIGHT = 3.0  # degrees: the most the planes of a face's points on either side along the edge may differ
MIN_POINTS = 12  # points that make a plane (half of them on either side along the edge)
PASSES = 3
MAX_SPREAD = 1.5  # the wider spread of a face's points off its plane, over the narrower (both share the noise)
MAX_TILT = 10.0  # degrees a refitted plane may turn from the face it was read from
MAX_MOVE = 0.02  # unit frame: the farthest a crease vertex or curve sample moves
_CHUNK = 1024  # rows refitted at a time
# Input points read at most, a seeded draw of a larger cloud: at 1 M points the balls of REACH held
# some 60 times the 16,384-point cloud's points, and the step took 15 s and 940 MB more instead of
# 1 s; twice the sample data's density leaves about 3,000 in a ball, well over MAX_POINTS.
CLOUD_POINTS = 32_768
# The normals of the points beside a curve (``normals_on_faces``). Unit frame: points this near a
# curve sample whose refit holds, and no more than HELD_GAP farther from it than from the nearest
# sample. The planes of a sample hold along a flat stretch of its edge, so a point beside a sample
# whose refit failed (near a corner, say) takes those of the nearest one where it held: half as
# much again off the mean error, but two points 0.03 and 0.07 nearer a stretch where none held
# (another edge, a curved face) were given the wrong face (docs/benchmarks.md).
NORMAL_REACH = 0.09
HELD_GAP = 0.02
# Noise widths (the median spread of the faces' points off their refitted planes): a point takes a
# face's normal if it lies within this many of that face's plane and this many nearer it than the
# other's. Nearer the edge, noise may have carried a point from the other face, and a normal
# given the wrong face of a right-angled edge points inward by a hair: at 2.5 one point of the
# cube's 16,384 did (docs/benchmarks.md).
CLEAR = 3.0
MAX_TURN = 30.0  # degrees: the most a point's normal turns from the fit's to take its face's
# Degrees: and the most the fit's normal may lean along the edge. A fit rounds an edge about the
# edge's direction, so near a flat face's edge ∇f leans towards the other face only; on a curved
# face (a cylinder's wall at its rim) the plane refitted at a curve sample is turned along the edge
# from the face's normal beside it, as ∇f there is.
ALONG_EDGE = 2.0


def onto_refitted(
    mesh: trimesh.Trimesh, curves: list[Curve], angle: float, points: np.ndarray, normals: np.ndarray
) -> tuple[trimesh.Trimesh, list[Curve]]:
    """``mesh`` and ``curves`` (unit frame) with the mesh's crease vertices (on mesh edges whose
    faces' normals differ by more than ``angle`` degrees, between two faces only) and the curves'
    samples on the edge of their two faces' planes refitted to ``points`` (n, 3, unit frame), with
    the fit's unit ``normals`` (n, 3) at them, where the refit holds; one search of the points
    (at most ``CLOUD_POINTS`` of them) serves both. A vertex that would turn one of its faces
    over, or leave a face crossing another, stays where it was. Returns a new mesh (same faces)
    and new curves.

    The curves must be read from the mesh before its creases move: moved crease vertices turn the
    faces between them unevenly, and the chains of creased mesh edges broke up (44 % of the
    flange's true edges farther than 0.01 from every curve, against 13 %)."""
    rows = subsample_rows(len(points), CLOUD_POINTS, seed=0)
    points, normals = points[rows], normals[rows]
    vertex, side_a, side_b, convex = _crease_sides(mesh, angle)
    before = np.asarray(mesh.vertices, dtype=np.float64)
    lengths = [len(curve.points) for curve in curves]
    at = np.concatenate([before[vertex], *(curve.points for curve in curves)])
    if len(at) == 0 or len(points) < MIN_POINTS:
        return mesh, curves
    target, holds = _refitted(
        at,
        np.concatenate([side_a, *(curve.left for curve in curves)]),
        np.concatenate([side_b, *(curve.right for curve in curves)]),
        np.concatenate([convex, *(np.full(count, curve.convex) for curve, count in zip(curves, lengths, strict=True))]),
        points,
        normals,
    )
    on_mesh = slice(0, len(vertex))
    ends = len(vertex) + np.cumsum([0, *lengths])
    curves = [replace(curve, points=target[ends[i] : ends[i + 1]]) for i, curve in enumerate(curves)]
    if not holds[on_mesh].any():
        return mesh, curves
    faces = np.asarray(mesh.faces)
    vertices = before.copy()
    vertices[vertex[holds[on_mesh]]] = target[on_mesh][holds[on_mesh]]
    vertices = _unturned(vertices, before, faces)
    return trimesh.Trimesh(uncrossed(vertices, before, faces), faces, process=False), curves


def normals_on_faces(points: np.ndarray, normals: np.ndarray, curves: list[Curve], workers: int = 1) -> np.ndarray:
    """The fit's unit ``normals`` (n, 3) at ``points`` (n, 3, unit frame), those of the points
    within ``NORMAL_REACH`` of a sample of ``curves`` that lie clearly on one of its two faces
    replaced by the normal of that face's plane refitted to the points (as ``onto_refitted``
    refits them; at the nearest sample where the refit holds, both faces flat along the edge and
    neither turned far, if it is no more than ``HELD_GAP`` farther than the nearest sample).

    The fit rounds every edge, so ∇f tilts towards the other face over a band some 0.04 wide
    beside it: on seed-0 fits of the sample parts, the points between 0.01 and 0.04 from an edge
    carried a quarter to a third of the mean normal error. A point too near the edge to tell its
    face (not ``CLEAR`` noise widths nearer one plane than the other) keeps the fit's normal, as
    does one whose fit normal is more than ``MAX_TURN`` degrees from the face's (a third face's
    point, near a corner) or leans along the edge by more than ``ALONG_EDGE`` (a curved face).
    """
    if not curves:
        return normals
    rows = subsample_rows(len(points), CLOUD_POINTS, seed=0)
    at = np.concatenate([curve.points for curve in curves])
    normal_a, offset_a, normal_b, offset_b, spread, holds = _planes(
        at,
        np.concatenate([curve.left for curve in curves]),
        np.concatenate([curve.right for curve in curves]),
        np.concatenate([np.full(len(curve.points), curve.convex) for curve in curves]),
        points[rows],
        normals[rows],
    )
    if not holds.any():
        return normals
    noise = float(np.median(spread[holds]))
    held = np.flatnonzero(holds)
    to_held, nearest = kd_tree(at[held]).query(points, distance_upper_bound=NORMAL_REACH, workers=workers)
    found = np.flatnonzero(nearest < len(held))
    to_any, _ = kd_tree(at).query(points[found], workers=workers)
    found = found[to_held[found] - to_any < HELD_GAP]
    sample = held[nearest[found]]
    offsets = points[found] - at[sample]
    to_a = np.abs(_dot(offsets, normal_a[sample]) - offset_a[sample])
    to_b = np.abs(_dot(offsets, normal_b[sample]) - offset_b[sample])
    face = np.where((to_a < to_b)[:, None], normal_a[sample], normal_b[sample])
    clear = (np.abs(to_a - to_b) > CLEAR * noise) & (np.minimum(to_a, to_b) < CLEAR * noise)
    clear &= _dot(face, normals[found]) > np.cos(np.radians(MAX_TURN))
    edge = unit(np.cross(normal_a[sample], normal_b[sample]))
    clear &= np.abs(_dot(normals[found], edge)) < np.sin(np.radians(ALONG_EDGE))
    result = normals.copy()
    result[found[clear]] = face[clear]
    return result


def _crease_sides(mesh: trimesh.Trimesh, angle: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The crease vertices (c,) between two faces, the unit normals of those faces (c, 3) each (the
    mean over the vertex's crease edges, paired to agree), and whether the crease is convex (c,).
    A vertex whose crease edges disagree on their faces by more than ``SAME_FACE`` (a corner, where
    three faces meet) is left out: ``core.corners`` puts corners back."""
    sharp = mesh.face_adjacency_angles > np.radians(angle)
    pairs = mesh.face_adjacency[sharp]
    normals_of = np.asarray(mesh.face_normals)
    # One row per (vertex, crease edge), sorted by vertex; the vertex's first row is its reference.
    owner = mesh.face_adjacency_edges[sharp].ravel()
    order = np.argsort(owner, kind="stable")
    owner = owner[order]
    first = np.repeat(normals_of[pairs[:, 0]], 2, axis=0)[order]
    second = np.repeat(normals_of[pairs[:, 1]], 2, axis=0)[order]
    convex = np.repeat(mesh.face_adjacency_convex[sharp], 2)[order]
    vertex, start, row_of = np.unique(owner, return_index=True, return_inverse=True)
    reference_a, reference_b = first[start][row_of], second[start][row_of]
    swap = _dot(first, reference_b) + _dot(second, reference_a) > _dot(first, reference_a) + _dot(second, reference_b)
    side_a = np.where(swap[:, None], second, first)
    side_b = np.where(swap[:, None], first, second)
    cosine = np.cos(np.radians(SAME_FACE))
    disagree = (_dot(side_a, reference_a) <= cosine) | (_dot(side_b, reference_b) <= cosine)
    count = len(vertex)
    mean_a, mean_b = np.zeros((count, 3)), np.zeros((count, 3))
    np.add.at(mean_a, row_of, side_a)
    np.add.at(mean_b, row_of, side_b)
    rows = np.bincount(row_of, minlength=count)
    is_convex = 2 * np.bincount(row_of, weights=convex, minlength=count) >= rows
    keep = np.bincount(row_of, weights=disagree, minlength=count) == 0
    return vertex[keep], unit(mean_a[keep]), unit(mean_b[keep]), is_convex[keep]


def _refitted(
    at: np.ndarray, side_a: np.ndarray, side_b: np.ndarray, convex: np.ndarray, points: np.ndarray, normals: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """For points ``at`` (c, 3) on an edge between faces of unit normals ``side_a`` and ``side_b``
    (c, 3) through them, convex or not (c,): the nearest point (c, 3) of the line where the planes
    refitted to the input ``points`` meet (``at`` itself where the refit does not hold), and
    whether it holds (c,)."""
    normal_a, offset_a, normal_b, offset_b, _, holds = _planes(at, side_a, side_b, convex, points, normals)
    step = _onto_line(normal_a, offset_a, normal_b, offset_b)
    holds &= np.linalg.norm(step, axis=1) <= MAX_MOVE
    return np.where(holds[:, None], at + step, at), holds


def _planes(
    at: np.ndarray, side_a: np.ndarray, side_b: np.ndarray, convex: np.ndarray, points: np.ndarray, normals: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The two faces' planes refitted to the input ``points`` around each of ``at`` (as in
    ``_refitted``): their unit normals (c, 3) and offsets (c,) as n·(x - at) = offset, a's then
    b's, the spread of each face's points off its plane (c, 2), and whether the refit holds (c,).
    In chunks of ``_CHUNK`` rows: each row holds up to ``MAX_POINTS`` points' coordinates and
    moments (about 50 kB), so memory stays bounded for any mesh."""
    tree = kd_tree(points)
    parts = [
        _planes_chunk(at[rows], side_a[rows], side_b[rows], convex[rows], tree, points, normals)
        for rows in (slice(start, start + _CHUNK) for start in range(0, len(at), _CHUNK))
    ]
    if not parts:
        return np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 2)), np.zeros(0, dtype=bool)
    normal_a, offset_a, normal_b, offset_b, spread, holds = (np.concatenate(part) for part in zip(*parts, strict=True))
    return normal_a, offset_a, normal_b, offset_b, spread, holds


def _planes_chunk(
    at: np.ndarray,
    side_a: np.ndarray,
    side_b: np.ndarray,
    convex: np.ndarray,
    tree: cKDTree,
    points: np.ndarray,
    normals: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``_planes`` of one chunk of rows, with a k-d ``tree`` of ``points``."""
    near, valid = _neighbours(at, tree)
    offsets = points[near] - at[:, None]  # (c, k, 3), relative to the edge point
    moments = _moments(offsets)
    edge = unit(np.cross(side_a, side_b))
    cosine = np.cos(np.radians(SAME_FACE))
    facing = []
    # Along each face, away from the edge: into the other plane's solid side at a convex edge,
    # out of it at a concave one.
    for face, other in ((side_a, side_b), (side_b, side_a)):
        along = unit(np.cross(np.cross(face, other), face))
        along *= np.where((_dot(along, other) < 0) != convex, -1.0, 1.0)[:, None]
        facing.append(valid & (_along(offsets, along) > OFF_EDGE) & (_along(normals[near], face) > cosine))
    half = _along(offsets, edge) > 0
    normal_a, normal_b = side_a, side_b
    offset_a, offset_b = np.zeros(len(at)), np.zeros(len(at))
    holds = np.ones(len(at), dtype=bool)
    for _ in range(PASSES):
        on_a = facing[0] & (np.abs(_along(offsets, normal_a) - offset_a[:, None]) < BAND)
        on_b = facing[1] & (np.abs(_along(offsets, normal_b) - offset_b[:, None]) < BAND)
        on_a, on_b = on_a & ~on_b, on_b & ~on_a  # a point near both planes is neither face's
        normal_a, offset_a, spread_a = _plane(moments, on_a, side_a)
        normal_b, offset_b, spread_b = _plane(moments, on_b, side_b)
    for chosen, face in ((on_a, side_a), (on_b, side_b)):
        holds &= ((chosen & half).sum(axis=1) >= MIN_POINTS // 2) & ((chosen & ~half).sum(axis=1) >= MIN_POINTS // 2)
        one_side, _, _ = _plane(moments, chosen & half, face)
        other_side, _, _ = _plane(moments, chosen & ~half, face)
        holds &= _dot(one_side, other_side) > np.cos(np.radians(STRAIGHT))
    tilt = np.cos(np.radians(MAX_TILT))
    holds &= (_dot(normal_a, side_a) > tilt) & (_dot(normal_b, side_b) > tilt)
    holds &= np.maximum(spread_a, spread_b) <= MAX_SPREAD * np.minimum(spread_a, spread_b)
    return normal_a, offset_a, normal_b, offset_b, np.stack([spread_a, spread_b], axis=1), holds


def _neighbours(at: np.ndarray, tree: cKDTree) -> tuple[np.ndarray, np.ndarray]:
    """The indices (c, k) of at most ``MAX_POINTS`` input points (in the k-d ``tree``) within
    ``REACH`` of each of ``at`` (c, 3), and which of them are real (c, k) (the rest pad the rows)."""
    found = tree.query_ball_point(at, REACH)
    width = max(1, min(MAX_POINTS, max(len(row) for row in found)))
    near = np.zeros((len(at), width), dtype=np.int64)
    valid = np.zeros((len(at), width), dtype=bool)
    for row, indices in enumerate(found):
        if len(indices) > MAX_POINTS:
            # Every so many of them, in input order: the same for the same point, whatever else is asked.
            indices = np.sort(indices)[:: -(-len(indices) // MAX_POINTS)]
        near[row, : len(indices)] = indices
        valid[row, : len(indices)] = True
    return near, valid


def _moments(offsets: np.ndarray) -> np.ndarray:
    """Each point's coordinates and their products, (c, k, 9): x, y, z, xx, xy, xz, yy, yz, zz,
    so that a plane fit to any subset of a row is one product with its mask."""
    x, y, z = offsets[..., 0], offsets[..., 1], offsets[..., 2]
    return np.stack([x, y, z, x * x, x * y, x * z, y * y, y * z, z * z], axis=2)


def _plane(moments: np.ndarray, chosen: np.ndarray, towards: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row, the plane of the ``chosen`` (c, k) points (``_moments``, (c, k, 9)): its unit normal
    (c, 3) along the axis they spread least on, turned to the side of ``towards`` (c, 3), its offset
    (c,) and their spread off it (standard deviation, (c,)). Rows of fewer than three points give
    planes the callers' counts refuse."""
    total = np.maximum(chosen.sum(axis=1), 1)[:, None]
    sums = (chosen[:, None, :].astype(np.float64) @ moments)[:, 0] / total  # (c, 9): means of each moment
    mean = sums[:, :3]
    xx, xy, xz, yy, yz, zz = (sums[:, 3 + i] for i in range(6))
    second = np.stack([np.stack([xx, xy, xz], 1), np.stack([xy, yy, yz], 1), np.stack([xz, yz, zz], 1)], 1)
    covariance = second - mean[:, :, None] * mean[:, None, :]
    variances, axes = np.linalg.eigh(covariance)
    normal = axes[:, :, 0] * np.where(_dot(axes[:, :, 0], towards) < 0, -1.0, 1.0)[:, None]
    return normal, _dot(normal, mean), np.sqrt(np.maximum(variances[:, 0], 0.0))


def _onto_line(normal_a: np.ndarray, offset_a: np.ndarray, normal_b: np.ndarray, offset_b: np.ndarray) -> np.ndarray:
    """The shortest step (c, 3) from the origin onto the line where the planes n·x = offset (unit
    normals (c, 3), offsets (c,)) a and b meet: in the span of the two normals. Zero where they
    are parallel."""
    cosine = _dot(normal_a, normal_b)
    determinant = 1.0 - cosine**2
    safe = np.where(determinant > 1e-6, determinant, np.inf)
    weight_a = (offset_a - cosine * offset_b) / safe
    weight_b = (offset_b - cosine * offset_a) / safe
    return weight_a[:, None] * normal_a + weight_b[:, None] * normal_b


def _unturned(vertices: np.ndarray, before: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``vertices`` with the moved ones (those not at ``before``) of faces turned over (against their
    normal at ``before``) put back, until no face is."""
    vertices = vertices.copy()
    for _ in range(PASSES):
        moved = np.flatnonzero((vertices != before).any(axis=1))
        around = np.flatnonzero(np.isin(faces, moved).any(axis=1))
        turned = around[_dot(face_normals(before, faces[around]), face_normals(vertices, faces[around])) <= 0]
        back = np.intersect1d(faces[turned], moved)
        if len(back) == 0:
            break
        vertices[back] = before[back]
    return vertices


def _along(vectors: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Each row's vectors (c, k, 3) along its direction (c, 3): (c, k)."""
    return (vectors @ directions[:, :, None])[:, :, 0]


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products of (n, 3) arrays: (n,)."""
    return np.einsum("ij,ij->i", a, b)
