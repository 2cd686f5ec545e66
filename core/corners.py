"""Corners: where three faces meet, the mesh's vertex goes back onto the point their planes share.

The sharpening of ``core.dual`` reads the faces beside each edge by walking across it; near a corner
those walks run onto a third face, so the edges' curves stop 0.02 to 0.04 short of the corner and
the mesh keeps it rounded: the true corner lies 0.012 to 0.015 from the mesh on the fits of the
sample parts, the largest part of their Hausdorff distance. The curves themselves say where the
corner is: the curves ending near one another carry, sample by sample, the normals of the faces on
their two sides. Where those normals fall into three faces, each pair of which has an edge among
the samples, the three planes meet at one point; the mesh vertex nearest to it is put there, and
the vertices of the rounding around it onto the faces. The side normals near a corner are partly the
rounding's, so where the input points are given, each plane is then refitted to the points of its
face around the corner, off the other two faces. Where the curves do not show three faces (an
acute ridge comes out as two creases a strip apart, and the edges of the thin face it runs into
in scraps), the faces are read from the input points around the curves' ends instead, grouped
by the fit's normals there; and where a curve runs round a corner whose third edge stops short of
it (a pocket's floor corner), from the points around its bend. The same walks, run onto the third
face, also read tilted planes that meet beyond the true faces, and the sharpening pushes vertices
near a corner past them (into the solid of a concave corner, out of a convex one's); those go back
onto the corner's faces too. At a saddle (a slot's end, where its concave edge meets the end face's
convex ones) the fit rounds the convex edges from the solid and fills the concave one from the
empty side: there every vertex near the corner off its faces may go onto them, as far as the points
agree.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np
import trimesh
from scipy.sparse import csr_matrix

from core.curves import Curve, curve_ends, linked
from core.features import angles, face_normals, unit
from core.intersections import uncrossed
from core.trees import kd_tree

CORNER_REACH = 0.08  # unit frame: the curve samples read around the curves' ends that meet
SAME_FACE = 15.0  # degrees: normals of one face (the sample parts' faces meet at 35 degrees or more)
MIN_NORMALS = 6  # side normals that make a face (three samples of each of its two edges)
MIN_SUPPORT = 3  # samples of each of the corner's three edges (a hole's rim has one edge, not three)
MIN_DETERMINANT = 0.3  # |det| of the three faces' normals: far from a fan of nearly parallel faces
SNAP_RADIUS = 0.02  # unit frame: mesh vertices this near a corner and inside its faces go onto them
# Unit frame: the farthest a vertex beyond a corner's faces (within BEYOND_REACH of it) moves onto
# them, as far as ``core.creases`` moves a crease vertex. On the seed-0 fits of octagon_pocket and
# l_bracket the sharpening had put vertices 0.012 to 0.024 past the faces of a corner.
BEYOND_MOVE = 0.02
# Unit frame: how far from a corner its planes are read as its faces for that. Within the join
# (0.05) octagon_pocket's pocket floor edges were left 0.011 into the wall 0.05 from the corner,
# where the crease refit does not hold (its worst vertex 0.0141 and 0.0145 from the truth at seeds
# 0 and 1); at 0.08 0.0102 and 0.0109. The planes are fitted to the points within 0.16.
BEYOND_REACH = 0.08
# Shares of its way back that a vertex beyond a corner's faces tries, in turn, where its move onto
# them turns over, collapses or folds one of its faces (several go onto the corner's point), before
# it stays where it was.
_BACK_SHARES = (0.25, 0.5)
# The least share of its area, seen along its normal before, that a face keeps when vertices
# beyond a corner's faces move: less is a face turned over, collapsed or folded edge-on. At 0 (only
# faces turned over) faces folded edge-on were left on the open box, three of which crossed once
# the OBJ file rounded them; at 0.25 none, and octagon_pocket's d_H 0.0140 -> 0.0121.
_LEAST_AREA = 0.25
# Input points whose mean distance says whether a move onto a corner's faces brings a vertex
# nearer the surface they sample (with 4 or 8, hex_nut's or octagon_pocket's d_H came out higher).
_NEAREST_POINTS = 16
# The planes of a corner found from the curves are refitted to the input points within
# _REFIT_REACH of it that lie within _REFIT_BAND of one plane and inside the other two by more
# than PLANE_BAND (off the rounding), _REFIT_PASSES times. Read from the curves' side normals alone,
# which near the corner include the rounding's, the planes of octagon_pocket's pocket corner were
# tilted by 4-11 degrees and the corner went 0.0196 off the truth; refitted, the corners of
# thirteen fits of seven shapes lie 40 % nearer the truth on average, the worst 0.0080 off it
# (docs/benchmarks.md).
PLANE_BAND = 0.01
_REFIT_REACH = 0.16
_REFIT_BAND = 0.02  # four times the noise of the sample data: nearly the whole spread of a face's points
_REFIT_PASSES = 3
_REFIT_POINTS = 12  # input points that make a plane
_REFIT_SPREAD = 1.5  # the widest spread of a plane's points off it, over the narrowest
# Where the curves do not show a corner's three faces (wedge's acute ridge comes out as two creases
# a strip apart, and its end face's edges in scraps), the faces are read from the input points
# within _POINTS_REACH of the curves' ends, grouped by the fit's normals. Wider than _REFIT_REACH:
# two faces meeting at 26 degrees cross at a point four times as far off as their planes are,
# and the wedge's ridge tips (two fits) came out 0.0046-0.0058 from the truth at 0.35 against
# 0.0135-0.0227 at 0.16 (docs/benchmarks.md).
_POINTS_REACH = 0.35
_GROUPED = 1024  # of those points, grouped by normal (its cost grows as the square of their number)
_FACES_TRIED = 6  # largest groups read as faces: every three of them are tried (20 at most)
_FLAT = 5.0  # degrees: a face's plane is fitted to its points whose fit normal is this near its own
# The least share of a group's normals within _FLAT of their mean that makes it a face. A strip of a
# cylinder's wall, its normals spread evenly over SAME_FACE either way, has a third (flat within the
# noise though it is); the faces of the sample parts have 0.6 and more: on a shaft's rim such strips
# made corners 0.02 off the surface.
_FLAT_SHARE = 0.5
_CANDIDATES = 8  # mesh vertices tried for the corner itself, nearest first
_INSIDE = 1e-6  # unit frame: how far inside a plane counts as inside
# Where the edges of a corner come out as one curve that runs round it (a pocket's floor edges,
# when the upright edge between its walls stops short of the floor), the corner has no ends near
# it. A curve's course over BEND_REACH before a sample and over BEND_REACH after it turning by more
# than BEND_ANGLE degrees marks a place to look for one in the input points, as for the ends of
# curves that show no corner (``_corner_of_points``); a hole's rim turns as much where its radius
# is under 0.05, and the points there show no three faces that meet.
BEND_REACH = 0.04
BEND_ANGLE = 45.0
BEND_POINTS_REACH = 0.16
# Read that near, a cylinder's strips pass for faces (a strip within SAME_FACE of one normal is flat
# within the noise), and a shaft's rim gave seven corners 0.02 off its surface. Such a corner is
# kept only where the curves show each of its three edges: SEEN_SAMPLES samples within
# BEND_POINTS_REACH of it and SEEN_BAND of the line two of its planes share. Two strips of a smooth
# wall have no crease between them; a pocket's upright edge, stopped 0.08 above its floor, has.
SEEN_SAMPLES = 3
SEEN_BAND = 0.015


@dataclass
class Corner:
    """A corner: its ``point`` (3,), and the planes of its three faces, ``normals`` (3, 3) and
    ``offsets`` (3,), oriented so that n·x <= offset holds on the side the fit rounds it from (the
    solid of a convex corner, the empty space of a concave one): the corner's region is inside all
    three. A saddle (a concave edge meeting two convex ones, or a convex edge two concave ones) has
    the face ``apart`` whose two edges are alike: its region is inside that plane and inside
    either of the other two (the solid where the odd edge is concave, the empty space where it is
    convex), so that every edge of it but the odd one is rounded from inside it."""

    point: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray
    apart: int | None = None

    def inside(self, points: np.ndarray) -> np.ndarray:
        """How far each of ``points`` (m, 3) lies inside each plane (m, 3); negative outside."""
        return self.offsets[None] - points @ self.normals.T

    def region(self, inside: np.ndarray) -> np.ndarray:
        """Whether points that lie ``inside`` (m, 3) each plane by so much are in the region (m,)."""
        within = np.asarray(inside >= 0)
        if self.apart is None:
            return np.all(within, axis=1)
        first, second = (index for index in range(3) if index != self.apart)
        return (within[:, first] | within[:, second]) & within[:, self.apart]

    def on_faces(self, points: np.ndarray) -> np.ndarray:
        """Whether each of ``points`` (m, 3) lies on the region's boundary (within ``_INSIDE``): its
        faces, edges or the corner itself (m,)."""
        inside = self.inside(points)
        return self.region(inside + _INSIDE) & ~self.region(inside - _INSIDE)


@dataclass
class _Face:
    """A face read from the input points: its plane (unit ``normal``, ``offset``), how far its
    ``points`` (m, 3) ``spread`` off it (their standard deviation)."""

    normal: np.ndarray
    offset: float
    spread: float
    points: np.ndarray


def snap_corners(
    mesh: trimesh.Trimesh,
    curves: list[Curve],
    join: float,
    points: np.ndarray | None = None,
    normals: np.ndarray | None = None,
) -> tuple[trimesh.Trimesh, list[Corner]]:
    """``mesh`` with its rounded corners put back, and the corners of ``curves`` (``corners``).

    With the input ``points`` (n, 3, unit frame) and the fit's ``normals`` (n, 3) at them, the
    corners are found as ``corners`` finds them with those. For each corner the nearest vertex
    within ``join`` goes onto its point (or the next nearest, of ``_CANDIDATES``, where that would
    turn a face over); then, at a corner whose edges are alike, each vertex within ``SNAP_RADIUS``
    that lies inside all three faces' planes (the rounding) goes onto the nearest point of the
    faces, unless a face of it would turn over. A moved vertex of a face that then crosses or
    touches another (``core.intersections``) goes back where it was: on featuretype two faces did.
    Last, the vertices within ``BEYOND_REACH`` beyond one of the planes (any off a saddle's faces)
    go onto the faces (``_beyond_onto_faces``), and back again where a face of theirs then crosses
    another. Returns a new mesh, same faces."""
    found = corners(curves, join, points, normals)
    if not found:
        return mesh, found
    vertices, faces = np.array(mesh.vertices, dtype=np.float64), mesh.faces
    rows = np.repeat(np.arange(len(faces)), 3)
    faces_of = csr_matrix((np.ones(len(rows), dtype=np.int8), (faces.ravel(), rows)), (len(vertices), len(faces)))
    tree = kd_tree(vertices)
    for corner in found:
        distance, nearest = (np.atleast_1d(a) for a in tree.query(corner.point, k=min(_CANDIDATES, len(vertices))))
        for vertex in nearest[distance <= join]:
            if _move(vertices, faces[faces_of[vertex].indices], vertex, corner.point):
                break
        around = np.asarray(tree.query_ball_point(corner.point, SNAP_RADIUS), dtype=np.int64)
        for vertex in around[np.argsort(np.linalg.norm(vertices[around] - corner.point, axis=1))]:
            if corner.apart is None and (corner.inside(vertices[vertex][None]) > _INSIDE).all():
                _move(vertices, faces[faces_of[vertex].indices], vertex, _onto_faces(vertices[vertex], corner))
    snapped = uncrossed(vertices, mesh.vertices, faces)
    vertices = _beyond_onto_faces(snapped, faces, found, BEYOND_REACH, points)
    return trimesh.Trimesh(uncrossed(vertices, snapped, faces), faces, process=False), found


def _beyond_onto_faces(
    vertices: np.ndarray, faces: np.ndarray, found: list[Corner], reach: float, points: np.ndarray | None = None
) -> np.ndarray:
    """``vertices`` (v, 3) with each one within ``reach`` of a corner of ``found`` that lies beyond
    one of its planes (off its faces either way, at a saddle, whose rounding lies on both sides)
    moved onto the nearest point of its faces (``_onto_faces``), if that is no more than
    ``BEYOND_MOVE`` away and, given the input ``points`` (n, 3), brings it nearer them
    (the mean distance to its ``_NEAREST_POINTS`` nearest); ``faces`` (f, 3).

    Near a corner the sharpening reads planes tilted by the third face's rounding, which meet past
    the true faces: on octagon_pocket's pocket corners vertices lay 0.017 inside the solid, its
    Hausdorff distance. The points keep a corner whose planes are off from moving the mesh off
    the surface: around a chamfered block's small corner facets the mesh went 0.0106 from the
    truth without them (0.0095 before this step). Several vertices go onto the corner's point or
    one of its edges and would collapse the faces between them, so the moves are made together
    and a vertex whose move turns over, collapses or folds a face goes back part of the way
    (``_partway``), or stays."""
    target = vertices.copy()
    tree = kd_tree(vertices)
    for corner in found:
        around = np.asarray(tree.query_ball_point(corner.point, reach), dtype=np.int64)
        if corner.apart is None:  # beyond a plane of the region
            off = ~corner.region(corner.inside(vertices[around]) + _INSIDE)
        else:  # a saddle's rounding lies on either side: every vertex off its faces
            off = ~corner.on_faces(vertices[around])
        beyond = around[off]
        onto = np.array([_onto_faces(vertices[vertex], corner) for vertex in beyond]).reshape(-1, 3)
        moved = np.linalg.norm(onto - vertices[beyond], axis=1) <= BEYOND_MOVE
        beyond, onto = beyond[moved], onto[moved]
        if points is not None and len(beyond):
            # The points that the mean distances from both ends of every move read.
            local = points[np.linalg.norm(points - corner.point, axis=1) <= reach + 2 * BEYOND_MOVE]
            if len(local) < _NEAREST_POINTS:
                continue
            local_tree = kd_tree(local)
            nearer = local_tree.query(onto, _NEAREST_POINTS)[0].mean(axis=1) < local_tree.query(
                vertices[beyond], _NEAREST_POINTS
            )[0].mean(axis=1)
            beyond, onto = beyond[nearer], onto[nearer]
        target[beyond] = onto
    return _partway(vertices, target, faces)


def _partway(before: np.ndarray, target: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``before`` (v, 3) moved to ``target`` (v, 3), but for the vertices of a face (f, 3) that
    the moves turn over, collapse or fold edge-on (seen along its normal before, it keeps less than
    ``_LEAST_AREA`` of its area; a sliver of no area, which dual contouring leaves a few of, keeps
    none): those go back ``_BACK_SHARES`` of their way in turn, and stay at ``before`` when every
    share does."""
    moving = np.flatnonzero((target != before).any(axis=1))
    around = np.flatnonzero(np.isin(faces, moving).any(axis=1))
    reference = face_normals(before, faces[around])
    shares = np.array([0.0, *_BACK_SHARES, 1.0])
    tries = np.zeros(len(before), dtype=np.int64)
    while True:
        vertices = target + shares[tries][:, None] * (before - target)
        after = face_normals(vertices, faces[around])
        kept = np.einsum("ij,ij->i", reference, after) > _LEAST_AREA * np.einsum("ij,ij->i", reference, reference)
        turned = around[~kept]
        back = np.intersect1d(faces[turned], moving)
        back = back[tries[back] < len(shares) - 1]
        if len(back) == 0:
            return vertices
        tries[back] += 1


def extend_to_corners(curves: list[Curve], found: list[Corner], join: float, spacing: float) -> list[Curve]:
    """``curves`` carried on to the corners of ``found``: a curve that runs round a corner is cut
    there (``_cut_round``); then for each corner and each of its three edges, the curve end nearest
    to it within ``join`` whose side normals are that edge's two faces gains samples up to the
    corner (every ``spacing`` or less, with the end's side normals). A part's edges meet at its
    corners, as in its drawing; only the nearest end, since an edge may come out in pieces."""
    for corner in found:
        curves = [piece for curve in curves for piece in _cut_round(curve, corner, join)]
    chosen: dict[tuple[int, int], np.ndarray] = {}  # (curve, end) -> the corner it goes on to
    for corner in found:
        nearest: dict[tuple[int, int], tuple[float, int, int]] = {}  # edge (two faces) -> gap, curve, end
        for index, curve in enumerate(curves):
            if curve.closed:
                continue
            for end in (0, -1):
                gap = float(np.linalg.norm(curve.points[end] - corner.point))
                faces, on_edge = _corner_edges(corner, curve.left[[end]], curve.right[[end]])
                if 1e-9 < gap <= join and on_edge[0]:
                    edge = (int(faces[0, 0]), int(faces[0, 1]))
                    if edge not in nearest or gap < nearest[edge][0]:
                        nearest[edge] = (gap, index, end)
        for _, index, end in nearest.values():
            chosen[(index, end)] = corner.point
    extended = []
    for index, curve in enumerate(curves):
        points, left, right = curve.points, curve.left, curve.right
        for end in (0, -1):
            if (index, end) not in chosen:
                continue
            target = chosen[(index, end)]
            steps = int(np.ceil(np.linalg.norm(target - points[end]) / spacing))
            added = points[end] + np.linspace(0.0, 1.0, steps + 1)[1:, None] * (target - points[end])
            if end == 0:
                points = np.vstack([added[::-1], points])
                left, right = (np.vstack([np.tile(side[0], (steps, 1)), side]) for side in (left, right))
            else:
                points = np.vstack([points, added])
                left, right = (np.vstack([side, np.tile(side[-1], (steps, 1))]) for side in (left, right))
        extended.append(Curve(points, left, right, curve.dihedral, curve.convex))
    return extended


def _cut_round(curve: Curve, corner: Corner, join: float) -> list[Curve]:
    """``curve`` in two where it runs round ``corner`` (``_bends``): the stretch of its samples
    within ``join`` of the corner, around the nearest, whose side normals are not two of the
    corner's faces (the rounding) left out, if the samples on either side of it are two different
    edges of the corner. An open curve's pieces then end by the corner and are carried on to it; a
    loop stays as it is."""
    gap = np.linalg.norm(curve.points - corner.point, axis=1)
    nearest = int(np.argmin(gap))
    if curve.closed or gap[nearest] > join:
        return [curve]
    faces, on_edge = _corner_edges(corner, curve.left, curve.right)
    rounding = ~on_edge & (gap <= join)
    if not rounding[nearest]:
        return [curve]
    first, last = nearest, nearest
    while first > 0 and rounding[first - 1]:
        first -= 1
    while last < len(gap) - 1 and rounding[last + 1]:
        last += 1
    if first < 2 or last > len(gap) - 3:  # the rounding reaches an end: nothing runs on past it
        return [curve]
    before, after = first - 1, last + 1
    if not (on_edge[before] and on_edge[after]) or (faces[before] == faces[after]).all():
        return [curve]
    return [
        Curve(curve.points[part], curve.left[part], curve.right[part], curve.dihedral, curve.convex)
        for part in (slice(0, first), slice(last + 1, None))
    ]


def _corner_edges(corner: Corner, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For curve samples with side normals ``left`` and ``right`` (m, 3): the two of ``corner``'s
    faces nearest their sides, in order (m, 2), and whether they lie on one of its edges (m,):
    each side within ``SAME_FACE`` of one of its faces, and the two faces different."""
    alike = np.abs(np.stack([left, right], axis=1) @ corner.normals.T)  # (m, 2, 3)
    faces = alike.argmax(axis=2)
    on_edge = (alike.max(axis=2) > np.cos(np.radians(SAME_FACE))).all(axis=1) & (faces[:, 0] != faces[:, 1])
    return np.sort(faces, axis=1), on_edge


def corners(
    curves: list[Curve], join: float, points: np.ndarray | None = None, normals: np.ndarray | None = None
) -> list[Corner]:
    """The corners where curves of ``curves`` end within ``join`` of one another.

    The ends are grouped as in ``core.curves.without_isolated``; around each group's centre the
    samples of every curve within ``CORNER_REACH`` give their two side normals. The three largest
    sets of normals within ``SAME_FACE`` of one another are the faces; the corner is the point
    on all three planes (each plane through the samples that carry its normal, at their median
    offset), kept if every pair of the faces meets at ``MIN_SUPPORT`` samples or more and the
    corner lies within ``join`` of the group's centre; where the centre shows none, each end of
    the group is read so in turn (the ends along an edge shorter than twice ``join`` link its two
    corners' groups in one). Closed curves (loops) have no ends. A corner where a concave edge meets
    two convex ones, or the reverse, is a saddle (``Corner.apart``).

    With the input ``points`` (n, 3), each such corner's planes are refitted to them
    (``_refitted``); with the fit's ``normals`` (n, 3) at them as well, a group whose curves show no
    corner gets the one its points show (``_corner_of_points``) if it lies within ``join`` of one
    of the group's ends. Then, farther than ``join`` from every corner found, such a group and each
    place where a curve bends round a corner (``_bends``) get the corner the points within
    ``BEND_POINTS_REACH`` show, if the curves show its three edges (``_edges_seen``).
    """
    found, unresolved = _corners_at_ends(curves, join, points, normals)
    if points is None or normals is None:
        return found
    # A nearer look where the wide reach took in other parts' faces larger than the corner's, and
    # where a curve bends round a corner; second, since it is the less sure.
    bends = [(bend, bend[None]) for curve in curves for bend in _bends(curve.points)]
    samples = np.concatenate([curve.points for curve in curves]) if curves else np.zeros((0, 3))
    for centre, ends in [*unresolved, *bends]:
        if any(np.linalg.norm(corner.point - centre) <= join for corner in found):
            continue
        corner = _corner_of_points(centre, ends, points, normals, BEND_POINTS_REACH)
        if corner is None or _gap(corner, ends) > join or not _edges_seen(corner, samples):
            continue
        if not any(np.linalg.norm(corner.point - other.point) <= join for other in found):
            found.append(corner)
    return found


def _corners_at_ends(
    curves: list[Curve], join: float, points: np.ndarray | None, normals: np.ndarray | None
) -> tuple[list[Corner], list[tuple[np.ndarray, np.ndarray]]]:
    """The corners of ``corners`` where curves end near one another, and the groups of ends
    (their centre (3,) and the ends (e, 3)) where neither the curves nor the points show one."""
    open_curves = [curve for curve in curves if not curve.closed]
    if len(open_curves) < 2:
        return [], []
    ends = curve_ends(open_curves)
    group = linked(kd_tree(ends).query_pairs(join, output_type="ndarray"), len(ends))
    samples = np.concatenate([curve.points for curve in curves])
    left = np.concatenate([curve.left for curve in curves])
    right = np.concatenate([curve.right for curve in curves])
    convex = np.concatenate([np.full(len(curve.points), curve.convex) for curve in curves])
    tree = kd_tree(samples)
    found: list[Corner] = []
    unresolved: list[tuple[np.ndarray, np.ndarray]] = []

    def meeting(at: np.ndarray) -> Corner | None:
        """The corner the samples within ``CORNER_REACH`` of ``at`` show, if within ``join`` of it."""
        near = np.asarray(tree.query_ball_point(at, CORNER_REACH), dtype=np.int64)
        corner = _meeting_point(samples[near], left[near], right[near], convex[near])
        return corner if corner is not None and np.linalg.norm(corner.point - at) <= join else None

    for label in np.unique(group):
        members = np.flatnonzero(group == label)
        if len(np.unique(members // 2)) < 2:  # one curve's two ends: no corner
            continue
        centre = ends[members].mean(axis=0)
        meetings = [corner for corner in [meeting(centre)] if corner is not None]
        if not meetings:
            # The ends along an edge shorter than twice the join link two corners' groups in one
            # (the wedge's slot wall meets its end face over 0.1), whose centre lies between them
            # and sees four faces: each end is read on its own (one corner may show from two groups).
            for end in ends[members]:
                corner = meeting(end)
                if corner is not None and all(
                    np.linalg.norm(corner.point - other.point) > join for other in [*found, *meetings]
                ):
                    meetings.append(corner)
        if meetings:
            for corner in meetings:
                refitted = corner if points is None else _refitted(corner, points, join)
                # A saddle only where its planes refit to the points: on a small hole's rim, strips of
                # its wall between the fit's creases pass for two faces meeting on a concave edge
                # (six saddles on the flange's bolt holes, whose refit held at one).
                if corner.apart is None or points is None or refitted is not corner:
                    found.append(refitted)
        elif points is not None and normals is not None:
            corner = _corner_of_points(centre, ends[members], points, normals)
            if corner is not None and _gap(corner, ends[members]) <= join:
                found.append(corner)
            else:
                unresolved.append((centre, ends[members]))
    return found, unresolved


def _edges_seen(corner: Corner, samples: np.ndarray) -> bool:
    """Whether the curves' ``samples`` (s, 3) show each of ``corner``'s three edges: ``SEEN_SAMPLES``
    of them within ``BEND_POINTS_REACH`` of it lie within ``SEEN_BAND`` of the line two of its
    planes share, farther than twice that from the corner along it."""
    samples = samples - corner.point
    samples = samples[np.linalg.norm(samples, axis=1) <= BEND_POINTS_REACH]
    for i, j in ((0, 1), (0, 2), (1, 2)):
        along = unit(np.cross(corner.normals[i], corner.normals[j])[None])[0]
        on_line = samples @ along
        off_line = np.linalg.norm(samples - np.outer(on_line, along), axis=1)
        # Away from the corner, where every sample is near all three lines.
        if np.count_nonzero((off_line <= SEEN_BAND) & (np.abs(on_line) > 2 * SEEN_BAND)) < SEEN_SAMPLES:
            return False
    return True


def _bends(points: np.ndarray) -> np.ndarray:
    """The samples (b, 3) of the polyline ``points`` (m, 3; a loop where its first and last are
    the same) where its course over ``BEND_REACH`` before and over ``BEND_REACH`` after turns by
    more than ``BEND_ANGLE`` degrees, the sharpest of each stretch of such samples."""
    lengths = np.linalg.norm(np.diff(points, axis=0), axis=1)
    along = np.concatenate([[0.0], np.cumsum(lengths)])
    total = along[-1]
    loop = len(points) > 2 and np.array_equal(points[0], points[-1])
    reach_along, reach_points = along, points
    if loop:  # three rounds, so that every reach from the middle one falls inside
        reach_along = np.concatenate([along[:-1] - total, along[:-1], along + total])
        reach_points = np.concatenate([points[:-1], points[:-1], points])

    def at(distance: np.ndarray) -> np.ndarray:
        return np.stack([np.interp(distance, reach_along, reach_points[:, axis]) for axis in range(3)], axis=1)

    before, after = points - at(along - BEND_REACH), at(along + BEND_REACH) - points
    turning = angles(unit(before), unit(after))
    inside = loop | ((along >= BEND_REACH) & (along <= total - BEND_REACH))
    bending = np.flatnonzero(inside & (turning > BEND_ANGLE))
    if len(bending) == 0:
        return np.zeros((0, 3))
    stretches = np.split(bending, np.flatnonzero(np.diff(bending) > 1) + 1)
    return np.array([points[stretch[np.argmax(turning[stretch])]] for stretch in stretches])


def _meeting_point(points: np.ndarray, left: np.ndarray, right: np.ndarray, convex: np.ndarray) -> Corner | None:
    """The point where the three faces of the curve samples ``points`` (m, 3), with side normals
    ``left`` and ``right`` (m, 3) and their curves' ``convex`` (m,), meet; None unless the samples
    show three faces that meet pairwise, each edge's samples all convex or all concave (a saddle
    where the edges differ)."""
    normals = np.concatenate([left, right])
    face = np.full(len(normals), -1)
    for index, members in enumerate(_faces(normals)[:3]):
        face[members] = index
    if face.max(initial=-1) < 2:  # fewer than three faces (or no samples near the group's centre)
        return None
    sides = np.sort(np.stack([face[: len(points)], face[len(points) :]], axis=1), axis=1)
    on_edge = np.zeros(len(points), dtype=bool)
    for pair in ((0, 1), (0, 2), (1, 2)):
        edge = (sides == pair).all(axis=1)
        if np.count_nonzero(edge) < MIN_SUPPORT:
            return None
        on_edge |= edge
    on = np.concatenate([points, points])
    planes = unit(np.array([normals[face == index].mean(axis=0) for index in range(3)]))
    if abs(np.linalg.det(planes)) < MIN_DETERMINANT:
        return None
    offsets = np.array([np.median(on[face == index] @ planes[index]) for index in range(3)])
    point = np.linalg.solve(planes, offsets)
    # The side normals are the mesh's, outward of the solid. Each edge's samples must agree on
    # whether it is convex (the creases of a rounded corner's own facets, either way, are no edge).
    kinds = [set(convex[(sides == pair).all(axis=1)].tolist()) for pair in ((0, 1), (0, 2), (1, 2))]
    if any(len(kind) > 1 for kind in kinds):
        return None
    edge_convex = [kind.pop() for kind in kinds]
    if len(set(edge_convex)) == 1:
        sign = 1.0 if edge_convex[0] else -1.0
        return Corner(point, sign * planes, sign * offsets)
    # A saddle: the odd edge's faces are the two other than the one apart.
    odd = [edge_convex.count(kind) for kind in edge_convex].index(1)
    apart = 2 - odd  # edges (0, 1), (0, 2), (1, 2) leave out faces 2, 1, 0
    sign = -1.0 if edge_convex[odd] else 1.0
    return Corner(point, sign * planes, sign * offsets, apart)


def _corner_of_points(
    centre: np.ndarray, ends: np.ndarray, points: np.ndarray, normals: np.ndarray, reach: float = _POINTS_REACH
) -> Corner | None:
    """The corner that the input ``points`` (n, 3) within ``reach`` of ``centre`` (3,) show
    nearest to the curve ``ends`` (e, 3) around it, or None.

    A face is a group of the points' ``normals`` (n, 3, the fit's) within ``SAME_FACE`` of one
    another (``_faces`` of ``_GROUPED`` of them, the ``_FACES_TRIED`` largest), and its plane the
    one through the mean of the points whose normal lies within ``_FLAT`` of the group's that
    they are least far from, refitted to those within ``_REFIT_BAND`` of it (off a parallel
    face's points). A face whose plane turns from its normals by more than ``SAME_FACE`` is a
    rounded edge's points, a line, and is passed over, as is a group of which fewer than
    ``_FLAT_SHARE`` lie within ``_FLAT`` of its normal (a strip of a curved wall). Of every three
    faces that make a corner (``_corner_of_faces``), the one nearest the ends: within the reach
    lie other parts' faces, often larger than the corner's own."""
    near = np.flatnonzero(np.linalg.norm(points - centre, axis=1) <= reach)
    grouped = near[np.unique(np.linspace(0, len(near) - 1, min(_GROUPED, len(near))).astype(np.int64))]
    smallest = max(3, int(np.ceil(_REFIT_POINTS * len(grouped) / max(len(near), 1))))
    cosine, flat = np.cos(np.radians(SAME_FACE)), np.cos(np.radians(_FLAT))
    faces: list[_Face] = []
    for group in _faces(normals[grouped], smallest)[:_FACES_TRIED]:
        normal = unit(normals[grouped[group]].mean(axis=0)[None])[0]
        if np.mean(normals[grouped[group]] @ normal > flat) < _FLAT_SHARE:  # a strip of a curved wall
            continue
        chosen = points[near[normals[near] @ normal > flat]]  # off the rounding, which pulls the plane round
        if len(chosen) < _REFIT_POINTS:
            continue
        for _ in range(_REFIT_PASSES):  # off the points of a parallel face nearby
            axis, offset, spread = _plane(chosen, normal)
            on_plane = np.abs(chosen @ axis - offset) < _REFIT_BAND
            if on_plane.all() or np.count_nonzero(on_plane) < _REFIT_POINTS:
                break
            chosen = chosen[on_plane]
        if axis @ normal >= cosine:  # else a rounded edge's points: a line, not a face
            faces.append(_Face(axis, offset, spread, chosen))
    best: Corner | None = None
    for triple in combinations(faces, 3):
        corner = _corner_of_faces(triple)
        if corner is not None and (best is None or _gap(corner, ends) < _gap(best, ends)):
            best = corner
    return best


def _gap(corner: Corner, ends: np.ndarray) -> float:
    """How far ``corner`` lies from the nearest of ``ends`` (e, 3)."""
    return float(np.linalg.norm(ends - corner.point, axis=1).min())


def _corner_of_faces(faces: tuple[_Face, ...]) -> Corner | None:
    """The corner of three ``faces``, or None unless their points spread alike
    (``_REFIT_SPREAD``), they meet at a point (``MIN_DETERMINANT``) that each face's points reach
    (``MIN_SUPPORT`` of them within ``_REFIT_REACH``: near a tip a thin face has few), and their
    edges are all convex or all concave (each face's points by the corner inside both other
    planes, or outside both); the planes oriented as ``_meeting_point`` orients them."""
    normals = np.array([face.normal for face in faces])
    offsets = np.array([face.offset for face in faces])
    spreads = [face.spread for face in faces]
    if abs(np.linalg.det(normals)) < MIN_DETERMINANT or max(spreads) > _REFIT_SPREAD * min(spreads):
        return None
    point = np.linalg.solve(normals, offsets)
    inside = np.empty((3, 3))  # face i's points by the corner: how far inside plane j
    for index, face in enumerate(faces):
        by_corner = face.points[np.linalg.norm(face.points - point, axis=1) <= _REFIT_REACH]
        if len(by_corner) < MIN_SUPPORT:  # a thin face near a tip has few
            return None
        inside[index] = np.median(offsets[None] - by_corner @ normals.T, axis=0)
    others = ~np.eye(3, dtype=bool)
    if (inside[others] > 0).all():
        return Corner(point, normals, offsets)
    if (inside[others] < 0).all():
        return Corner(point, -normals, -offsets)
    return None


def _refitted(corner: Corner, points: np.ndarray, join: float) -> Corner:
    """``corner`` with each plane refitted to the input ``points`` (n, 3) near it that lie on that
    plane and inside the other two (``PLANE_BAND``): the plane through their mean that they are
    least far from (the smallest principal axis). ``corner`` as it was where a plane has fewer
    than ``_REFIT_POINTS`` such points, where one plane's points spread off it more than
    ``_REFIT_SPREAD`` times another's (the three faces share the cloud's noise: a wider spread is
    another surface's points taken in, as at featuretype's small steps and pockets), or where the
    refitted planes are nearly parallel (``MIN_DETERMINANT``) or meet farther than ``join`` from it."""
    near = points[np.linalg.norm(points - corner.point, axis=1) <= _REFIT_REACH]
    planes, offsets = corner.normals, corner.offsets
    for _ in range(_REFIT_PASSES):
        inside = offsets[None] - near @ planes.T  # (n, 3): how far inside each plane
        refit_normals, refit_offsets, spreads = [], [], []
        for index in range(3):
            on_face = (np.abs(inside[:, index]) < _REFIT_BAND) & _off_rounding(corner, inside, index)
            if np.count_nonzero(on_face) < _REFIT_POINTS:
                return corner
            normal, offset, spread = _plane(near[on_face], planes[index])
            refit_normals.append(normal)
            refit_offsets.append(offset)
            spreads.append(spread)
        planes, offsets = np.array(refit_normals), np.array(refit_offsets)
    if max(spreads) > _REFIT_SPREAD * min(spreads) or abs(np.linalg.det(planes)) < MIN_DETERMINANT:
        return corner
    point = np.linalg.solve(planes, offsets)
    if np.linalg.norm(point - corner.point) > join:
        return corner
    return Corner(point, planes, offsets, corner.apart)


def _off_rounding(corner: Corner, inside: np.ndarray, index: int) -> np.ndarray:
    """Whether points that lie ``inside`` (m, 3) each of ``corner``'s planes by so much lie over
    its face ``index`` (m,): farther than ``PLANE_BAND`` from the other two planes (off the
    rounding), where that plane bounds the corner's region (inside the other two at a corner whose
    edges are alike; at a saddle, outside the odd edge's other face as well, or inside either)."""
    others = [other for other in range(3) if other != index]
    above, below = inside.copy(), inside.copy()
    above[:, index], below[:, index] = 1.0, -1.0
    clear = (np.abs(inside[:, others]) > PLANE_BAND).all(axis=1)
    return clear & (corner.region(above) != corner.region(below))


def _plane(points: np.ndarray, towards: np.ndarray) -> tuple[np.ndarray, float, float]:
    """The plane of ``points`` (m, 3): through their mean, along the axis they spread least on
    (its unit normal, turned to the side of ``towards`` (3,)), its offset, and their spread off
    it (standard deviation)."""
    mean = points.mean(axis=0)
    variances, axes = np.linalg.eigh(np.cov((points - mean).T))  # variances ascending
    normal = axes[:, 0] if axes[:, 0] @ towards > 0 else -axes[:, 0]
    return normal, float(mean @ normal), float(np.sqrt(max(variances[0], 0.0)))


def _faces(normals: np.ndarray, smallest: int = MIN_NORMALS) -> list[np.ndarray]:
    """The unit ``normals`` (n, 3) in sets within ``SAME_FACE`` of a seed, largest first: the seed
    is the normal with the most others that close, and each set is taken away before the next; sets
    of fewer than ``smallest`` are left out."""
    cosine = np.cos(np.radians(SAME_FACE))
    left = np.arange(len(normals))
    faces = []
    while len(left) >= smallest:
        close = normals[left] @ normals[left].T > cosine
        seed = np.argmax(close.sum(axis=1))
        if close[seed].sum() < smallest:
            break
        faces.append(left[close[seed]])
        left = left[~close[seed]]
    return faces


def _move(vertices: np.ndarray, around: np.ndarray, vertex: int, target: np.ndarray) -> bool:
    """Put ``vertex`` at ``target`` in ``vertices`` (in place) unless one of its faces ``around``
    ((f, 3)) would turn over; whether it moved."""
    before = face_normals(vertices, around)
    kept = vertices[vertex].copy()
    vertices[vertex] = target
    if (np.einsum("ij,ij->i", before, face_normals(vertices, around)) > 0).all():
        return True
    vertices[vertex] = kept
    return False


def _onto_faces(point: np.ndarray, corner: Corner) -> np.ndarray:
    """The nearest point to ``point`` (3,) on ``corner``'s faces (``Corner.on_faces``): on a face,
    on an edge (two faces' line through the corner) or the corner itself."""
    normals, offsets, apex = corner.normals, corner.offsets, corner.point
    candidates = [point - (normals[i] @ point - offsets[i]) * normals[i] for i in range(3)]
    for i, j in ((0, 1), (0, 2), (1, 2)):
        along = unit(np.cross(normals[i], normals[j])[None])[0]
        candidates.append(apex + ((point - apex) @ along) * along)
    on = [candidate for candidate, kept in zip(candidates, corner.on_faces(np.array(candidates)), strict=True) if kept]
    return min([apex, *on], key=lambda candidate: float(np.linalg.norm(candidate - point)))
