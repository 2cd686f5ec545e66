"""The HTTP API, v1 (run it with ``uvicorn service.app:app``; OpenAPI at /docs).

    POST   /v1/jobs                   submit: multipart form, ``points`` (PLY) and parameters -> 202 + Location
    GET    /v1/jobs/{id}              status, progress, parameters, timestamps, error, result summary, links
    GET    /v1/jobs/{id}/mesh.obj     the outputs, once the job succeeded (409 before, 404 unknown)
    GET    /v1/jobs/{id}/normals.json
    GET    /v1/jobs/{id}/edges.json
    GET    /v1/jobs/{id}/preview.json
    GET    /v1/jobs/{id}/mesh.ply         the mesh in other formats, converted on request (service.formats)
    GET    /v1/jobs/{id}/mesh.stl
    GET    /v1/jobs/{id}/mesh.glb
    GET    /v1/jobs/{id}/events           Server-Sent Events: the job at every change (service.events)
    DELETE /v1/jobs/{id}              cancel a queued or running job -> 204
    GET    /healthz                   whether Redis answers and how many workers listen (503: Redis down)
    GET    /metrics                   Prometheus text format: jobs, workers, stage durations, HTTP (service.metrics)

Every error is JSON, ``{"detail": ...}``. The API key and the upload limit are checked before a
body is read, in ``service.middleware``. Jobs and their outputs live in Redis (``worker.store``),
workers announce themselves there (``worker.registry``). This process never imports torch:
uploads are checked with ``core.ply`` and ``core.params`` only, and jobs are enqueued by the name
of their function.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import AsyncIterator, Iterator
from contextlib import asynccontextmanager, contextmanager
from datetime import datetime
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, FastAPI, File, Form, HTTPException, Request, Response, Security, UploadFile
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.security import HTTPBearer
from pydantic import BaseModel, Field
from redis.exceptions import RedisError

from core.errors import PointCloudError
from core.params import FitParams
from core.ply import read_points
from service.events import events_router
from service.formats import MESH_FILES
from service.formats import router as formats_router
from service.metrics import install as install_metrics
from service.middleware import HttpMethods, RequestGuard
from service.page import router as page_router
from worker.connection import connect, connect_async
from worker.contract import OUTPUT_NAMES, JobRecord, JobStatus, Progress, is_job_id, new_job_id
from worker.errors import StoreFull
from worker.registry import WorkerRegistry
from worker.settings import Settings, get_settings
from worker.store import JobStore

log = logging.getLogger("edgerecon.api")

MEDIA_TYPES = {
    "mesh.obj": "model/obj",
    "normals.json": "application/json",
    "edges.json": "application/json",
    "preview.json": "application/json",
}
assert set(MEDIA_TYPES) == set(OUTPUT_NAMES)


class JobForm(FitParams):
    """The form of ``POST /v1/jobs``: the cloud, and any parameter of the fit (the rest keep their defaults)."""

    points: UploadFile = File(description="the point cloud: a PLY file (ASCII or binary) whose vertices have x y z")


class JobView(BaseModel):
    """A job as the API shows it: its record (``worker.contract.JobRecord``) and its links."""

    id: str
    status: JobStatus
    progress: Progress | None
    params: FitParams = Field(description="every parameter of the fit, defaults filled in")
    points: int = Field(description="number of points in the uploaded cloud")
    created_at: datetime
    started_at: datetime | None
    ended_at: datetime | None
    expires_at: datetime | None = Field(description="when the job and its outputs will be deleted")
    error: str | None = Field(description="why the job failed")
    result: dict[str, Any] | None = Field(
        description="vertex and face counts, edge point count, timings (succeeded jobs)"
    )
    attempts: int = Field(
        description="how many times a worker started the job (one whose worker died or was shut down runs again)"
    )
    links: dict[str, str] = Field(description="this job, and its outputs once it has succeeded")

    @classmethod
    def of(cls, record: JobRecord) -> JobView:
        base = f"/v1/jobs/{record.id}"
        links = {"self": base}
        if record.status == JobStatus.SUCCEEDED:
            links.update({name: f"{base}/{name}" for name in (*OUTPUT_NAMES, *MESH_FILES)})
        return cls(**record.model_dump(exclude={"worker"}), links=links)


class Health(BaseModel):
    status: Literal["ok", "unavailable"]
    redis: bool
    workers: int | None = Field(description="workers that signalled within the heartbeat period")
    detail: str | None = None


class ErrorBody(BaseModel):
    detail: str


# Documents the bearer scheme in OpenAPI; the check itself is RequestGuard's (before the body is read).
_bearer = HTTPBearer(auto_error=False, description="required when EDGERECON_API_KEY is set")
v1 = APIRouter(prefix="/v1", tags=["jobs"], dependencies=[Security(_bearer)])
health = APIRouter(tags=["health"])


# The dependencies are coroutines so that FastAPI runs them on the event loop, not in its thread
# pool: the status poll, the busiest route, stays off the pool altogether.


async def _job_store(request: Request) -> JobStore:
    return request.app.state.store


async def _registry(request: Request) -> WorkerRegistry:
    return request.app.state.registry


async def _settings(request: Request) -> Settings:
    return request.app.state.settings


async def _checked_id(job_id: str) -> str:
    """``job_id`` if it has the shape of a job id; 404 otherwise, before any Redis key is built."""
    if not is_job_id(job_id):
        raise HTTPException(404, "no such job: job ids are 22 characters of A-Z, a-z, 0-9, '-' and '_'")
    return job_id


Store = Annotated[JobStore, Depends(_job_store)]
Registry = Annotated[WorkerRegistry, Depends(_registry)]
AppSettings = Annotated[Settings, Depends(_settings)]
JobId = Annotated[str, Depends(_checked_id)]


def _not_found(job_id: str) -> HTTPException:
    return HTTPException(404, f"no job {job_id} (never submitted, or expired)")


@contextmanager
def _parsing_slot(request: Request) -> Iterator[None]:
    """One of the ``EDGERECON_MAX_PARSING`` uploads this process parses at once (each costs up to
    a few hundred MB and seconds of CPU); 503 with ``Retry-After`` when all are taken."""
    parsing: threading.BoundedSemaphore = request.app.state.parsing
    if not parsing.acquire(blocking=False):
        detail = "this API process is checking as many uploads as it may at once: try again in a moment"
        raise HTTPException(503, detail, headers={"Retry-After": "2"})
    try:
        yield
    finally:
        parsing.release()


async def _strict_form(request: Request) -> None:
    """422 for what FastAPI would let through silently: an empty value (it would become the
    default) and a field given twice (the last would win), a second ``points`` file included."""
    form = await request.form()  # already parsed for the route: FastAPI caches it on the request
    problems = []
    for name in dict.fromkeys(form.keys()):
        values = form.getlist(name)
        if len(values) > 1:
            problems.append(
                {"type": "repeated", "loc": ["body", name], "msg": f"'{name}' is given {len(values)} times"}
            )
        elif values[0] == "":
            problems.append(
                {"type": "empty", "loc": ["body", name], "msg": f"'{name}' is empty: give a value or leave it out"}
            )
    if problems:
        raise RequestValidationError(problems)


@v1.post(
    "/jobs",
    status_code=202,
    response_model=JobView,
    responses={
        400: {"model": ErrorBody, "description": "not a usable point cloud"},
        408: {"model": ErrorBody, "description": "the upload stalled"},
        413: {"model": ErrorBody},
        503: {"model": ErrorBody, "description": "too many uploads at once, or Redis is unavailable: retry"},
        507: {"model": ErrorBody, "description": "the job store is full: try again later"},
    },
)
def submit_job(
    form: Annotated[JobForm, Form(media_type="multipart/form-data")],
    _strict: Annotated[None, Depends(_strict_form)],
    store: Store,
    settings: AppSettings,
    request: Request,
    response: Response,
) -> JobView:
    """Submit a cloud for reconstruction. The job is queued; poll ``Location`` for its status."""
    with _parsing_slot(request):
        try:
            points = read_points(
                form.points.file.read(), min_points=settings.min_points, max_points=settings.max_points, compact=True
            )
        except PointCloudError as error:
            raise HTTPException(400, f"points: {error}") from None
        params = FitParams(**form.model_dump(exclude={"points"}))
        job_id = new_job_id()
        try:
            store.create(job_id, points, params)
        except StoreFull as error:
            raise HTTPException(507, str(error)) from None
    log.info("job %s queued: %d points, %s", job_id, len(points), params.model_dump())
    response.headers["Location"] = f"/v1/jobs/{job_id}"
    record = store.get(job_id)
    if record is None:  # expired at once: only with an absurdly short EDGERECON_JOB_TTL
        raise _not_found(job_id)
    return JobView.of(record)


@v1.get("/jobs/{job_id}", response_model=JobView, responses={404: {"model": ErrorBody}})
async def get_job(job_id: JobId, store: Store) -> JobView:
    """The job's status, progress, parameters, timestamps, error or result summary, and links."""
    record = await store.get_async(job_id)
    if record is None:
        raise _not_found(job_id)
    return JobView.of(record)


@v1.delete("/jobs/{job_id}", status_code=204, responses={404: {"model": ErrorBody}, 409: {"model": ErrorBody}})
def cancel_job(job_id: JobId, store: Store) -> Response:
    """Cancel a queued job (it never runs) or a running one (its worker stops within seconds)."""
    found = store.cancel(job_id)
    if found is None:
        raise _not_found(job_id)
    if found not in (JobStatus.QUEUED, JobStatus.RUNNING, JobStatus.CANCELED):
        raise HTTPException(409, f"the job has already {found}: only queued or running jobs can be canceled")
    if found != JobStatus.CANCELED:
        log.info("job %s canceled while %s", job_id, found)
    return Response(status_code=204)


def _output(store: JobStore, job_id: str, name: str) -> Response:
    status, content = store.output(job_id, name)
    if status is None:
        raise _not_found(job_id)
    if status != JobStatus.SUCCEEDED:
        raise HTTPException(409, f"the job is {status}: {name} exists once it has succeeded")
    if content is None:
        raise _not_found(job_id)
    disposition = {"Content-Disposition": f'attachment; filename="{name}"'}
    return Response(content, media_type=MEDIA_TYPES[name], headers=disposition)


_OUTPUT_RESPONSES: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorBody},
    409: {"model": ErrorBody, "description": "not succeeded (yet)"},
}


@v1.get("/jobs/{job_id}/mesh.obj", response_class=Response, responses=_OUTPUT_RESPONSES)
def get_mesh(job_id: JobId, store: Store) -> Response:
    """The reconstructed mesh (Wavefront OBJ), in the input's coordinates."""
    return _output(store, job_id, "mesh.obj")


@v1.get("/jobs/{job_id}/normals.json", response_class=Response, responses=_OUTPUT_RESPONSES)
def get_normals(job_id: JobId, store: Store) -> Response:
    """``{"normals": [[nx, ny, nz], ...]}``: one outward unit normal per input point, in input order."""
    return _output(store, job_id, "normals.json")


@v1.get("/jobs/{job_id}/edges.json", response_class=Response, responses=_OUTPUT_RESPONSES)
def get_edges(job_id: JobId, store: Store) -> Response:
    """``{"tau", "count", "indices", "points", "laplacian"}``: the input points on sharp edges."""
    return _output(store, job_id, "edges.json")


@v1.get("/jobs/{job_id}/preview.json", response_class=Response, responses=_OUTPUT_RESPONSES)
def get_preview(job_id: JobId, store: Store) -> Response:
    """``{"total", "points", "normals", "edge"}``: at most 50,000 input points drawn at random, their
    normals and edge flags (0 or 1), for a viewer."""
    return _output(store, job_id, "preview.json")


@health.get("/healthz", response_model=Health, responses={503: {"model": Health, "description": "Redis is down"}})
def healthz(registry: Registry) -> Health | JSONResponse:
    """Liveness and readiness: whether Redis answers and how many workers listen (503 when Redis is down)."""
    try:
        workers = registry.count_live()
    except RedisError as error:
        body = Health(status="unavailable", redis=False, workers=None, detail=f"Redis does not answer: {error}")
        return JSONResponse(body.model_dump(), status_code=503)
    return Health(status="ok", redis=True, workers=workers)


async def _sweep_orphans(store: JobStore, interval: float) -> None:
    """Requeue (or fail), every ``interval`` seconds, the running jobs whose worker stopped signalling."""
    while True:
        await asyncio.sleep(interval)
        try:
            for job_id, status in (await asyncio.to_thread(store.recover_orphans)).items():
                log.warning("job %s %s: its worker stopped signalling", job_id, status)
        except RedisError as error:
            log.debug("orphan sweep skipped: %s", error)


@asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[None]:
    settings: Settings = app.state.settings
    if not settings.redis_url:
        raise RuntimeError("REDIS_URL is not set: point it at the Redis the workers use (or run `edgerecon serve`)")
    timeouts = {"connect_timeout": settings.redis_connect_timeout, "socket_timeout": settings.redis_socket_timeout}
    redis, async_redis = (
        connect(settings.redis_url, fail_fast=True, **timeouts),
        connect_async(settings.redis_url, **timeouts),
    )
    app.state.store = JobStore(redis, settings, async_redis)
    app.state.registry = WorkerRegistry(redis, settings, async_redis)
    sweeper = asyncio.create_task(_sweep_orphans(app.state.store, settings.sweep_interval))
    try:
        yield
    finally:
        sweeper.cancel()
        redis.close()
        await async_redis.aclose()


async def _redis_unavailable(request: Request, error: Exception) -> JSONResponse:  # a RedisError
    return JSONResponse({"detail": f"the job store (Redis) is unavailable, try again: {error}"}, status_code=503)


async def _internal_error(request: Request, error: Exception) -> JSONResponse:
    log.exception("unhandled error on %s %s", request.method, request.url.path)
    return JSONResponse({"detail": "internal server error"}, status_code=500)


def create_app(settings: Settings | None = None) -> FastAPI:
    """The application, configured by ``settings`` (default: from the environment)."""
    settings = settings or get_settings()
    app = FastAPI(
        title="edgerecon",
        version="1",
        summary="Edge-preserving surface reconstruction of noisy point clouds",
        lifespan=_lifespan,
    )
    app.state.settings = settings
    app.state.parsing = threading.BoundedSemaphore(settings.max_parsing)
    app.include_router(v1)
    app.include_router(health)
    app.include_router(formats_router)  # the mesh in other formats: mesh.ply, mesh.stl, mesh.glb
    app.include_router(events_router(JobView.of))  # live progress: GET /v1/jobs/{id}/events
    app.include_router(page_router)  # the web page: GET / and /static, outside the OpenAPI schema
    app.add_exception_handler(RedisError, _redis_unavailable)
    app.add_exception_handler(Exception, _internal_error)
    api_key = settings.api_key.get_secret_value() if settings.api_key else None
    app.add_middleware(
        RequestGuard,
        max_body_bytes=settings.max_upload_bytes,
        api_key=api_key,
        max_uploads=settings.max_uploads,
        body_idle_timeout=settings.body_idle_timeout,
    )
    app.add_middleware(HttpMethods, routes=app.router.routes)
    install_metrics(app)  # GET /metrics, and the outermost middleware, which counts every request
    return app


app = create_app()
