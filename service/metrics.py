"""``GET /metrics``: the service in the Prometheus text format (prometheus-client).

Two kinds of numbers:

- The jobs, read from Redis at every scrape, so that every API process reports the same truth:
  jobs submitted, started and finished by outcome (counters the store keeps at each transition),
  jobs queued and running and live workers (gauges), and how long jobs spent in each stage
  (histograms the workers record). If Redis does not answer within half a second these are left
  out and ``edgerecon_redis_up`` is 0, so a scrape is prompt even while Redis hangs.
- This process: HTTP requests by method, route template (``/v1/jobs/{job_id}``, never the raw
  path) and status, their latency to the response's first byte (so an event stream counts its
  start, not its length), the sizes of accepted uploads, and the live event streams; plus the
  process's own CPU and memory.

``EDGERECON_METRICS_NEED_API_KEY`` makes the route ask for the API key (default: open, like
/healthz, so a scraper needs no secret).
"""

from __future__ import annotations

import asyncio
import functools
import re
import secrets
import time
from collections.abc import Iterable

from fastapi import APIRouter, FastAPI, HTTPException, Request, Response
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.process_collector import ProcessCollector
from prometheus_client.utils import floatToGoString
from redis.exceptions import RedisError
from starlette.routing import compile_path
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.events import LiveStreams
from worker.registry import WorkerRegistry
from worker.settings import Settings
from worker.store import JobStore, StoreStats

# How long a scrape waits for Redis before it reports edgerecon_redis_up 0.
REDIS_TIMEOUT = 0.5
UPLOAD_BUCKETS = (2**10, 2**14, 2**17, 2**20, 2**22, 2**24, 2**26, 2**28)  # 1 KiB to 256 MiB

router = APIRouter(tags=["metrics"])


def install(app: FastAPI) -> None:
    """Serve /metrics and count every request of ``app``: call it after the app's other middleware,
    so that requests those refuse (401, 413) are counted too."""
    registry = CollectorRegistry()
    ProcessCollector(registry=registry)
    streams = Gauge("edgerecon_event_streams", "event streams this API process serves now", registry=registry)
    streams.set_function(lambda: LiveStreams.count)
    app.state.metrics = registry
    app.include_router(router)
    app.add_middleware(HttpMetrics, registry=registry)


@router.get(
    "/metrics",
    response_class=Response,
    responses={200: {"content": {CONTENT_TYPE_LATEST: {}}, "description": "Prometheus text format"}},
)
async def metrics(request: Request) -> Response:
    """The service's metrics in the Prometheus text format."""
    settings: Settings = request.app.state.settings
    if settings.metrics_need_api_key and settings.api_key:
        scheme, _, token = request.headers.get("authorization", "").partition(" ")
        expected = settings.api_key.get_secret_value().encode()
        if scheme.lower() != "bearer" or not secrets.compare_digest(token.strip().encode(), expected):
            detail = "missing or wrong API key: send the header 'Authorization: Bearer <key>'"
            raise HTTPException(401, detail, headers={"WWW-Authenticate": "Bearer"})
    jobs = _Families(await _job_metrics(request.app.state.store, request.app.state.registry))
    body = generate_latest(request.app.state.metrics) + generate_latest(jobs)
    return Response(body, media_type=CONTENT_TYPE_LATEST)


class _Families:
    """Metric families computed for one scrape, in the shape generate_latest reads."""

    def __init__(self, families: list[Metric]):
        self.families = families

    def collect(self) -> Iterable[Metric]:
        return self.families


async def _job_metrics(store: JobStore, registry: WorkerRegistry) -> list[Metric]:
    """The jobs' metrics from Redis; only ``edgerecon_redis_up 0`` when Redis does not answer in time."""
    up = GaugeMetricFamily("edgerecon_redis_up", "whether Redis answered this scrape (0: the job metrics are absent)")
    try:
        async with asyncio.timeout(REDIS_TIMEOUT):
            stats = await store.stats_async()
            workers = await registry.count_live_async()
    except (RedisError, TimeoutError):
        up.add_metric([], 0)
        return [up]
    up.add_metric([], 1)
    return [up, *_job_families(stats, workers)]


def _job_families(stats: StoreStats, workers: int) -> list[Metric]:
    entered = stats.entered
    finished = CounterMetricFamily("edgerecon_jobs_finished", "jobs that ended, by outcome", labels=["outcome"])
    for outcome in ("succeeded", "failed", "canceled"):
        finished.add_metric([outcome], entered.get(outcome, 0))
    durations = HistogramMetricFamily(
        "edgerecon_job_stage_seconds",
        "seconds jobs spent in each stage: queued (waiting for a worker), fitting, extracting (succeeded jobs)",
        labels=["stage"],
    )
    for stage, histogram in stats.durations.items():
        buckets = [(floatToGoString(bound), count) for bound, count in histogram.buckets.items()]
        durations.add_metric([stage], buckets, sum_value=histogram.sum)
    return [
        CounterMetricFamily("edgerecon_jobs_submitted", "jobs submitted", value=entered.get("queued", 0)),
        CounterMetricFamily(
            "edgerecon_jobs_started",
            "starts of jobs by workers (a job run again counts again)",
            value=entered.get("running", 0),
        ),
        CounterMetricFamily(
            "edgerecon_jobs_requeued",
            "jobs put back in the queue because their worker died or was shut down",
            value=entered.get("requeued", 0),
        ),
        finished,
        GaugeMetricFamily("edgerecon_jobs_queued", "jobs waiting for a worker", value=stats.queued),
        GaugeMetricFamily("edgerecon_jobs_running", "jobs running", value=stats.running),
        GaugeMetricFamily("edgerecon_workers", "workers that signalled within the heartbeat period", value=workers),
        durations,
    ]


class HttpMetrics:
    """ASGI middleware: counts requests by method, route template and status, times them to the
    response's first byte, and measures accepted uploads (``POST /v1/jobs`` answered 202)."""

    def __init__(self, app: ASGIApp, registry: CollectorRegistry):
        self.app = app
        self.requests = Counter(
            "edgerecon_http_requests",
            "HTTP requests answered, by method, route template and status",
            ["method", "route", "status"],
            registry=registry,
        )
        self.latency = Histogram(
            "edgerecon_http_request_duration_seconds",
            "seconds from a request's arrival to its response's first byte, by method and route template",
            ["method", "route"],
            registry=registry,
        )
        self.uploads = Histogram(
            "edgerecon_upload_bytes",
            "sizes of accepted uploads (POST /v1/jobs)",
            buckets=UPLOAD_BUCKETS,
            registry=registry,
        )

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        started = time.perf_counter()
        status, body_bytes = 500, 0  # 500: the app raised before it answered
        answered_after: float | None = None

        async def counting_receive() -> Message:
            nonlocal body_bytes
            message = await receive()
            body_bytes += len(message.get("body", b""))
            return message

        async def timing_send(message: Message) -> None:
            nonlocal status, answered_after
            if message["type"] == "http.response.start":
                status, answered_after = message["status"], time.perf_counter() - started
            await send(message)

        try:
            await self.app(scope, counting_receive, timing_send)
        finally:
            route, method = _route_template(scope), scope["method"]
            self.requests.labels(method, route, str(status)).inc()
            self.latency.labels(method, route).observe(answered_after or time.perf_counter() - started)
            if method == "POST" and route == "/v1/jobs" and status == 202:
                self.uploads.observe(body_bytes)


def _route_template(scope: Scope) -> str:
    """The path template of the route that answered, or would have: a request refused before routing
    (a 401 or 413 of ``service.middleware``) is matched against the API's documented paths here;
    ``unmatched`` for paths no route has, so that labels stay few."""
    route = scope.get("route")
    if route is not None:
        return getattr(route, "path", None) or "unmatched"
    return next(
        (template for pattern, template in _templates(scope["app"]) if pattern.match(scope["path"])), "unmatched"
    )


@functools.cache
def _templates(app: FastAPI) -> list[tuple[re.Pattern[str], str]]:
    """The app's documented path templates, each with the pattern of the paths it matches."""
    return [(compile_path(template)[0], template) for template in app.openapi()["paths"]]
