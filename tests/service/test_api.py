"""The HTTP contract without workers: status codes, validation, limits, API key, health, no torch.

Real uvicorn processes on a redis-server of the test module's own; no worker runs here, so every
job stays queued (the tests with workers are in test_jobs.py).
"""

from __future__ import annotations

import contextlib
import json
import signal
import socket
import subprocess
import sys
import threading
import time

import httpx
import numpy as np
import pytest

from core.params import FitParams
from tests.helpers import (
    ROOT,
    TEST_ENV,
    TINY,
    Service,
    clean_environ,
    ply_ascii,
    ply_binary,
    ply_header,
    sphere,
    wait_for,
)
from worker.redis_server import RedisServer

LIMIT = 1024 * 1024  # the upload limit of this module's API


@pytest.fixture(scope="module")
def api(redis_server, tmp_path_factory):
    service = Service(redis_server.url, tmp_path_factory.mktemp("api"), max_upload_bytes=LIMIT)
    service.start_api()
    yield service
    service.stop()


@pytest.fixture
def nothing_stored(api):
    """Asserts, after the test, that it stored no job key and queued nothing."""
    before = api.keys(), api.redis.llen(f"rq:queue:{api.queue}")
    yield
    assert (api.keys(), api.redis.llen(f"rq:queue:{api.queue}")) == before


def test_submit_poll_cancel_a_queued_job(api):
    cloud = sphere(500)
    response = httpx.post(api.url + "/v1/jobs", files={"points": ("s.ply", ply_binary(cloud))}, data={"tau": "15"})
    assert response.status_code == 202
    job = response.json()
    assert response.headers["location"] == f"/v1/jobs/{job['id']}"
    assert len(job["id"]) == 22 and job["status"] == "queued" and job["points"] == 500
    assert job["params"]["tau"] == 15 and job["params"]["iterations"] == FitParams().iterations  # defaults filled in
    assert job["links"] == {"self": f"/v1/jobs/{job['id']}"}
    assert job["created_at"] and job["expires_at"] and job["started_at"] is None

    with api.client() as client:
        status = client.get(response.headers["location"])
        assert status.status_code == 200 and status.json()["status"] == "queued"
        for name in ("mesh.obj", "normals.json", "edges.json", "preview.json", "mesh.ply", "mesh.stl", "mesh.glb"):
            early = client.get(f"/v1/jobs/{job['id']}/{name}")
            assert early.status_code == 409 and "queued" in early.json()["detail"]
        assert api.redis.llen(f"rq:queue:{api.queue}") == 1
        assert client.delete(f"/v1/jobs/{job['id']}").status_code == 204
        assert client.get(f"/v1/jobs/{job['id']}").json()["status"] == "canceled"
        assert api.redis.llen(f"rq:queue:{api.queue}") == 0  # taken off the queue: it never runs
        assert client.delete(f"/v1/jobs/{job['id']}").status_code == 204  # canceling twice is fine
        assert client.get(f"/v1/jobs/{job['id']}/mesh.obj").status_code == 409


def test_a_finished_job_cannot_be_canceled(api):
    job = api.submit(ply_binary(sphere(300)))
    api.redis.hset(f"{api.prefix}:job:{job['id']}", "status", "succeeded")  # as a worker would
    response = httpx.delete(f"{api.url}/v1/jobs/{job['id']}")
    assert response.status_code == 409 and "succeeded" in response.json()["detail"]


def test_ascii_and_binary_uploads_are_accepted(api, example_cloud):
    for cloud in (ply_ascii(sphere(200)), example_cloud):
        job = api.submit(cloud, **TINY)
        assert job["status"] == "queued" and job["params"]["width"] == TINY["width"]
    with_faces = ply_header("ascii", 4, "element face 1\nproperty list uchar int vertex_indices\n")
    with_faces += b"0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n"
    response = httpx.post(api.url + "/v1/jobs", files={"points": ("f.ply", with_faces)}, data={"iterations": "5"})
    assert response.status_code == 400 and "at least" in response.json()["detail"]  # faces ignored, 4 points


def test_openapi_documents_the_form(api):
    assert httpx.get(api.url + "/docs").status_code == 200
    spec = httpx.get(api.url + "/openapi.json").json()
    body = spec["paths"]["/v1/jobs"]["post"]["requestBody"]["content"]
    assert "multipart/form-data" in body
    form = spec["components"]["schemas"]["JobForm"]["properties"]
    assert {"points", "iterations", "lambda1", "lambda2", "tau", "edge_sampling", "resolution", "seed"} <= set(form)
    assert {"/v1/jobs/{job_id}", "/v1/jobs/{job_id}/mesh.obj", "/healthz"} <= set(spec["paths"])


def _truncated() -> bytes:
    return ply_binary(sphere(500))[:-700]


def _with_nan() -> bytes:
    cloud = sphere(500)
    cloud[17, 1] = np.nan
    return ply_binary(cloud)


# Each is refused by core.ply, whose own tests check the wording; here: 400, a message, nothing stored.
BAD_FILES = {
    "not PLY": b"solid cube\nfacet normal 0 0 1\n",
    "empty": b"",
    "header only": b"ply\nformat ascii 1.0\nelement vertex 3\n",
    "truncated binary": _truncated(),
    "NaN": _with_nan(),
    "too few points": ply_binary(sphere(20)),
    "huge declared count": ply_binary(sphere(500), count=10**12),
    "huge declared count ascii": ply_header("ascii", 10**12) + b"0 0 0\n",
    "malformed ascii row": ply_header("ascii", 2) + b"0 0 0\n1 one 1\n",
    "non-numeric count": ply_header("ascii", "many") + b"0 0 0\n",
    "collinear": ply_binary(np.outer(np.linspace(0, 1, 200), [1, 2, 3])),
}


@pytest.mark.parametrize("name", BAD_FILES)
def test_bad_files_get_400_and_store_nothing(api, nothing_stored, name):
    files = {"points": ("bad.ply", BAD_FILES[name])}
    response = httpx.post(api.url + "/v1/jobs", files=files, data={"iterations": "10"})
    assert response.status_code == 400, response.text
    detail = response.json()["detail"]
    assert detail.startswith("points: ") and len(detail) > 20, detail


BAD_PARAMS = [
    ("iterations", "0"),
    ("iterations", "1000001"),
    ("iterations", "ten"),
    ("iterations", "3.5"),
    ("resolution", "8"),
    ("resolution", "100000"),
    ("tau", "0"),
    ("tau", "nan"),
    ("lambda1", "-1"),
    ("lambda2", "inf"),
    ("edge_sampling", "maybe"),
    ("seed", "-1"),
    ("width", "1e9"),
    ("iteration", "100"),  # a typo: unknown fields are refused, not ignored
]


@pytest.mark.parametrize("field,value", BAD_PARAMS)
def test_bad_parameters_get_422_naming_the_field(api, nothing_stored, field, value):
    files = {"points": ("s.ply", ply_binary(sphere(300)))}
    response = httpx.post(api.url + "/v1/jobs", files=files, data={field: value})
    assert response.status_code == 422, response.text
    problems = response.json()["detail"]
    assert [problem["loc"] for problem in problems] == [["body", field]]
    assert problems[0]["msg"]


def test_missing_or_non_file_points_get_422(api, nothing_stored):
    for files, data in (({}, {"iterations": "10"}), ({}, {"points": "1 2 3"})):
        response = httpx.post(api.url + "/v1/jobs", files=files or None, data=data)
        assert response.status_code == 422
        assert response.json()["detail"][0]["loc"] == ["body", "points"]


def test_unknown_job_ids_get_404(api):
    unknown = "A" * 22
    with api.client() as client:
        for method, path in [
            ("GET", ""),
            ("DELETE", ""),
            ("GET", "/mesh.obj"),
            ("GET", "/normals.json"),
            ("GET", "/edges.json"),
            ("GET", "/preview.json"),
            ("GET", "/mesh.ply"),
            ("GET", "/mesh.stl"),
            ("GET", "/mesh.glb"),
        ]:
            response = client.request(method, f"/v1/jobs/{unknown}{path}")
            assert response.status_code == 404 and "no job" in response.json()["detail"]


MALFORMED_IDS = [
    "abc",
    "A" * 21,
    "A" * 23,
    "A" * 21 + "!",
    "A" * 20 + "%2F.",
    "..%2F..%2Fetc%2Fpasswd",
    "A" * 21 + "%2A",
    "%E2%9C%93" * 8,
    "x" * 5000,
]


def test_malformed_job_ids_get_404_without_touching_redis(api):
    """No Redis command may carry (part of) a malformed id: watched with MONITOR."""
    seen: list[str] = []
    monitor_ready = threading.Event()
    done = threading.Event()

    def watch():
        with api.redis.monitor() as monitor:
            monitor_ready.set()
            for command in monitor.listen():
                seen.append(command["command"])
                if done.is_set() and "monitor-stop" in command["command"]:
                    return

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    monitor_ready.wait(5)
    time.sleep(0.2)
    answers = []
    try:
        with api.client() as client:
            for job_id in MALFORMED_IDS:
                for method, path in [("GET", ""), ("DELETE", ""), ("GET", "/mesh.obj"), ("GET", "/mesh.glb")]:
                    answers.append((job_id, client.request(method, f"/v1/jobs/{job_id}{path}")))
    finally:
        done.set()
        api.redis.get("monitor-stop")
        thread.join(5)
    for job_id, response in answers:
        assert response.status_code == 404, (job_id, response.text)
        # "no such job"; or the router's "Not Found" when a decoded %2F makes the path another one
        assert response.json()["detail"] in ("Not Found",) or "no such job" in response.json()["detail"]
    assert seen, "MONITOR saw nothing"
    leaked = [command for command in seen if "job:" in command and "monitor-stop" not in command]
    assert leaked == []


def _raw_request(url: str, head: bytes, body_chunks) -> tuple[int, dict, int]:
    """Send a request over a plain socket while reading the answer; return its status, its JSON
    body and how many body bytes were sent before the server stopped reading."""
    host, port = url.removeprefix("http://").split(":")
    sent = 0
    with socket.create_connection((host, int(port)), timeout=20) as connection:

        def send():
            nonlocal sent
            try:
                connection.sendall(head)
                for chunk in body_chunks:
                    connection.sendall(chunk)
                    sent += len(chunk)
            except OSError:
                pass  # the server answered and closed: what a limit should do

        sender = threading.Thread(target=send, daemon=True)
        sender.start()
        answer = b""
        while b"\r\n\r\n" not in answer or len(answer.partition(b"\r\n\r\n")[2]) < _length(answer):
            chunk = connection.recv(65536)
            if not chunk:
                break
            answer += chunk
        with contextlib.suppress(OSError):  # the server may have closed the connection first
            connection.shutdown(socket.SHUT_RDWR)
        sender.join(10)
    head_part, _, body = answer.partition(b"\r\n\r\n")
    return int(head_part.split()[1]), json.loads(body), sent


def _length(answer: bytes) -> int:
    for line in answer.partition(b"\r\n\r\n")[0].split(b"\r\n"):
        if line.lower().startswith(b"content-length:"):
            return int(line.split(b":")[1])
    return 1 << 62


def test_declared_oversized_upload_gets_413_before_the_body(api, nothing_stored):
    head = (
        f"POST /v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n"
        f"Content-Length: {LIMIT + 1}\r\n\r\n"
    ).encode()
    status, body, _ = _raw_request(api.url, head, [])  # the body is never sent
    assert status == 413 and "larger than the limit" in body["detail"]


def test_streamed_oversized_upload_is_cut_off_with_413(api, nothing_stored):
    """Chunked, no Content-Length: the limit is enforced while the body streams in."""
    total = 64 * LIMIT
    head = (
        b"POST /v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n"
        b"Transfer-Encoding: chunked\r\n\r\n"
    )
    start = b'--b\r\nContent-Disposition: form-data; name="points"; filename="big.ply"\r\n\r\n'

    def chunks():
        yield b"%x\r\n%s\r\n" % (len(start), start)
        piece = b"0" * 65536
        for _ in range(total // len(piece)):
            yield b"%x\r\n%s\r\n" % (len(piece), piece)

    status, body, sent = _raw_request(api.url, head, chunks())
    assert status == 413 and "larger than the limit" in body["detail"]
    assert sent < total / 4  # cut off early: the server did not read the whole body


def test_upload_just_under_the_limit_is_accepted(api):
    content = ply_binary(sphere(87_000))  # 1,044,120 bytes, a little under the 1 MiB limit with the form
    assert len(content) < LIMIT
    response = httpx.post(api.url + "/v1/jobs", files={"points": ("p.ply", content)})
    assert response.status_code == 202, response.text
    assert httpx.delete(api.url + response.headers["location"]).status_code == 204


def test_api_key_guards_every_v1_route(redis_server, tmp_path):
    service = Service(redis_server.url, tmp_path, api_key="s3cret")
    service.start_api()
    try:
        cloud = {"points": ("s.ply", ply_binary(sphere(300)))}
        routes = [
            ("POST", "/v1/jobs"),
            ("GET", "/v1/jobs/" + "A" * 22),
            ("DELETE", "/v1/jobs/" + "A" * 22),
            ("GET", "/v1/jobs/" + "A" * 22 + "/mesh.obj"),
            ("GET", "/v1/jobs/" + "A" * 22 + "/mesh.glb"),
            ("GET", "/v1/jobs/" + "A" * 22 + "/events"),
            ("GET", "/v1/nothing"),
        ]
        with service.client() as client:
            for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": "Basic s3cret"}):
                for method, path in routes:
                    response = client.request(method, path, headers=headers, files=cloud if method == "POST" else None)
                    assert response.status_code == 401, (method, path, headers)
                    assert response.headers["www-authenticate"] == "Bearer"
                    assert "API key" in response.json()["detail"]
            good = {"Authorization": "Bearer s3cret"}
            assert client.post("/v1/jobs", headers=good, files=cloud).status_code == 202
            assert client.get("/v1/jobs/" + "A" * 22, headers=good).status_code == 404
            assert client.get("/v1/jobs/" + "A" * 22 + "/events", headers=good).status_code == 404
            assert client.get("/healthz").status_code == 200  # health, metrics and docs stay open
            assert client.get("/metrics").status_code == 200
            assert client.get("/docs").status_code == 200
        # Without the key, even a huge declared upload is refused as unauthorized, unread.
        head = f"POST /v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Length: {10**10}\r\n\r\n".encode()
        assert _raw_request(service.url, head, [])[0] == 401
    finally:
        service.stop()


def test_health_answers_503_while_redis_is_down_and_recovers(tmp_path):
    redis = RedisServer(tmp_path).start()
    service = Service(redis.url, tmp_path)
    try:
        service.start_api()
        with service.client() as client:
            assert client.get("/healthz").json() == {"status": "ok", "redis": True, "workers": 0, "detail": None}
            job = service.submit(ply_binary(sphere(300)))
            redis.stop()
            started = time.monotonic()
            down = client.get("/healthz")
            assert down.status_code == 503 and time.monotonic() - started < 5
            assert down.json()["redis"] is False and "Redis" in down.json()["detail"]
            cloud = {"points": ("s.ply", ply_binary(sphere(300)))}
            for response in (client.get(f"/v1/jobs/{job['id']}"), client.post("/v1/jobs", files=cloud)):
                assert response.status_code == 503 and "unavailable" in response.json()["detail"]
            redis.start()  # same port, empty (no persistence)
            wait_for(lambda: client.get("/healthz").status_code == 200, 10, 0.2, "the API to see Redis again")
            assert client.get(f"/v1/jobs/{job['id']}").status_code == 404
            assert service.submit(ply_binary(sphere(300)))["status"] == "queued"
    finally:
        service.stop()
        redis.stop()


def test_api_process_never_imports_torch(api, example_cloud):
    """The uvicorn process serves uploads without torch; and in-process, sys.modules stays clean."""
    api.submit(example_cloud, **TINY)
    api.submit(ply_ascii(sphere(200)))
    httpx.post(api.url + "/v1/jobs", files={"points": ("bad.ply", _with_nan())})
    maps = open(f"/proc/{api.api.pid}/maps").read()
    assert "libtorch" not in maps

    script = f"""
import sys
from fastapi.testclient import TestClient
from service.app import app
with TestClient(app) as client:
    for content in ({ply_binary(sphere(300))!r}, {ply_ascii(sphere(200))!r}):
        response = client.post("/v1/jobs", files={{"points": ("s.ply", content)}})
        assert response.status_code == 202, response.text
        assert client.get(response.headers["location"]).status_code == 200
    assert client.get("/healthz").status_code == 200
print("torch" in sys.modules)
"""
    env = {
        **clean_environ(),
        **TEST_ENV,
        "REDIS_URL": api.env["REDIS_URL"],
        "EDGERECON_KEY_PREFIX": api.prefix,
        "EDGERECON_QUEUE": api.queue,
    }
    result = subprocess.run(
        [sys.executable, "-W", "ignore", "-c", script], env=env, cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "False"


def test_every_route_answers_503_within_a_second_while_redis_hangs_and_post_stores_nothing(tmp_path):
    """Redis stopped with SIGSTOP (a hung server: connections open, nothing answers), then resumed."""
    redis = RedisServer(tmp_path).start()
    service = Service(redis.url, tmp_path)
    try:
        service.start_api()
        job = service.submit(ply_binary(sphere(300)))["id"]
        keys = service.keys()
        assert redis.process is not None
        redis.process.send_signal(signal.SIGSTOP)
        cloud = {"points": ("s.ply", ply_binary(sphere(300)))}
        with service.client() as client:
            for method, path in [
                ("GET", "/healthz"),
                ("POST", "/v1/jobs"),
                ("GET", f"/v1/jobs/{job}"),
                ("DELETE", f"/v1/jobs/{job}"),
                ("GET", f"/v1/jobs/{job}/mesh.obj"),
                ("GET", f"/v1/jobs/{job}/mesh.glb"),
                ("GET", f"/v1/jobs/{job}/events"),
                ("GET", f"/v1/jobs/{job}"),  # again, on connections that timed out before
                ("POST", "/v1/jobs"),
            ]:
                started = time.monotonic()
                response = client.request(method, path, files=cloud if method == "POST" else None)
                elapsed = time.monotonic() - started
                assert response.status_code == 503, (method, path, response.text)
                assert elapsed < 1.2, f"{method} {path}: {elapsed:.2f} s"
            redis.process.send_signal(signal.SIGCONT)
            wait_for(lambda: client.get("/healthz").status_code == 200, 10, 0.2, "the API to see Redis again")
            time.sleep(0.5)  # anything a hung request left in Redis's buffers has been applied by now
            assert service.keys() == keys  # the POSTs answered 503 stored nothing
            assert client.get(f"/v1/jobs/{job}").json()["status"] == "queued"
            assert service.submit(ply_binary(sphere(300)))["status"] == "queued"
    finally:
        if redis.process is not None:
            redis.process.send_signal(signal.SIGCONT)
        service.stop()
        redis.stop()


def _post_raw_form(url: str, parts: list[tuple[str, bytes, str | None]]) -> httpx.Response:
    """POST a multipart form with exactly these parts (name, content, filename), repeats included."""
    body = b""
    for name, content, filename in parts:
        disposition = f'form-data; name="{name}"' + (f'; filename="{filename}"' if filename else "")
        body += f"--b\r\nContent-Disposition: {disposition}\r\n\r\n".encode() + content + b"\r\n"
    body += b"--b--\r\n"
    return httpx.post(url + "/v1/jobs", content=body, headers={"Content-Type": "multipart/form-data; boundary=b"})


STRICT_FORMS = {
    "empty value": ([("iterations", b"", None)], "iterations"),
    "repeated field": ([("tau", b"10", None), ("tau", b"20", None)], "tau"),
    "second points file": ([("points", ply_binary(sphere(300)), "t.ply")], "points"),
}


@pytest.mark.parametrize("name", STRICT_FORMS)
def test_empty_and_repeated_fields_get_422_naming_the_field(api, nothing_stored, name):
    parts, field = STRICT_FORMS[name]
    response = _post_raw_form(api.url, [("points", ply_binary(sphere(300)), "s.ply"), *parts])
    assert response.status_code == 422, response.text
    problems = response.json()["detail"]
    assert [problem["loc"] for problem in problems] == [["body", field]] and field in problems[0]["msg"]


def test_list_typed_coordinates_get_400_with_one_line(api, nothing_stored):
    for fmt in ("ascii", "binary_little_endian"):
        header = f"ply\nformat {fmt} 1.0\nelement vertex 200\nproperty list uchar float x\nproperty float y\n"
        content = (header + "property float z\nend_header\n").encode() + b"1 0.5 0.25 0.125\n" * 200
        response = httpx.post(api.url + "/v1/jobs", files={"points": ("l.ply", content)})
        assert response.status_code == 400, response.text
        assert "list" in response.json()["detail"] and "\n" not in response.json()["detail"]


def test_head_works_wherever_get_does_and_allow_lists_every_method(api):
    job = api.submit(ply_binary(sphere(300)))["id"]
    with api.client() as client:
        for path in ("/healthz", f"/v1/jobs/{job}", "/openapi.json", "/metrics", "/"):
            get, head = client.get(path), client.head(path)
            assert head.status_code == get.status_code == 200, path
            assert head.content == b"" and head.headers["content-type"] == get.headers["content-type"]
        assert client.head(f"/v1/jobs/{job}/mesh.obj").status_code == 409  # as GET answers
        assert client.head("/v1/jobs/" + "A" * 22).status_code == 404
        assert client.head("/static/page.css").status_code == 200
        events = client.head(f"/v1/jobs/{job}/events")  # a stream: the headers, and no wait for the job
        assert events.status_code == 200 and events.headers["content-type"].startswith("text/event-stream")
        assert client.get("/healthz").status_code == 200  # the connection survives the cut stream
        for method, path, allowed in [
            ("PUT", f"/v1/jobs/{job}", "DELETE, GET, HEAD"),
            ("POST", "/healthz", "GET, HEAD"),
            ("GET", "/v1/jobs", "POST"),
            ("HEAD", "/v1/jobs", "POST"),
        ]:
            response = client.request(method, path)
            assert response.status_code == 405 and response.headers["allow"] == allowed, (method, path)
