"""Speed side by side, in one run: edgerecon as a command and as a service, screened Poisson, and
large clouds. Prints one markdown table and writes it to bench/results/speed.md.

    .venv/bin/python bench/speed.py                            # everything (about 20 minutes on 2 cores)
    .venv/bin/python bench/speed.py --iterations 50            # a quick check of the machinery
    .venv/bin/python bench/speed.py --only fit,poisson         # some of the parts
    .venv/bin/python bench/speed.py --five-million             # also 5 M points (off by default)

Parts (``--only``, comma-separated):

- ``fit``: ``edgerecon fit`` on ../shared/data/cube/points.ply and box_hole/points.ply, each as a whole
  process: wall time, CPU (user + sys of the process and everything it waited for, from
  getrusage(RUSAGE_CHILDREN)), peak resident memory of its process tree (psutil, polled every
  0.1 s), and the time to its first fitting step (from its progress bar: import, reading,
  set-up and any kernel compilation).
- ``cold``: ``edgerecon fit`` on the cube as the first fit after an install: torch's compile cache
  (``TORCHINDUCTOR_CACHE_DIR``) an empty temporary folder, so every kernel is compiled anew.
- ``serve``: the same clouds through a fresh ``edgerecon serve`` (free port, its own --data-dir in a
  temporary folder, its defaults: one worker on every core), started and warmed up before the
  clock runs; one job at a time, timed from the POST to ``succeeded`` (polled every 0.25 s). CPU and
  peak memory are those of the whole service tree (API, embedded Redis, worker) during the job.
- ``poisson``: screened Poisson with Open3D on the same files, in a subprocess timed like ``fit``:
  PCA normals (KNN 30), orient_normals_consistent_tangent_plane(30), flipped as a whole if they
  point inward on average (the orientation is only relative), depth 9, vertices below the 2 %
  density quantile removed. Needs the ``bench`` extra (``pip install -e '.[bench]'``; the wheel
  needs Debian's libusb-1.0-0); without Open3D these rows are skipped with a message.
- ``large``: the cube at 100 k and 1 M points (5 M with ``--five-million``), sampled uniformly by area
  from ../shared/data/cube/gt.ply with noise 0.005 and labelled like ../shared/data, through
  ``edgerecon fit``. The clouds are cached in ``--cache`` (default bench/results/clouds, not
  committed).

Every row is scored with evaluation.sample_data.evaluate_shape against the ground truth: exact
Chamfer and Hausdorff distances, mean oriented normal error, edge IoU (Poisson reports no edges).
``vs Poisson`` is each edgerecon wall time over Poisson's on the same file in this run; ``vs 16 k``
a large cloud's wall time over the 16,384-point cube's ``edgerecon fit``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

DATA = ROOT.parent / "shared" / "data"
CLOUDS = ("cube", "box_hole")
PARTS = ("fit", "cold", "serve", "poisson", "large")
LARGE = {"100k": 100_000, "1M": 1_000_000}
HUGE = {"5M": 5_000_000}
NOISE = 0.005
EDGERECON = [sys.executable, "-m", "service.cli"]
# The first fitting step in tqdm's bar: "fitting:   0%|  | 1/1800 [...]".
STEP = re.compile(r"\|\s*(\d+)/\d+ \[")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, help="passed to every edgerecon run (default: edgerecon's)")
    parser.add_argument("--only", default=",".join(PARTS), help="comma-separated, from: " + ", ".join(PARTS))
    parser.add_argument("--five-million", action="store_true", help="also the 5 M point cloud (large)")
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--cache", type=Path, default=ROOT / "bench" / "results" / "clouds")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "speed.md")
    parser.add_argument("--poisson", nargs=2, metavar=("INPUT", "OUT"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.poisson:
        print(json.dumps(poisson(Path(args.poisson[0]), Path(args.poisson[1]))))
        return 0
    parts = [part for part in args.only.split(",") if part]
    unknown = sorted(set(parts) - set(PARTS))
    if unknown:
        parser.error(f"unknown part {', '.join(unknown)}; choose from {', '.join(PARTS)}")
    if not args.data.is_dir():
        print(f"bench: {args.data} is missing (the sample shapes of ../shared/data)", file=sys.stderr)
        return 2
    options = ["--iterations", str(args.iterations)] if args.iterations else []
    notes: list[str] = []
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="edgerecon-speed-") as tmp:
        work = Path(tmp)
        if "fit" in parts:
            for shape in CLOUDS:
                rows.append(run_fit("edgerecon fit", shape, args.data / shape, "points.ply", work, options))
        if "cold" in parts:
            empty_cache = {"TORCHINDUCTOR_CACHE_DIR": str(work / "empty-compile-cache")}
            label = "edgerecon fit, empty compile cache"
            rows.append(run_fit(label, "cube", args.data / "cube", "points.ply", work, options, empty_cache))
        if "serve" in parts:
            rows += run_serve(args.data, work, args.iterations, notes)
        if "poisson" in parts:
            if open3d_missing():
                notes.append(
                    "Screened Poisson skipped: Open3D is not installed (`pip install -e '.[bench]'`; its wheel "
                    "needs Debian's libusb-1.0-0)."
                )
                print("bench: " + notes[-1], file=sys.stderr)
            else:
                rows += [run_poisson(shape, args.data / shape, work) for shape in CLOUDS]
        if "large" in parts:
            sizes = {**LARGE, **(HUGE if args.five_million else {})}
            for label, count in sizes.items():
                folder, points_file = large_cloud(args.data / "cube", args.cache, label, count)
                rows.append(run_fit("edgerecon fit", f"cube {label}", folder, points_file, work, options))
    report = render(rows, notes, args)
    print(report)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(report)
    print(f"written to {args.out}", file=sys.stderr)
    return 0


# --- measuring a process tree ----------------------------------------------------------------------


class TreeMonitor(threading.Thread):
    """The peak of the summed resident memory of a process and its descendants, polled."""

    def __init__(self, pid: int, period: float = 0.1) -> None:
        super().__init__(daemon=True)
        self.pid, self.period = pid, period
        self.peak = 0
        self._stop_event = threading.Event()

    def run(self) -> None:

        while not self._stop_event.is_set():
            self.peak = max(self.peak, tree_rss(self.pid))
            self._stop_event.wait(self.period)

    def stop(self) -> int:
        self._stop_event.set()
        self.join()
        return self.peak


def tree_processes(pid: int) -> list:
    import psutil

    try:
        root = psutil.Process(pid)
        return [root, *root.children(recursive=True)]
    except psutil.NoSuchProcess:
        return []


def tree_rss(pid: int) -> int:
    import psutil

    total = 0
    for process in tree_processes(pid):
        try:
            total += process.memory_info().rss
        except psutil.Error:
            pass
    return total


def tree_cpu(pid: int) -> float:
    """User + system seconds of a living tree (each process's own and its reaped children's)."""
    import psutil

    total = 0.0
    for process in tree_processes(pid):
        try:
            times = process.cpu_times()
            total += times.user + times.system + times.children_user + times.children_system
        except psutil.Error:
            pass
    return total


def children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def timed_process(
    command: list[str], on_line: Callable[[str, float], None] | None = None, env: dict[str, str] | None = None
) -> dict[str, Any]:
    """Run ``command`` to its end: wall seconds, CPU seconds, peak tree RSS (MB), its stdout and the
    tail of its stderr. ``on_line`` gets every stderr line (tqdm's carriage returns split too) with
    the seconds since the start; ``env`` is added to ``clean_env()``."""
    cpu_before = children_cpu()
    started = time.perf_counter()
    environment = clean_env() | (env or {})
    child = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=environment)
    monitor = TreeMonitor(child.pid)
    monitor.start()
    stdout: list[bytes] = []
    reader = threading.Thread(target=lambda: stdout.append(child.stdout.read() if child.stdout else b""))
    reader.start()
    tail: list[str] = []
    assert child.stderr is not None
    buffer = b""
    while chunk := child.stderr.read1(4096):
        buffer += chunk
        *lines, buffer = re.split(rb"[\r\n]", buffer)
        for line in lines:
            text = line.decode(errors="replace")
            if on_line:
                on_line(text, time.perf_counter() - started)
            if text.strip():
                tail = [*tail[-30:], text]
    child.wait()
    wall = time.perf_counter() - started
    reader.join()
    peak = monitor.stop()
    return {
        "returncode": child.returncode,
        "wall": wall,
        "cpu": children_cpu() - cpu_before,
        "peak_mb": peak / 2**20,
        "stdout": b"".join(stdout).decode(errors="replace"),
        "stderr": "\n".join(tail),
    }


def clean_env() -> dict[str, str]:
    """This environment without the service's settings, so every run uses edgerecon's defaults."""
    return {name: value for name, value in os.environ.items() if not name.startswith("EDGERECON_")} | {
        "PYTHONUNBUFFERED": "1"
    }


# --- edgerecon fit ----------------------------------------------------------------------------------


def run_fit(
    label: str,
    cloud: str,
    folder: Path,
    points_file: str,
    work: Path,
    options: list[str],
    env: dict[str, str] | None = None,
) -> dict[str, Any]:
    out = work / f"fit-{cloud.replace(' ', '-')}"
    first_step: list[float] = []

    def watch(line: str, seconds: float) -> None:
        match = STEP.search(line)
        if not first_step and match and int(match.group(1)) >= 1 and line.lstrip().startswith("fitting"):
            first_step.append(seconds)

    print(f"{label} on {cloud}...", file=sys.stderr, flush=True)
    command = [*EDGERECON, "fit", str(folder / points_file), "--out", str(out), *options]
    done = timed_process(command, watch, env)
    row = {"run": label, "cloud": cloud, "points": count_points(folder / points_file), **done}
    row["first_step"] = first_step[0] if first_step else None
    if done["returncode"] != 0:
        print(done["stderr"][-2000:], file=sys.stderr)
        return row
    reported = re.search(r"in ([\d.]+) s fit \+ ([\d.]+) s extraction", done["stdout"])
    if reported:
        row["fit_timings"] = {"fit_seconds": float(reported.group(1)), "extract_seconds": float(reported.group(2))}
    row.update(score_outputs(out, folder, points_file))
    shutil.rmtree(out, ignore_errors=True)
    progress(row)
    return row


def score_outputs(out: Path, folder: Path, points_file: str) -> dict[str, Any]:
    import trimesh

    from evaluation.sample_data import evaluate_shape

    mesh = trimesh.load(out / "mesh.obj", force="mesh", process=False)
    normals = np.asarray(json.loads((out / "normals.json").read_text())["normals"], dtype=np.float64)
    edges = np.asarray(json.loads((out / "edges.json").read_text())["indices"], dtype=np.int64)
    return evaluate_shape(mesh, normals, edges, folder, points_file=points_file)


def count_points(path: Path) -> int:
    from core.ply import read_points

    return len(read_points(path, max_points=10**9))


def progress(row: dict[str, Any]) -> None:
    print(
        f"  wall {row['wall']:.1f} s, CPU {row['cpu']:.1f} s, peak {row['peak_mb']:.0f} MB, "
        f"d_C {row.get('chamfer_exact', float('nan')):.4f}, d_H {row.get('hausdorff_exact', float('nan')):.4f}",
        file=sys.stderr,
        flush=True,
    )


# --- edgerecon serve --------------------------------------------------------------------------------


def run_serve(data: Path, work: Path, iterations: int | None, notes: list[str]) -> list[dict[str, Any]]:
    import httpx

    from worker.redis_server import free_port

    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = {name: value for name, value in clean_env().items() if name != "REDIS_URL"}
    log = open(work / "serve.log", "ab")
    command = [*EDGERECON, "serve", "--port", str(port), "--data-dir", str(work / "serve-data")]
    print("starting edgerecon serve...", file=sys.stderr, flush=True)
    started = time.perf_counter()
    service = subprocess.Popen(command, cwd=ROOT, env=env, stdout=log, stderr=log, start_new_session=True)
    rows = []
    try:
        with httpx.Client(base_url=url, timeout=60) as client:
            deadline = time.monotonic() + 600
            while True:
                if service.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"edgerecon serve did not start; see {work / 'serve.log'}")
                try:
                    if client.get("/healthz").json().get("workers", 0) >= 1:
                        break
                except httpx.HTTPError:
                    pass
                time.sleep(0.25)
            ready = time.perf_counter() - started
            notes.append(
                f"`edgerecon serve` was ready (a worker warmed up and signalled) {ready:.0f} s after its start; "
                "that time is not in its rows."
            )
            for shape in CLOUDS:
                rows.append(serve_job(client, service.pid, shape, data / shape, work, iterations))
    except (RuntimeError, httpx.HTTPError) as error:
        print(f"bench: serve: {error}", file=sys.stderr)
        notes.append(f"The serve rows failed: {error}.")
    finally:
        os.killpg(service.pid, signal.SIGTERM)
        try:
            service.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(service.pid, signal.SIGKILL)
            service.wait()
        log.close()
    return rows


def serve_job(client: Any, pid: int, shape: str, folder: Path, work: Path, iterations: int | None) -> dict[str, Any]:
    print(f"edgerecon serve on {shape}...", file=sys.stderr, flush=True)
    fields = {"iterations": str(iterations)} if iterations else {}
    body = (folder / "points.ply").read_bytes()
    monitor = TreeMonitor(pid)
    monitor.start()
    cpu_before = tree_cpu(pid)
    started = time.perf_counter()
    response = client.post("/v1/jobs", files={"points": ("points.ply", body)}, data=fields)
    response.raise_for_status()
    job = response.json()
    first_step = None
    while job["status"] in ("queued", "running"):
        time.sleep(0.25)
        job = client.get(f"/v1/jobs/{job['id']}").json()
        if first_step is None and (job.get("progress") or {}).get("iteration", 0) >= 1:
            first_step = time.perf_counter() - started
    wall = time.perf_counter() - started
    cpu = tree_cpu(pid) - cpu_before
    peak = monitor.stop()
    row: dict[str, Any] = {"run": "edgerecon serve", "cloud": shape, "points": count_points(folder / "points.ply")}
    row.update(wall=wall, cpu=cpu, peak_mb=peak / 2**20, first_step=first_step)
    if job["status"] != "succeeded":
        print(f"bench: the job {job['status']}: {job.get('error')}", file=sys.stderr)
        return row
    out = work / f"serve-{shape}"
    out.mkdir()
    for name in ("mesh.obj", "normals.json", "edges.json"):
        (out / name).write_bytes(client.get(f"/v1/jobs/{job['id']}/{name}").content)
    row.update(score_outputs(out, folder, "points.ply"))
    row["worker_seconds"] = job["result"]["timings"]
    progress(row)
    return row


# --- screened Poisson ---------------------------------------------------------------------------------


def open3d_missing() -> bool:
    done = subprocess.run([sys.executable, "-c", "import open3d"], capture_output=True, check=False)
    return done.returncode != 0


def screened_poisson(source: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, float]]:
    """Screened Poisson of the PLY cloud ``source``: the mesh's vertices and triangles, the cloud's
    normals (file order) and seconds per stage. bench/run.py's ``poisson`` configuration uses it too."""
    started = time.perf_counter()
    import open3d as o3d

    imported = time.perf_counter()
    cloud = o3d.io.read_point_cloud(str(source))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=30))
    cloud.orient_normals_consistent_tangent_plane(30)
    points, normals = np.asarray(cloud.points), np.asarray(cloud.normals)
    if np.mean(np.einsum("ij,ij->i", normals, points - points.mean(axis=0))) < 0:
        cloud.normals = o3d.utility.Vector3dVector(-normals)  # consistent, but all inward
    oriented = time.perf_counter()
    mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(cloud, depth=9)
    densities = np.asarray(densities)
    mesh.remove_vertices_by_mask(densities < np.quantile(densities, 0.02))
    done = time.perf_counter()
    stages = {
        "import_seconds": imported - started,
        "normals_seconds": oriented - imported,
        "poisson_seconds": done - oriented,
    }
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles), np.asarray(cloud.normals), stages


def poisson(source: Path, out: Path) -> dict[str, float]:
    """Screened Poisson of ``source`` into ``out``/mesh.npz and normals.npy; seconds per stage. Runs
    in the measured subprocess."""
    vertices, triangles, normals, stages = screened_poisson(source)
    out.mkdir(parents=True, exist_ok=True)
    np.savez(out / "mesh.npz", vertices=vertices, faces=triangles)
    np.save(out / "normals.npy", normals)
    return stages


def run_poisson(shape: str, folder: Path, work: Path) -> dict[str, Any]:
    import trimesh

    from evaluation.sample_data import evaluate_shape

    print(f"screened Poisson on {shape}...", file=sys.stderr, flush=True)
    out = work / f"poisson-{shape}"
    done = timed_process([sys.executable, __file__, "--poisson", str(folder / "points.ply"), str(out)])
    row = {"run": "screened Poisson (Open3D)", "cloud": shape, "points": count_points(folder / "points.ply"), **done}
    row["first_step"] = None
    if done["returncode"] != 0:
        print(done["stderr"][-2000:], file=sys.stderr)
        return row
    row["stages"] = json.loads(done["stdout"].strip().splitlines()[-1])
    with np.load(out / "mesh.npz") as arrays:
        mesh = trimesh.Trimesh(arrays["vertices"], arrays["faces"], process=False)
    normals = np.load(out / "normals.npy")
    row.update(evaluate_shape(mesh, normals, np.zeros(0, dtype=np.int64), folder))
    row["edge_iou"] = None  # Poisson has no edge output
    progress(row)
    return row


# --- large clouds -------------------------------------------------------------------------------------


def large_cloud(shape_dir: Path, cache: Path, label: str, count: int) -> tuple[Path, str]:
    """A shape folder in ``cache`` with ``count`` points sampled from ``shape_dir``'s gt.ply (noise
    0.005, uniform by area) and their labels, as ../shared/data makes them; made once."""
    import trimesh

    from core.ply import read_points
    from evaluation.shapes import sample_mesh, write_ply

    folder = cache / shape_dir.name
    points_file, labels = f"points_{label}.ply", f"labels_{label}.npz"
    if (folder / points_file).exists() and (folder / labels).exists():
        return folder, points_file
    print(f"sampling {count:,} points from {shape_dir / 'gt.ply'}...", file=sys.stderr, flush=True)
    folder.mkdir(parents=True, exist_ok=True)
    for name in ("gt.ply", "edges_gt.npy"):
        shutil.copyfile(shape_dir / name, folder / name)
    mesh = trimesh.load(shape_dir / "gt.ply", force="mesh", process=False)
    shape = sample_mesh(mesh, shape_dir.name, count, NOISE, seed=count)
    write_ply(folder / points_file, shape.points)
    points = read_points(folder / points_file, max_points=10**9)  # float32, as edgerecon reads them
    np.savez(
        folder / labels, points=points, points_clean=shape.clean_points, normals=shape.normals, is_edge=shape.is_edge
    )
    return folder, points_file


# --- the table ------------------------------------------------------------------------------------------


def render(rows: list[dict[str, Any]], notes: list[str], args: argparse.Namespace) -> str:
    import torch

    command = "python bench/speed.py " + " ".join(sys.argv[1:])
    poisson_wall = {r["cloud"]: r["wall"] for r in rows if r["run"].startswith("screened") and r["returncode"] == 0}
    small_fit = next((r["wall"] for r in rows if r["run"] == "edgerecon fit" and r["cloud"] == "cube"), None)
    lines = [
        f"Made by `{command.strip()}` on {datetime.now(UTC):%Y-%m-%d %H:%M} UTC: {os.cpu_count()} cores, "
        f"torch {torch.__version__}, Python {platform.python_version()}, iterations "
        f"{args.iterations or 'default'}.",
        "",
        "| run | cloud | points | wall s | vs Poisson | vs 16 k fit | CPU s | peak MB | first step s "
        "| d_C exact | d_H exact | normal mean | edge IoU |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        ok = row.get("returncode", 0) == 0 and "chamfer_exact" in row
        ratio = poisson_wall.get(row["cloud"]) if row["run"].startswith("edgerecon") else None
        large = row["cloud"].startswith("cube ")
        cells = [
            row["run"],
            row["cloud"],
            f"{row['points']:,}",
            f"{row['wall']:.1f}",
            f"{row['wall'] / ratio:.1f}x" if ratio else "–",
            f"{row['wall'] / small_fit:.2f}x" if large and small_fit else "–",
            f"{row['cpu']:.1f}",
            f"{row['peak_mb']:.0f}",
            f"{row['first_step']:.1f}" if row.get("first_step") is not None else "–",
            f"{row['chamfer_exact']:.4f}" if ok else "failed",
            f"{row['hausdorff_exact']:.4f}" if ok else "–",
            f"{row['normal_mean_oriented']:.2f}°" if ok else "–",
            f"{row['edge_iou']:.2f}" if ok and row.get("edge_iou") is not None else "n/a (no edges)" if ok else "–",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    details = []
    for row in rows:
        if "stages" in row:
            stages = ", ".join(
                f"{name.removesuffix('_seconds')} {value:.1f} s" for name, value in row["stages"].items()
            )
            details.append(f"Poisson on {row['cloud']}: {stages}.")
        if "worker_seconds" in row:
            timings = ", ".join(
                f"{name.removesuffix('_seconds')} {value:.1f} s" for name, value in row["worker_seconds"].items()
            )
            details.append(f"The service's job on {row['cloud']}, as its worker timed it: {timings}.")
        if "fit_timings" in row:
            timings = ", ".join(
                f"{name.removesuffix('_seconds')} {value:.1f} s" for name, value in row["fit_timings"].items()
            )
            details.append(
                f"`edgerecon fit` on {row['cloud']}, as it reports: {timings} (the rest of its wall time is "
                "start-up, reading, writing the outputs)."
            )
    lines += ["", *(f"- {text}" for text in [*notes, *details])] if notes or details else []
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
