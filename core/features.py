"""Sharp features of a fitted f: the tangent planes of the faces on both sides of each edge.

A fitted network rounds every sharp edge over a band a few hundredths wide, so its own tangent
planes there turn gradually and dual contouring alone would keep the rounding. Beside the band the
faces are flat again. For each crossing of f = 0 where the normal turns (a candidate), this module
walks over the surface across the direction of turning, by ``SIDE_STEP`` to each side, and reads
the normal there; at one and a half steps it reads it again. Both sides flat (the two readings of
each side within ``FLAT_TURNING``; for a face narrower than the walk, two readings nearer the
edge, ``_WINDOWS``) and turned from one another by at least ``EDGE_TURNING``: the
candidate lies in the band of an edge, and the planes of the two faces meet on that edge, provided
the turn between them is as narrow as a fit's rounding (``BAND_WIDTH``), and not so wide that they
are a thin wall's two sides (``MAX_EDGE_TURNING``). One side may instead curve steadily beside a
broadly flat one at a convex edge (a shaft beside its flat, ``_curved_side``): its plane is then
its tangent where it meets the flat side's. Any other curved face is never sharpened: up to a
radius of about 0.2 (a hole's wall) it keeps turning over the walk, beyond that its two sides are
turned by less than ``EDGE_TURNING``, and a bend between flat sides (the bump of a scan, a
filleted edge of radius 0.04 or more) turns over a band wider than ``BAND_WIDTH``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from core.trees import kd_tree

# (n, 3) points -> f (n,) and ∇f (n, 3), float64
Derivatives = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]

SIDE_STEP = 0.04  # unit frame: past a fitted edge's rounding band (0.03 left more of it; 0.05 overshot small faces)
FLAT_TURNING = 5.0  # degrees the normal may turn from one to one and a half steps on a face (radius 0.2: 5.7)
MAX_OFFSET = 0.02  # unit frame: the farthest a crossing lies from a face's plane beside it (rounding)
EDGE_TURNING = 25.0  # degrees between the two faces' normals for an edge (faces meeting at up to 155°)
# Degrees between the two faces' normals beyond which they are the two sides of a wall thinner than
# a walk (nearly opposite), read across its rounded end, not the faces of one edge: their planes
# meet far off or not at all, and a U-channel's wall tops 0.03 thick, mixed with the rounding's own
# planes, went 0.025 above the truth. The sharpest edges asked for meet at 35° (normals 145° apart).
MAX_EDGE_TURNING = 160.0
# A side whose normal turns at each step of the walk's far end by at most this many degrees (a
# radius of 0.095 or more), steadily (the two steps within STEADY_TURNING), is a curved face: a
# shaft's surface beside a flat or a keyway (``_curved_side``).
MAX_SIDE_TURNING = 6.0
STEADY_TURNING = 2.5
# ... and only where the other side is flat from the second reading of its walk to the last (a
# shaft's flat, 0.02 to 0.06 from the edge) within BROAD_TURNING, the curved side turns on about an
# axis along the edge (within ALONG_EDGE, cosine) and the edge is convex. A scan's bumps pass the
# other tests: the bunny's false edges rose from 0.99 % to 2.30 % of its points without these, 1.18 %
# with all but convexity, 0.98 % with it. A fit's facets on the rounded box's fillets (radius 0.1)
# passed with BROAD_TURNING at 5 (false edges 0.78 % -> 1.42 %; 1.22 % at 3, 1.09 % at 2, where the
# keyed shaft's edge IoU fell back from 0.49 to 0.45-0.46).
BROAD_READINGS = (2, 6)
BROAD_TURNING = 3.0
ALONG_EDGE = 0.95
# Unit frame: the widest band over which the normal may turn from one face's to the other's (from
# 10 % to 90 % of the way) at an edge. A fit rounds a sharp edge over 0.02 to 0.035 (90 % of the
# walks across the sample CAD shapes' edges, featuretype's 0.055); a smooth bend of radius R
# turning by θ spreads over 0.8 R θ (a box rounded by 0.04: 0.05), and the tips of a smooth
# blob's narrow bumps, whose flanks pass the other tests, over 0.046 to 0.088 (82 % above 0.05).
BAND_WIDTH = 0.05
_CANDIDATE_TURNING = 3.0  # degrees to a nearby crossing's normal that make a crossing worth the walk
_NEIGHBOURS = 8
_PROJECTION_STEPS = 2
_WALK_STEPS = 6  # to one and a half SIDE_STEP
# The readings (steps of a walk, from 1) between which a face must stay flat, tried in order: from
# SIDE_STEP to one and a half of it, then nearer the edge for a face narrower than that walk (a thin
# plate's wall, 0.07 across the flange, where the walk reaches the rounding of its other edge): the
# flange's edge IoU 0.531 -> 0.578, curve ECD 0.0062 -> 0.0050 on one fit (docs/benchmarks.md).
_WINDOWS = ((4, 6), (3, 5), (2, 4))
# A nearer window counts only where the normal turns by this many degrees after it (the wall's other
# edge), on the way it turned at this edge (``_wall_turns_on``). Without the first the bunny's false
# edges went from 1.15 % to 2.23 % of its points; with the first only, to 1.45 %; with both 1.22 %.
_NEXT_EDGE_TURNING = 20.0
WALK_SPACING = 0.015  # unit frame: one walk per cube of this size


@dataclass
class SidePlanes:
    """The faces beside each crossing: for an edge crossing (``edge``), a point and unit normal on
    each side's face; elsewhere both sides are the crossing's own tangent plane. Arrays (c, 3), (c,)."""

    points_a: np.ndarray
    normals_a: np.ndarray
    points_b: np.ndarray
    normals_b: np.ndarray
    edge: np.ndarray


def side_planes(crossings: np.ndarray, normals: np.ndarray, derivatives_at: Derivatives) -> SidePlanes:
    """The planes of the faces beside each crossing (c, 3) with unit normals (c, 3) on f = 0.

    The walk is made from one candidate per ``WALK_SPACING`` cube (the faces beside an edge are the
    same all along it); every other candidate takes the planes of the nearest walked one.
    """
    count = len(crossings)
    planes = SidePlanes(crossings.copy(), normals.copy(), crossings.copy(), normals.copy(), np.zeros(count, bool))
    candidates, across = _turning(crossings, normals)
    if len(candidates) == 0:
        return planes
    _, walker = np.unique(np.floor(crossings[candidates] / WALK_SPACING).astype(np.int64), axis=0, return_index=True)
    start, direction = crossings[candidates[walker]], across[walker]
    walks = [_walk(start, sign * direction, derivatives_at) for sign in (1.0, -1.0)]
    sides = [list(_face_beside(*walk)) for walk in walks]
    # A side that curves steadily (a shaft's surface beside its flat) where the other is flat, and
    # broadly (``BROAD_READINGS``, ``BROAD_TURNING``): its plane is its tangent plane where it meets
    # the other's.
    broad = [
        angles(walk[1][:, BROAD_READINGS[0] - 1], walk[1][:, BROAD_READINGS[1] - 1]) <= BROAD_TURNING for walk in walks
    ]
    curved = [(sides[i][3] == 0) & (sides[1 - i][3] == _WINDOWS[0][0]) & broad[1 - i] for i in (0, 1)]
    for i in (0, 1):
        rows = np.flatnonzero(curved[i])
        flat_point, flat_normal = sides[1 - i][0][rows], sides[1 - i][1][rows]
        walk_points, walk_normals = walks[i][0][rows], walks[i][1][rows]
        point, normal, turns, found = _curved_side(walk_points, walk_normals, start[rows], flat_point, flat_normal)
        rows = rows[found]
        sides[i][0][rows], sides[i][1][rows], sides[i][2][rows] = point[found], normal[found], turns[found]
        sides[i][3][rows] = _WINDOWS[0][0]
    (point_a, normal_a, turns_a, read_a), (point_b, normal_b, turns_b, read_b) = sides
    cosine = np.einsum("ij,ij->i", normal_a, normal_b)
    edge = (
        (read_a > 0)
        & (read_b > 0)
        & (cosine < np.cos(np.radians(EDGE_TURNING)))
        & (cosine > np.cos(np.radians(MAX_EDGE_TURNING)))
        & _wall_turns_on(read_a, normal_b, normal_a, walks[0][1][:, -1])
        & _wall_turns_on(read_b, normal_a, normal_b, walks[1][1][:, -1])
    )
    profile = np.concatenate([turns_a[:, ::-1], normals[candidates[walker], None], turns_b], axis=1)
    edge &= band_width(profile, 1.5 * SIDE_STEP / _WALK_STEPS) <= BAND_WIDTH
    if not edge.any():
        return planes
    distance, nearest = kd_tree(start[edge]).query(crossings[candidates])
    point_a, normal_a, point_b, normal_b = point_a[edge], normal_a[edge], point_b[edge], normal_b[edge]
    # A candidate takes the nearest walk's planes if both pass near it: near a corner the nearest
    # walk may have crossed onto another edge's faces.
    here = crossings[candidates]
    offset_a = np.abs(np.einsum("ij,ij->i", normal_a[nearest], here - point_a[nearest]))
    offset_b = np.abs(np.einsum("ij,ij->i", normal_b[nearest], here - point_b[nearest]))
    close = (distance <= WALK_SPACING * math.sqrt(3)) & (np.maximum(offset_a, offset_b) <= MAX_OFFSET)
    chosen, nearest = candidates[close], nearest[close]
    planes.points_a[chosen], planes.normals_a[chosen] = point_a[nearest], normal_a[nearest]
    planes.points_b[chosen], planes.normals_b[chosen] = point_b[nearest], normal_b[nearest]
    planes.edge[chosen] = True
    return planes


def _turning(crossings: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The crossings whose normal turns towards a neighbour's by more than ``_CANDIDATE_TURNING``,
    and for each the unit direction (in its tangent plane) in which the normal turns fastest."""
    k = min(_NEIGHBOURS + 1, len(crossings))
    _, neighbours = kd_tree(crossings).query(crossings, k)
    neighbours = neighbours[:, 1:]
    cosines = np.einsum("ij,ikj->ik", normals, normals[neighbours])
    candidates = np.flatnonzero(cosines.min(axis=1) < np.cos(np.radians(_CANDIDATE_TURNING)))
    if len(candidates) == 0:
        return candidates, np.zeros((0, 3))
    normal = normals[candidates]
    first = unit(np.cross(normal, np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])))
    second = np.cross(normal, first)
    basis = np.stack([first, second], axis=2)  # (m, 3, 2)
    offsets = np.einsum("mkj,mja->mka", crossings[neighbours[candidates]] - crossings[candidates, None], basis)
    turns = np.einsum("mkj,mja->mka", normals[neighbours[candidates]] - normal[:, None], basis)
    # The shape operator S (2 x 2) from turns ≈ offsets S, by least squares; the normal turns
    # fastest along the top right-singular vector of S^T, i.e. the top eigenvector of S S^T.
    gram = np.einsum("mka,mkb->mab", offsets, offsets) + 1e-12 * np.eye(2)
    shape = np.linalg.solve(gram, np.einsum("mka,mkb->mab", offsets, turns))
    _, vectors = np.linalg.eigh(np.einsum("mab,mcb->mac", shape, shape))
    across = np.einsum("mja,ma->mj", basis, vectors[:, :, -1])
    return candidates, unit(across)


def _walk(start: np.ndarray, direction: np.ndarray, derivatives_at: Derivatives) -> tuple[np.ndarray, np.ndarray]:
    """Walk over f = 0 from ``start`` (m, 3) along ``direction`` (m, 3), in ``_WALK_STEPS`` small
    steps, each followed by Newton steps back onto the surface and with the direction turned
    into the new tangent plane: a straight step would leave a rounded edge into empty space and
    fall back onto the rounding, never reaching the face beyond. Returns the point and the unit
    normal after every step, (m, ``_WALK_STEPS``, 3) each."""
    step = 1.5 * SIDE_STEP / _WALK_STEPS
    point, direction = start.copy(), direction.copy()
    points, normals = [], []
    for _ in range(_WALK_STEPS):
        point = point + step * direction
        for _ in range(_PROJECTION_STEPS):
            value, gradient = derivatives_at(point)
            point = point - (value / np.maximum(np.einsum("ij,ij->i", gradient, gradient), 1e-12))[:, None] * gradient
        normal = unit(gradient)
        points.append(point)
        normals.append(normal)
        turned = direction - np.einsum("ij,ij->i", direction, normal)[:, None] * normal
        direction = np.where(np.linalg.norm(turned, axis=1, keepdims=True) > 1e-6, unit(turned), direction)
    return np.stack(points, axis=1), np.stack(normals, axis=1)


def _face_beside(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The face one walk (``_walk``'s points and normals, (m, k, 3) each) reached: the first of
    ``_WINDOWS`` over which the normal stays within ``FLAT_TURNING``, read at the window's start.

    A nearer window counts only where the normal turns by ``_NEXT_EDGE_TURNING`` after it. Returns
    the point and normal (m, 3), the walk's normals with those past the window replaced by the
    window's last (so that a thin wall's other edge does not widen the band) and the reading the
    face was read at (m,), 0 where no window was flat."""
    rows = np.arange(len(points))
    flat = np.zeros(len(points), dtype=bool)
    near = np.full(len(points), _WINDOWS[0][0])
    far = np.full(len(points), _WINDOWS[0][1])
    cosine = np.cos(np.radians(FLAT_TURNING))
    beyond = np.cos(np.radians(_NEXT_EDGE_TURNING))
    for index, (first, last) in enumerate(_WINDOWS):
        here = ~flat & (np.einsum("ij,ij->i", normals[:, first - 1], normals[:, last - 1]) > cosine)
        if index:
            here &= np.einsum("ij,ij->i", normals[:, last - 1], normals[:, -1]) < beyond
        near[here], far[here] = first, last
        flat |= here
    reading = np.arange(1, normals.shape[1] + 1)
    held = np.where((reading > far[:, None])[:, :, None], normals[rows, far - 1][:, None], normals)
    return points[rows, near - 1], normals[rows, near - 1], held, np.where(flat, near, 0)


def _curved_side(
    points: np.ndarray, normals: np.ndarray, start: np.ndarray, flat_point: np.ndarray, flat_normal: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where a walk's side curves steadily, as a cylinder does across its axis: the point and unit
    normal (m, 3) of its tangent plane where it meets the other side's plane (``flat_point``,
    ``flat_normal``, (m, 3)), the walk's normals with the side's steady turn taken out (m, k, 3),
    and whether the side did curve so, about an axis along the edge, and meet that plane near the
    walk's ``start`` (m,).

    The side turns steadily when its normal turns at each of the walk's last two steps by half
    ``FLAT_TURNING`` to ``MAX_SIDE_TURNING``, by amounts within ``STEADY_TURNING`` of each
    other, about one axis. The circle through the last reading, with the curvature of the last two
    steps, continued back towards the edge, meets the flat side's plane there.
    """
    count = len(points)
    step = 1.5 * SIDE_STEP / _WALK_STEPS
    first, middle, last = normals[:, -3], normals[:, -2], normals[:, -1]
    turns = [angles(first, middle), angles(middle, last)]
    axis_first, axis_last = unit(np.cross(first, middle)), unit(np.cross(middle, last))
    steady = (
        (np.minimum(*turns) >= FLAT_TURNING / 2)
        & (np.maximum(*turns) <= MAX_SIDE_TURNING)
        & (np.abs(turns[0] - turns[1]) <= STEADY_TURNING)
        & (np.einsum("ij,ij->i", axis_first, axis_last) > 0.9)
    )
    axis = unit(axis_first + axis_last)
    curvature = np.radians(turns[0] + turns[1]) / (2 * step)  # rad per unit length
    radius = 1.0 / np.maximum(curvature, 1e-12)
    # The circle's centre lies behind the last reading along its normal when the side bulges out
    # (its normal turns away from the walk's direction of travel), in front of it when hollow.
    travel = unit(points[:, -1] - points[:, -2])
    bulge = np.where(np.einsum("ij,ij->i", last - middle, travel) > 0, 1.0, -1.0)
    centre = points[:, -1] - (bulge * radius)[:, None] * last
    # The circle: centre + radius (cos θ u + sin θ v), u towards the last reading, v = axis × u.
    u = unit(points[:, -1] - centre)
    v = np.cross(axis, u)
    a = radius * np.einsum("ij,ij->i", flat_normal, u)
    b = radius * np.einsum("ij,ij->i", flat_normal, v)
    c = np.einsum("ij,ij->i", flat_normal, centre - flat_point)
    reach = np.hypot(a, b)
    meets = reach > np.abs(c)
    phase = np.arctan2(b, a)
    spread = np.arccos(np.clip(-c / np.maximum(reach, 1e-12), -1, 1))
    best = np.zeros((count, 3))
    nearest = np.full(count, np.inf)
    for angle in (phase + spread, phase - spread):
        at = centre + radius[:, None] * (np.cos(angle)[:, None] * u + np.sin(angle)[:, None] * v)
        gap = np.linalg.norm(at - start, axis=1)
        better = gap < nearest
        best[better], nearest[better] = at[better], gap[better]
    normal = unit(bulge[:, None] * (best - centre))
    # The walk's normals turned back by the side's steady turn from the start, about its axis.
    back = -curvature[:, None] * step * np.arange(1, normals.shape[1] + 1)
    unbent = _rotate(normals, axis[:, None, :], back)
    # Along the edge, and turning on the way it turned at the edge (from the flat side's normal to
    # its own): a fit's bump on a hole's wall beside its rim turned back, and passed for a shaft.
    along = np.einsum("ij,ij->i", axis, unit(np.cross(flat_normal, normal))) >= ALONG_EDGE
    # Convex: the flat side lies behind the curved side's plane at the edge (a shaft's flat, a
    # keyway's top); the concave creases this found on the bunny were the scan's folds.
    convex = np.einsum("ij,ij->i", normal, flat_point - best) < 0
    found = steady & meets & along & convex & (nearest <= SIDE_STEP)
    return best, normal, unbent, found


def _rotate(vectors: np.ndarray, axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """``vectors`` (..., 3) turned by ``angle`` (...) radians about the unit ``axis`` (..., 3)
    (Rodrigues' formula; broadcast)."""
    cos, sin = np.cos(angle)[..., None], np.sin(angle)[..., None]
    along = np.sum(axis * vectors, axis=-1, keepdims=True)
    return vectors * cos + np.cross(axis, vectors) * sin + axis * along * (1 - cos)


def _wall_turns_on(read: np.ndarray, before: np.ndarray, face: np.ndarray, last: np.ndarray) -> np.ndarray:
    """Whether each face read nearer its edge (``read``, (m,), from ``_face_beside``) is a wall
    whose far edge turns the normal on the way it turned at the near one: from the other side's
    normal ``before`` to the face's ``face``, then to the walk's ``last`` (m, 3) each, as a thin
    plate's top, wall and bottom do (a scan's ridges turn either way). True for faces read at
    ``SIDE_STEP``."""
    sense = np.einsum("ij,ij->i", np.cross(before, face), np.cross(face, last))
    return (read == _WINDOWS[0][0]) | (sense > 0)


def band_width(profile: np.ndarray, spacing: float) -> np.ndarray:
    """The length (m,) over which each row of unit normals ``profile`` (m, k, 3), read every
    ``spacing`` along a path across an edge, turns from 10 % to 90 % of the way from its first
    normal to its last (the angle to the first normal, made non-decreasing, linearly interpolated)."""
    first, last = profile[:, :1], profile[:, -1:]
    total = np.arccos(np.clip(np.einsum("mkj,mkj->mk", first, last), -1.0, 1.0))
    angle = np.arccos(np.clip(np.einsum("mkj,mkj->mk", profile, first), -1.0, 1.0))
    share = np.maximum.accumulate(angle / np.maximum(total, 1e-12), axis=1)
    return spacing * (_first_reaching(share, 0.9) - _first_reaching(share, 0.1))


def _first_reaching(share: np.ndarray, level: float) -> np.ndarray:
    """Where each row of the non-decreasing ``share`` (m, k) first reaches ``level``, in steps
    (fractional, linear between readings); k - 1 where it never does."""
    rows = np.arange(len(share))
    after = np.where((share >= level).any(axis=1), np.argmax(share >= level, axis=1), share.shape[1] - 1)
    after = np.maximum(after, 1)
    low, high = share[rows, after - 1], share[rows, after]
    return after - 1 + np.clip((level - low) / np.maximum(high - low, 1e-12), 0.0, 1.0)


def angles(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The angle in degrees (m,) between the unit vectors ``u`` and ``v`` (m, 3), row by row."""
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", u, v), -1.0, 1.0)))


def unit(vectors: np.ndarray) -> np.ndarray:
    """Each row of ``vectors`` (n, 3) scaled to length 1 (a zero row stays zero)."""
    return vectors / np.maximum(np.linalg.norm(vectors, axis=1, keepdims=True), 1e-12)


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The (unnormalised) normals (f, 3) of ``faces`` (f, 3) on ``vertices``: whether a moved
    vertex turned a face over is the sign of their dot product before and after."""
    corner = vertices[faces]
    return np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])
