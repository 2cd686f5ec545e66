"""Jobs through real worker processes: end to end, cancel, crash (SIGKILL), two workers, expiry, time limit.

Each fit here is tiny (a small network, a coarse grid) so the module stays within about two
minutes on two shared cores; only ``test_two_workers_drain_four_jobs`` runs two fits at once.
"""

from __future__ import annotations

import io
import os
import signal
import time
from datetime import datetime

import httpx
import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from core.ply import read_points
from tests.helpers import ENDLESS, SHARED_DATA, TINY, Service, ply_binary, sphere, wait_for
from worker.settings import Settings
from worker.store import JobStore

OUTPUTS = ("mesh.obj", "normals.json", "edges.json", "preview.json")
# Enough fitting for a recognisable surface in a few seconds.
E2E = {"iterations": 150, "resolution": 48, "width": 64, "depth": 2, "batch_points": 512}
# A coarse fit followed by a long extraction (a fine grid of a wider network).
SLOW_EXTRACTION = {"iterations": 2, "resolution": 512, "width": 128, "depth": 2, "batch_points": 128}


@pytest.fixture(scope="module")
def svc(redis_server, tmp_path_factory):
    """The API and one worker."""
    service = Service(redis_server.url, tmp_path_factory.mktemp("jobs"))
    service.start_api()
    service.start_worker()
    service.wait_workers(1)
    yield service
    service.stop()


def _run_to_success(service: Service, cloud: bytes, params: dict, timeout: float = 180) -> tuple[dict, list[dict]]:
    """Submit, poll until succeeded; return the final job and every status seen on the way."""
    job_id = service.submit(cloud, **params)["id"]
    seen = []

    def finished():
        seen.append(service.job(job_id))
        assert seen[-1]["status"] in ("queued", "running", "succeeded"), seen[-1]
        return seen[-1]["status"] == "succeeded"

    wait_for(finished, timeout, 0.1, f"job {job_id} to succeed (logs: {service.directory})")
    return seen[-1], seen


def _download_and_check(service: Service, job: dict, points: np.ndarray) -> trimesh.Trimesh:
    """Download the outputs, check their formats against the input; return the mesh."""
    assert set(job["links"]) == {"self", *OUTPUTS, "mesh.ply", "mesh.stl", "mesh.glb"}
    with service.client() as client:
        mesh_response, normals_response, edges_response = (
            client.get(job["links"][name]) for name in ("mesh.obj", "normals.json", "edges.json")
        )
    for response in (mesh_response, normals_response, edges_response):
        assert response.status_code == 200
    assert mesh_response.headers["content-type"] == "model/obj"
    assert normals_response.headers["content-type"] == "application/json"

    mesh = trimesh.load(io.BytesIO(mesh_response.content), file_type="obj", process=False)
    assert len(mesh.vertices) == job["result"]["vertices"] and len(mesh.faces) == job["result"]["faces"]
    _check_mesh_formats(service, job, mesh)

    normals = np.asarray(normals_response.json()["normals"])
    assert normals.shape == points.shape
    assert np.allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-4)

    edges = edges_response.json()
    assert set(edges) == {"tau", "count", "indices", "points", "laplacian", "curves"}
    assert edges["tau"] == job["params"]["tau"] and edges["count"] == job["result"]["edge_points"]
    assert len(edges["indices"]) == len(edges["points"]) == len(edges["laplacian"]) == edges["count"]
    assert len(edges["curves"]) == job["result"]["edge_curves"]
    for curve in edges["curves"]:
        assert set(curve) == {"points", "dihedral", "convex"} and len(curve["points"]) >= 2
        assert 0 < curve["dihedral"] < 180 and isinstance(curve["convex"], bool)
    if edges["count"]:
        indices = np.asarray(edges["indices"])
        assert 0 <= indices.min() and indices.max() < len(points)
        assert np.allclose(np.asarray(edges["points"]), points[indices])
        if job["params"]["extraction"] == "mc":  # the sharp extraction's edge points are those near its curves
            assert min(edges["laplacian"]) > edges["tau"]
    _check_preview(service, job, points)
    return mesh


MESH_MEDIA_TYPES = {"ply": "application/octet-stream", "stl": "model/stl", "glb": "model/gltf-binary"}


def _check_mesh_formats(service: Service, job: dict, obj: trimesh.Trimesh) -> None:
    """mesh.ply, mesh.stl and mesh.glb: each loads in trimesh with the OBJ's vertex and face counts and bounds."""
    with service.client() as client:
        for fmt, media_type in MESH_MEDIA_TYPES.items():
            response = client.get(job["links"][f"mesh.{fmt}"])
            assert response.status_code == 200 and response.headers["content-type"] == media_type
            assert response.headers["content-disposition"] == f'attachment; filename="mesh.{fmt}"'
            mesh = trimesh.load(io.BytesIO(response.content), file_type=fmt, force="mesh")  # STL: vertices merged
            assert (len(mesh.vertices), len(mesh.faces)) == (len(obj.vertices), len(obj.faces)), fmt
            np.testing.assert_allclose(mesh.bounds, obj.bounds, rtol=1e-6, atol=1e-6 * np.abs(obj.bounds).max())


def _check_preview(service: Service, job: dict, points: np.ndarray) -> dict:
    """preview.json: at most 50,000 of the input points (to float32's 7 digits), their unit normals,
    and whether each is one of edges.json's points."""
    with service.client() as client:
        response = client.get(job["links"]["preview.json"])
        edge_indices = client.get(job["links"]["edges.json"]).json()["indices"]
    assert response.status_code == 200 and response.headers["content-type"] == "application/json"
    preview = response.json()
    assert set(preview) == {"total", "points", "normals", "edge"} and preview["total"] == len(points)
    sample, normals = np.asarray(preview["points"]), np.asarray(preview["normals"])
    assert len(sample) == len(normals) == len(preview["edge"]) == min(len(points), 50_000)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-4)
    distance, index = cKDTree(points).query(sample)
    assert distance.max() < 1e-5 * np.abs(points).max(), "a preview point is not an input point"
    assert len(set(index)) == len(sample)  # no point twice
    assert set(index[np.asarray(preview["edge"]) == 1]) == set(index) & set(edge_indices)
    return preview


def test_end_to_end_on_a_shared_shape(svc):
    folder = SHARED_DATA / "cube"
    if not folder.is_dir():
        pytest.skip("../shared/data is absent (a fresh clone has no shared data)")
    cloud = (folder / "points.ply").read_bytes()
    job, seen = _run_to_success(svc, cloud, E2E)
    fitting = [s["progress"] for s in seen if s["status"] == "running" and s["progress"]["stage"] == "fitting"]
    assert fitting and fitting[-1]["total"] == E2E["iterations"] and "total" in fitting[-1]["losses"]
    assert job["started_at"] and job["ended_at"] and job["error"] is None
    assert job["result"]["timings"]["fit_seconds"] > 0

    mesh = _download_and_check(svc, job, read_points(cloud))
    truth = trimesh.load(folder / "gt.ply")
    ours, theirs = mesh.sample(20_000), truth.sample(20_000)
    chamfer = (cKDTree(theirs).query(ours)[0].mean() + cKDTree(ours).query(theirs)[0].mean()) / 2
    assert chamfer < 0.04, chamfer  # the unit cube; a finished fit scores about 0.005


def test_end_to_end_on_the_example_cloud(svc, example_cloud):
    points = read_points(example_cloud)
    job, _ = _run_to_success(svc, example_cloud, E2E)
    mesh = _download_and_check(svc, job, points)
    low, high = points.min(axis=0), points.max(axis=0)
    margin = 0.1 * (high - low).max()
    assert (mesh.vertices > low - margin).all() and (mesh.vertices < high + margin).all()
    distances = cKDTree(mesh.sample(20_000)).query(points)[0]
    assert distances.mean() < 0.03 * (high - low).max()


def test_preview_samples_at_most_50000_points_of_a_bigger_cloud(svc):
    points = sphere(60_000, seed=3) * 250.0 + 1000.0  # far from the origin: rounding must keep points exact enough
    job, _ = _run_to_success(svc, ply_binary(points), TINY)
    preview = _check_preview(svc, job, points.astype(np.float32).astype(np.float64))
    assert preview["total"] == 60_000 and len(preview["points"]) == 50_000


def test_cancel_of_a_queued_job_means_it_never_runs(svc):
    cloud = ply_binary(sphere(500))
    busy = svc.submit(cloud, **ENDLESS)["id"]
    svc.wait_fitting(busy)
    waiting = svc.submit(cloud, **TINY)["id"]
    with svc.client() as client:
        assert client.delete(f"/v1/jobs/{waiting}").status_code == 204
        assert client.get(f"/v1/jobs/{waiting}").json()["status"] == "canceled"
        assert client.delete(f"/v1/jobs/{busy}").status_code == 204
    after = svc.submit(cloud, **TINY)["id"]  # the worker is free again and takes the next job
    svc.wait_status(after, {"succeeded"})
    record = svc.record(waiting)
    assert record["status"] == "canceled" and "started_at" not in record and "progress" not in record


def test_cancel_of_a_running_job_stops_its_worker_within_5_s(svc):
    cloud = ply_binary(sphere(500))
    busy = svc.submit(cloud, **ENDLESS)["id"]
    svc.wait_fitting(busy)
    following = svc.submit(cloud, **TINY)["id"]  # queued behind it on the only worker
    canceled_at = time.monotonic()
    assert httpx.delete(f"{svc.url}/v1/jobs/{busy}").status_code == 204
    job = svc.job(busy)
    assert job["status"] == "canceled" and job["ended_at"]
    svc.wait_status(following, {"running", "succeeded"}, timeout=5)
    assert time.monotonic() - canceled_at < 5
    stopped_at = svc.job(busy)["progress"]["iteration"]
    svc.wait_status(following, {"succeeded"})
    assert svc.job(busy)["progress"]["iteration"] == stopped_at and svc.job(busy)["status"] == "canceled"
    assert httpx.get(f"{svc.url}/v1/jobs/{busy}/mesh.obj").status_code == 409


def test_cancel_during_the_set_up_of_a_million_points_frees_the_worker_within_2_s(svc):
    cloud = ply_binary(sphere(1_000_000))  # its neighbour queries alone take over 10 s
    busy = svc.submit(cloud, **ENDLESS)["id"]
    wait_for(lambda: (svc.job(busy)["progress"] or {}).get("stage") == "starting", 60, 0.05, "the set-up")
    following = svc.submit(ply_binary(sphere(500)), **TINY)["id"]
    time.sleep(1.0)  # well into the set-up
    assert svc.job(busy)["progress"]["stage"] == "starting"
    canceled_at = time.monotonic()
    assert httpx.delete(f"{svc.url}/v1/jobs/{busy}").status_code == 204
    svc.wait_status(following, {"running", "succeeded"}, timeout=10)
    assert time.monotonic() - canceled_at < 2
    svc.wait_status(following, {"succeeded"})
    assert svc.job(busy)["status"] == "canceled"


def test_cancel_during_extraction_stops_within_5_s(svc):
    cloud = ply_binary(sphere(500))
    busy = svc.submit(cloud, **SLOW_EXTRACTION)["id"]
    wait_for(lambda: (svc.job(busy)["progress"] or {}).get("stage") == "extracting", 60, 0.1, "extraction")
    following = svc.submit(cloud, **TINY)["id"]
    time.sleep(0.5)
    canceled_at = time.monotonic()
    assert httpx.delete(f"{svc.url}/v1/jobs/{busy}").status_code == 204
    svc.wait_status(following, {"running", "succeeded"}, timeout=5)
    assert time.monotonic() - canceled_at < 5
    svc.wait_status(following, {"succeeded"})
    assert svc.job(busy)["status"] == "canceled"


def test_a_job_over_its_time_limit_fails_with_the_reason(svc, tmp_path):
    strict = Service(svc.env["REDIS_URL"], tmp_path, run=svc.prefix, job_timeout=2)  # same queue, 2 s limit
    strict.start_api()
    try:
        job_id = strict.submit(ply_binary(sphere(500)), **ENDLESS)["id"]
        job = strict.wait_status(job_id, {"failed"}, timeout=30)
        assert "time limit of 2 s" in job["error"]
        assert job["ended_at"] and job["result"] is None
    finally:
        strict.stop()


def test_reading_the_status_requeues_a_job_whose_worker_died_then_fails_it_after_its_last_attempt(
    redis_server, tmp_path
):
    service = Service(redis_server.url, tmp_path, sweep_interval=3600)  # no sweep: only the read
    service.start_api()
    try:
        job_id = service.submit(ply_binary(sphere(300)), **TINY)["id"]
        assert service.job(job_id)["attempts"] == 0
        store = JobStore(service.redis, Settings(key_prefix=service.prefix, queue=service.queue))
        for attempt in (1, 2):  # EDGERECON_MAX_ATTEMPTS: 2
            assert store.start(job_id, "a-worker") is not None  # a worker took the job...
            service.redis.delete(f"{service.prefix}:job:{job_id}:alive")  # ...and died: its heartbeat lapsed
            assert service.record(job_id)["status"] == "running"
            job = service.job(job_id)
            assert job["attempts"] == attempt
            assert job["status"] == ("queued" if attempt == 1 else "failed"), job
        assert "stopped unexpectedly" in job["error"] and "after 2 attempts" in job["error"]
    finally:
        service.stop()


def _worker_running(service: Service, job_id: str):
    """The worker process that runs the job (its rq name, in the record, is in its log)."""
    name = service.record(job_id)["worker"]
    logs = [(service.directory / f"worker-{index}.log").read_text() for index in range(len(service.workers))]
    return next(worker for worker, log in zip(service.workers, logs) if f"Worker {name}:" in log)


def test_a_job_whose_worker_is_shut_down_then_killed_runs_again_each_time_and_succeeds(redis_server, tmp_path):
    service = Service(redis_server.url, tmp_path, max_attempts=3)
    service.start_api()
    service.start_worker(), service.start_worker()
    service.wait_workers(2)
    try:
        # Long enough (about 13 s on an idle machine) that each attempt is still fitting when it is
        # stopped: at 300 steps a quiet machine finished the job before the SIGTERM arrived.
        job_id = service.submit(ply_binary(sphere(500)), **{**ENDLESS, "iterations": 2000})["id"]
        service.wait_fitting(job_id)
        first = _worker_running(service, job_id)
        first.send_signal(signal.SIGTERM)  # a rolling restart: the job goes back to the queue at once
        stopped_at = time.monotonic()
        wait_for(lambda: service.job(job_id)["attempts"] == 2, 30, 0.1, "the second attempt")
        assert time.monotonic() - stopped_at < 5
        assert first.wait(15) == 0
        service.wait_fitting(job_id)
        second = _worker_running(service, job_id)
        assert second is not first

        os.kill(second.pid, signal.SIGKILL)  # nobody reads the status: the API's sweep alone requeues it
        killed_at = time.monotonic()
        wait_for(lambda: service.record(job_id)["status"] == "queued", 30, 0.2, "the sweep to requeue the job")
        assert time.monotonic() - killed_at < 3 + 1 + 2  # heartbeat TTL, sweep interval, slack
        service.start_worker()
        job = service.wait_status(job_id, {"succeeded", "failed"}, timeout=120)
        assert job["status"] == "succeeded" and job["attempts"] == 3 and job["error"] is None
        assert httpx.get(f"{service.url}/v1/jobs/{job_id}/mesh.obj").status_code == 200
    finally:
        service.stop()


@pytest.fixture(scope="module")
def pair(redis_server, tmp_path_factory):
    """The API and two workers; jobs expire 60 s after their last change (long enough for a job
    to wait in the queue behind two others on a machine busy with the rest of the suite, where 30 s
    was not, and short enough to watch one expire)."""
    service = Service(redis_server.url, tmp_path_factory.mktemp("pair"), job_ttl=60)
    service.start_api()
    service.start_worker()
    service.start_worker()
    service.wait_workers(2)
    yield service
    service.stop()


def test_two_workers_drain_four_jobs(pair):
    cloud = ply_binary(sphere(500))
    jobs = [pair.submit(cloud, **{**TINY, "iterations": 200, "seed": seed})["id"] for seed in range(4)]
    done: dict[str, str] = {}  # job id -> the worker that ran it

    def all_done():
        for job_id in set(jobs) - set(done):
            status = pair.job(job_id)["status"]
            assert status in ("queued", "running", "succeeded")
            if status == "succeeded":
                done[job_id] = pair.record(job_id)["worker"]
        return len(done) == len(jobs)

    wait_for(all_done, 120, 0.1, "four jobs to succeed")
    assert len(set(done.values())) == 2
    # From the jobs' own start and end times (a sweep of polls is not a snapshot): two at a time.
    events = []
    for job_id in jobs:
        job = pair.job(job_id)
        events += [(datetime.fromisoformat(job["started_at"]), 1), (datetime.fromisoformat(job["ended_at"]), -1)]
    running = [0]
    for _, change in sorted(events):  # at equal times the end (-1) sorts first
        running.append(running[-1] + change)
    assert max(running) == 2


def test_results_expire_together_with_their_artifacts(pair):
    job_id = pair.submit(ply_binary(sphere(500)), **TINY)["id"]
    job = pair.wait_status(job_id, {"succeeded"})
    for name in ("mesh.obj", "normals.json", "edges.json"):
        assert httpx.get(pair.url + job["links"][name]).status_code == 200
    assert not pair.redis.exists(f"{pair.prefix}:job:{job_id}:points")  # the input went when the job ended
    parts = ("", ":mesh.obj", ":normals.json", ":edges.json")
    keys = [f"{pair.prefix}:job:{job_id}{part}" for part in parts]
    ttls = [pair.redis.ttl(key) for key in keys]
    assert all(0 < ttl <= 60 for ttl in ttls) and max(ttls) - min(ttls) <= 1, ttls

    wait_for(lambda: httpx.get(f"{pair.url}/v1/jobs/{job_id}").status_code == 404, 65, 0.2, "the job to expire")
    for name in ("mesh.obj", "normals.json", "edges.json"):
        assert httpx.get(f"{pair.url}/v1/jobs/{job_id}/{name}").status_code == 404
    wait_for(lambda: not pair.redis.keys(f"{pair.prefix}:job:{job_id}*"), 5, 0.2, "every key of the job to expire")
