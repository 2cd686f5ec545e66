"""The mesh in other formats: ``GET /v1/jobs/{id}/mesh.ply``, ``mesh.stl`` and ``mesh.glb``.

Each is converted on request from the job's stored OBJ by trimesh's exporters
(``core.mesh_formats``), and not cached: for a mesh of a million faces a conversion takes about
2 s of one core, nearly all of it reading the OBJ, while keeping the three files would hold about
40 MB more per such job in Redis for the job's whole life, to speed up downloads that a person
makes once. The answers are those of the other outputs: 404 unknown job, 409 until it succeeded.
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException, Request, Response, Security
from fastapi.security import HTTPBearer

from worker.contract import JobStatus, is_job_id
from worker.store import JobStore

# PLY has no registered media type: a binary file, as such. STL and glTF binary have theirs.
MEDIA_TYPES = {"mesh.ply": "application/octet-stream", "mesh.stl": "model/stl", "mesh.glb": "model/gltf-binary"}
MESH_FILES = tuple(MEDIA_TYPES)  # what this module serves, listed in a succeeded job's links

_bearer = HTTPBearer(auto_error=False, description="required when EDGERECON_API_KEY is set")
router = APIRouter(prefix="/v1", tags=["jobs"], dependencies=[Security(_bearer)])

_RESPONSES: dict[int | str, dict[str, Any]] = {
    404: {"description": "unknown or expired job"},
    409: {"description": "not succeeded (yet)"},
}


def _converted(request: Request, job_id: str, name: str) -> Response:
    """The job's mesh as file ``name``, with the same 404 and 409 as its OBJ."""
    if not is_job_id(job_id):
        raise HTTPException(404, "no such job: job ids are 22 characters of A-Z, a-z, 0-9, '-' and '_'")
    store: JobStore = request.app.state.store
    status, obj = store.output(job_id, "mesh.obj")
    if status is None or (status == JobStatus.SUCCEEDED and obj is None):
        raise HTTPException(404, f"no job {job_id} (never submitted, or expired)")
    if status != JobStatus.SUCCEEDED or obj is None:
        raise HTTPException(409, f"the job is {status}: {name} exists once it has succeeded")
    from core.mesh_formats import convert_obj  # trimesh and scipy: 60 MB that an API never converting need not hold

    content = convert_obj(obj, name.removeprefix("mesh."))
    disposition = {"Content-Disposition": f'attachment; filename="{name}"'}
    return Response(content, media_type=MEDIA_TYPES[name], headers=disposition)


# Plain (not async) routes: FastAPI runs them in its thread pool, so a conversion never holds up the event loop.


@router.get("/jobs/{job_id}/mesh.ply", response_class=Response, responses=_RESPONSES)
def get_mesh_ply(job_id: str, request: Request) -> Response:
    """The mesh as binary PLY (float32 vertices, triangles), in the input's coordinates."""
    return _converted(request, job_id, "mesh.ply")


@router.get("/jobs/{job_id}/mesh.stl", response_class=Response, responses=_RESPONSES)
def get_mesh_stl(job_id: str, request: Request) -> Response:
    """The mesh as binary STL (triangles with their normals), in the input's coordinates."""
    return _converted(request, job_id, "mesh.stl")


@router.get("/jobs/{job_id}/mesh.glb", response_class=Response, responses=_RESPONSES)
def get_mesh_glb(job_id: str, request: Request) -> Response:
    """The mesh as glTF binary (positions and triangles; viewers compute the normals), in the input's coordinates."""
    return _converted(request, job_id, "mesh.glb")
