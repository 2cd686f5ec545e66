"""From a fitted network to outputs: the mesh (a coarse-to-fine grid, then dual contouring or marching
cubes), normals, Laplacian.

Everything here works in the unit frame and in chunks, so memory stays bounded however many
points or grid nodes there are.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator
from functools import partial

import numpy as np
import torch
import trimesh
from scipy.ndimage import zoom
from skimage.measure import marching_cubes

from core.dual import dual_contour
from core.errors import CancelCheck, EmptySurfaceError, check_cancel
from core.grid import Grid
from core.network import ImplicitNetwork

log = logging.getLogger(__name__)

# The grid covers the cloud's bounding box plus this margin on every side (unit frame).
GRID_MARGIN = 0.05
# A cell is refined when some corner has |f| below this many cell diagonals. Every point of a
# cell lies within half a diagonal of a corner, so for a distance function (|∇f| = 1) 0.5 would
# be exact; 0.75 leaves room for |∇f| up to 1.5.
_NEAR_DIAGONALS = 0.75
_COARSEST_CELLS = 32
# Dual contouring puts one vertex on each patch of a cell's surface, so a cell through which two
# sheets pass joined by a tunnel (one marching-cubes patch) joins them at one vertex, and a mesh
# edge can get four faces: not a manifold. Seen once in the sample shapes' fits (featuretype,
# one edge of 150,000). The grid one cell finer falls differently on the surface, so the
# extraction samples it again, up to this many grids in all, then falls back to marching cubes.
DUAL_ATTEMPTS = 3
# A closed part of the mesh enclosing less than this many grid cells³ is dropped (``without_specks``).
SPECK_CELLS = 8


@torch.no_grad()
def evaluate(
    model: ImplicitNetwork, points: np.ndarray, chunk: int = 65_536, should_cancel: CancelCheck | None = None
) -> np.ndarray:
    """f at ``points`` (n, 3), float32, in chunks; ``should_cancel`` is polled before each."""
    values = np.empty(len(points), dtype=np.float32)
    for rows, batch in _chunks(points, chunk, should_cancel):
        values[rows] = model(batch).numpy()
    return values


@torch.no_grad()
def normals_and_laplacian(
    model: ImplicitNetwork, points: np.ndarray, chunk: int = 8192, should_cancel: CancelCheck | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals ∇f/‖∇f‖ (outward, since f < 0 inside) and Δf at ``points``, in chunks."""
    normals = np.empty((len(points), 3), dtype=np.float32)
    laplacian = np.empty(len(points), dtype=np.float32)
    for rows, batch in _chunks(points, chunk, should_cancel):
        _, grad, lap = model.derivatives(batch)
        normals[rows] = torch.nn.functional.normalize(grad, dim=1).numpy()
        laplacian[rows] = lap.numpy()
    return normals, laplacian


@torch.no_grad()
def unit_normals(
    model: ImplicitNetwork, points: np.ndarray, chunk: int = 16_384, should_cancel: CancelCheck | None = None
) -> np.ndarray:
    """Unit normals ∇f/‖∇f‖ at ``points`` (n, 3), float32, without the Laplacian: by reverse mode
    (``ImplicitNetwork.gradient``), two rows per point through the products, against four carrying
    the Jacobian forward and five with the Laplacian (at 1 M points, the extraction's largest part)."""
    result = np.empty((len(points), 3), dtype=np.float32)
    for rows, batch in _chunks(points, chunk, should_cancel):
        _, grad = model.gradient(batch)
        result[rows] = torch.nn.functional.normalize(grad, dim=1).numpy()
    return result


def _chunks(points: np.ndarray, chunk: int, should_cancel: CancelCheck | None) -> Iterator[tuple[slice, torch.Tensor]]:
    """The rows of ``points`` (n, 3), ``chunk`` at a time, as float32 tensors with their slice;
    ``should_cancel`` is polled before each."""
    for start in range(0, len(points), chunk):
        check_cancel(should_cancel)
        rows = slice(start, start + chunk)
        yield rows, torch.as_tensor(points[rows], dtype=torch.float32)


def extract_mesh(
    model: ImplicitNetwork,
    resolution: int,
    low: np.ndarray,
    high: np.ndarray,
    should_cancel: CancelCheck | None = None,
    method: str = "mc",
) -> tuple[trimesh.Trimesh, dict]:
    """The mesh of f = 0 over the box [low, high] plus a margin, in the unit frame.

    ``method`` "mc" is marching cubes of the sampled grid (it cuts across every sharp edge);
    "sharp" is dual contouring of the same grid (``core.dual``), whose vertices sit on edges and
    corners. Returns the mesh and statistics (how many grid nodes were evaluated, of how many).
    """
    values_at = partial(evaluate, model, should_cancel=should_cancel)
    if method == "sharp":
        derivatives_at = partial(derivatives, model, should_cancel=should_cancel)
        for attempt in range(DUAL_ATTEMPTS):
            grid = sample_grid(values_at, resolution + attempt, low, high, should_cancel)
            mesh = dual_contour(grid, values_at, derivatives_at)
            if is_closed_manifold(mesh):
                return without_specks(mesh, grid.cell), _grid_stats(grid)
            log.warning("dual contouring on %d cells left a non-manifold edge", resolution + attempt)
        log.warning("the mesh is marching cubes' after %d dual-contoured grids", DUAL_ATTEMPTS)
    else:
        grid = sample_grid(values_at, resolution, low, high, should_cancel)
    vertices, faces, _, _ = marching_cubes(
        grid.values_off_zero(), 0.0, spacing=(grid.cell,) * 3, gradient_direction="descent"
    )
    mesh = trimesh.Trimesh(vertices + grid.origin, faces, process=False)
    return without_specks(mesh, grid.cell), _grid_stats(grid)


def without_specks(mesh: trimesh.Trimesh, cell: float) -> trimesh.Trimesh:
    """``mesh`` without its connected parts that enclose less than ``SPECK_CELLS`` cells³ either
    way (a lump outside or a void inside), the largest part always kept; the vertices keep their
    order.

    Why: a part that small is a grid node or two on the wrong side of f = 0, below what the grid
    resolves; on the public rabbit model three voids of one or two cells inside the solid, whose
    sharpened faces cross one another (7 crossing faces).
    """
    faces = np.asarray(mesh.faces)
    if len(faces) == 0:
        return mesh
    adjacency = trimesh.graph.face_adjacency(faces=faces)
    parts = trimesh.graph.connected_component_labels(adjacency, node_count=len(faces))
    corners = np.asarray(mesh.vertices)[faces]  # (F, 3, 3)
    signed = np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])) / 6
    keep = np.abs(np.bincount(parts, weights=signed)) >= SPECK_CELLS * cell**3
    keep[np.argmax(np.bincount(parts))] = True
    if keep.all():
        return mesh
    used, renumbered = np.unique(faces[keep[parts]], return_inverse=True)
    return trimesh.Trimesh(np.asarray(mesh.vertices)[used], renumbered.reshape(-1, 3), process=False)


def _grid_stats(grid: Grid) -> dict:
    """How many grid nodes the extraction evaluated, of how many."""
    return {"grid_nodes": int(grid.values.size), "evaluated_nodes": grid.evaluated}


def is_closed_manifold(mesh: trimesh.Trimesh) -> bool:
    """``mesh`` has faces and every edge has exactly two (trimesh's ``is_watertight``)."""
    return len(mesh.faces) > 0 and bool(mesh.is_watertight)


@torch.no_grad()
def derivatives(
    model: ImplicitNetwork, points: np.ndarray, chunk: int = 16_384, should_cancel: CancelCheck | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """f (n,) and ∇f (n, 3) at ``points`` (n, 3), float64, in chunks: the network's exact values."""
    values = np.empty(len(points), dtype=np.float64)
    grads = np.empty((len(points), 3), dtype=np.float64)
    for rows, batch in _chunks(points, chunk, should_cancel):
        f, grad = model.gradient(batch)
        values[rows], grads[rows] = f.numpy(), grad.numpy()
    return values, grads


def sample_grid(
    values_at: Callable[[np.ndarray], np.ndarray],
    resolution: int,
    low: np.ndarray,
    high: np.ndarray,
    should_cancel: CancelCheck | None = None,
) -> Grid:
    """f on a grid over the box [low, high] plus a margin, evaluated only where the surface may be.

    The cells are (1 + 2 * GRID_MARGIN) / ``resolution`` wide. f is evaluated on a coarse grid
    first; each finer level starts from the coarser one's values interpolated (trilinear, so a
    cell whose coarse parent has corners of one sign keeps that sign) and evaluates only the cells
    that may hold the surface: near the zero level on intermediate levels; at the finest level
    every cell whose corners (evaluated or interpolated) change sign, again after each evaluation
    (a node found on the other side of the surface than its interpolation said turns the cells
    around it), until every cell that changes sign has all its corners evaluated. The grid's
    boundary is kept outside (f > 0) so that the surface is always closed.
    """
    cell = (1.0 + 2 * GRID_MARGIN) / resolution
    levels = max(0, int(math.floor(math.log2(resolution / _COARSEST_CELLS))))
    step = 2**levels
    size = np.asarray(high) - np.asarray(low) + 2 * GRID_MARGIN
    cells = (np.ceil(size / (cell * step)).astype(int)) * step  # fine cells per axis
    origin = (np.asarray(low) + np.asarray(high)) / 2 - cells * cell / 2

    coarse_cells = cells // step
    values = values_at(_grid_nodes(origin, cell * step, coarse_cells).reshape(-1, 3)).reshape(coarse_cells + 1)
    known = np.ones(values.shape, dtype=bool)
    for level in range(levels - 1, -1, -1):
        check_cancel(should_cancel)
        spacing = cell * 2**level
        near = None if level == 0 else _near_cells(values, spacing * 2)
        values = zoom(values, (2 * np.asarray(values.shape) - 1) / np.asarray(values.shape), order=1)
        was_known, known = known, np.zeros(values.shape, dtype=bool)
        known[::2, ::2, ::2] = was_known
        if near is not None:
            wanted = _cell_nodes(_split_cells(near)) & ~known
            values[wanted] = values_at(origin + np.argwhere(wanted) * spacing)
            known |= wanted
            continue
        wanted = _cell_nodes(_sign_change_cells(values)) & ~known
        while wanted.any():
            values[wanted] = values_at(origin + np.argwhere(wanted) * spacing)
            known |= wanted
            wanted = _cell_nodes(_sign_change_cells(values)) & ~known

    if not (values.min() < 0 < values.max()):
        raise EmptySurfaceError("the fitted function has no zero level set: no surface was found")
    for axis in range(3):  # close surfaces that reach the grid's boundary
        boundary = [slice(None)] * 3
        for end in (0, -1):
            boundary[axis] = end
            values[tuple(boundary)] = np.maximum(values[tuple(boundary)], cell)
    return Grid(values=values, origin=origin, cell=cell, evaluated=int(np.count_nonzero(known)))


def _grid_nodes(origin: np.ndarray, spacing: float, cells: np.ndarray) -> np.ndarray:
    axes = [origin[a] + spacing * np.arange(cells[a] + 1) for a in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


def _near_cells(values: np.ndarray, spacing: float) -> np.ndarray:
    """Cells with a corner where |f| is below ``_NEAR_DIAGONALS`` cell diagonals."""
    magnitude = np.abs(values)
    nx, ny, nz = np.asarray(values.shape) - 1
    corners = [magnitude[dx : dx + nx, dy : dy + ny, dz : dz + nz] for dx, dy, dz in _CORNERS]
    return np.minimum.reduce(corners) < _NEAR_DIAGONALS * spacing * math.sqrt(3)


def _sign_change_cells(values: np.ndarray) -> np.ndarray:
    """Cells whose corners are not all on one side of the zero level."""
    nx, ny, nz = np.asarray(values.shape) - 1
    corners = [values[dx : dx + nx, dy : dy + ny, dz : dz + nz] for dx, dy, dz in _CORNERS]
    return (np.minimum.reduce(corners) < 0) & (np.maximum.reduce(corners) >= 0)


def _split_cells(cells: np.ndarray) -> np.ndarray:
    """Each cell of a level as its eight children on the next finer level."""
    return cells.repeat(2, axis=0).repeat(2, axis=1).repeat(2, axis=2)


def _cell_nodes(cells: np.ndarray) -> np.ndarray:
    """The nodes that are corners of at least one of the given cells."""
    nodes = np.zeros(np.asarray(cells.shape) + 1, dtype=bool)
    nx, ny, nz = cells.shape
    for dx, dy, dz in _CORNERS:
        nodes[dx : dx + nx, dy : dy + ny, dz : dz + nz] |= cells
    return nodes


_CORNERS = [(dx, dy, dz) for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)]
