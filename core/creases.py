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
face meets the other off the edge. Where the curved face is a wall upright on a flat one (a drilled
hole, a boss), a cylinder about the flat face's normal is fitted to the wall's points instead, the
rim goes onto the circle where it meets the plane, and the mesh's vertices around the rim go onto
the two faces (``_onto_rims``, ``_onto_rim_faces``).

The same planes give the normals of the input points beside an edge (``normals_on_faces``): ∇f
there leans towards the other face over the band the fit rounds, and the refitted plane is the
face the point lies on. Where no refit holds, a face's normal is read from ∇f farther along it,
past the rounding.
"""

from __future__ import annotations

from dataclasses import replace
from typing import NamedTuple

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from core.curves import Curve
from core.features import angles, face_normals, unit
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
# A rim (``_onto_rims``): degrees a wall's point's fit normal may lean from upright on the flat
# face, and the largest radius of a wall refitted as a cylinder (unit frame): at most REACH, so
# that the points around a rim point hold a third of its circle or more. Fitted over less, the
# circle misplaced the rim by the noise: on idler_riser's wall of radius about 0.4, neighbouring
# rim points read radii 0.385 and 0.474, 0.005-0.010 off the true rim, and its exact d_C went 0.0014 ->
# 0.0016 (docs/benchmarks.md).
UPRIGHT = 15.0
MAX_RADIUS = REACH
# Degrees: a wall point's fit normal lies within FACING of the circle's normal there; the points
# that start the circle, within START_FACING of the wall's normal at the rim point and within
# RIM_START (unit frame) of its tangent plane there: a wider arc than BAND's, since Kåsa's fit to a
# short arc's noisy points goes far astray (a radius of 0.004 for a hole of 0.088).
FACING = 30.0
START_FACING = 45.0
RIM_START = 0.05
WALL_REACH = 0.03  # unit frame: mesh vertices this near a refitted rim point go onto its faces (``_onto_rim_faces``)
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
# face's normal if it lies within this many of that face (the half-plane on its side of the edge,
# or the rim's plane or wall) and this many nearer it than the other. Nearer the edge, noise may
# have carried a point from the other face, and a normal given the wrong face of a right-angled
# edge points inward by a hair: at 2.5 one point of the cube's 16,384 did (docs/benchmarks.md).
CLEAR = 3.0
MAX_TURN = 30.0  # degrees: the most a point's normal turns from the fit's to take its face's
# Degrees: and the most the fit's normal may lean along the edge. A fit rounds an edge about the
# edge's direction, so near a flat face's edge ∇f leans towards the other face only; on a curved
# face (a cylinder's wall at its rim) the plane refitted at a curve sample is turned along the edge
# from the face's normal beside it, as ∇f there is.
ALONG_EDGE = 2.0
# A point nearer the edge than that, but within CLEAR of a face, takes the nearer face's normal all
# the same: a wrong face costs the angle between the faces' normals, the fit's rounded normal about
# half of it at every point, and the nearer face is the likelier. Where those normals are about
# square (within SQUARE degrees of 90 apart, or more: a refitted plane may be a few degrees off),
# the point's is turned towards the other's until it is HEDGE degrees short of square with it, so
# that a wrong face does not point inward (at 1 degree 4 points of l_bracket's 16,384 did, at 2
# none of five shapes'; 4 leaves room for planes refitted to noisier points; without SQUARE one of
# slotted_plate's, between planes refitted 86 degrees apart). At an acute edge (normals more than
# HEDGE_LIMIT apart) that turn costs more than the fit's rounding: the point keeps ∇f. On seed-0
# fits, mean normal error: l_bracket 5.05° -> 4.15°, cube 2.27° -> 1.98°, box_hole 3.29° -> 2.74°
# (docs/benchmarks.md).
HEDGE = 4.0
HEDGE_LIMIT = 95.0
SQUARE = 10.0
# Beside a stretch of edge where no refit holds (a face curved along the edge, as the flange's rim of
# radius 0.5, wider than MAX_RADIUS; a short edge between corners; on seed-0 fits 86 % of the
# flange's curve samples and 97 % of idler_riser's), a point within ACROSS_REACH of it takes its
# face's normal as the fit has it ACROSS from the edge along the face, past the band the fit rounds:
# the mean ∇f of the input points within READ_REACH of there that face as the face does (at least
# MIN_READ of them). A face flat across the edge, or curved only along it (a cylinder's wall at its
# rim), has the same normal there as at the edge. The mesh's two faces at the crease say which face
# a point lies on (the nearer half-plane, by SIDE_MARGIN noise widths or more), and the point's ∇f
# must lie between that face and the other's as read (``MAX_TURN``) and nearer the point's face as
# read. Only at edges whose faces are MIN_APART degrees apart or more: at a shallower edge the fit
# rounds less, and a face curved across the edge reads as far off as the rounding (the flats of a
# shaft of radius 0.12: keyed_shaft's mean error rose 0.24°; a rounded block's fillets, 0.08°).
# And only where the reads are as far apart as the mesh's faces, within AGREE degrees (at seed 1
# featuretype's mesh faces were 50° apart and its reads 82°, one of them off its face). A read is
# a few degrees off where a refitted plane is a fraction of one (5° at a point of l_bracket's seed
# 1 that then pointed inward), so a point not CLEAR of the other face is turned READ_HEDGE short
# of square, not HEDGE. Seed-0 fits, mean normal error: flange 7.51° -> 7.02°, idler_riser 8.45°
# -> 8.14° (docs/benchmarks.md).
ACROSS_REACH = 0.03
ACROSS = 0.04
READ_REACH = 0.02
MIN_READ = 3
SIDE_MARGIN = 1.0
MIN_APART = 60.0
AGREE = 15.0
READ_HEDGE = 6.0


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
    target, holds, walls = _refitted(
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
    vertices = _onto_rim_faces(before, np.asarray(mesh.vertex_normals), walls)
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
    carried a quarter to a third of the mean normal error. A point's face is the nearer of the two
    as faces end, at the edge (a half-plane, not the whole plane: at an edge of 135 degrees the
    other face's plane runs on past the edge close beside this face). A point too near the edge to
    tell its face for sure (not ``CLEAR`` noise widths nearer one than the other) takes the nearer
    one's normal turned towards the other's as far as ``HEDGE`` asks, if ∇f there lies between the
    two (within ``MAX_TURN``) and the edge is not acute (``HEDGE_LIMIT``); a point clear of the
    edge takes its face's normal if ∇f is within ``MAX_TURN`` of it (a third face's point, near a
    corner, is not). Either keeps ∇f where it leans along the edge by more than ``ALONG_EDGE`` (a
    curved face). A point beside a sample where no refit holds, within ``ACROSS_REACH``, takes its
    face's normal as the fit has it ``ACROSS`` from the edge, past its rounding (``_read_across``),
    where the rules there allow; the noise width is read from the refits that hold, and without
    one every point keeps ∇f.
    """
    if not curves:
        return normals
    rows = subsample_rows(len(points), CLOUD_POINTS, seed=0)
    at = np.concatenate([curve.points for curve in curves])
    side_a = np.concatenate([curve.left for curve in curves])
    side_b = np.concatenate([curve.right for curve in curves])
    convex = np.concatenate([np.full(len(curve.points), curve.convex) for curve in curves])
    tree = kd_tree(points[rows])
    planes = _planes(at, side_a, side_b, convex, tree, points[rows], normals[rows])
    rim_rows, rims = _rims_beside(at, side_a, side_b, convex, planes, tree, points[rows], normals[rows])
    holds = planes.holds.copy()
    holds[rim_rows] = True
    if not holds.any():
        return normals
    noise = float(np.median(np.concatenate([planes.spread[planes.holds].ravel(), rims.spread])))
    held = np.flatnonzero(holds)
    to_held, nearest = kd_tree(at[held]).query(points, distance_upper_bound=NORMAL_REACH, workers=workers)
    found = np.flatnonzero(nearest < len(held))
    samples = kd_tree(at)
    to_any, _ = samples.query(points[found], workers=workers)
    found = found[to_held[found] - to_any < HELD_GAP]
    sample = held[nearest[found]]
    face, other = np.zeros((len(found), 3)), np.zeros((len(found), 3))
    to_face, to_other = np.zeros(len(found)), np.zeros(len(found))
    on_planes = planes.holds[sample]
    by_plane = sample[on_planes]
    face[on_planes], other[on_planes], to_face[on_planes], to_other[on_planes] = _face_of_planes(
        points[found[on_planes]] - at[by_plane],
        (planes.normal_a[by_plane], planes.offset_a[by_plane]),
        (planes.normal_b[by_plane], planes.offset_b[by_plane]),
        convex[by_plane],
    )
    rim_of = np.full(len(at), -1)
    rim_of[rim_rows] = np.arange(len(rim_rows))
    on_rims = ~on_planes
    face[on_rims], other[on_rims], to_face[on_rims], to_other[on_rims] = _face_of_rims(
        points[found[on_rims]], rims, rim_of[sample[on_rims]]
    )
    fitted = normals[found]
    edge = unit(np.cross(planes.normal_a[sample], planes.normal_b[sample]))
    near = to_face < CLEAR * noise
    near &= ~on_planes | (np.abs(_dot(fitted, edge)) < np.sin(np.radians(ALONG_EDGE)))
    off_face = angles(fitted, face)
    clear = near & (to_other - to_face > CLEAR * noise) & (off_face < MAX_TURN)
    apart = angles(face, other)
    between = off_face + angles(fitted, other) < apart + MAX_TURN
    unsure = near & ~clear & between & (apart < HEDGE_LIMIT)
    result = normals.copy()
    result[found[clear]] = face[clear]
    result[found[unsure]] = _hedged(face[unsure], other[unsure], apart[unsure])
    done = np.zeros(len(points), dtype=bool)
    done[found[clear | unsure]] = True
    _, closest = samples.query(points, distance_upper_bound=ACROSS_REACH, workers=workers)
    beside = np.flatnonzero(~done & (closest < len(at)))
    beside = beside[~holds[closest[beside]]]
    sample = closest[beside]
    bare, which = np.unique(sample, return_inverse=True)
    (read_a, enough_a), (read_b, enough_b) = (
        _read_across(at[bare], this[bare], that[bare], convex[bare], tree, normals[rows])
        for this, that in ((side_a, side_b), (side_b, side_a))
    )
    across, read = _faces_across(
        points[beside] - at[sample],
        normals[beside],
        (side_a[sample], side_b[sample]),
        (read_a[which], read_b[which]),
        convex[sample],
        noise,
    )
    read &= enough_a[which] & enough_b[which]
    result[beside[read]] = across[read]
    return result


def _faces_across(
    offsets: np.ndarray,
    fitted: np.ndarray,
    sides: tuple[np.ndarray, np.ndarray],
    reads: tuple[np.ndarray, np.ndarray],
    convex: np.ndarray,
    noise: float,
) -> tuple[np.ndarray, np.ndarray]:
    """For points at ``offsets`` (n, 3) from curve samples where no refit holds, with their fit's
    unit normals ``fitted`` (n, 3), beside edges between two faces of unit normals ``sides`` (n, 3)
    each as the mesh has them at the crease and ``reads`` (n, 3) each as read across them
    (``_read_across``), convex or not (n,), in a cloud of ``noise`` width: the point's face's
    normal as read (n, 3), turned as ``_hedged`` asks where the point is not ``CLEAR`` of the other
    face, and whether the rules given with ``ACROSS_REACH`` let it take that (n,)."""
    (side_a, side_b), (read_a, read_b) = sides, reads
    no_offset = np.zeros(len(offsets))
    to_a, to_b = _to_faces(offsets, (side_a, no_offset), (side_b, no_offset), convex)
    mesh_face, _, to_face, to_other = _nearer_first(side_a, to_a, side_b, to_b)
    face, other, _, _ = _nearer_first(read_a, to_a, read_b, to_b)
    crease = angles(mesh_face, other)
    off_face, off_other = angles(fitted, face), angles(fitted, other)
    use = to_other - to_face > SIDE_MARGIN * noise
    use &= (off_face < off_other) & (angles(fitted, mesh_face) + off_other < crease + MAX_TURN)
    use &= (crease >= MIN_APART) & (crease < HEDGE_LIMIT)
    use &= np.abs(angles(read_a, read_b) - angles(side_a, side_b)) < AGREE
    sure = (to_other - to_face > CLEAR * noise)[:, None]
    return np.where(sure, face, _hedged(face, other, angles(face, other), READ_HEDGE)), use


def _read_across(
    at: np.ndarray, face: np.ndarray, other: np.ndarray, convex: np.ndarray, tree: cKDTree, normals: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """For points ``at`` (s, 3) on edges between faces of unit normals ``face`` and ``other`` (s,
    3), convex or not (s,): the mean unit normal (s, 3) of the points (in the k-d ``tree``, their
    fit's unit ``normals`` (m, 3)) within ``READ_REACH`` of the spot ``ACROSS`` from each along
    ``face``, those within ``MAX_TURN`` of ``face``, and whether there were ``MIN_READ`` (s,)."""
    spots = at + ACROSS * _into_face(face, other, convex)
    found = tree.query_ball_point(spots, READ_REACH)
    counts = np.fromiter((len(row) for row in found), dtype=np.int64, count=len(found))
    owner = np.repeat(np.arange(len(spots)), counts)
    near = np.fromiter((index for row in found for index in row), dtype=np.int64, count=int(counts.sum()))
    facing = _dot(normals[near], face[owner]) > np.cos(np.radians(MAX_TURN))
    total = np.zeros((len(spots), 3))
    np.add.at(total, owner[facing], normals[near[facing]])
    enough = np.bincount(owner[facing], minlength=len(spots)) >= MIN_READ
    return unit(total), enough


def _hedged(face: np.ndarray, other: np.ndarray, apart: np.ndarray, hedge: float = HEDGE) -> np.ndarray:
    """Unit normals ``face`` (n, 3) turned towards ``other`` (n, 3) until ``hedge`` degrees short
    of square with it where they are ``apart`` (n,) degrees, within ``SQUARE`` of square or more."""
    turn = np.where(apart > 90.0 - SQUARE, np.maximum(apart, 90.0) - (90.0 - hedge), 0.0)
    return _turned(face, other, np.radians(turn))


def _face_of_planes(
    offsets: np.ndarray,
    plane_a: tuple[np.ndarray, np.ndarray],
    plane_b: tuple[np.ndarray, np.ndarray],
    convex: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For points at ``offsets`` (n, 3) from their edge samples, on edges ``convex`` (n,) or not
    between two faces' planes, unit normals (n, 3) and offsets (n,) as n·offset = offset, each:
    the unit normals (n, 3) of the nearer face and of the other, and their distances (n,) to the
    nearer and to the other (``_to_faces``)."""
    to_a, to_b = _to_faces(offsets, plane_a, plane_b, convex)
    return _nearer_first(plane_a[0], to_a, plane_b[0], to_b)


def _to_faces(
    offsets: np.ndarray,
    plane_a: tuple[np.ndarray, np.ndarray],
    plane_b: tuple[np.ndarray, np.ndarray],
    convex: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The distances (n,) of points at ``offsets`` (n, 3) to face a and to face b, as in
    ``_face_of_planes``. A face is the half of its plane on its side of the line where the planes
    meet."""
    (normal_a, offset_a), (normal_b, offset_b) = plane_a, plane_b
    from_line = offsets - _onto_line(normal_a, offset_a, normal_b, offset_b)
    distances = []
    for normal, offset, other in ((normal_a, offset_a, normal_b), (normal_b, offset_b, normal_a)):
        across = _dot(offsets, normal) - offset
        into = _dot(from_line, _into_face(normal, other, convex))
        distances.append(np.where(into >= 0, np.abs(across), np.hypot(across, into)))
    return distances[0], distances[1]


def _into_face(face: np.ndarray, other: np.ndarray, convex: np.ndarray) -> np.ndarray:
    """The unit direction (c, 3) along a face (unit normals ``face`` (c, 3)) away from its edge
    with the face of normals ``other`` (c, 3): into the other plane's solid side at a ``convex``
    (c,) edge, out of it at a concave one."""
    along = unit(np.cross(np.cross(face, other), face))
    return along * np.where((_dot(along, other) < 0) != convex, -1.0, 1.0)[:, None]


def _face_of_rims(
    points: np.ndarray, rims: _Rims, rim: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For ``points`` (n, 3) beside their rims (rows ``rim`` (n,) of ``rims``): the unit normals (n,
    3) of the nearer of the rim's faces (the flat face's plane on its side of the circle, the
    wall's cylinder past the plane) and of the other, and their distances (n,) to the nearer and
    to the other."""
    depth, beyond, outward = _about_rim(points, rims, rim)
    to_flat = np.hypot(depth, np.minimum(beyond, 0.0))
    to_wall = np.hypot(beyond, np.minimum(depth, 0.0))
    return _nearer_first(rims.flat[rim], to_flat, rims.facing[rim][:, None] * outward, to_wall)


def _nearer_first(
    normal_a: np.ndarray, to_a: np.ndarray, normal_b: np.ndarray, to_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Of two faces per point, unit normals ``normal_a`` and ``normal_b`` (n, 3) at distances
    ``to_a`` and ``to_b`` (n,): the nearer face's normal and the other's (n, 3), and the distances
    (n,) to the nearer and to the other."""
    nearer_a = (to_a < to_b)[:, None]
    return (
        np.where(nearer_a, normal_a, normal_b),
        np.where(nearer_a, normal_b, normal_a),
        np.minimum(to_a, to_b),
        np.maximum(to_a, to_b),
    )


def _turned(face: np.ndarray, other: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Unit vectors ``face`` (n, 3) turned towards ``other`` (n, 3) by ``angle`` (n,) radians, in
    their plane."""
    towards = unit(other - _dot(face, other)[:, None] * face)
    return np.cos(angle)[:, None] * face + np.sin(angle)[:, None] * towards


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
) -> tuple[np.ndarray, np.ndarray, _Rims]:
    """For points ``at`` (c, 3) on an edge between faces of unit normals ``side_a`` and ``side_b``
    (c, 3) through them, convex or not (c,): the nearest point (c, 3) of the line where the planes
    refitted to the input ``points`` meet, or, beside a flat face whose other face is curved, of
    the circle where that face's plane meets a wall upright on it (``_onto_rims``); ``at`` itself
    where neither refit holds. And whether one holds (c,), and the walls' cylinders of the rim
    refits that hold (``_Rims``)."""
    tree = kd_tree(points)
    planes = _planes(at, side_a, side_b, convex, tree, points, normals)
    step = _onto_line(planes.normal_a, planes.offset_a, planes.normal_b, planes.offset_b)
    holds = planes.holds.copy()
    rows, rims = _rims_beside(at, side_a, side_b, convex, planes, tree, points, normals)
    step[rows] = rims.step
    holds[rows] = True
    holds &= np.linalg.norm(step, axis=1) <= MAX_MOVE
    return np.where(holds[:, None], at + step, at), holds, rims


def _rims_beside(
    at: np.ndarray,
    side_a: np.ndarray,
    side_b: np.ndarray,
    convex: np.ndarray,
    planes: _Planes,
    tree: cKDTree,
    points: np.ndarray,
    normals: np.ndarray,
) -> tuple[np.ndarray, _Rims]:
    """The rows of ``at`` (c, 3) whose ``planes`` do not hold because one face is flat and the other
    curved, and whose rim refit (``_onto_rims``, ``_CHUNK`` rows at a time) holds and moves the
    point at most ``MAX_MOVE``, with those refits."""
    sides = (side_a, side_b)
    flats = ((planes.normal_a, planes.offset_a), (planes.normal_b, planes.offset_b))
    found, refits = [np.zeros(0, dtype=np.int64)], [_no_rims()]
    for flat, wall in ((0, 1), (1, 0)):
        rows = np.flatnonzero(~planes.holds & planes.flat[:, flat] & ~planes.flat[:, wall])
        normal, offset = flats[flat]
        for part in (rows[start : start + _CHUNK] for start in range(0, len(rows), _CHUNK)):
            rims = _onto_rims(
                at[part],
                normal[part],
                offset[part],
                planes.spread[part, flat],
                sides[wall][part],
                convex[part],
                tree,
                points,
                normals,
            )
            held = rims.holds & (np.linalg.norm(rims.step, axis=1) <= MAX_MOVE)
            found.append(part[held])
            refits.append(_Rims(*(field[held] for field in rims)))
    return np.concatenate(found), _Rims(*(np.concatenate(part) for part in zip(*refits, strict=True)))


def _no_rims() -> _Rims:
    """No rim refits."""
    empty, none = np.zeros((0, 3)), np.zeros(0)
    return _Rims(empty, np.zeros(0, dtype=bool), empty, empty, empty, empty, empty, none, none, none)


class _Planes(NamedTuple):
    """Two faces' planes refitted around c points on their edge: unit normals (c, 3) and offsets
    (c,) as n·(x - at) = offset, a's then b's; the spread of each face's points off its plane (c,
    2); whether each face is flat along the edge and not turned far from its face (c, 2); and
    whether the refit holds (c,): both flat, spread alike."""

    normal_a: np.ndarray
    offset_a: np.ndarray
    normal_b: np.ndarray
    offset_b: np.ndarray
    spread: np.ndarray
    flat: np.ndarray
    holds: np.ndarray


class _Rims(NamedTuple):
    """Rim refits of c points (``_onto_rims``): the step (c, 3) onto the rim and whether it holds
    (c,); the crease point it was read at and the rim point (c, 3) each; the flat face's refitted
    outward normal (c, 3); the wall's cylinder: a point (c, 3) of its axis on the flat face's
    plane, the axis's unit direction (c, 3) into the wall (depth grows along it), its radius (c,),
    and which way the wall faces (c,): 1 away from the axis (a boss), -1 towards it (a hole); and
    the spread of the flat face's points off its plane (c,)."""

    step: np.ndarray
    holds: np.ndarray
    at: np.ndarray
    point: np.ndarray
    flat: np.ndarray
    centre: np.ndarray
    axis: np.ndarray
    radius: np.ndarray
    facing: np.ndarray
    spread: np.ndarray


def _planes(
    at: np.ndarray,
    side_a: np.ndarray,
    side_b: np.ndarray,
    convex: np.ndarray,
    tree: cKDTree,
    points: np.ndarray,
    normals: np.ndarray,
) -> _Planes:
    """The two faces' planes refitted to the input ``points`` (in the k-d ``tree``) around each of
    ``at`` (as in ``_refitted``).
    In chunks of ``_CHUNK`` rows: each row holds up to ``MAX_POINTS`` points' coordinates and
    moments (about 50 kB), so memory stays bounded for any mesh."""
    parts = [
        _planes_chunk(at[rows], side_a[rows], side_b[rows], convex[rows], tree, points, normals)
        for rows in (slice(start, start + _CHUNK) for start in range(0, len(at), _CHUNK))
    ]
    if not parts:
        empty = np.zeros((0, 3))
        return _Planes(
            empty, np.zeros(0), empty, np.zeros(0), np.zeros((0, 2)), np.zeros((0, 2), bool), np.zeros(0, bool)
        )
    return _Planes(*(np.concatenate(part) for part in zip(*parts, strict=True)))


def _planes_chunk(
    at: np.ndarray,
    side_a: np.ndarray,
    side_b: np.ndarray,
    convex: np.ndarray,
    tree: cKDTree,
    points: np.ndarray,
    normals: np.ndarray,
) -> _Planes:
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
        along = _into_face(face, other, convex)
        facing.append(valid & (_along(offsets, along) > OFF_EDGE) & (_along(normals[near], face) > cosine))
    half = _along(offsets, edge) > 0
    normal_a, normal_b = side_a, side_b
    offset_a, offset_b = np.zeros(len(at)), np.zeros(len(at))
    for _ in range(PASSES):
        on_a = facing[0] & (np.abs(_along(offsets, normal_a) - offset_a[:, None]) < BAND)
        on_b = facing[1] & (np.abs(_along(offsets, normal_b) - offset_b[:, None]) < BAND)
        on_a, on_b = on_a & ~on_b, on_b & ~on_a  # a point near both planes is neither face's
        normal_a, offset_a, spread_a = _plane(moments, on_a, side_a)
        normal_b, offset_b, spread_b = _plane(moments, on_b, side_b)
    flat = []
    tilt = np.cos(np.radians(MAX_TILT))
    for chosen, face, normal in ((on_a, side_a, normal_a), (on_b, side_b, normal_b)):
        both_halves = ((chosen & half).sum(axis=1) >= MIN_POINTS // 2) & (
            (chosen & ~half).sum(axis=1) >= MIN_POINTS // 2
        )
        one_side, _, _ = _plane(moments, chosen & half, face)
        other_side, _, _ = _plane(moments, chosen & ~half, face)
        flat.append(
            both_halves & (_dot(one_side, other_side) > np.cos(np.radians(STRAIGHT))) & (_dot(normal, face) > tilt)
        )
    holds = flat[0] & flat[1] & (np.maximum(spread_a, spread_b) <= MAX_SPREAD * np.minimum(spread_a, spread_b))
    return _Planes(
        normal_a, offset_a, normal_b, offset_b, np.stack([spread_a, spread_b], axis=1), np.stack(flat, axis=1), holds
    )


def _onto_rims(
    at: np.ndarray,
    flat: np.ndarray,
    flat_offset: np.ndarray,
    flat_spread: np.ndarray,
    wall: np.ndarray,
    convex: np.ndarray,
    tree: cKDTree,
    points: np.ndarray,
    normals: np.ndarray,
) -> _Rims:
    """For points ``at`` (c, 3) on the rim where a flat face, of refitted plane ``flat`` (unit
    normals, (c, 3)) · (x - at) = ``flat_offset`` (c,) with its points' ``flat_spread`` (c,), meets
    a curved wall (its side's unit normal ``wall``, (c, 3)), convex or not (c,): the step (c, 3)
    onto the circle where that plane meets a cylinder about its normal refitted to the wall's
    points (a drilled hole, a boss, a disc's edge), whether it holds, and the cylinders (``_Rims``).

    A plane fitted to a curved wall meets the flat face off the rim, so such a refit is refused
    (``STRAIGHT``) and the rim stayed where the fit's rounding put it: on l_bracket's holes the
    wall bulges into the hole near the rim, the crease vertex followed its flank, and those rim
    vertices were that mesh's farthest (0.012 inside the holes at seed 0). The wall
    is the points upright on the plane (fit normal within ``UPRIGHT`` degrees of it) beyond the
    rim's rounding on the wall's side, within ``BAND`` of the circle and facing as the wall does;
    the circle is their least-squares fit (``_circle``) in the plane's coordinates, started from
    the wall's tangent plane at the rim point. The input ``points`` are in the k-d ``tree``."""
    near, valid = _neighbours(at, tree)
    offsets = points[near] - at[:, None]  # (c, k, 3), relative to the rim point
    # The plane's coordinates: x along the wall's normal, y along the rim, each row's own.
    across = unit(wall - _dot(wall, flat)[:, None] * flat)
    along = np.cross(flat, across)
    x, y = _along(offsets, across), _along(offsets, along)
    # The points' normals in the plane: the fit tilts a wall's normals out of it near the rim.
    normal_x, normal_y = _along(normals[near], across), _along(normals[near], along)
    length = np.maximum(np.hypot(normal_x, normal_y), 1e-12)
    normal_x, normal_y = normal_x / length, normal_y / length
    # Beyond the rounding on the wall's side of the plane: under it at a convex rim, over it at a concave one.
    depth = (_along(offsets, flat) - flat_offset[:, None]) * np.where(convex, -1.0, 1.0)[:, None]
    upright = valid & (depth > OFF_EDGE) & (np.abs(_along(normals[near], flat)) < np.sin(np.radians(UPRIGHT)))
    on_wall = upright & (np.abs(x) < RIM_START) & (normal_x > np.cos(np.radians(START_FACING)))
    centre_x, centre_y, radius = _circle(x, y, on_wall)
    for _ in range(PASSES):
        facing, distance, radial = _about_circle(centre_x, centre_y, x, y, normal_x, normal_y)
        on_wall = upright & (np.abs(distance - radius[:, None]) < BAND) & (radial > np.cos(np.radians(FACING)))
        centre_x, centre_y, radius = _circle(x, y, on_wall)
    facing, distance, radial = _about_circle(centre_x, centre_y, x, y, normal_x, normal_y)
    count = np.maximum(on_wall.sum(axis=1), 1)
    spread = np.sqrt(np.where(on_wall, (distance - radius[:, None]) ** 2, 0.0).sum(axis=1) / count)
    half = y > 0
    holds = ((on_wall & half).sum(axis=1) >= MIN_POINTS // 2) & ((on_wall & ~half).sum(axis=1) >= MIN_POINTS // 2)
    holds &= (radius < MAX_RADIUS) & (np.maximum(spread, flat_spread) <= MAX_SPREAD * np.minimum(spread, flat_spread))
    # A cylinder's normals lie along its radius: two flat walls at a corner read as one bend are off it.
    holds &= np.where(on_wall, radial, 0.0).sum(axis=1) / count > np.cos(np.radians(SAME_FACE))
    # The wall's normal at the rim turns no more than MAX_TILT from its side's (in the plane).
    from_centre = np.maximum(np.hypot(centre_x, centre_y), 1e-12)
    holds &= -facing * centre_x / from_centre > np.cos(np.radians(MAX_TILT))
    # The rim point on the plane (x = y = 0 there), then along the radius onto the circle.
    radius = np.where(holds, radius, 0.0)
    rim_x = centre_x - radius * centre_x / from_centre
    rim_y = centre_y - radius * centre_y / from_centre
    step = np.where(holds[:, None], flat_offset[:, None] * flat + rim_x[:, None] * across + rim_y[:, None] * along, 0.0)
    axis = flat * np.where(convex, -1.0, 1.0)[:, None]
    centre = at + flat_offset[:, None] * flat + centre_x[:, None] * across + centre_y[:, None] * along
    return _Rims(step, holds, at, at + step, flat, centre, axis, radius, facing, flat_spread)


def _onto_rim_faces(vertices: np.ndarray, normals: np.ndarray, rims: _Rims) -> np.ndarray:
    """``vertices`` (n, 3) within ``WALL_REACH`` of a refitted rim point (``rims``) moved onto its
    two faces, the flat face's plane and the wall's cylinder. A vertex's place across the rim is
    how far it lies beyond the circle along the plane less its depth past the plane (+ on the
    plane, - down the wall); that of the crease point the rim was read at goes to 0 (the rim), and
    the shift fades to nothing WALL_REACH along from it, so the rows of vertices across a rounded
    or bulging rim keep their order on the faces instead of meeting on the rim, where the faces
    between them would turn over. A vertex that would move more than ``BAND``, or whose mesh
    normal (``normals``, (n, 3)) leans against the flat face's (more than ``UPRIGHT`` beyond
    upright: the other side of a thin part), stays. Each takes the faces of its nearest rim point.

    The fit's surface is off where its rim is: on l_bracket's seed-0 fit the wall bulged 0.007-0.010
    into a hole over its top 0.03 and the flat face ran past the rim into it, and those vertices
    were that mesh's farthest."""
    vertices = vertices.copy()
    if len(rims.point) == 0:
        return vertices
    _, nearest = kd_tree(rims.point).query(vertices, distance_upper_bound=WALL_REACH)
    found = np.flatnonzero(nearest < len(rims.point))
    rim = nearest[found]
    centre, axis, radius = rims.centre[rim], rims.axis[rim], rims.radius[rim]
    depth, beyond, outward = _about_rim(vertices[found], rims, rim)
    along = beyond - depth
    start_depth, start_beyond, _ = _about_rim(rims.at[rim], rims, rim)
    shift = start_beyond - start_depth
    from_start = along - shift
    along = from_start + shift * np.minimum(np.abs(from_start) / WALL_REACH, 1.0)
    flat_side = _flat_side(rims, rim)
    on_flat = centre + (radius + flat_side * np.maximum(along, 0.0))[:, None] * outward
    target = on_flat + np.maximum(-along, 0.0)[:, None] * axis
    moves = np.linalg.norm(target - vertices[found], axis=1) < BAND
    moves &= _dot(normals[found], rims.flat[rim]) > -np.sin(np.radians(UPRIGHT))
    vertices[found[moves]] = target[moves]
    return vertices


def _about_rim(points: np.ndarray, rims: _Rims, rim: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where ``points`` (n, 3) lie about the faces of their rims (``rim``, (n,), rows of ``rims``):
    their depth past the flat face's plane into the wall (n,), how far they lie beyond the wall's
    circle on the plane's side of it (n,), and the unit direction (n, 3) from the axis to them."""
    offsets = points - rims.centre[rim]
    depth = _dot(offsets, rims.axis[rim])
    radial = offsets - depth[:, None] * rims.axis[rim]
    length = np.maximum(np.linalg.norm(radial, axis=1), 1e-12)
    return depth, _flat_side(rims, rim) * (length - rims.radius[rim]), radial / length[:, None]


def _flat_side(rims: _Rims, rim: np.ndarray) -> np.ndarray:
    """Which side of the wall's circle the flat face lies on (n,) for rows ``rim`` of ``rims``: 1
    outside, -1 inside. Beyond the circle from the wall's face at a convex rim (a hole's, a boss's
    top), before it at a concave one (a boss's foot, a counterbore's floor)."""
    return rims.facing[rim] * np.where(_dot(rims.axis[rim], rims.flat[rim]) < 0, -1.0, 1.0)


def _about_circle(
    centre_x: np.ndarray, centre_y: np.ndarray, x: np.ndarray, y: np.ndarray, normal_x: np.ndarray, normal_y: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row, of a wall about the centre (c,) x and y, through the rim point at the origin: which
    way it faces there (c,), 1 away from the centre (a boss), -1 towards it (a hole); the points'
    (x, y) (c, k) distances from the centre (c, k); and the cosine (c, k) between their unit
    normals (``normal_x``, ``normal_y``) and the wall's there, along the radius."""
    facing = np.where(centre_x < 0, 1.0, -1.0)
    to_x, to_y = x - centre_x[:, None], y - centre_y[:, None]
    distance = np.maximum(np.hypot(to_x, to_y), 1e-12)
    return facing, distance, facing[:, None] * (normal_x * to_x + normal_y * to_y) / distance


def _circle(x: np.ndarray, y: np.ndarray, chosen: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row, the circle through the ``chosen`` (c, k) points (x, y) (c, k) in the least-squares
    sense of x² + y² + d x + e y + f = 0 (Kåsa's fit: linear, exact on a circle): centres (c,) x
    and y, and radii (c,); an infinite radius about the origin where the points lie on a line or
    are too few."""
    weight = chosen.astype(np.float64)
    rows = np.stack([x, y, np.ones_like(x)], axis=2) * weight[:, :, None]  # (c, k, 3)
    system = np.einsum("cki,ckj->cij", rows, np.stack([x, y, np.ones_like(x)], axis=2))
    rhs = -np.einsum("cki,ck->ci", rows, x**2 + y**2)
    solvable = np.abs(np.linalg.det(system)) > 1e-18 * np.maximum(np.abs(system).max(axis=(1, 2)), 1e-300) ** 3
    safe = np.where(solvable[:, None, None], system, np.eye(3))
    d, e, f = np.linalg.solve(safe, rhs[:, :, None])[:, :, 0].T
    centre_x, centre_y = -d / 2, -e / 2
    radius = np.sqrt(np.maximum(centre_x**2 + centre_y**2 - f, 0.0))
    return np.where(solvable, centre_x, 0.0), np.where(solvable, centre_y, 0.0), np.where(solvable, radius, np.inf)


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
