"""What one upload may cost the API, and how many it takes on at once: real uvicorn processes on a
redis-server of the module's own, no worker (every job stays queued).

The cost is measured on the API process itself: its peak RSS (``VmHWM``, reset before each upload
through ``/proc/<pid>/clear_refs``) and its CPU time.
"""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import psutil
import pytest

from tests.helpers import Service, ply_binary, ply_header, sphere, wait_for

MiB = 1 << 20


@pytest.fixture(scope="module")
def api(redis_server, tmp_path_factory):
    """The API with the default upload limit (64 MiB) and one upload parsed at a time."""
    service = Service(redis_server.url, tmp_path_factory.mktemp("limits"), max_parsing=1, max_uploads=4)
    service.start_api()
    yield service
    service.stop()


def _faces(count: int) -> bytes:
    """200 vertices, then ``count`` triangles: the element that is never read."""
    rows = "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in sphere(200)).encode()
    header = ply_header("ascii", 200, f"element face {count}\nproperty list uchar int vertex_indices\n")
    return header + rows + b"3 0 1 2\n" * count


def _ascii_integers(count: int) -> bytes:
    """``count`` vertices of small integers, declared double: the most float64 points an upload holds."""
    rows = np.random.default_rng(0).integers(-99, 100, size=(200_000, 3))
    body = "".join(f"{x} {y} {z}\n" for x, y, z in rows).encode() * (count // len(rows))
    header = ply_header("ascii", count).replace(b"property float", b"property double")
    return header + body


UPLOADS = {
    "ascii, 200 vertices and 7.5 M faces": lambda: _faces(7_500_000),
    "binary, 5 M points": lambda: ply_binary(np.random.default_rng(0).normal(size=(5_000_000, 3))),
    "ascii, 5 M points declared double": lambda: _ascii_integers(5_000_000),
}


def _peak_rss(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmHWM")


@pytest.mark.parametrize("name", UPLOADS)
def test_an_upload_at_the_limit_costs_the_api_under_300_mb_and_10_s_of_cpu(api, name):
    content = UPLOADS[name]()
    assert 48 * MiB < len(content) < 64 * MiB
    process = psutil.Process(api.api.pid)
    Path(f"/proc/{api.api.pid}/clear_refs").write_text("5")  # resets the peak RSS to the current one
    cpu = sum(process.cpu_times()[:2])
    response = httpx.post(api.url + "/v1/jobs", files={"points": ("big.ply", content)}, timeout=60)
    cpu = sum(process.cpu_times()[:2]) - cpu
    assert response.status_code in (202, 400), response.text
    peak = _peak_rss(api.api.pid)
    assert peak < 300 * MiB, f"peak RSS {peak / MiB:.0f} MB"
    # The 5 M ASCII doubles took 2.7 s of CPU on one machine and 5.1 s on another, twice as slow
    # at everything (its fitting steps too): the bound leaves room for that, not for a parser
    # that grows worse than linearly (a 64 MB body is read in 1 MB blocks).
    assert cpu < 10, f"{cpu:.1f} s of CPU"
    if response.status_code == 202:
        assert httpx.delete(api.url + response.headers["location"]).status_code == 204


def test_uploads_beyond_max_parsing_get_503_with_retry_after(api):
    """One large upload is being parsed (EDGERECON_MAX_PARSING=1): small ones meanwhile are refused."""
    big = UPLOADS["ascii, 5 M points declared double"]()
    answers: list[httpx.Response] = []

    def send_big() -> None:
        # Refused itself when it arrives while a small one is checked; a client retries, as told.
        for _ in range(20):
            answers.append(httpx.post(api.url + "/v1/jobs", files={"points": ("b.ply", big)}, timeout=60))
            if answers[-1].status_code != 503:
                return
            time.sleep(0.1)

    sender = threading.Thread(target=send_big)
    sender.start()
    small = {"points": ("s.ply", ply_binary(sphere(300)))}
    refused = []
    while sender.is_alive() and not refused:
        response = httpx.post(api.url + "/v1/jobs", files=small, timeout=10)
        if response.status_code == 503:
            refused.append(response)
        else:
            assert response.status_code == 202, response.text
        time.sleep(0.02)
    sender.join()
    assert answers[-1].status_code == 202, answers[-1].text
    assert refused, "no upload was refused while the large one was parsed"
    assert refused[0].headers["retry-after"].isdigit() and "uploads" in refused[0].json()["detail"]
    assert httpx.post(api.url + "/v1/jobs", files=small, timeout=10).status_code == 202  # the slot is free again


def _stalled_upload(url: str) -> socket.socket:
    """A POST that declares a body, sends its first bytes and then nothing."""
    host, port = url.removeprefix("http://").split(":")
    connection = socket.create_connection((host, int(port)), timeout=30)
    connection.sendall(
        b"POST /v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n"
        b"Content-Length: 100000\r\n\r\n"
        b'--b\r\nContent-Disposition: form-data; name="points"; filename="s.ply"\r\n\r\nply\n'
    )
    return connection


def test_uploads_in_flight_are_bounded_and_a_stalled_one_is_dropped_with_408(redis_server, tmp_path):
    service = Service(redis_server.url, tmp_path, max_uploads=2, body_idle_timeout=1.5)
    service.start_api()
    try:
        stalled = [_stalled_upload(service.url) for _ in range(2)]
        time.sleep(0.3)
        small = {"points": ("s.ply", ply_binary(sphere(300)))}
        beyond = httpx.post(service.url + "/v1/jobs", files=small, timeout=10)
        assert beyond.status_code == 503 and beyond.headers["retry-after"].isdigit(), beyond.text
        assert httpx.get(service.url + "/healthz").status_code == 200  # requests without a body still pass
        started = time.monotonic()
        for connection in stalled:
            with connection:
                answer = b""
                while chunk := connection.recv(65536):  # the server closes the connection after its answer
                    answer += chunk
                assert answer.startswith(b"HTTP/1.1 408 "), answer
                assert b"sent nothing for 1.5 s" in answer
        assert time.monotonic() - started < 5
        wait_for(
            lambda: httpx.post(service.url + "/v1/jobs", files=small, timeout=10).status_code == 202,
            5,
            message="the slots of the dropped uploads to be free",
        )
        assert service.keys()  # the one accepted job; the dropped uploads stored nothing
        assert len([key for key in service.keys() if key.endswith("points")]) == 1
    finally:
        service.stop()
