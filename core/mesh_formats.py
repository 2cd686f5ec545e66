"""The mesh in the formats edgerecon offers: Wavefront OBJ, which jobs store, and PLY, STL and glTF
binary, made from it by trimesh's exporters.

One place for all of them, used by ``edgerecon fit --format`` and by the API (on request), both
from the OBJ, so that a fit's files are the same either way. No torch here: the API imports it.
"""

from __future__ import annotations

import io

import trimesh

from core.outputs import MESH_FORMATS


def mesh_file(mesh: trimesh.Trimesh, fmt: str) -> bytes:
    """``mesh`` as a file of format ``fmt`` (one of ``MESH_FORMATS``): binary PLY, binary STL, GLB
    with positions and triangles only (no normals: viewers compute them)."""
    if fmt == "obj":
        return trimesh.exchange.obj.export_obj(mesh, include_normals=False, include_texture=False).encode()
    if fmt == "ply":
        return trimesh.exchange.ply.export_ply(mesh, encoding="binary", vertex_normal=False, include_attributes=False)
    if fmt == "stl":
        return trimesh.exchange.stl.export_stl(mesh)
    if fmt == "glb":
        return trimesh.exchange.gltf.export_glb(trimesh.Scene(mesh), include_normals=False)
    raise ValueError(f"no mesh format {fmt!r}: one of {', '.join(MESH_FORMATS)}")


def read_obj(content: bytes) -> trimesh.Trimesh:
    """An OBJ file as written by ``mesh_file``, with its vertices and faces as they are (not merged
    or reordered), so every format has the stored mesh's counts."""
    mesh = trimesh.load(io.BytesIO(content), file_type="obj", process=False, force="mesh")
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValueError("the OBJ file holds no triangle mesh")
    return mesh


def convert_obj(content: bytes, fmt: str) -> bytes:
    """A stored OBJ file in format ``fmt``."""
    if fmt == "obj":
        return content
    return mesh_file(read_obj(content), fmt)
