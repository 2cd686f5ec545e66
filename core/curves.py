"""Edge curves: the sharp edges of a mesh as ordered polylines, and what lies near them.

The dual-contoured mesh (``core.dual``) has its vertices on the sharp edges, so the edges of the
shape are chains of mesh edges whose two faces meet at a crease. Those chains are followed from
end to end (or round a loop), lightly smoothed (a vertex of a chain may sit a little off the true
edge), resampled at a fixed spacing, and each keeps the normals of the faces on its two sides: a
point near a curve lies on the face whose plane is nearer, and is as far from the edge as it lies
along that face (``distance_to_curves``); three faces meeting give a corner (``core.corners``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from core.features import angles, unit
from core.trees import kd_tree

_SMOOTHING_PASSES = 3
_DENSE = 5  # a curve is matched against points five times denser than its samples


@dataclass
class Curve:
    """One sharp edge: ``points`` (m, 3) in order, every ``spacing`` or so along it; ``left`` and
    ``right`` (m, 3), the unit normals of the faces on its two sides; ``dihedral``, the angle in
    degrees between those faces, measured through the solid (90 on a cube, 135 on an octagonal
    prism's sides); ``convex``: the solid's side of the edge is the narrow one."""

    points: np.ndarray
    left: np.ndarray
    right: np.ndarray
    dihedral: float
    convex: bool

    @property
    def length(self) -> float:
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum())

    @property
    def closed(self) -> bool:
        """A loop (a hole's rim): its first and last points are the same, and it has no ends."""
        return bool(np.array_equal(self.points[0], self.points[-1]))


def edge_curves(mesh: trimesh.Trimesh, angle: float, min_length: float, spacing: float) -> list[Curve]:
    """The chains of mesh edges whose faces' normals differ by more than ``angle`` degrees,
    at least ``min_length`` long, resampled every ``spacing`` (all lengths in the mesh's frame)."""
    pairs = mesh.face_adjacency
    if len(pairs) == 0:
        return []
    sharp = mesh.face_adjacency_angles > np.radians(angle)
    edges = mesh.face_adjacency_edges[sharp]
    faces = pairs[sharp]
    convex = mesh.face_adjacency_convex[sharp]
    # Read once: each read of a trimesh cached property hashes the mesh's arrays to check the
    # cache (0.7 s over a cube's few hundred chains).
    face_normals, vertices, mesh_faces = mesh.face_normals, mesh.vertices, mesh.faces
    curves = []
    for chain, steps in _chains(edges):
        if len(chain) < 2:
            continue
        # Measured after smoothing: a zigzag of creases across a face is long only before it.
        points = _smooth(vertices[chain])
        lengths = np.linalg.norm(np.diff(points, axis=0), axis=1)
        if lengths.sum() < min_length:
            continue
        left, right = _sides(face_normals, mesh_faces, chain, faces[steps])
        turning = angles(left, right)
        curves.append(
            _resample(
                points,
                left,
                right,
                dihedral=180.0 - float(np.average(turning, weights=lengths + 1e-12)),
                convex=bool(np.average(convex[steps], weights=lengths + 1e-12) >= 0.5),
                spacing=spacing,
            )
        )
    return curves


def without_isolated(curves: list[Curve], gap: float, min_length: float, keep_dihedral: float) -> list[Curve]:
    """The ``curves`` that belong to a group at least ``min_length`` long in all, a group being the
    curves linked end to end (an end within ``gap`` of another curve's end, transitively), and
    those whose faces meet at less than ``keep_dihedral`` degrees, however short.

    A part's edges meet at its corners, and its curves stop within a few hundredths of one another
    where the extraction breaks an edge; a crease of a smooth scan's detail (a fold, an ear's base)
    stands alone and short, and turns by 35-50°. Length alone does not tell them apart (a part's
    edges come out in pieces as short as the creases), and a poor fit finds a part's right-angled
    edges in lone pieces too.
    """
    if not curves:
        return []
    pairs = kd_tree(curve_ends(curves)).query_pairs(gap, output_type="ndarray") // 2  # the curves whose ends meet
    group = linked(pairs, len(curves))
    length = np.bincount(group, weights=[curve.length for curve in curves])
    return [curve for curve, g in zip(curves, group) if length[g] >= min_length or curve.dihedral < keep_dihedral]


def curve_ends(curves: list[Curve]) -> np.ndarray:
    """The first and last points of ``curves``, (2k, 3): curve i's at rows 2i and 2i + 1."""
    return np.array([[curve.points[0], curve.points[-1]] for curve in curves]).reshape(-1, 3)


def linked(pairs: np.ndarray, count: int) -> np.ndarray:
    """The group (count,) of each of ``count`` items, two items of a row of ``pairs`` (p, 2) being
    in one group (transitively): the connected components of that graph."""
    graph = coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), (count, count))
    return connected_components(graph, directed=False)[1]


def distance_to_curves(
    points: np.ndarray, curves: list[Curve], spacing: float, within: float = np.inf, workers: int = 1
) -> np.ndarray:
    """The distance (n,) of each of ``points`` (n, 3) to the nearest curve, along the face it lies
    on: its offset from the nearest point of the curves (matched at a fifth of their spacing, to
    within ``spacing`` / 50), less the parts along the curve and along the normal of the nearer of
    the curve's two faces there. inf without curves and beyond ``within``, which ends each search
    early (at 1 M points, 0.4-0.6 s instead of 6 when most points lie far from every edge).

    Noise moves an input point off its face as much as along it, but only the move along the face
    changes how far from the edge it was sampled, which is what an edge point is (the truth labels
    clean positions within 0.01 of an edge): leaving the move off the face out (and the width 0.013
    to 0.0125) raised the edge IoU of twelve fits of six CAD shapes from 0.606 to 0.611 on average,
    ten of the twelve higher, one equal, one 0.001 lower (docs/benchmarks.md).
    """
    if not curves:
        return np.full(len(points), np.inf)
    dense, left, right, tangent, beyond = (
        np.concatenate(parts) for parts in zip(*(_dense(c, spacing / _DENSE) for c in curves))
    )
    # Searched to twice ``within``: a point within it along its face is found up to √3 ``within`` off it.
    _, nearest = kd_tree(dense).query(points, distance_upper_bound=2 * within, workers=workers)
    found = nearest < len(dense)
    at = nearest[found]
    offset = points[found] - dense[at]
    along_curve = np.einsum("ij,ij->i", offset, tangent[at])
    # Past a curve's end a point is that far from the edge along the curve too.
    past_end = along_curve * beyond[at] > 0
    offset -= tangent[at] * np.where(past_end, 0.0, along_curve)[:, None]
    off_face = np.minimum(
        np.abs(np.einsum("ij,ij->i", offset, left[at])), np.abs(np.einsum("ij,ij->i", offset, right[at]))
    )
    along_face = np.sqrt(np.maximum(np.einsum("ij,ij->i", offset, offset) - off_face**2, 0.0))
    distance = np.full(len(points), np.inf)
    distance[found] = np.where(along_face <= within, along_face, np.inf)
    return distance


def _dense(curve: Curve, spacing: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Samples of ``curve`` every ``spacing`` or less (m, 3), with the normals of its two faces
    there (m, 3) each, its unit direction there (m, 3), and which way along it the curve ends there
    (m,): -1 at the first sample, 1 at the last, 0 elsewhere and all along a loop."""
    samples, step = _along(curve.points, spacing)
    directions = unit(np.diff(curve.points, axis=0))
    beyond = np.zeros(len(samples))
    if not curve.closed:
        beyond[0], beyond[-1] = -1.0, 1.0
    return samples, curve.left[step], curve.right[step], directions[step], beyond


def _chains(edges: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The sharp edges (e, 2) as chains: vertex sequences and, for each step, the edge's row.
    A chain runs between vertices that do not have exactly two sharp edges (ends, corners,
    junctions), or round a loop."""
    neighbours: dict[int, list[tuple[int, int]]] = {}
    for row, (u, v) in enumerate(edges.tolist()):
        neighbours.setdefault(u, []).append((v, row))
        neighbours.setdefault(v, []).append((u, row))
    used = np.zeros(len(edges), dtype=bool)
    chains = []
    starts = [v for v, around in neighbours.items() if len(around) != 2] + list(neighbours)
    for start in starts:
        for first, row in neighbours[start]:
            if used[row]:
                continue
            chain, steps = [start], []
            vertex, step = first, row
            while True:
                used[step] = True
                chain.append(vertex)
                steps.append(step)
                if len(neighbours[vertex]) != 2:
                    break
                following = [(w, r) for w, r in neighbours[vertex] if not used[r]]
                if not following:
                    break
                vertex, step = following[0]
            chains.append((np.asarray(chain), np.asarray(steps)))
    return chains


def _sides(
    normals: np.ndarray, mesh_faces: np.ndarray, chain: np.ndarray, faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The unit normals of the faces left and right of each step of a chain (s, 3) each, given the
    mesh's face ``normals`` (F, 3) and ``mesh_faces`` (F, 3): the left face is the one whose winding
    runs along the step's direction."""
    first = mesh_faces[faces[:, 0]]
    u, v = chain[:-1], chain[1:]
    # Does the first face hold the directed edge u -> v (v follows u in its winding)?
    position = np.argmax(first == u[:, None], axis=1)
    forward = first[np.arange(len(first)), (position + 1) % 3] == v
    left = np.where(forward[:, None], normals[faces[:, 0]], normals[faces[:, 1]])
    right = np.where(forward[:, None], normals[faces[:, 1]], normals[faces[:, 0]])
    return left, right


def _smooth(points: np.ndarray) -> np.ndarray:
    """A few passes of averaging each inner vertex with its neighbours (ends stay; a loop's first
    and last vertex are the same point and move together)."""
    points = points.copy()
    loop = len(points) > 2 and np.array_equal(points[0], points[-1])
    for _ in range(_SMOOTHING_PASSES):
        inner = (points[:-2] + 2 * points[1:-1] + points[2:]) / 4
        if loop:
            points[0] = points[-1] = (points[-2] + 2 * points[0] + points[1]) / 4
        points[1:-1] = inner
    return points


def _resample(
    points: np.ndarray, left: np.ndarray, right: np.ndarray, dihedral: float, convex: bool, spacing: float
) -> Curve:
    """The polyline ``points`` (k, 3) with per-step ``left``/``right`` normals (k - 1, 3), resampled
    every ``spacing`` or less (both ends kept), each sample taking its step's normals."""
    samples, step = _along(points, spacing)
    return Curve(samples, left[step], right[step], dihedral, convex)


def _along(points: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Samples (m, 3) every ``spacing`` or less along the polyline ``points`` (k, 3), both ends
    kept, and the step (segment index, (m,)) each lies on."""
    lengths = np.linalg.norm(np.diff(points, axis=0), axis=1)
    along = np.concatenate([[0.0], np.cumsum(lengths)])
    count = max(int(np.ceil(along[-1] / spacing)), 1) + 1
    at = np.linspace(0.0, along[-1], count)
    step = np.clip(np.searchsorted(along, at, side="right") - 1, 0, len(lengths) - 1)
    t = np.clip((at - along[step]) / np.where(lengths[step] > 0, lengths[step], 1.0), 0.0, 1.0)
    return points[step] + t[:, None] * (points[step + 1] - points[step]), step
