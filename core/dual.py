"""Dual contouring of a sampled grid: vertices on sharp edges and corners instead of across them.

Marching cubes puts its vertices on the grid's edges, so it cuts across every sharp edge and corner
of the surface. Here the topology still comes from marching cubes (same grid, same cases, so the
same closed manifold), but the mesh is its dual: each cell's marching-cubes triangles form one or
more patches (connected pieces); each patch becomes one vertex, and each marching-cubes vertex (a
crossing of f = 0 with a grid edge) becomes the quad of the four patches around that grid edge.
Each vertex is placed where the tangent planes of f at its patch's crossings meet best (a quadric
error function, QEF, on f and ∇f: Hermite data): on a corner where three planes meet, on an edge
where two do, on the surface where all agree. It stays within its cell (plus ``CELL_SLACK``), and
a vertex whose faces would fold over is put back at its crossings' mean, so the mesh stays free of
flipped faces.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from skimage.measure import marching_cubes

from core.features import Derivatives, SidePlanes, side_planes, unit
from core.grid import Grid
from core.intersections import crossing_faces
from core.trees import kd_tree

# Directions whose weight in a patch's QEF is below this fraction of the strongest are left free
# (truncated pseudo-inverse): along a flat face or an edge the vertex stays at the crossings' mean.
QEF_CUTOFF = 0.1
# How far (in cells) a vertex may leave its cell: a corner near the cell's face may lie just past it.
CELL_SLACK = 0.5
# How far (in cells) a vertex in the band of a rounded edge may move to reach the sharp edge.
SHARP_SLACK = 3.0
_FOLD_PASSES = 4
_UNCROSS_PASSES = 8  # one vertex per crossing face per pass: a crossing may take two or three
# Vertices that f's own planes (the QEF) put this many cells or more from their crossings' mean are
# checked for crossings too, besides the sharpened ones: on featuretype, QEF vertices 0.4-0.7 cells
# from their means left 21 faces through others. (Their faces add 7 % to the faces tested there;
# testing every face took five times as long.)
UNCROSS_FROM = 0.25
# Vertices with another vertex this many cells away or nearer whose faces face the other way (the
# two sheets of a wall thinner than a cell or two, whose vertices can cross even near their
# means), and those of folds sharper than 60° (a thin wall's end), are checked for crossings too
# (``_folded``): a public tray 0.01 thick kept 6 crossing faces at its rim.
FACING_REACH = 1.5
# The share of the way back of the first pass: enough to part faces that only touch (vertices
# placed on one edge line), too little to move the mesh.
_TOUCH_SHARE = 1e-3

Function = Callable[[np.ndarray], np.ndarray]


def dual_contour(grid: Grid, values_at: Function, derivatives_at: Derivatives, sharpen: bool = True) -> trimesh.Trimesh:
    """The mesh of f = 0 on ``grid`` by dual contouring, in the grid's (unit) frame.

    ``values_at`` (n, 3) -> (n,) evaluates f, ``derivatives_at`` (n, 3) -> (n,), (n, 3) f and ∇f.
    ``sharpen``: where f rounds an edge, fit the planes of the faces on its two sides
    (``core.features.side_planes``) instead of f's own; a vertex that would then leave its cell's
    neighbourhood (one on the band's flank, far from the edge) takes the nearer face's plane only.
    """
    values = grid.values_off_zero()
    corners, triangles, _, _ = marching_cubes(values, 0.0)
    crossings, axis, lower = _crossings(grid, corners)
    normals = unit(derivatives_at(crossings)[1])

    cells = np.asarray(values.shape) - 1
    # A triangle's cell from the midpoints of its vertices' grid edges: their centre is strictly
    # inside the cell, where the vertices' own centre may sit on its face (a crossing at a node).
    midpoints = lower + 0.5 * np.eye(3)[axis]
    triangle_cell = np.clip(np.floor(midpoints[triangles].mean(axis=1)).astype(np.int64), 0, cells - 1)
    total = int(np.prod(cells))
    keys, patch_of_key, patch_cell = _patches(triangles, np.ravel_multi_index(triangle_cell.T, cells), total)
    patches = len(patch_cell)
    key_vertex = keys // total
    own = crossings[key_vertex], normals[key_vertex]
    placed, mean = _place(patch_of_key, [own], own[0], patches)
    slack = np.full(patches, CELL_SLACK)
    if sharpen:
        sides = side_planes(crossings, normals, derivatives_at)
        placed, slack = _sharpen(patch_of_key, sides, key_vertex, own[0], placed, slack)
    cell_index = np.stack(np.unravel_index(patch_cell, cells), axis=1)
    low = grid.position(cell_index - slack[:, None])
    high = grid.position(cell_index + 1 + slack[:, None])
    placed = np.clip(placed, low, high)
    moved = slack > CELL_SLACK

    quads, quad_normals = _quads(keys, patch_of_key, cells, axis, lower, values, normals)
    faces, face_normals = _triangulate(quads, quad_normals, placed, moved, values_at)
    placed = _unfold(placed, mean, faces, face_normals, derivatives_at, 0.01 * grid.cell**2)
    off_mean = np.linalg.norm(placed - mean, axis=1) >= UNCROSS_FROM * grid.cell
    folded = _folded(placed, faces, FACING_REACH * grid.cell)
    placed = _uncross(placed, mean, faces, moved | off_mean | folded)
    return trimesh.Trimesh(placed, faces, process=False)


def _crossings(grid: Grid, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each marching-cubes vertex (index coordinates): its unit-frame point (c, 3), the axis of its
    grid edge (c,) and the edge's lower node (c, 3). The point stays marching cubes' linear
    interpolation: within h²|κ|/8 of f = 0 (under 0.001 for a cell of 0.007 on a bend of radius
    0.01), well below what the QEF needs, and refining it would cost one more pass per crossing."""
    rows = np.arange(len(corners))
    axis = np.argmax(np.abs(corners - np.round(corners)), axis=1)
    lower = np.round(corners).astype(np.int64)
    lower[rows, axis] = np.floor(corners[rows, axis]).astype(np.int64)
    return grid.position(corners), axis, lower


def _patches(
    triangles: np.ndarray, triangle_cell: np.ndarray, cell_count: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The patches: connected pieces of each cell's triangles.

    A key ``vertex * cell_count + cell`` stands for a marching-cubes vertex as seen from one of its
    cells; triangles of one cell that share a vertex share its key, and are joined through it.
    Returns the sorted keys (k,), each key's patch (k,), and each patch's cell (p,).
    """
    corner_keys = triangles.astype(np.int64) * cell_count + triangle_cell[:, None]
    keys, key_of_corner = np.unique(corner_keys.ravel(), return_inverse=True)
    count = len(triangles) + len(keys)
    rows = np.repeat(np.arange(len(triangles)), 3)
    graph = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, len(triangles) + key_of_corner)), (count, count))
    _, labels = connected_components(graph, directed=False)
    _, patch_of_key = np.unique(labels[len(triangles) :], return_inverse=True)
    patch_cell = np.empty(patch_of_key.max() + 1, dtype=np.int64)
    patch_cell[patch_of_key] = keys % cell_count
    return keys, patch_of_key, patch_cell


def _place(
    patch_of_key: np.ndarray,
    planes: list[tuple[np.ndarray, np.ndarray]],
    crossings: np.ndarray,
    patch_count: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Each patch's vertex: the minimiser of Σ (n·(x - p))² over its keys' ``planes`` (each a
    (points, unit normals) pair of (k, 3) arrays), nearest to the mean of its ``crossings``
    (truncated pseudo-inverse, ``QEF_CUTOFF``); and that mean. Shapes (p, 3)."""
    count = np.bincount(patch_of_key, minlength=patch_count).astype(np.float64)[:, None]
    mean = np.zeros((patch_count, 3))
    np.add.at(mean, patch_of_key, crossings)
    mean /= np.maximum(count, 1)
    a = np.zeros((patch_count, 3, 3))
    b = np.zeros((patch_count, 3))
    for points, normals in planes:
        np.add.at(a, patch_of_key, normals[:, :, None] * normals[:, None, :])
        np.add.at(b, patch_of_key, normals * np.einsum("ij,ij->i", normals, points)[:, None])
    weights, vectors = np.linalg.eigh(a)
    strongest = weights[:, -1:]
    inverse = np.where(weights > QEF_CUTOFF * strongest, 1.0 / np.where(weights > 0, weights, 1.0), 0.0)
    residual = b - np.einsum("pij,pj->pi", a, mean)
    step = np.einsum("pij,pj->pi", vectors, inverse * np.einsum("pji,pj->pi", vectors, residual))
    return mean + step, mean


def _sharpen(
    patch_of_key: np.ndarray,
    sides: SidePlanes,
    key_vertex: np.ndarray,
    crossings: np.ndarray,
    placed: np.ndarray,
    slack: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Move the vertices of patches in an edge's band onto the sharp surface of the side planes.

    Each crossing of such a patch contributes the plane of the face it lies nearer; the vertex is
    the QEF of those planes. A patch whose crossings are all nearer one face goes onto that face,
    one whose crossings are nearer two faces onto their edge, and one at a corner, with crossings
    near three faces, onto the corner. (Fitting both planes of every crossing instead put a
    corner's vertex on one of its edges: a box rounded by 0.02 kept its corners 0.011 to 0.0125
    from the mesh, against 0.003 to 0.008 here.) These vertices may move ``SHARP_SLACK`` cells, as
    far as the fitted rounding lies from the edge.
    """
    a = sides.points_a[key_vertex], sides.normals_a[key_vertex]
    b = sides.points_b[key_vertex], sides.normals_b[key_vertex]
    edge = sides.edge[key_vertex]
    patches = len(placed)
    sharp = np.zeros(patches, dtype=bool)
    sharp[patch_of_key[edge]] = True
    if not sharp.any():
        return placed, slack
    offset_a = np.abs(np.einsum("ij,ij->i", a[1], crossings - a[0]))
    offset_b = np.abs(np.einsum("ij,ij->i", b[1], crossings - b[0]))
    nearer_a = (offset_a <= offset_b)[:, None]
    nearer = np.where(nearer_a, a[0], b[0]), np.where(nearer_a, a[1], b[1])
    faces, _ = _place(patch_of_key, [nearer], crossings, patches)
    return np.where(sharp[:, None], faces, placed), np.where(sharp, SHARP_SLACK, slack)


def _quads(
    keys: np.ndarray,
    patch_of_key: np.ndarray,
    cells: np.ndarray,
    axis: np.ndarray,
    lower: np.ndarray,
    values: np.ndarray,
    normals: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The quad of each crossing: the patches of the four cells around its grid edge, ordered
    counter-clockwise seen from outside (f increasing), and the crossing's normal. (c, 4), (c, 3)."""
    rows = np.arange(len(axis))
    b, c = (axis + 1) % 3, (axis + 2) % 3
    quads = np.empty((len(axis), 4), dtype=np.int64)
    total = np.prod(cells)
    for corner, (db, dc) in enumerate(((0, 0), (-1, 0), (-1, -1), (0, -1))):
        cell = lower.copy()
        cell[rows, b] += db
        cell[rows, c] += dc
        cell = np.clip(cell, 0, cells - 1)
        key = rows * total + np.ravel_multi_index(cell.T, cells)
        found = np.clip(np.searchsorted(keys, key), 0, len(keys) - 1)
        quads[:, corner] = np.where(keys[found] == key, patch_of_key[found], -1)
    inside_below = values[tuple(lower.T)] < 0
    quads[~inside_below] = quads[~inside_below][:, ::-1]
    complete = (quads >= 0).all(axis=1)
    return quads[complete], normals[complete]


def _triangulate(
    quads: np.ndarray, quad_normals: np.ndarray, vertices: np.ndarray, sharpened: np.ndarray, values_at: Function
) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles per quad. A quad with a ``sharpened`` vertex is split along the diagonal that
    lies on the surface (the smaller |f| at its midpoint): along a sharp edge that is the diagonal
    on the edge, not the one across it; any other along its shorter diagonal.
    Returns the faces (2q, 3) and each face's reference normal, its crossing's (2q, 3)."""
    a, b, c, d = (vertices[quads[:, i]] for i in range(4))
    along_ac = np.einsum("ij,ij->i", c - a, c - a) <= np.einsum("ij,ij->i", d - b, d - b)
    sharp = np.flatnonzero(sharpened[quads].any(axis=1))
    if len(sharp):
        off_ac = np.abs(values_at((a[sharp] + c[sharp]) / 2))
        off_bd = np.abs(values_at((b[sharp] + d[sharp]) / 2))
        along_ac[sharp] = off_ac <= off_bd
    first = np.where(along_ac[:, None], quads[:, [0, 1, 2]], quads[:, [0, 1, 3]])
    second = np.where(along_ac[:, None], quads[:, [0, 2, 3]], quads[:, [1, 2, 3]])
    return np.concatenate([first, second]), np.concatenate([quad_normals, quad_normals])


def _uncross(vertices: np.ndarray, fallback: np.ndarray, faces: np.ndarray, movable: np.ndarray) -> np.ndarray:
    """Take the ``movable`` vertices of faces that cross another face back towards ``fallback``.

    Two sharpened vertices whose side planes cross can push a face through one of the other side
    (``core.intersections``), as can vertices that f's own planes put far from their crossings'
    mean; only faces with such a vertex (``movable``) are tested, and after the first pass only
    the faces of the vertices moved. Each pass takes back, of each crossing face, only the vertex
    that moved the farthest, and half its way (a thousandth in the first pass, which parts faces
    that merely touch; all of it in the last): putting every sharpened vertex of the crossing
    faces all the way back rounded the edges there (on the same fits: l_bracket's edge IoU 0.583
    -> 0.577, octagon_pocket's d_H 0.0110 -> 0.0139; MeshLab's self-intersecting faces the same
    either way, 31 -> 4 and 6 -> 0 on l_bracket and the cube, docs/benchmarks.md).
    """
    vertices = vertices.copy()
    suspects = np.flatnonzero(movable[faces].any(axis=1))
    for remaining in range(_UNCROSS_PASSES, 0, -1):
        crossing = faces[crossing_faces(vertices, faces, suspects)]
        # Of each crossing face, the vertex that moved the farthest: the least taken back.
        moved = np.where(movable[crossing], np.linalg.norm(vertices[crossing] - fallback[crossing], axis=2), 0.0)
        back = np.unique(crossing[np.arange(len(crossing)), moved.argmax(axis=1)])
        back = back[movable[back] & (vertices[back] != fallback[back]).any(axis=1)]
        if len(back) == 0:
            break
        # A thousandth of the way first (_TOUCH_SHARE), then half the way each pass (a crossing is
        # often undone by less), all of it at the last.
        share = _TOUCH_SHARE if remaining == _UNCROSS_PASSES else 0.5 if remaining > 1 else 1.0
        vertices[back] += share * (fallback[back] - vertices[back])
        suspects = np.flatnonzero(np.isin(faces, back).any(axis=1))
    return vertices


def _folded(vertices: np.ndarray, faces: np.ndarray, reach: float) -> np.ndarray:
    """(v,) bool: the vertices of the mesh edges whose two faces' normals differ by more than 120°
    (a fold sharper than 60°, such as a thin wall's end), and those with another vertex within
    ``reach`` whose vertex normal differs by as much (the two sides of a thin wall)."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    folded = np.zeros(len(vertices), dtype=bool)
    folded[mesh.face_adjacency_edges[mesh.face_adjacency_angles > np.radians(120)].ravel()] = True
    pairs = kd_tree(vertices).query_pairs(reach, output_type="ndarray")
    normal = mesh.vertex_normals
    folded[pairs[np.einsum("ij,ij->i", normal[pairs[:, 0]], normal[pairs[:, 1]]) < -0.5].ravel()] = True
    return folded


def _unfold(
    vertices: np.ndarray,
    fallback: np.ndarray,
    faces: np.ndarray,
    reference: np.ndarray,
    derivatives_at: Derivatives,
    min_area: float,
) -> np.ndarray:
    """Put back at ``fallback`` the vertices of faces that face away from the surface.

    A face beside a sharp edge may lie on the other face of the edge than its crossing, so its
    crossing's normal (``reference``) only picks the suspects (more than 60° off); ∇f at a suspect's
    centre decides: a face is folded when it points against ∇f there.
    """
    vertices = vertices.copy()
    for _ in range(_FOLD_PASSES):
        corner = vertices[faces]
        normal = np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])
        suspect = np.flatnonzero(np.einsum("ij,ij->i", normal, reference) <= 0.5 * np.linalg.norm(normal, axis=1))
        if len(suspect) == 0:
            break
        gradient = derivatives_at(corner[suspect].mean(axis=1))[1]
        # Slivers along an edge (three vertices on one line) have no side to fold to.
        area = np.linalg.norm(normal[suspect], axis=1) / 2
        folded = suspect[(np.einsum("ij,ij->i", normal[suspect], gradient) < 0) & (area > min_area)]
        if len(folded) == 0:
            break
        moved = np.unique(faces[folded])
        vertices[moved] = fallback[moved]
    return vertices
