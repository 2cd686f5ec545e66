"""Synthetic test clouds with known ground truth (no torch, no ../shared needed).

Each shape is a watertight, outward-oriented triangle mesh, centred on its bounding box and
scaled so that its largest extent is 1 (the unit frame). ``sample_shape`` draws points uniformly
by area, adds Gaussian noise and labels every point the way ../shared/data does: clean position,
outward normal, distance to the nearest sharp edge (a mesh edge whose two faces' normals differ
by more than 30 degrees) and ``is_edge`` (that distance <= 0.01).

    >>> shape = sample_shape("cube", n_points=6000, seed=0)
    >>> write_ply("cube.ply", shape.points)

From a shell: ``python -m evaluation.shapes cube --points 6000 --seed 0 --out cube.ply``.

Any mesh file (a public test model, a scan) is sampled the same way by ``sample_mesh``, and
``write_shape_folder`` writes the result as a shape folder of ../shared/data's layout, which
``bench/run.py --data`` scores: ``python -m evaluation.shapes --mesh bunny.ply --folder out/bunny``.

Shapes: ``cube``; ``box`` (1.0 x 0.8 x 0.5); ``l_shape`` (an extruded L with a concave inner
edge); ``cylinder`` (96 sections: two circular rims, a smooth side); ``sphere`` (smooth control,
no sharp edges); ``bumps`` (a smooth blob like a scan: a sphere with seven Gaussian bumps and dents,
the tips of the narrowest with a curvature radius of 0.03 to 0.05; no sharp edges). Booleans
(holes) would need an extra engine (manifold3d), so there are none.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from evaluation.metrics import sample_triangles

SHAPES = ("cube", "box", "l_shape", "cylinder", "sphere", "bumps")
# The bumps of ``bumps``: angular widths (radians) and heights, on a sphere of radius 1.
BUMP_WIDTHS = (0.15, 0.2, 0.3, 0.12, 0.25, 0.4, 0.18)
BUMP_HEIGHTS = (0.45, -0.12, 0.3, 0.35, -0.1, 0.25, 0.5)
NOISE = 0.005
EDGE_DELTA = 0.01
SHARP_ANGLE_DEG = 30.0
EDGE_SPACING = 0.002


@dataclass
class SampledShape:
    """A noisy cloud and its ground truth, all in the unit frame, in the same point order.

    ``edge_dist`` is inf on shapes without sharp edges; ``edge_samples`` (M, 3) are points along
    every sharp edge at most ``EDGE_SPACING`` apart (empty (0, 3) for smooth shapes).
    """

    name: str
    points: np.ndarray  # (N, 3) float64, noisy
    clean_points: np.ndarray  # (N, 3) on the mesh
    normals: np.ndarray  # (N, 3) unit, outward
    face_index: np.ndarray  # (N,) the triangle each point was drawn from
    edge_dist: np.ndarray  # (N,)
    is_edge: np.ndarray  # (N,) bool
    edge_samples: np.ndarray  # (M, 3)
    mesh: trimesh.Trimesh


def make_mesh(name: str) -> trimesh.Trimesh:
    """The named shape as a watertight mesh in the unit frame (bounding-box centre 0, extent 1)."""
    if name == "cube":
        mesh = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    elif name == "box":
        mesh = trimesh.creation.box(extents=(1.0, 0.8, 0.5))
    elif name == "l_shape":
        # The L (legs 0.4 thick) fan-triangulated from its outer corner, extruded by 0.5.
        outline = np.array([[0, 0], [1, 0], [1, 0.4], [0.4, 0.4], [0.4, 1], [0, 1]], dtype=float)
        fan = np.array([[0, i, i + 1] for i in range(1, 5)])
        mesh = trimesh.creation.extrude_triangulation(outline, fan, height=0.5)
    elif name == "cylinder":
        mesh = trimesh.creation.cylinder(radius=0.5, height=0.6, sections=96)
    elif name == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    elif name == "bumps":
        mesh = _bumps()
    else:
        raise ValueError(f"unknown shape {name!r}; choose one of {', '.join(SHAPES)}")
    mesh = unit_frame(mesh)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    return mesh


def unit_frame(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """``mesh`` merged (duplicate vertices joined), turned outward when it encloses a negative
    volume, centred on its bounding box and scaled to a largest extent of 1, as ../shared/data's
    shapes are. A mesh that is not watertight (a scan open at its base) keeps its own winding."""
    mesh = trimesh.Trimesh(mesh.vertices, mesh.faces, process=True)
    if mesh.is_watertight and mesh.volume < 0:
        mesh.invert()
    low, high = mesh.bounds
    mesh.apply_translation(-(low + high) / 2)
    mesh.apply_scale(1.0 / (high - low).max())
    return mesh


def sample_shape(
    name: str, n_points: int = 16_384, noise: float = NOISE, seed: int = 0, edge_delta: float = EDGE_DELTA
) -> SampledShape:
    """``n_points`` points drawn uniformly by area on the named shape, with Gaussian ``noise``.

    The same arguments give the same cloud (numpy's PCG64 seeded with ``seed``).
    """
    return sample_mesh(make_mesh(name), name, n_points, noise, seed, edge_delta)


def sample_mesh(
    mesh: trimesh.Trimesh,
    name: str,
    n_points: int = 16_384,
    noise: float = NOISE,
    seed: int = 0,
    edge_delta: float = EDGE_DELTA,
) -> SampledShape:
    """``n_points`` points drawn uniformly by area on ``mesh`` (already in the unit frame, see
    ``unit_frame``), with Gaussian ``noise``, labelled as ``sample_shape`` labels them."""
    rng = np.random.default_rng(seed)
    clean, face_index, weights = sample_triangles(mesh.triangles, n_points, rng)
    points = clean + rng.normal(0.0, noise, size=clean.shape)

    sharp = sharp_edges(mesh)
    edge_dist = _distance_to_segments(clean, sharp)
    return SampledShape(
        name=name,
        points=points,
        clean_points=clean,
        normals=_smooth_normals(mesh, face_index, weights),
        face_index=face_index,
        edge_dist=edge_dist,
        is_edge=edge_dist <= edge_delta,
        edge_samples=_resample(sharp, EDGE_SPACING),
        mesh=mesh,
    )


def _bumps() -> trimesh.Trimesh:
    """A sphere of radius 1 (81,920 faces, neighbours at most 27° apart on the narrowest bump) with a
    Gaussian bump or dent of ``BUMP_WIDTHS`` and ``BUMP_HEIGHTS`` around each of seven seeded
    directions: flat-sided narrow bumps such as a scan's ears, where a sharp-edge detector that
    looks only at the flanks finds a ridge."""
    sphere = trimesh.creation.icosphere(subdivisions=6, radius=1.0)
    directions = np.random.default_rng(3).normal(size=(len(BUMP_WIDTHS), 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    radius = np.ones(len(sphere.vertices))
    for direction, width, height in zip(directions, BUMP_WIDTHS, BUMP_HEIGHTS, strict=True):
        angle = np.arccos(np.clip(sphere.vertices @ direction, -1.0, 1.0))
        radius += height * np.exp(-((angle / width) ** 2))
    return trimesh.Trimesh(sphere.vertices * radius[:, None], sphere.faces)


def sharp_edges(mesh: trimesh.Trimesh, angle_deg: float = SHARP_ANGLE_DEG) -> np.ndarray:
    """(K, 2, 3) end points of the mesh edges whose face normals differ by more than ``angle_deg``."""
    sharp = mesh.face_adjacency_angles > np.radians(angle_deg)
    return mesh.vertices[mesh.face_adjacency_edges[sharp]]


def write_ply(path: str | Path, points: np.ndarray) -> None:
    """Write ``points`` (N, 3) as a binary little-endian PLY with float32 ``x y z`` only."""
    from plyfile import PlyData, PlyElement

    vertex = np.empty(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    for axis, column in zip("xyz", np.asarray(points, dtype=np.float32).T):
        vertex[axis] = column
    PlyData([PlyElement.describe(vertex, "vertex")], text=False, byte_order="<").write(str(path))


def _smooth_normals(mesh: trimesh.Trimesh, face_index: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Outward normals interpolated inside each triangle from vertex normals that average only the
    faces of the same smooth surface (faces joined by non-sharp edges), as ../shared/data does.
    On flat faces this is the face normal; on a tessellated curved surface it removes the faceting.
    """
    smooth_pairs = mesh.face_adjacency[mesh.face_adjacency_angles <= np.radians(SHARP_ANGLE_DEG)]
    groups = trimesh.graph.connected_component_labels(smooth_pairs, node_count=len(mesh.faces))
    # One normal per (vertex, smooth group): the angle-weighted mean of that group's face normals.
    keys = mesh.faces.astype(np.int64) * (groups.max() + 1) + groups[:, None]
    unique, slot = np.unique(keys.ravel(), return_inverse=True)
    sums = np.zeros((len(unique), 3))
    contribution = mesh.face_normals[:, None, :] * mesh.face_angles[:, :, None]
    np.add.at(sums, slot, contribution.reshape(-1, 3))
    corner_normals = sums[slot.reshape(-1, 3)[face_index]]  # (N, 3 corners, 3)
    normals = (weights[:, :, None] * corner_normals).sum(axis=1)
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def _distance_to_segments(points: np.ndarray, segments: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """Straight 3D distance from each point to the nearest segment (inf when there is none)."""
    if len(segments) == 0:
        return np.full(len(points), np.inf)
    start, direction = segments[:, 0], segments[:, 1] - segments[:, 0]
    length2 = (direction**2).sum(axis=1)
    result = np.empty(len(points))
    for i in range(0, len(points), chunk):
        offset = points[i : i + chunk, None, :] - start[None]
        t = np.clip((offset * direction[None]).sum(axis=2) / length2, 0.0, 1.0)
        result[i : i + chunk] = np.linalg.norm(offset - t[..., None] * direction[None], axis=2).min(axis=1)
    return result


def _resample(segments: np.ndarray, spacing: float) -> np.ndarray:
    """Points along each segment, ends included, at most ``spacing`` apart; shared ends once."""
    pieces = [np.zeros((0, 3))]
    for start, end in segments:
        count = max(int(np.ceil(np.linalg.norm(end - start) / spacing)), 1)
        pieces.append(start + np.linspace(0.0, 1.0, count + 1)[:, None] * (end - start))
    return np.unique(np.round(np.concatenate(pieces), 12), axis=0)


def write_shape_folder(shape: SampledShape, folder: str | Path) -> Path:
    """Write ``shape`` as a shape folder of ../shared/data's layout: ``points.ply``, ``labels.npz``
    (``points``, ``points_clean``, ``normals``, ``face_index``, ``edge_dist``, ``is_edge``),
    ``gt.ply`` and ``edges_gt.npy`` (float32). Returns the folder."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    write_ply(folder / "points.ply", shape.points)
    np.savez(
        folder / "labels.npz",
        points=shape.points.astype(np.float32),
        points_clean=shape.clean_points.astype(np.float32),
        normals=shape.normals.astype(np.float32),
        face_index=shape.face_index.astype(np.int32),
        edge_dist=shape.edge_dist.astype(np.float32),
        is_edge=shape.is_edge,
    )
    shape.mesh.export(folder / "gt.ply")
    np.save(folder / "edges_gt.npy", shape.edge_samples.astype(np.float32))
    return folder


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description="write a noisy cloud of a synthetic shape as a binary PLY, or of any mesh as a shape folder"
    )
    parser.add_argument("shape", nargs="?", choices=SHAPES)
    parser.add_argument("--mesh", type=Path, help="sample this mesh file instead of a named shape")
    parser.add_argument("--points", type=int, default=16_384)
    parser.add_argument("--noise", type=float, default=NOISE)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, help="the cloud, a binary PLY")
    parser.add_argument("--folder", type=Path, help="a shape folder: points, labels, gt.ply, edges_gt.npy")
    args = parser.parse_args(argv)
    if (args.shape is None) == (args.mesh is None) or (args.out is None) == (args.folder is None):
        parser.error("give a shape or --mesh, and --out or --folder")
    if args.mesh is not None:
        loaded = trimesh.load(args.mesh, force="mesh")
        if not isinstance(loaded, trimesh.Trimesh) or not len(loaded.faces):
            parser.error(f"{args.mesh} holds no triangle mesh")
        mesh = unit_frame(loaded)
        shape = sample_mesh(mesh, args.mesh.stem, args.points, args.noise, args.seed)
    else:
        shape = sample_shape(args.shape, args.points, args.noise, args.seed)
    if args.folder is not None:
        write_shape_folder(shape, args.folder)
    else:
        write_ply(args.out, shape.points)


if __name__ == "__main__":
    main()
