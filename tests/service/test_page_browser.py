"""The web page in a real browser: headless Chromium (Debian's /usr/bin/chromium, driven by Playwright;
nothing here downloads a browser) against a live ``edgerecon serve``, as a person would use it.

- submit examples/cube.ply with a few changed parameters (an invalid value is refused first, before
  anything is sent), watch it through the event stream, see the progress bar move and the loss curve
  drawn, see the 3D view of the result (its pixels: the mesh, and the edge points that a toggle hides
  and shows), the input points and normals from the job's preview.json, and download outputs, the
  mesh in glTF binary among them;
- cancel a long job and see ``canceled``;
- see the API's own 400 ``detail`` for a file that is no cloud, and the plain 401 message for a
  wrong API key (the service runs with ``EDGERECON_API_KEY`` set; the page itself needs no key).

A last test runs the page against a small stand-in for the API with what this service does not
have yet (edge curves in edges.json), a stream that breaks off (the page falls back to polling)
and a job without preview.json (the input points come from the file picked in the page), so the
page's other paths are proven in the browser too.

Screenshots go to tests/artifacts/. ``EDGERECON_UPDATE_SCREENSHOT=1`` also writes the finished cube
to docs/page.png (the README's picture).
"""

from __future__ import annotations

import asyncio
import io
import json
import os
import secrets
import signal
import subprocess
import sys
import threading
import time
from datetime import UTC, datetime
from pathlib import Path

import httpx
import numpy as np
import pytest
import trimesh
import uvicorn
from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse, Response, StreamingResponse

from service.app import create_app
from service.page import router as page_router
from tests.helpers import (
    EXAMPLE_CLOUD,
    ROOT,
    TEST_ENV,
    clean_environ,
    ply_ascii,
    ply_binary,
    ply_header,
    stop_process,
    wait_for,
)
from worker.redis_server import free_port
from worker.settings import Settings

CHROMIUM = Path("/usr/bin/chromium")
pytestmark = pytest.mark.skipif(
    not CHROMIUM.exists(), reason="no Chromium at /usr/bin/chromium (Debian: apt-get install chromium; .ci/run does)"
)
sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (pip install -e '.[test]')")
Image = pytest.importorskip("PIL.Image")

ARTIFACTS = ROOT / "tests" / "artifacts"
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    # WebGL without a GPU: ANGLE on SwiftShader, in software.
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
]  # fmt: skip
API_KEY = secrets.token_urlsafe(16)
# A cube that fits in about 15 s on one busy core, with its edges found (tau 10 marks them at 300 steps,
# with the marching-cubes extraction: so short a fit is too round for the sharp one's edge curves).
QUICK = {
    "iterations": 300,
    "resolution": 64,
    "width": 128,
    "depth": 3,
    "batch_points": 512,
    "tau": 10,
    "extraction": "mc",
}
LONG = {"iterations": 100000, "resolution": 32, "width": 16, "depth": 1, "batch_points": 128}
EDGE_RGB, CONVEX_RGB = (255, 61, 0), (255, 179, 0)  # the viewer's colours (viewer.js)
VANISH_RGB, EIKONAL_RGB = (31, 119, 180), (44, 160, 44)  # two loss curves' colours (progress.js)


# --- the service and the browser ----------------------------------------------------------------


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    """``edgerecon serve`` as the README starts it (its own Redis, one worker), with an API key."""
    directory = tmp_path_factory.mktemp("serve")
    port = free_port()
    script = Path(sys.executable).with_name("edgerecon")
    command = [str(script)] if script.exists() else [sys.executable, "-m", "service.cli"]
    # Its own data folder: the user's (~/.local/share/edgerecon) keeps the jobs of an earlier run
    # that was stopped, and serve resumes them first (a long one held the one worker past every wait).
    env = {**clean_environ(), **TEST_ENV, "EDGERECON_API_KEY": API_KEY, "EDGERECON_DATA_DIR": str(directory / "data")}
    log = open(directory / "serve.log", "wb")
    process = subprocess.Popen([*command, "serve", "--port", str(port)], env=env, cwd=ROOT, stdout=log, stderr=log)
    url = f"http://127.0.0.1:{port}"

    def ready():
        assert process.poll() is None, (directory / "serve.log").read_text()
        try:
            return httpx.get(url + "/healthz", timeout=2).json().get("workers") == 1
        except httpx.HTTPError:
            return False

    try:
        wait_for(ready, 60, 0.2, "edgerecon serve to be ready")
        yield url
    finally:
        stop_process(process, signal.SIGINT, timeout=30)
        log.close()


@pytest.fixture(scope="module")
def playwright():
    with sync_api.sync_playwright() as driver:
        yield driver


@pytest.fixture
def page(playwright, tmp_path, request):
    """A page in a fresh Chromium profile; uncaught page errors fail the test; a screenshot at the end."""
    context = playwright.chromium.launch_persistent_context(
        str(tmp_path / "profile"), executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS,
        viewport={"width": 1280, "height": 1000}, accept_downloads=True,
    )  # fmt: skip
    page = context.pages[0] if context.pages else context.new_page()
    page.set_default_timeout(30_000)
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    try:
        yield page
        assert errors == [], f"uncaught errors in the page: {errors}"
        assert page.locator("#page-error").is_hidden(), page.inner_text("#page-error")
    finally:
        ARTIFACTS.mkdir(exist_ok=True)
        try:
            page.screenshot(path=str(ARTIFACTS / f"{request.node.name}.png"), full_page=True)
        finally:
            context.close()


# --- helpers --------------------------------------------------------------------------------------


def pixels(locator) -> np.ndarray:
    """The element as the browser shows it: an (h, w, 3) array of RGB."""
    return np.asarray(Image.open(io.BytesIO(locator.screenshot())).convert("RGB")).astype(int)


def count_near(image: np.ndarray, rgb, tolerance: int = 40) -> int:
    return int(np.all(np.abs(image - np.array(rgb)) <= tolerance, axis=-1).sum())


def distinct_colours(image: np.ndarray) -> int:
    return len(np.unique(image.reshape(-1, 3), axis=0))


def frames(page) -> int:
    return int(page.get_attribute("#viewer", "data-frames") or 0)


def set_checkbox(page, selector: str, checked: bool) -> None:
    """Tick or untick a viewer toggle and wait until the view has been drawn again."""
    before = frames(page)
    page.set_checked(selector, checked)
    page.wait_for_function("n => Number(document.getElementById('viewer').dataset.frames) > n", arg=before)


def job_result(url: str, job_id: str) -> dict:
    return httpx.get(f"{url}/v1/jobs/{job_id}", headers={"Authorization": f"Bearer {API_KEY}"}).json()["result"]


def open_page(page, url: str, key: str | None) -> None:
    page.goto(url + "/")
    page.wait_for_selector("#param-iterations", state="attached")  # the form, from /openapi.json
    if key is not None:
        page.fill("#api-key", key)
        page.press("#api-key", "Tab")  # the change event stores it


def fill_params(page, params: dict) -> None:
    if page.get_attribute("#params", "open") is None:
        page.click("#params summary")
    for name, value in params.items():
        selector = f"#param-{name}"
        if page.eval_on_selector(selector, "field => field.tagName") == "SELECT":
            page.select_option(selector, str(value))
        else:
            page.fill(selector, str(value))


def submit(page, cloud: Path, params: dict) -> str:
    page.set_input_files("#file", str(cloud))
    fill_params(page, params)
    page.click("#submit")
    page.wait_for_selector("#job-panel:not([hidden])")
    return page.locator("#job-list li.current").get_attribute("data-job")


def wait_status(page, status: str, timeout: float) -> None:
    page.wait_for_function(
        "s => document.getElementById('job-status').textContent === s", arg=status, timeout=timeout * 1000
    )


# Drops a file with this name and text on the page's drop box.
DROP_FILE = """([name, text]) => {
    const transfer = new DataTransfer();
    transfer.items.add(new File([text], name));
    document.getElementById('drop-zone').dispatchEvent(new DragEvent('drop', {dataTransfer: transfer, bubbles: true}));
}"""


# --- the tests ------------------------------------------------------------------------------------


def test_submit_watch_view_and_download(service, page):
    open_page(page, service, API_KEY)

    # An invalid value is refused in the page, before anything is sent.
    page.set_input_files("#file", str(EXAMPLE_CLOUD))
    page.wait_for_function("document.getElementById('file-info').textContent.includes('announces 6,000 points')")
    fill_params(page, {**QUICK, "resolution": 16})
    page.click("#submit")
    assert "resolution: must be at least 32" in page.inner_text("#submit-error")
    assert page.inner_text("#param-resolution-error") == "resolution must be at least 32"
    assert page.locator("#job-panel").is_hidden()
    assert page.get_attribute("#param-resolution", "aria-invalid") == "true"

    started = time.monotonic()
    job_id = submit(page, EXAMPLE_CLOUD, QUICK)
    job = httpx.get(f"{service}/v1/jobs/{job_id}", headers={"Authorization": f"Bearer {API_KEY}"}).json()
    assert job["points"] == 6000
    assert {name: job["params"][name] for name in QUICK} == QUICK  # only the changed fields were sent...
    assert job["params"]["lambda1"] == 0.1  # ...the others kept the service's defaults

    # The progress bar moves, the loss curve is drawn.
    bar = "document.getElementById('job-progress')"
    page.wait_for_function(f"{bar}.value > 0 && {bar}.value < {bar}.max", timeout=60_000)
    first = page.eval_on_selector("#job-progress", "bar => bar.value")
    page.wait_for_function(f"{bar}.value > {first}", timeout=30_000)
    assert page.inner_text("#job-updates") == "Updates: live: event stream."  # not polling
    assert page.inner_text("#job-remaining") not in ("", "–")
    chart = pixels(page.locator("#loss-chart"))
    assert count_near(chart, VANISH_RGB, 30) > 20 and count_near(chart, EIKONAL_RGB, 30) > 20, "no loss curve drawn"

    wait_status(page, "succeeded", timeout=120)
    page.wait_for_selector("#viewer-wrap[data-state=ready]")
    page.wait_for_function("Number(document.getElementById('viewer').dataset.frames) > 0")
    fitted = time.monotonic() - started

    # The 3D view: a shaded mesh (many colours, not one) with the edge points over it.
    viewer = page.locator("#viewer")
    with_edges = pixels(viewer)
    assert distinct_colours(with_edges) > 50, "the 3D view is blank"
    assert count_near(with_edges, EDGE_RGB) > 50, "no edge points drawn"
    assert "Edge points" in page.inner_text("#viewer-note")
    page.locator("#params").evaluate("details => details.open = false")
    page.screenshot(path=str(ARTIFACTS / "page-cube.png"))
    if os.environ.get("EDGERECON_UPDATE_SCREENSHOT") == "1":
        page.screenshot(path=str(ROOT / "docs" / "page.png"))

    set_checkbox(page, "#show-edges", False)
    without_edges = pixels(viewer)
    assert count_near(without_edges, EDGE_RGB) < count_near(with_edges, EDGE_RGB) / 10
    set_checkbox(page, "#show-edges", True)
    assert count_near(pixels(viewer), EDGE_RGB) > 50

    # Input points and normals: from the job's preview.json (all 6,000: fewer than its bound).
    assert page.is_enabled("#show-points") and page.is_enabled("#show-normals")
    set_checkbox(page, "#show-mesh", False)
    points_off = pixels(viewer)
    set_checkbox(page, "#show-points", True)
    assert "6,000 of 6,000 points (preview.json)" in page.inner_text("#viewer-note")
    assert np.abs(pixels(viewer) - points_off).sum() > 0, "the input points changed nothing"
    set_checkbox(page, "#show-normals", True)
    set_checkbox(page, "#show-mesh", True)
    viewer.screenshot(path=str(ARTIFACTS / "view-points-normals.png"))

    # The result's counts, and a button per output that downloads it.
    assert "faces" in page.inner_text("#result-table") and "fit seconds" in page.inner_text("#result-table")
    buttons = page.locator("#downloads button")
    assert {buttons.nth(i).get_attribute("data-output") for i in range(buttons.count())} == {
        "mesh.obj", "normals.json", "edges.json", "preview.json", "mesh.ply", "mesh.stl", "mesh.glb"
    }  # fmt: skip
    with page.expect_download() as download:
        page.click("#downloads button[data-output='mesh.obj']")
    assert download.value.suggested_filename == "mesh.obj"
    lines = Path(download.value.path()).read_text().splitlines()
    assert any(line.startswith("v ") for line in lines) and any(line.startswith("f ") for line in lines)
    with page.expect_download() as download:
        page.click("#downloads button[data-output='edges.json']")
    assert "points" in json.loads(Path(download.value.path()).read_text())
    with page.expect_download() as download:
        page.click("#downloads button[data-output='mesh.glb']")
    assert download.value.suggested_filename == "mesh.glb"
    glb = trimesh.load(download.value.path(), file_type="glb", force="mesh")
    assert len(glb.faces) == job_result(service, job_id)["faces"]

    # The job is listed in this browser, with its status.
    assert "succeeded" in page.inner_text(f"#job-list li[data-job='{job_id}']")
    print(f"the quick job took {fitted:.1f} s from submit to its 3D view")


def test_cancel_a_long_job(service, page):
    open_page(page, service, API_KEY)
    job_id = submit(page, EXAMPLE_CLOUD, LONG)
    wait_status(page, "running", timeout=60)
    page.wait_for_function("document.getElementById('job-progress').value > 0")
    page.click("#cancel")
    wait_status(page, "canceled", timeout=30)
    assert page.is_disabled("#cancel")
    listed = f"document.querySelector(\"#job-list li[data-job='{job_id}']\")"
    page.wait_for_function(f"{listed}.textContent.includes('canceled')")


def test_api_errors_are_shown_as_the_api_says_them(service, page, tmp_path):
    open_page(page, service, API_KEY)
    not_a_cloud = tmp_path / "notes.ply"
    not_a_cloud.write_text("these are notes, not a point cloud\n")
    page.evaluate(DROP_FILE, ["notes.ply", not_a_cloud.read_text()])  # dropped on the box, as from a file manager
    page.wait_for_function("document.getElementById('file-info').textContent.includes('not a PLY file')")
    assert "notes.ply" in page.inner_text("#file-info")
    page.click("#submit")
    page.wait_for_selector("#submit-error:not([hidden])")
    detail = httpx.post(f"{service}/v1/jobs", files={"points": ("notes.ply", not_a_cloud.read_bytes())},
                        headers={"Authorization": f"Bearer {API_KEY}"}).json()["detail"]  # fmt: skip
    assert detail.startswith("points:") and detail in page.inner_text("#submit-error")  # verbatim

    page.fill("#api-key", "not-the-key")
    page.press("#api-key", "Tab")
    page.set_input_files("#file", str(EXAMPLE_CLOUD))
    page.click("#submit")
    page.wait_for_function("document.getElementById('submit-error').textContent.includes('401')")
    message = page.inner_text("#submit-error")
    assert "The API key is missing or wrong (401)" in message
    assert "missing or wrong API key" in message  # the API's own detail, too
    assert page.get_attribute("#api-key", "aria-invalid") == "true"
    assert page.locator("#job-panel").is_hidden()


# --- the page against the API as issue 12 extends it ----------------------------------------------


def _stand_in_api():
    """A stand-in for the API with the routes issue 12 adds: GET /v1/jobs/{id}/events (Server-Sent
    Events), preview.json, edge curves in edges.json, more mesh formats. It serves the real page and
    the real form schema; its "fit" is a few scripted events. ``seed`` 1 makes the stream stop
    before the final state, which the page must notice and poll for, and leaves preview.json out
    of the job's links."""
    schema = create_app(Settings(redis_url="redis://127.0.0.1:1/0")).openapi()
    app = FastAPI(openapi_url=None)
    app.state.forms = []  # the fields of every submitted form, but the file
    app.state.files = {}  # files a test hands to the page: GET /test-files/{name}
    app.include_router(page_router)
    jobs: dict[str, dict] = {}
    now = datetime.now(UTC).isoformat()
    corners = [[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)]
    rng = np.random.default_rng(0)
    faces_points = rng.random((3000, 3))
    faces_points[np.arange(3000), rng.integers(0, 3, 3000)] = rng.integers(0, 2, 3000)
    # The cube's 12 edges: pairs of corners that differ in one coordinate.
    lines = [
        (a, b) for a in range(8) for b in range(a + 1, 8) if np.abs(np.subtract(corners[a], corners[b])).sum() == 1
    ]
    outputs = {
        "mesh.obj": "".join(f"v {x} {y} {z}\n" for x, y, z in corners) + "f 1 2 4\nf 1 4 3\nf 5 7 8\nf 5 8 6\n"
        "f 1 5 6\nf 1 6 2\nf 3 4 8\nf 3 8 7\nf 1 3 7\nf 1 7 5\nf 2 6 8\nf 2 8 4\n",
        "edges.json": json.dumps(
            {
                "tau": 30,
                "count": 8,
                "indices": list(range(8)),
                "points": corners,
                "laplacian": [40.0] * 8,
                "curves": [{"points": [corners[a], corners[b]], "angle": 90.0, "convex": True} for a, b in lines],
            }
        ),
        "preview.json": json.dumps(
            {
                "total": 6000,
                "points": faces_points.tolist(),
                "normals": [[0, 0, 1]] * 3000,
                "edge": [0] * 3000,
            }
        ),
        "normals.json": json.dumps({"normals": [[0, 0, 1]] * 6000}),
        "mesh.ply": "ply\nformat ascii 1.0\nelement vertex 0\nend_header\n",
    }

    def view(job_id: str, status: str, iteration: int = 0) -> dict:
        base = f"/v1/jobs/{job_id}"
        listed = [name for name in outputs if not (name == "preview.json" and jobs[job_id]["breaks"])]
        links = {"self": base, **({name: f"{base}/{name}" for name in listed} if status == "succeeded" else {})}
        losses = {"total": 1 / (1 + iteration), "vanish": 0.5 / (1 + iteration), "eikonal": 0.1, "laplacian": 2.0}
        return {
            "id": job_id, "status": status, "points": 6000, "params": {"iterations": 50},
            "progress": None if status == "queued" else
            {"stage": "fitting", "iteration": iteration, "total": 50, "losses": losses, "edge_share": 0.02},
            "created_at": now, "started_at": now, "ended_at": now if status == "succeeded" else None,
            "expires_at": None, "error": None, "links": links,
            "result": {"vertices": 8, "faces": 12, "watertight": True, "edge_points": 8,
                       "timings": {"fit_seconds": 1.0}} if status == "succeeded" else None,
        }  # fmt: skip

    @app.get("/openapi.json", include_in_schema=False)
    def openapi():
        return schema

    @app.post("/v1/jobs", status_code=202)
    async def submit_job(request: Request):
        form = await request.form()
        job_id = secrets.token_urlsafe(16)[:22]
        jobs[job_id] = {"breaks": form.get("seed") == "1"}
        app.state.forms.append({name: value for name, value in form.items() if name != "points"})
        # The form is seen here before the page has the answer, as on a loaded machine.
        await asyncio.sleep(0.5)
        return view(job_id, "queued")

    @app.get("/v1/jobs/{job_id}")
    def get_job(job_id: str):
        return view(job_id, "succeeded") if job_id in jobs else JSONResponse({"detail": "no job"}, 404)

    @app.get("/v1/jobs/{job_id}/events")
    async def events(job_id: str):
        async def stream():
            yield ": a comment, which the page ignores\n\n"
            yield "event: job\ndata: " + json.dumps(view(job_id, "queued")) + "\n\n"
            for iteration in range(10, 51, 10):
                await asyncio.sleep(0.2)
                body = json.dumps(view(job_id, "running", iteration))
                if iteration == 20:  # one message over two data lines, \r\n line ends, cut mid-line
                    head, tail = body.split(", ", 1)
                    yield f"event: job\r\ndata: {head},\r\ndata: {tail[:10]}"
                    await asyncio.sleep(0.05)
                    yield f"{tail[10:]}\r\n\r\n"
                else:
                    yield f"event: job\ndata: {body}\n\n"
            if jobs[job_id]["breaks"]:
                return  # the stream ends before the final state
            yield "event: job\ndata: " + json.dumps(view(job_id, "succeeded")) + "\n\n"

        return StreamingResponse(stream(), media_type="text/event-stream")

    @app.get("/test-files/{name}")
    def test_file(name: str):
        return Response(app.state.files[name], media_type="application/octet-stream")

    @app.get("/v1/jobs/{job_id}/{name}")
    def output(job_id: str, name: str):
        return Response(outputs[name], media_type="application/json" if name.endswith(".json") else "text/plain")

    return app


@pytest.fixture(scope="module")
def stand_in():
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(_stand_in_api(), host="127.0.0.1", port=port, log_level="warning",
                                           timeout_graceful_shutdown=1))  # fmt: skip
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    wait_for(lambda: server.started, 20, 0.05, "the stand-in API to start")
    yield f"http://127.0.0.1:{port}", server.config.app
    server.should_exit = True
    thread.join(10)


def test_page_uses_the_event_stream_preview_and_curves_when_the_api_has_them(stand_in, page):
    url, app = stand_in
    open_page(page, url, None)
    page.click("#params summary")
    page.uncheck("#param-edge_sampling")
    page.select_option("#param-laplacian_penalty", "quadratic")
    first_job = submit(page, EXAMPLE_CLOUD, {"iterations": 50})
    assert first_job
    # Only what was changed is sent, booleans and choices as the API reads them.
    assert app.state.forms[-1] == {"iterations": "50", "edge_sampling": "false", "laplacian_penalty": "quadratic"}
    wait_status(page, "succeeded", timeout=20)
    assert page.inner_text("#job-updates") == "Updates: live: event stream."
    assert page.eval_on_selector("#job-progress", "bar => [bar.value, bar.max]") == [50, 50]
    chart = pixels(page.locator("#loss-chart"))
    assert count_near(chart, VANISH_RGB, 30) > 20, "no loss curve drawn from the events"
    page.wait_for_selector("#viewer-wrap[data-state=ready]")

    # Every output in the links gets a button; edge curves and the preview's points are drawn.
    buttons = page.locator("#downloads button")
    assert {buttons.nth(i).get_attribute("data-output") for i in range(buttons.count())} == {
        "mesh.obj", "edges.json", "preview.json", "normals.json", "mesh.ply"
    }  # fmt: skip
    assert page.is_enabled("#show-curves") and "Edge curves: 12" in page.inner_text("#viewer-note")
    page.wait_for_function("Number(document.getElementById('viewer').dataset.frames) > 0")
    viewer = page.locator("#viewer")
    assert count_near(pixels(viewer), CONVEX_RGB, 30) > 20, "no edge curves drawn"
    set_checkbox(page, "#show-curves", False)
    assert count_near(pixels(viewer), CONVEX_RGB, 30) < 5
    set_checkbox(page, "#show-points", True)
    assert "3,000 of 6,000 points (preview.json)" in page.inner_text("#viewer-note")
    set_checkbox(page, "#show-normals", True)

    # A stream that ends before the final state: the page polls instead, and gets there.
    page.click("#reset-params")
    sent = len(app.state.forms)
    submit(page, EXAMPLE_CLOUD, {"iterations": 50, "seed": 1})
    # The job panel is already open from the first job: wait for this job's form to arrive.
    wait_for(lambda: len(app.state.forms) > sent, 10, 0.05, "the second job's form")
    assert app.state.forms[-1] == {"iterations": "50", "seed": "1"}
    # Until the page has the API's answer, its panel still shows the first job, succeeded.
    page.wait_for_function(
        "first => document.querySelector('#job-list li.current')?.dataset.job !== first", arg=first_job, timeout=10_000
    )
    wait_status(page, "succeeded", timeout=20)
    assert "the event stream ended early" in page.inner_text("#job-updates")
    # No preview.json: the input points are read from the file picked here, the normals from normals.json.
    page.wait_for_selector("#viewer-wrap[data-state=ready]")
    assert page.is_checked("#show-points")  # as chosen for the first job
    page.wait_for_function("document.getElementById('viewer-note').textContent.includes('of cube.ply')")
    assert "6,000 of 6,000 points of cube.ply" in page.inner_text("#viewer-note")


def test_the_page_reads_ply_files_of_every_kind_and_samples_big_ones(stand_in, page, tmp_path):
    """formats.js, in the browser: ASCII and binary of both byte orders, another element before the
    vertices, extra vertex properties; at most 50,000 points drawn from a bigger cloud."""
    url, app = stand_in
    page.goto(url + "/")
    rng = np.random.default_rng(1)
    small = rng.normal(size=(300, 3)).astype(np.float32)
    big = rng.normal(size=(120_000, 3)).astype(np.float32)
    extra = "property uchar red\n"
    before = "element camera 1\nproperty float f\n"
    clouds = {
        "ascii": ply_ascii(small),
        "little": ply_binary(small),
        "big": ply_header("binary_big_endian", len(small)) + small.astype(">f4").tobytes(),
        "extra": ply_header("binary_little_endian", len(small), extra).replace(b"element vertex", before.encode() +
                 b"element vertex") + np.float32(7).tobytes() + b"".join(p.tobytes() + b"\x01" for p in small),
        "ascii_extra": b"ply\nformat ascii 1.0\n" + before.encode() + b"element vertex 300\nproperty float x\n"
                       b"property float y\nproperty float z\n" + extra.encode() + b"end_header\n7\n" +
                       "".join(f"{x:.6f} {y:.6f} {z:.6f} 1\n" for x, y, z in small).encode(),
        "sampled": ply_binary(big),
    }  # fmt: skip
    app.state.files.update(clouds)
    read = """async (name) => {
        const {readPlySample} = await import('./static/js/formats.js');
        const sample = readPlySample(await (await fetch(`test-files/${name}`)).arrayBuffer(), 50000);
        return {total: sample.total, indices: Array.from(sample.indices), positions: Array.from(sample.positions)};
    }"""
    for name in clouds:
        sample = page.evaluate(read, name)
        source = big if name == "sampled" else small
        indices = np.array(sample["indices"])
        assert sample["total"] == len(source), name
        assert len(indices) == min(len(source), 50_000) and np.all(np.diff(indices) > 0), name
        positions = np.array(sample["positions"]).reshape(-1, 3)
        np.testing.assert_allclose(positions, source[indices], atol=1e-5, err_msg=name)
