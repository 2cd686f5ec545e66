"""GET /v1/jobs/{id}/events, the Server-Sent Events stream, against a real API, worker and Redis.

The module's API sends keep-alive comments after half a second of silence and serves at most two
streams at once, so that both limits show within seconds.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator

import httpx
import pytest

from tests.helpers import ENDLESS, TINY, Service, ply_binary, scrape, sphere, wait_for

MAX_STREAMS = 2
STATUS_ORDER = {"queued": 0, "running": 1, "succeeded": 2, "failed": 2, "canceled": 2}
# A fit of a few seconds: enough progress writes (every 0.25 s here) to watch.
WATCHABLE = {**TINY, "iterations": 600}


@pytest.fixture(scope="module")
def svc(redis_server, tmp_path_factory):
    service = Service(
        redis_server.url, tmp_path_factory.mktemp("events"), event_keepalive=0.5, max_event_streams=MAX_STREAMS
    )
    service.start_api()
    service.start_worker()
    service.wait_workers(1)
    yield service
    service.stop()


def messages(response: httpx.Response) -> Iterator[tuple[str, str]]:
    """The stream's messages as (field, value): ("job", the data) for events, ("comment", text) for comments."""
    event, data = "", []
    for line in response.iter_lines():
        if line.startswith(":"):
            yield "comment", line[1:].strip()
        elif line.startswith("event:"):
            event = line.partition(":")[2].strip()
        elif line.startswith("data:"):
            data.append(line.partition(":")[2].removeprefix(" "))
        elif line == "" and data:
            yield event, "\n".join(data)
            event, data = "", []


def events_url(service: Service, job_id: str) -> str:
    return f"{service.url}/v1/jobs/{job_id}/events"


def subscribers(service: Service, job_id: str) -> int:
    """Connections subscribed to the job's changes in Redis: one per live stream."""
    return dict(service.redis.pubsub_numsub(f"{service.prefix}:job:{job_id}:changes"))[
        f"{service.prefix}:job:{job_id}:changes".encode()
    ]


def live_streams(service: Service) -> float:
    """The streams the API serves now, by its own count (a stream leaves it once its task has ended)."""
    return scrape(service.url)[("edgerecon_event_streams", frozenset())]


def test_the_stream_sends_the_job_at_every_change_in_order_and_closes_after_the_final_state(svc):
    job_id = svc.submit(ply_binary(sphere(500)), **WATCHABLE)["id"]
    jobs = []
    started = time.monotonic()
    with httpx.stream("GET", events_url(svc, job_id), timeout=60) as response:
        assert response.status_code == 200
        assert response.headers["content-type"].startswith("text/event-stream")
        assert response.headers["cache-control"] == "no-cache"
        for kind, data in messages(response):
            if kind == "job":
                jobs.append(json.loads(data))
        # The loop ends because the server closed the stream after the final state.
    assert time.monotonic() - started < 60
    statuses = [job["status"] for job in jobs]
    assert statuses[-1] == "succeeded" and statuses.count("succeeded") == 1
    assert [STATUS_ORDER[s] for s in statuses] == sorted(STATUS_ORDER[s] for s in statuses)
    iterations = [job["progress"]["iteration"] for job in jobs if job["progress"]]
    assert iterations == sorted(iterations) and iterations[-1] == WATCHABLE["iterations"]
    fitting = [job for job in jobs if job["status"] == "running" and job["progress"]["stage"] == "fitting"]
    assert len(fitting) >= 3, "the fit's progress was not streamed as it went"
    assert all(a != b for a, b in zip(jobs, jobs[1:])), "an event repeated the one before"
    # Each event is the job as GET /v1/jobs/{id} shows it (expires_at moves with every read).
    final = svc.job(job_id)
    assert {**jobs[-1], "expires_at": None} == {**final, "expires_at": None}
    assert "mesh.glb" in jobs[-1]["links"] and "preview.json" in jobs[-1]["links"]


def test_a_waiting_job_gets_keep_alive_comments_and_its_cancel_ends_the_stream(svc):
    cloud = ply_binary(sphere(500))
    busy = svc.submit(cloud, **ENDLESS)["id"]
    svc.wait_fitting(busy)
    waiting = svc.submit(cloud, **TINY)["id"]  # queued behind the busy one on the only worker
    seen = []
    try:
        with httpx.stream("GET", events_url(svc, waiting), timeout=30) as response:
            for kind, data in messages(response):
                seen.append((kind, json.loads(data)["status"] if kind == "job" else data))
                if len(seen) == 3:  # the queued job, then two keep-alives: cancel it
                    assert httpx.delete(f"{svc.url}/v1/jobs/{waiting}").status_code == 204
    finally:
        httpx.delete(f"{svc.url}/v1/jobs/{busy}")
    assert seen == [("job", "queued"), ("comment", "keep-alive"), ("comment", "keep-alive"), ("job", "canceled")]


def test_a_client_that_goes_away_frees_its_stream_and_the_bound_admits_another(svc):
    busy = svc.submit(ply_binary(sphere(500)), **ENDLESS)["id"]
    svc.wait_fitting(busy)
    try:
        with httpx.Client(timeout=30) as first, httpx.Client(timeout=30) as second:
            streams = [
                client.send(client.build_request("GET", events_url(svc, busy)), stream=True)
                for client in (first, second)
            ]
            readers = [messages(stream) for stream in streams]  # kept: a reader that is dropped closes its stream
            for stream, reader in zip(streams, readers):
                assert stream.status_code == 200 and next(reader)[0] == "job"
            assert subscribers(svc, busy) == MAX_STREAMS and live_streams(svc) == MAX_STREAMS
            refused = httpx.get(events_url(svc, busy), timeout=10)
            assert refused.status_code == 503 and refused.headers["retry-after"] == "10"
            assert "poll" in refused.json()["detail"]
            streams[0].close()  # the client goes away; the job runs on
            first.close()
            wait_for(lambda: (live_streams(svc), subscribers(svc, busy)) == (1, 1), 10, 0.1, "the server to end it")
            with httpx.stream("GET", events_url(svc, busy), timeout=30) as admitted:
                assert admitted.status_code == 200
            streams[1].close()
        wait_for(lambda: (live_streams(svc), subscribers(svc, busy)) == (0, 0), 10, 0.1, "the server to end all")
        assert svc.job(busy)["status"] == "running"
    finally:
        httpx.delete(f"{svc.url}/v1/jobs/{busy}")


def test_unknown_and_malformed_jobs_get_404_before_any_stream(svc):
    for job_id in ("A" * 22, "not-a-job"):
        response = httpx.get(events_url(svc, job_id), timeout=10)
        assert response.status_code == 404 and "no" in response.json()["detail"]
        assert response.headers["content-type"] == "application/json"
