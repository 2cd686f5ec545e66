"""One reconstruction end to end: normalise, fit, extract, and write the outputs."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import cache, partial
from pathlib import Path

import numpy as np
import torch
import trimesh

from core.corners import extend_to_corners, snap_corners
from core.creases import normals_on_faces, onto_refitted
from core.curves import Curve, distance_to_curves, edge_curves, without_isolated
from core.errors import CancelCheck
from core.extract import extract_mesh, normals_and_laplacian, unit_normals
from core.fit import FIT_POINTS, fit, fit_rows
from core.frame import Frame
from core.mesh_formats import convert_obj, mesh_file
from core.network import ImplicitNetwork
from core.outputs import FIT_OUTPUTS, MESH_FORMATS, OUTPUT_NAMES, PREVIEW_POINTS, write_atomically
from core.params import FitParams
from core.progress import Progress, ProgressCallback, Stage
from core.strays import strays

# Edge curves (unit frame): shorter chains of creased mesh edges are noise, not edges; samples
# every CURVE_SPACING.
CURVE_MIN_LENGTH = 0.02
CURVE_SPACING = 0.005
# A group of curves linked end to end within CURVE_JOIN_GAP shorter than CURVE_GROUP_LENGTH in all
# is a smooth surface's crease, not an edge, unless its faces meet at less than CURVE_KEEP_DIHEDRAL
# degrees (``core.curves.without_isolated``): the bunny scan's false edges 1.22 -> 0.70 % and
# 1.33 -> 0.92 % of its points (seeds 0 and 1), the sample CAD shapes' edge IoU unchanged
# (docs/benchmarks.md).
CURVE_JOIN_GAP = 0.05
CURVE_GROUP_LENGTH = 0.06
CURVE_KEEP_DIHEDRAL = 120.0


@dataclass
class Reconstruction:
    """The outputs of one reconstruction, in the input's coordinates.

    ``edge_laplacian`` holds |Δf| at the edge points in the unit frame, where ``tau`` applies;
    ``curves`` the edge curves (sharp extraction), in the input's coordinates; ``points`` is the
    input cloud (preview.json samples it).
    """

    mesh: trimesh.Trimesh
    normals: np.ndarray
    edge_indices: np.ndarray
    edge_points: np.ndarray
    edge_laplacian: np.ndarray
    tau: float
    points: np.ndarray
    curves: list[Curve] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    stats: dict[str, float] = field(default_factory=dict)

    def mesh_obj(self) -> bytes:
        """The mesh as Wavefront OBJ text."""
        return mesh_file(self.mesh, "obj")

    def normals_json(self) -> bytes:
        """``{"normals": [[nx, ny, nz], ...]}``, one unit vector per input point, input order."""
        return json.dumps({"normals": np.round(self.normals.astype(np.float64), 6).tolist()}).encode()

    def edges_json(self) -> bytes:
        """``{"tau", "count", "indices", "points", "laplacian", "curves"}``: the edge points, and the
        edge curves as ``{"points", "dihedral", "convex"}`` (ordered polylines on the edges)."""
        curves = [
            {"points": _short(curve.points).tolist(), "dihedral": round(curve.dihedral, 1), "convex": curve.convex}
            for curve in self.curves
        ]
        return json.dumps(
            {
                "tau": self.tau,
                "count": len(self.edge_indices),
                "indices": self.edge_indices.tolist(),
                "points": self.edge_points.tolist(),
                "laplacian": np.round(self.edge_laplacian.astype(np.float64), 4).tolist(),
                "curves": curves,
            }
        ).encode()

    def preview_json(self, size: int = PREVIEW_POINTS) -> bytes:
        """``{"total", "points", "normals", "edge"}``: at most ``size`` input points drawn at random
        (the same ones for the same cloud; in input order), their normals and whether each is an
        edge point (0 or 1), so that a viewer draws a cloud of any size from a bounded file."""
        total = len(self.points)
        chosen = np.arange(total)
        if total > size:
            chosen = np.sort(np.random.default_rng(0).choice(total, size, replace=False))
        edge = np.zeros(total, dtype=np.int8)
        edge[self.edge_indices] = 1
        preview = {
            "total": total,
            "points": _short(self.points[chosen]).tolist(),
            "normals": np.round(self.normals[chosen].astype(np.float64), 6).tolist(),
            "edge": edge[chosen].tolist(),
        }
        return json.dumps(preview).encode()

    def outputs(self, names: Iterable[str] = OUTPUT_NAMES) -> dict[str, bytes]:
        """The output files ``names`` by name: those a job stores (``core.outputs.OUTPUT_NAMES``) by
        default; ``mesh.<format>`` for any of ``core.mesh_formats.MESH_FORMATS``, each made from
        the OBJ as the API makes it from a job's stored OBJ, so that a fit's files are the same
        both ways (the OBJ's 8 decimals, not the unit frame's exact coplanar vertices, which
        MeshLab's self-intersection check misreads)."""
        obj = cache(self.mesh_obj)

        def mesh_in(fmt: str) -> bytes:
            return convert_obj(obj(), fmt)

        makers = {"normals.json": self.normals_json, "edges.json": self.edges_json, "preview.json": self.preview_json}
        makers.update({f"mesh.{fmt}": partial(mesh_in, fmt) for fmt in MESH_FORMATS})
        unknown = [name for name in names if name not in makers]
        if unknown:
            raise ValueError(f"no output called {', '.join(unknown)}")
        return {name: makers[name]() for name in names}

    def summary(self) -> dict:
        """Counts and timings, as a JSON-ready dict."""
        return {
            "vertices": len(self.mesh.vertices),
            "faces": len(self.mesh.faces),
            "watertight": bool(self.mesh.is_watertight),
            "edge_points": len(self.edge_indices),
            "edge_curves": len(self.curves),
            "timings": {name: round(seconds, 3) for name, seconds in self.timings.items()},
            **self.stats,
        }


def reconstruct(
    points: np.ndarray,
    params: FitParams,
    progress: ProgressCallback | None = None,
    should_cancel: CancelCheck | None = None,
) -> Reconstruction:
    """Fit ``points`` (N, 3, input coordinates) and extract the mesh, normals and edge points."""
    started = time.perf_counter()
    model = fit_cloud(points, params, progress, should_cancel)
    fitted = time.perf_counter()
    result = extract_outputs(model, points, params, progress, should_cancel)
    result.timings = {"fit_seconds": fitted - started, **result.timings}
    return result


def fit_cloud(
    points: np.ndarray,
    params: FitParams,
    progress: ProgressCallback | None = None,
    should_cancel: CancelCheck | None = None,
) -> ImplicitNetwork:
    """``core.fit.fit`` of ``points`` (N, 3, input coordinates), less their strays, in their unit
    frame (``fitted_rows``), the frame in which ``extract_outputs`` reads the network."""
    fitted = points[fitted_rows(points, params)]
    return fit(Frame.of(fitted).to_unit(fitted), params, progress=progress, should_cancel=should_cancel)


def fitted_rows(points: np.ndarray, params: FitParams) -> np.ndarray:
    """The rows of ``points`` (N, 3) a fit is given: those ``core.fit.fit_rows`` takes, less the strays
    among them (``core.strays``). Their bounding box is the unit frame, so that a stray neither
    shrinks the shape in it nor widens the grid the mesh is extracted on."""
    rows = fit_rows(len(points), params.seed)
    return rows[~strays(points[rows], torch.get_num_threads())]


def extract_outputs(
    model: ImplicitNetwork,
    points: np.ndarray,
    params: FitParams,
    progress: ProgressCallback | None = None,
    should_cancel: CancelCheck | None = None,
) -> Reconstruction:
    """The mesh, normals and edge points of ``model``, a network fitted to ``points`` (N, 3, input
    coordinates) in their unit frame (``fit_cloud``); apart from ``reconstruct`` so that a saved fit
    can be extracted again by changed extraction code (``bench/run.py --fits``)."""
    started = time.perf_counter()
    rows = fitted_rows(points, params)
    frame = Frame.of(points[rows])
    unit = frame.to_unit(points)
    if progress is not None:
        progress(Progress(stage=Stage.EXTRACTING, iteration=params.iterations, total=params.iterations))
    low, high = unit[rows].min(axis=0), unit[rows].max(axis=0)
    mesh, stats = extract_mesh(model, params.resolution, low, high, should_cancel, method=params.extraction)
    # Whether the fit read Fourier features (encoding "auto" decides in the fit), and how many.
    stats["fourier_features"] = model.features
    # The points left out of the fit as strays, of those it draws (every point of a cloud up to
    # FIT_POINTS): a user sees that some were, and how many.
    stats["stray_points"] = min(len(points), FIT_POINTS) - len(rows)
    curves: list[Curve] = []
    if params.extraction == "sharp":
        normals = unit_normals(model, unit, should_cancel=should_cancel)
        curves = edge_curves(mesh, params.edge_angle, CURVE_MIN_LENGTH, CURVE_SPACING)
        curves = without_isolated(curves, CURVE_JOIN_GAP, CURVE_GROUP_LENGTH, CURVE_KEEP_DIHEDRAL)
        mesh, curves = onto_refitted(mesh, curves, params.edge_angle, unit[rows], normals[rows])
        mesh, corners = snap_corners(mesh, curves, CURVE_JOIN_GAP, unit[rows], normals[rows])
        curves = extend_to_corners(curves, corners, CURVE_JOIN_GAP, CURVE_SPACING)
        normals = normals_on_faces(unit, normals, curves, torch.get_num_threads())
        near = distance_to_curves(unit, curves, CURVE_SPACING, params.edge_width, torch.get_num_threads())
        edges = np.flatnonzero(near <= params.edge_width)
        # Δf is reported at the edge points only, so only they pay for it.
        _, edge_laplacian = normals_and_laplacian(model, unit[edges], should_cancel=should_cancel)
    else:
        normals, laplacian = normals_and_laplacian(model, unit, should_cancel=should_cancel)
        edges = np.flatnonzero(np.abs(laplacian) > params.tau)
        edge_laplacian = laplacian[edges]
    mesh.vertices = frame.from_unit(mesh.vertices)
    for curve in curves:
        curve.points = frame.from_unit(curve.points)

    return Reconstruction(
        mesh=mesh,
        normals=normals,
        edge_indices=edges,
        edge_points=points[edges],
        edge_laplacian=np.abs(edge_laplacian),
        tau=params.tau,
        points=points,
        curves=curves,
        timings={"extract_seconds": time.perf_counter() - started},
        stats=stats,
    )


def _short(points: np.ndarray) -> np.ndarray:
    """``points`` rounded to 7 significant digits of their largest coordinate (float32's precision,
    which is what a viewer draws with), so that their JSON is short."""
    largest = float(np.abs(points).max(initial=0.0))
    decimals = 7 - math.ceil(math.log10(largest)) if largest > 0 else 0
    return np.round(points, max(decimals, 0))


def write_outputs(reconstruction: Reconstruction, directory: str | Path, names: Iterable[str] = FIT_OUTPUTS) -> Path:
    """Write the outputs ``names`` (default ``mesh.obj``, ``normals.json`` and ``edges.json``) into
    ``directory``, all or none (``core.outputs.write_atomically``); return the folder."""
    return write_atomically(reconstruction.outputs(names), directory)
