"""GET /metrics against a real API, worker and Redis: the numbers move as jobs run, every API
process reports the jobs' numbers from Redis, requests are counted by route template, and a scrape
stays prompt while Redis is down or hung.
"""

from __future__ import annotations

import signal
import time

import httpx
import pytest

from tests.helpers import ENDLESS, TINY, Service, ply_binary, scrape, sphere, wait_for
from worker.redis_server import RedisServer


@pytest.fixture(scope="module")
def svc(redis_server, tmp_path_factory):
    service = Service(redis_server.url, tmp_path_factory.mktemp("metrics"))
    service.start_api()
    service.start_worker()
    service.wait_workers(1)
    yield service
    service.stop()


def value(metrics: dict, name: str, **labels) -> float:
    return metrics.get((name, frozenset(labels.items())), 0.0)


def test_job_counters_gauges_and_stage_durations_follow_the_jobs(svc):
    before = scrape(svc.url)
    assert value(before, "edgerecon_redis_up") == 1 and value(before, "edgerecon_workers") == 1
    assert value(before, "edgerecon_jobs_submitted_total") == 0 and value(before, "edgerecon_jobs_running") == 0

    cloud = ply_binary(sphere(500))
    busy = svc.submit(cloud, **ENDLESS)["id"]
    svc.wait_fitting(busy)
    waiting = svc.submit(cloud, **TINY)["id"]  # behind the busy one on the only worker
    during = scrape(svc.url)
    assert value(during, "edgerecon_jobs_submitted_total") == 2 and value(during, "edgerecon_jobs_started_total") == 1
    assert value(during, "edgerecon_jobs_requeued_total") == 0
    assert value(during, "edgerecon_jobs_running") == 1 and value(during, "edgerecon_jobs_queued") == 1

    assert httpx.delete(f"{svc.url}/v1/jobs/{busy}").status_code == 204
    svc.wait_status(waiting, {"succeeded"})
    # A second API process on the same Redis reports the same numbers of jobs.
    other = Service(svc.env["REDIS_URL"], svc.directory, run=svc.prefix)
    try:
        other.start_api()
        after, elsewhere = scrape(svc.url), scrape(other.url)
    finally:
        other.stop()
    for metrics in (after, elsewhere):
        assert value(metrics, "edgerecon_jobs_submitted_total") == 2
        assert value(metrics, "edgerecon_jobs_finished_total", outcome="succeeded") == 1
        assert value(metrics, "edgerecon_jobs_finished_total", outcome="canceled") == 1
        assert value(metrics, "edgerecon_jobs_finished_total", outcome="failed") == 0
        assert value(metrics, "edgerecon_jobs_running") == 0 and value(metrics, "edgerecon_jobs_queued") == 0
        # Both jobs waited in the queue; only the one that succeeded has fitting and extraction times.
        assert value(metrics, "edgerecon_job_stage_seconds_count", stage="queued") == 2
        for stage in ("fitting", "extracting"):
            assert value(metrics, "edgerecon_job_stage_seconds_count", stage=stage) == 1
            assert value(metrics, "edgerecon_job_stage_seconds_bucket", stage=stage, le="+Inf") == 1
            assert value(metrics, "edgerecon_job_stage_seconds_sum", stage=stage) > 0
    assert value(after, "edgerecon_job_stage_seconds_bucket", stage="queued", le="0.5") >= 1  # the busy one: at once


def test_http_requests_are_counted_by_route_template_and_status_with_latency_and_upload_sizes(svc):
    before = scrape(svc.url)
    cloud = ply_binary(sphere(400))
    job_id = svc.submit(cloud)["id"]
    for _ in range(3):
        svc.job(job_id)
    assert httpx.get(f"{svc.url}/v1/jobs/{'A' * 22}").status_code == 404
    assert httpx.get(f"{svc.url}/no/such/page").status_code == 404
    httpx.delete(f"{svc.url}/v1/jobs/{job_id}")
    after = scrape(svc.url)

    def grew(name: str, **labels) -> float:
        return value(after, name, **labels) - value(before, name, **labels)

    job_route = "/v1/jobs/{job_id}"
    assert grew("edgerecon_http_requests_total", method="GET", route=job_route, status="200") == 3
    assert grew("edgerecon_http_requests_total", method="GET", route=job_route, status="404") == 1
    assert grew("edgerecon_http_requests_total", method="POST", route="/v1/jobs", status="202") == 1
    assert grew("edgerecon_http_requests_total", method="DELETE", route=job_route, status="204") == 1
    assert grew("edgerecon_http_requests_total", method="GET", route="unmatched", status="404") == 1
    assert not [labels for name, labels in after if ("route", f"/v1/jobs/{job_id}") in labels], "a raw path as a label"
    assert grew("edgerecon_http_request_duration_seconds_count", method="GET", route=job_route) == 4
    assert grew("edgerecon_http_request_duration_seconds_bucket", method="GET", route=job_route, le="1.0") == 4
    assert grew("edgerecon_upload_bytes_count") == 1
    assert len(cloud) < grew("edgerecon_upload_bytes_sum") < len(cloud) + 1000  # the file and its form's framing
    assert value(after, "edgerecon_event_streams") == 0
    assert value(after, "process_resident_memory_bytes") > 0


def test_the_api_key_guards_metrics_only_when_told_and_refusals_are_counted_by_route(redis_server, tmp_path):
    service = Service(redis_server.url, tmp_path, api_key="s3cret", metrics_need_api_key=1)
    service.start_api()
    try:
        refused = httpx.get(service.url + "/metrics")
        assert refused.status_code == 401 and refused.headers["www-authenticate"] == "Bearer"
        assert httpx.get(service.url + "/metrics", headers={"Authorization": "Bearer wrong"}).status_code == 401
        assert httpx.get(f"{service.url}/v1/jobs/{'A' * 22}").status_code == 401  # refused before routing...
        metrics = scrape(service.url, headers={"Authorization": "Bearer s3cret"})
        # ...and still counted under its route's template
        assert value(metrics, "edgerecon_http_requests_total", method="GET", route="/v1/jobs/{job_id}", status="401")
        assert value(metrics, "edgerecon_http_requests_total", method="GET", route="/metrics", status="401") == 2
    finally:
        service.stop()


def test_a_scrape_while_redis_is_down_or_hung_answers_within_a_second(tmp_path):
    redis = RedisServer(tmp_path).start()
    service = Service(redis.url, tmp_path)
    try:
        service.start_api()
        assert value(scrape(service.url), "edgerecon_redis_up") == 1
        redis.process.send_signal(signal.SIGSTOP)  # hung: connections open, nothing answers
        try:
            started = time.monotonic()
            hung = scrape(service.url)
            hung_seconds = time.monotonic() - started
        finally:
            redis.process.send_signal(signal.SIGCONT)
        redis.stop()  # down: connections refused
        started = time.monotonic()
        down = scrape(service.url)
        down_seconds = time.monotonic() - started
        for metrics, seconds in ((hung, hung_seconds), (down, down_seconds)):
            assert seconds < 1.0
            assert value(metrics, "edgerecon_redis_up") == 0
            assert ("edgerecon_jobs_submitted_total", frozenset()) not in metrics  # absent, not a made-up 0
            assert value(metrics, "edgerecon_http_requests_total", method="GET", route="/metrics", status="200") >= 1
        redis.start()
        wait_for(lambda: value(scrape(service.url), "edgerecon_redis_up") == 1, 10, 0.2, "Redis to be seen again")
    finally:
        service.stop()
        redis.stop()
