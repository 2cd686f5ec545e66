"""Benchmark the fit: quality and time per shape and configuration, the training step's speed,
and worker throughput. Prints markdown tables and writes them to bench/results/latest.md
(docs/benchmarks.md holds a copy of a full run, with what the numbers mean).

    .venv/bin/python bench/run.py                                  # everything (about an hour)
    .venv/bin/python bench/run.py --only quality --configs default --clouds cube
    .venv/bin/python bench/run.py --only quality --configs default --clouds cube,flange --seeds 0,1 --jobs 2
    .venv/bin/python bench/run.py --only steps                     # one training step, side by side
    .venv/bin/python bench/run.py --only step-parts                # a fit's step in its parts, at four batch sizes
    .venv/bin/python bench/run.py --only throughput                # 1 worker x 2 threads vs 2 x 1

Quality: every (configuration, cloud) pair is fitted in a fresh process (so its peak memory is
its own), then scored with evaluation.metrics against the ground truth in ../shared/data (see that
folder's README). Configurations differ only in the loss: ``igr`` (no Laplacian term), ``lap``
(the paper's quadratic Laplacian on every point), ``lap+des`` (the paper's method: quadratic,
dynamic edge sampling), ``default`` (what edgerecon ships), ``mc`` (the defaults with the old
marching-cubes extraction and |Δf| > τ edges: the same fit, so the difference is the extraction's).
All use the shipped schedule, network and free-space term. ``curve ECD`` scores the edge curves'
samples against the true edges as ECD does the edge points; ``worst vertex`` the exact distance of
the mesh vertex farthest from the true surface (steadier than the sampled d_H, whose samples one
moved vertex redraws); ``genus`` is the mesh's; ``crossing
faces`` those of the mesh, as its OBJ file holds it, that pass through or touch another. ``features``
the Fourier features the fit's network read (32 where ``encoding="auto"`` started it again with
them, 0 where not). A cloud
``<shape>/open`` is that shape's open variant (evaluation.open_clouds: the points beyond a plane or in a ball
deleted, scored against the whole true surface).
``poisson`` is the classical baseline instead of a fit: screened Poisson with Open3D
(bench/speed.py's pipeline: PCA normals, orientation, depth 9, trimming), scored the same way
with the cloud's normals; it has no edges (their scores are blank), its fit s is the normals'
estimation and orientation and its extract s the Poisson solve. It needs the ``bench`` extra, and
is in the default list only when Open3D is installed.

``--fits DIR`` keeps each fit's network in DIR and, where DIR already holds the same fit (the same
points and parameters, but for those of the extraction alone: ``extraction``, ``edge_angle``,
``edge_width``, ``resolution``), extracts that one again instead of fitting: a change to the
extraction is then measured on the same fits, from a checkout before it and one after (a fit
costs most of a job and differs with any change of rounding); the fit s column is then the saved fit's.

``--seeds 0,1,2`` fits every pair once per seed and adds the seeds' mean and range: a single fit's
d_H moves by about 15 % between seeds, so a change is judged over seeds. ``--jobs 2`` runs two fits
at once with the cores split between them (quicker for research runs; times are then a shared
machine's).

Steps: one training step (``core.fit.step_loss``, backward, Adam) with and without the
Laplacian term, alternated in one run so that the machine's load hits both; medians, the
step's matrix-product GFLOP/s, and this machine's float32 and bfloat16 matrix-product peaks
measured in the same run.

Throughput: the same four fits run by one process with two torch threads, one after another,
and by two processes with one thread each, side by side: jobs per hour for each worker layout.
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

DATA = ROOT.parent / "shared" / "data"
CONFIGS = {
    "igr": {"lambda2": 0.0},
    "lap": {"laplacian_penalty": "quadratic", "lambda2": 0.001, "tau": 20.0, "edge_sampling": False},
    "lap+des": {"laplacian_penalty": "quadratic", "lambda2": 0.001, "tau": 20.0, "edge_sampling": True},
    "default": {},
    "mc": {"extraction": "mc"},
}
# Baselines that are not a fit: scored like a configuration, run by run_baseline.
BASELINES = {"poisson": "screened Poisson (Open3D), as bench/speed.py runs it"}
CLOUDS = [
    "cube",
    "box_hole",
    "l_bracket",
    "sphere",
    "octagon_pocket",
    "wedge",
    "flange",
    "featuretype",
    "idler_riser",
    "box_hole/points_4096.ply",
    "box_hole/points_noise010.ply",
    "cube/open",
    "sphere/open",
    "l_bracket/open",
    "box_hole/open",
    "idler_riser/open",
    "flange/open",
    "wedge/open",
    "octagon_pocket/open",
]
COLUMNS = [
    ("d_C", "chamfer", "{:.4f}"),
    ("d_C exact", "chamfer_exact", "{:.4f}"),
    ("d_H exact", "hausdorff_exact", "{:.4f}"),
    ("worst vertex", "worst_vertex", "{:.4f}"),
    ("normal mean", "normal_mean_oriented", "{:.2f}°"),
    ("normal median", "normal_median_oriented", "{:.2f}°"),
    ("flipped", "normal_inward_share", "{:.2%}"),
    ("edge P", "edge_precision", "{:.2f}"),
    ("edge R", "edge_recall", "{:.2f}"),
    ("edge IoU", "edge_iou", "{:.2f}"),
    ("ECD", "ecd", "{:.4f}"),
    ("curve ECD", "curve_ecd", "{:.4f}"),
    ("genus", "genus", "{:.0f}"),
    ("crossing faces", "crossing_faces", "{:.0f}"),
    ("false edges", "edge_false_share", "{:.2%}"),
    ("features", "fourier_features", "{:.0f}"),
    ("fit s", "fit_seconds", "{:.1f}"),
    ("extract s", "extract_seconds", "{:.1f}"),
    ("peak MB", "peak_mb", "{:.0f}"),
]
# What a fit was rather than how well it did: shown per row, not averaged. ``features``: the
# Fourier features its network read (``encoding="auto"`` restarts a fit with them halfway).
NOT_AVERAGED = {"fourier_features"}
# The measures whose lowest and highest over the seeds ``--seeds`` reports.
SPREAD_COLUMNS = ["chamfer_exact", "hausdorff_exact", "normal_mean_oriented", "edge_iou", "genus"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--only", choices=["quality", "steps", "step-parts", "throughput"], action="append")
    parser.add_argument(
        "--configs", default=",".join(default_configs()), help="comma-separated, from: " + ", ".join(all_configs())
    )
    parser.add_argument("--clouds", default=",".join(CLOUDS), help="shape or shape/points file, comma-separated")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="override a FitParams field")
    parser.add_argument(
        "--seeds", help="comma-separated: each pair fitted once per seed, with the seeds' mean and range"
    )
    parser.add_argument(
        "--jobs", type=int, default=1, help="quality fits at once, the cores split among them (default 1)"
    )
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--fits", type=Path, help="keep the fitted networks here, and extract those it holds again")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "latest.md")
    parser.add_argument("--one", nargs=2, metavar=("CONFIG", "CLOUD"), help=argparse.SUPPRESS)
    parser.add_argument("--threads", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    overrides = dict(item.split("=", 1) for item in args.set)
    if args.one:
        print(json.dumps(run_one(args.one[0], args.one[1], args.data, overrides, args.threads, args.fits)))
        return 0
    seeds = [int(seed) for seed in args.seeds.split(",")] if args.seeds else None
    if seeds is not None and "seed" in overrides:
        parser.error("--seeds and --set seed= name the seed twice; give one of them")
    if args.jobs < 1:
        parser.error("--jobs must be at least 1")
    if not args.data.is_dir():
        print(f"bench: {args.data} is missing (the sample shapes of ../shared/data)", file=sys.stderr)
        return 2

    parts = args.only or ["quality", "steps", "throughput"]
    command = "python bench/run.py " + " ".join(sys.argv[1:])
    shared = f"; {args.jobs} fits at once, {fit_threads(args.jobs)} threads each" if args.jobs > 1 else ""
    sections = [f"Made by `{command.strip()}` on {datetime.now(UTC):%Y-%m-%d %H:%M} UTC, {machine()}{shared}."]
    if "quality" in parts:
        configs, clouds = args.configs.split(","), args.clouds.split(",")
        sections.append(quality(configs, clouds, args.data, overrides, seeds, args.jobs, args.fits))
    if "steps" in parts:
        sections.append(steps(overrides))
    if "step-parts" in parts:  # after "steps": its process set-up tunes the allocator, which stays
        sections.append(step_parts(overrides))
    if "throughput" in parts:
        sections.append(throughput(args.data, overrides))
    report = "\n\n".join(sections) + "\n"
    print(report)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(report)
    print(f"written to {args.out}", file=sys.stderr)
    return 0


def all_configs() -> list[str]:
    return [*CONFIGS, *BASELINES]


def default_configs() -> list[str]:
    import importlib.util

    return all_configs() if importlib.util.find_spec("open3d") else list(CONFIGS)


def machine() -> str:
    import torch

    threads = torch.get_num_threads()
    return f"{os.cpu_count()} cores, torch {torch.__version__}, {threads} threads, Python {platform.python_version()}"


# --- quality ---------------------------------------------------------------------------------


def configure_core(threads: int | None = None, tune_malloc: bool = True) -> None:
    """Set up this process as ``edgerecon fit`` and the worker do (EDGERECON_COMPILE is honoured)."""
    from core.runtime import configure
    from worker.settings import Settings

    configure(compile=Settings().compile, threads=threads, tune_malloc=tune_malloc)


def params_for(config: str, overrides: dict):
    from core.params import FitParams

    return FitParams(**{**CONFIGS[config], **overrides})


def run_one(
    config: str, cloud: str, data: Path, overrides: dict, threads: int | None = None, fits: Path | None = None
) -> dict:
    """Fit one cloud with one configuration in this process (on ``threads`` torch threads, None:
    torch's default), or take the fit from ``fits`` (``fitted``); its scores, times and peak memory."""
    from core.ply import read_points
    from core.reconstruct import extract_outputs
    from evaluation.metrics import edge_chamfer
    from evaluation.sample_data import evaluate_shape

    with tempfile.TemporaryDirectory() as variants:
        shape_dir, points_file = resolve_cloud(cloud, data, Path(variants))
        if config in BASELINES:
            return run_baseline(shape_dir, points_file)
        configure_core(threads)
        points = read_points(shape_dir / points_file)
        params = params_for(config, overrides)
        model, fit_seconds = fitted(points, params, cloud, fits)
        result = extract_outputs(model, points, params)
        result.timings = {"fit_seconds": fit_seconds, **result.timings}
        scores = evaluate_shape(result.mesh, result.normals, result.edge_indices, shape_dir, points_file=points_file)
        scores.update(mesh_scores(result.mesh, shape_dir))
        true_edges = np.load(shape_dir / "edges_gt.npy")
    scores["curve_ecd"] = float("nan")
    if result.curves and len(true_edges):
        scores["curve_ecd"] = edge_chamfer(np.concatenate([curve.points for curve in result.curves]), true_edges)
    peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    timings = {**result.timings, "peak_mb": peak_kb / 1024}
    return {**scores, **timings, "fourier_features": model.features, "edge_points": len(result.edge_indices)}


# The parameters that only the extraction reads: fits that differ in these alone are the same fit.
EXTRACTION_FIELDS = ("extraction", "edge_angle", "edge_width", "resolution")


def fitted(points: np.ndarray, params, cloud: str, fits: Path | None):
    """The network fitted to ``points`` (N, 3) with ``params``, and the seconds its fit took: from
    ``fits`` when it holds this fit (one file per cloud, by its points, and fitting parameters),
    else fitted now (and written there, whole or not at all)."""
    import torch

    from core.network import ImplicitNetwork
    from core.reconstruct import fit_cloud

    fitting = {name: value for name, value in params.model_dump().items() if name not in EXTRACTION_FIELDS}
    key = hashlib.sha256(points.tobytes() + json.dumps(fitting, sort_keys=True).encode()).hexdigest()[:16]
    path = fits / f"{key}.pt" if fits is not None else None
    if path is not None and path.exists():
        saved = torch.load(path, weights_only=True)
        # The network has Fourier features where its fit read them (encoding "auto" decides in the fit).
        features = len(saved["state"]["frequencies"])
        model = ImplicitNetwork(params.width, params.depth, params.beta, features=features)
        model.load_state_dict(saved["state"])
        return model, float(saved["fit_seconds"])
    started = time.perf_counter()
    model = fit_cloud(points, params)
    seconds = time.perf_counter() - started
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(".partial")
        torch.save({"state": model.state_dict(), "fit_seconds": seconds, "cloud": cloud, "params": fitting}, partial)
        partial.replace(path)
    return model, seconds


def mesh_scores(mesh, shape_dir: Path) -> dict:
    """What a fit's and Poisson's meshes are scored on beyond the data's measures: the genus
    (NaN unless watertight); the faces of the mesh as its OBJ file holds it (8 decimals) that
    pass through or touch another (``core.intersections``): what a mesh checker finds in the file
    a user gets; and the worst vertex, the exact distance of the mesh vertex farthest from the true
    surface (``gt.ply`` in ``shape_dir``). The sampled d_H draws its mesh samples by area, so one
    vertex moved anywhere redraws them all and moves it by up to 0.002; the worst vertex moves only
    where a vertex near it does."""
    import trimesh

    from core.intersections import crossing_faces
    from core.mesh_formats import mesh_file, read_obj
    from evaluation.metrics import distance_to_mesh

    written = read_obj(mesh_file(mesh, "obj"))
    truth = trimesh.load(shape_dir / "gt.ply", force="mesh", process=False)
    return {
        "genus": (2 - mesh.euler_number) / 2 if mesh.is_watertight else float("nan"),
        "crossing_faces": len(crossing_faces(written.vertices, written.faces, np.arange(len(written.faces)))),
        "worst_vertex": float(distance_to_mesh(np.asarray(mesh.vertices), truth.vertices, truth.faces).max()),
    }


def resolve_cloud(cloud: str, data: Path, variants: Path) -> tuple[Path, str]:
    """The shape folder and input file of a cloud name: ``cube`` is ``points.ply`` of ``cube``,
    ``box_hole/points_4096.ply`` that file, ``cube/open`` the open variant written under
    ``variants`` (evaluation.open_clouds: the points beyond a plane or in a ball deleted).
    """
    from evaluation.open_clouds import OPEN_POINTS, write_open_variant

    shape, _, points_file = cloud.partition("/")
    if points_file == "open":
        return write_open_variant(data / shape, variants), OPEN_POINTS
    return data / shape, points_file or "points.ply"


def run_baseline(shape_dir: Path, points_file: str) -> dict:
    """Screened Poisson of one cloud in this process, scored like a fit; edge scores NaN (no edges)."""
    import trimesh
    from speed import screened_poisson  # bench/speed.py, beside this file

    from evaluation.sample_data import evaluate_shape

    vertices, faces, normals, stages = screened_poisson(shape_dir / points_file)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    scores = evaluate_shape(mesh, normals, np.zeros(0, dtype=np.int64), shape_dir, points_file=points_file)
    for key in ("edge_precision", "edge_recall", "edge_iou", "ecd", "edge_false_share", "curve_ecd"):
        scores[key] = float("nan")
    scores.update(mesh_scores(mesh, shape_dir))
    peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    timings = {"fit_seconds": stages["normals_seconds"], "extract_seconds": stages["poisson_seconds"]}
    return {**scores, **timings, "peak_mb": peak_kb / 1024, "edge_points": 0}


def quality(
    configs: list[str],
    clouds: list[str],
    data: Path,
    overrides: dict,
    seeds: list[int] | None = None,
    jobs: int = 1,
    fits: Path | None = None,
) -> str:
    """The per-shape table and the averages; with ``seeds``, a row per seed and a table of the seeds'
    mean and range, since one fit's d_H moves by about 15 % between seeds (docs/benchmarks.md).
    ``jobs`` fits run at once, each on its share of the cores (the times are then those of a
    shared machine)."""
    runs = [(config, cloud, seed) for config in configs for cloud in clouds for seed in seeds or [None]]
    threads = fit_threads(jobs) if jobs > 1 else None
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        results = dict(zip(runs, pool.map(lambda run: fit_in_subprocess(*run, data, overrides, threads, fits), runs)))
    params = params_for("default", overrides)
    rows = [
        ((cloud, config, *seed_cell(seed)), results[config, cloud, seed])
        for cloud in clouds
        for config in configs
        for seed in seeds or [None]
    ]
    lines = [
        "## Quality and time per shape",
        "",
        f"Shipped defaults: {params.model_dump()}.",
        "Configurations: "
        + "; ".join(f"`{name}` = {BASELINES.get(name) or CONFIGS[name] or 'the defaults'}" for name in configs)
        + ".",
        "",
        table(["cloud", "config", *seed_cell("seed" if seeds else None)], rows),
        "",
    ]
    if seeds:
        pairs = [(cloud, config) for config in configs for cloud in clouds]
        per_pair = {pair: [results[pair[1], pair[0], seed] for seed in seeds] for pair in pairs}
        lines += [
            f"## Over seeds {', '.join(map(str, seeds))}",
            "",
            "The mean of each measure over the seeds:",
            "",
            table(["cloud", "config"], [(pair, average(per_pair[pair])) for pair in pairs]),
            "",
            "The range (lowest to highest) over the seeds:",
            "",
            spread_table(pairs, per_pair),
            "",
        ]
    lines += [
        "## Averages",
        "",
        "Surface and normal scores over the clouds with 16,384 points and noise 0.005 (the first four), edge "
        "scores over those of them with sharp edges, as the data's README defines the averages"
        + (", and over the seeds." if seeds else "."),
        "",
        table(
            ["config"],
            [
                ((config,), average([results[run] for run in runs if run[0] == config and "/" not in run[1]]))
                for config in configs
            ],
        ),
    ]
    return "\n".join(lines)


def fit_threads(jobs: int) -> int:
    """Torch threads for each of ``jobs`` fits at once: the cores split evenly, at least one."""
    return max(1, (os.cpu_count() or 1) // jobs)


def fit_in_subprocess(
    config: str, cloud: str, seed: int | None, data: Path, overrides: dict, threads: int | None, fits: Path | None
) -> dict | None:
    """``run_one`` in a fresh process (so that its peak memory is its own); None if it failed."""
    label = f"{cloud} with {config}" + (f", seed {seed}" if seed is not None else "")
    print(f"fitting {label}...", file=sys.stderr, flush=True)
    if seed is not None:
        overrides = {**overrides, "seed": seed}
    command = [sys.executable, __file__, "--one", config, cloud, "--data", str(data)]
    command += [f"--set={name}={value}" for name, value in overrides.items()]
    if fits is not None:
        command += ["--fits", str(fits)]
    env = None
    if threads is not None:  # OpenMP reads its count at start; torch's own is set in run_one
        command += ["--threads", str(threads)]
        env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    done = subprocess.run(command, capture_output=True, text=True, check=False, env=env)
    if done.returncode != 0:
        print(f"{label} failed:\n{done.stderr[-2000:]}", file=sys.stderr)
        return None
    result = json.loads(done.stdout.strip().splitlines()[-1])
    scores = ", ".join(f"{name} {fmt.format(result[key])}" for name, key, fmt in COLUMNS[:10])
    print(f"  {label}: {scores}", file=sys.stderr, flush=True)
    return result


def seed_cell(seed: object) -> list[str]:
    """The seed column's cell of a row: none when the run names no seeds."""
    return [] if seed is None else [str(seed)]


def spread_table(pairs: list[tuple[str, str]], per_pair: dict) -> str:
    """Lowest to highest of the main measures over the seeds, per (cloud, config)."""
    formats = {key: (name, fmt) for name, key, fmt in COLUMNS}
    lines = ["| cloud | config | " + " | ".join(formats[key][0] for key in SPREAD_COLUMNS) + " |"]
    lines.append("|" + "---|" * (2 + len(SPREAD_COLUMNS)))
    for pair in pairs:
        cells = []
        for key in SPREAD_COLUMNS:
            values = [r[key] for r in per_pair[pair] if r and r.get(key) is not None and r[key] == r[key]]
            fmt = formats[key][1]
            cells.append(f"{fmt.format(min(values))} – {fmt.format(max(values))}" if values else "–")
        lines.append("| " + " | ".join([*pair, *cells]) + " |")
    return "\n".join(lines)


def average(results: list[dict | None]) -> dict | None:
    results = [r for r in results if r]
    if not results:
        return None
    mean = {}
    for _, key, _ in COLUMNS:
        values = [r[key] for r in results if r.get(key) is not None and r[key] == r[key]]  # NaN: smooth shapes
        mean[key] = statistics.fmean(values) if values and key not in NOT_AVERAGED else float("nan")
    return mean


def table(heads: list[str], rows: list[tuple]) -> str:
    lines = ["| " + " | ".join(heads + [name for name, _, _ in COLUMNS]) + " |"]
    lines.append("|" + "---|" * (len(heads) + len(COLUMNS)))
    for keys, result in rows:
        cells = [
            fmt.format(result[key]) if result and key in result and result[key] == result[key] else "–"
            for _, key, fmt in COLUMNS
        ]
        lines.append("| " + " | ".join(list(keys) + cells) + " |")
    return "\n".join(lines)


# --- one training step -------------------------------------------------------------------------


def steps(overrides: dict, repeats: int = 30) -> str:
    import torch

    from core.fit import matmul_dtype_for, step_loss
    from core.network import ImplicitNetwork
    from core.sampling import draw_batch

    configure_core(tune_malloc=False)  # as before: the step's own allocations, glibc's defaults
    params = params_for("default", overrides)
    cloud, scales, free_space = _cube_step_inputs()
    batch, samples, _ = draw_batch(cloud, scales, params.batch_points, torch.Generator().manual_seed(0))
    variants = {
        "eikonal only (λ2 = 0)": params.model_copy(update={"lambda2": 0.0}),
        "with the Laplacian term": params,
    }
    dtypes = {"float32": None, "bfloat16": torch.bfloat16} if matmul_dtype_for(params.precision) else {"float32": None}
    models = {}
    times = {(name, dtype): [] for name in variants for dtype in dtypes}
    for _ in range(repeats + 3):
        for (name, dtype_name), samples_ms in times.items():
            model = models.setdefault((name, dtype_name), ImplicitNetwork(params.width, params.depth, params.beta))
            optimizer = torch.optim.Adam(model.parameters(), lr=1e-5)
            started = time.perf_counter()
            loss = step_loss(model, batch, samples, variants[name], free_space, dtypes[dtype_name])[0]
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            samples_ms.append((time.perf_counter() - started) * 1000)
    peak = {name: matmul_peak(dtype) for name, dtype in (("float32", torch.float32), ("bfloat16", torch.bfloat16))}
    rows_all = len(batch) + len(samples)
    lines = [
        "## One training step",
        "",
        f"{params.batch_points} input points, {len(samples)} eikonal samples, width {params.width}, "
        f"depth {params.depth}, {torch.get_num_threads()} threads; median of {repeats} alternated runs after 3 "
        "warm-ups. GFLOP/s counts the matrix products of the forward and backward passes (the element-wise work "
        "is not counted). Peaks: "
        + ", ".join(f"{name} {value:.0f} GFLOP/s" for name, value in peak.items())
        + " (a 16,384 x 256 by 256 x 256 product, median of 30).",
        "",
        "| step | matmul dtype | median ms | vs eikonal only | GFLOP/s | of the float32 peak "
        "| of the same dtype's peak |",
        "|---|---|---|---|---|---|---|",
    ]
    for dtype_name in dtypes:
        base = statistics.median(times["eikonal only (λ2 = 0)", dtype_name][3:])
        for name, variant in variants.items():
            ms = statistics.median(times[name, dtype_name][3:])
            laplacian_rows = len(batch) if variant.lambda2 > 0 else 0
            flops = step_flops(rows_all, laplacian_rows, params.width, params.depth)
            gflops = flops / ms / 1e6
            lines.append(
                f"| {name} | {dtype_name} | {ms:.1f} | {ms / base:.2f}x | {gflops:.0f} | "
                f"{gflops / peak['float32']:.0%} | {gflops / peak[dtype_name]:.0%} |"
            )
    reference = ImplicitNetwork(params.width, params.depth, params.beta)
    x = torch.cat([batch, samples])
    started = time.perf_counter()
    for _ in range(3):
        from core.network import derivatives_autograd

        f, grad, lap = derivatives_autograd(reference, x[: len(batch)])
        (f.abs().mean() + (grad.norm(dim=1) - 1).square().mean() + lap.square().mean()).backward()
    autograd_ms = (time.perf_counter() - started) / 3 * 1000
    lines += [
        "",
        f"For comparison, nested autograd (the tests' reference) takes {autograd_ms:.0f} ms for the same "
        f"Laplacian on the {len(batch)} input points alone (float32, mean of 3).",
    ]
    return "\n".join(lines)


def step_parts(overrides: dict, repeats: int = 30, sizes: tuple[int, ...] = (32, 128, 512, 1024)) -> str:
    """A fit's training step timed in its parts (the draw, ``step_loss``, the backward pass, fused
    Adam), as ``core.fit`` takes it in a process set up as a fit's, at several batch sizes: what a
    step costs whatever its size (dispatch and autograd's bookkeeping) and what grows with it; with
    the compiled kernels one by one (a cloud smaller than a batch) and compiled whole (the others).
    The normal term (the fit's first half) is left out; it adds one cheap loss."""
    import torch

    from core.fit import matmul_dtype_for, step_loss
    from core.network import ImplicitNetwork
    from core.sampling import draw_batch

    configure_core()
    params = params_for("default", overrides)
    cloud, scales, free_space = _cube_step_inputs()
    dtype = matmul_dtype_for(params.precision)
    generator = torch.Generator().manual_seed(0)
    residuals = torch.ones(len(cloud))
    model = ImplicitNetwork(params.width, params.depth, params.beta)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-5, fused=True)
    warm_ups = 10
    lines = [
        "## A fit's step in its parts",
        "",
        f"The cube's points, width {params.width}, depth {params.depth}, "
        f"{'bfloat16' if dtype is not None else 'float32'} products, {torch.get_num_threads()} threads; "
        f"median ms of {repeats} steps after {warm_ups} (the step's own median, not the parts' sum).",
        "",
        "| step | input points | eikonal samples | draw | forward | backward | Adam | step |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for (whole, path), size in itertools.product([(False, "kernels"), (True, "compiled whole")], sizes):
        times: dict[str, list[float]] = {"draw": [], "forward": [], "backward": [], "Adam": [], "step": []}
        for _ in range(warm_ups + repeats):
            started = time.perf_counter()
            batch, samples, rows = draw_batch(cloud, scales, size, generator, residuals, params.residual_share)
            drawn = time.perf_counter()
            loss, _, _, batch_residuals = step_loss(model, batch, samples, params, free_space, dtype, None, whole)
            residuals[rows] = batch_residuals
            forward = time.perf_counter()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            backward = time.perf_counter()
            optimizer.step()
            ended = time.perf_counter()
            spans = ((started, drawn), (drawn, forward), (forward, backward), (backward, ended), (started, ended))
            for part, (start, end) in zip(times, spans, strict=True):
                times[part].append((end - start) * 1000)
        cells = " | ".join(f"{statistics.median(values[warm_ups:]):.2f}" for values in times.values())
        lines.append(f"| {path} | {size:,} | {len(samples):,} | {cells} |")
    return "\n".join(lines)


def _cube_step_inputs():
    """What a step of the cube's fit reads besides the network: its 16,384 points (seed 0, noise
    0.005) as a tensor (n, 3), their local scales (n,) and their free-space map."""
    import torch

    from core.sampling import FreeSpace, local_scales
    from evaluation.shapes import sample_shape

    points = sample_shape("cube", n_points=16_384, noise=0.005, seed=0).points
    cloud = torch.as_tensor(points, dtype=torch.float32)
    return cloud, torch.as_tensor(local_scales(points), dtype=torch.float32), FreeSpace(points)


def step_flops(rows: int, laplacian_rows: int, width: int, depth: int) -> float:
    """Multiply-adds x 2 of one step's matrix products: forward, and backward (input and weights).

    A row with a Laplacian carries [f; ∇f (3 columns); Δf] through each layer (5 rows); one without
    carries f forward and ∂f/∂h back (2 rows, ``ImplicitNetwork.gradient``); each row is multiplied
    once forward and twice backward."""
    carried = 5 * laplacian_rows + 2 * (rows - laplacian_rows)
    hidden = (depth - 1) * carried * width * width * 2 * 3
    first = rows * 3 * width * 2 * 2
    last = carried * width * 2 * 3
    return hidden + first + last


def matmul_peak(dtype) -> float:
    import torch

    a = torch.randn(16_384, 256).to(dtype)
    b = torch.randn(256, 256).to(dtype)
    times = []
    for _ in range(33):
        started = time.perf_counter()
        a @ b
        times.append(time.perf_counter() - started)
    return 2 * 16_384 * 256 * 256 / statistics.median(times[3:]) / 1e9


# --- worker throughput ---------------------------------------------------------------------------


def throughput(data: Path, overrides: dict, jobs: int = 4) -> str:
    cloud = data / "box_hole" / "points.ply"
    script = (
        "import sys; from core.runtime import configure; from worker.settings import Settings;"
        "configure(compile=Settings().compile, threads=int(sys.argv[1]));"
        "from core.ply import read_points; from core.params import FitParams; from core.reconstruct import reconstruct;"
        f"params = FitParams(**{overrides!r}); points = read_points({str(cloud)!r});"
        "[reconstruct(points, params) for _ in range(int(sys.argv[2]))]"
    )

    def run(processes: int, threads: int) -> float:
        started = time.perf_counter()
        children = [
            subprocess.Popen([sys.executable, "-c", script, str(threads), str(jobs // processes)], cwd=ROOT)
            for _ in range(processes)
        ]
        for child in children:
            child.wait()
        return time.perf_counter() - started

    layouts = {"1 worker x 2 threads": run(1, 2), "2 workers x 1 thread": run(2, 1)}
    lines = [
        "## Worker throughput",
        "",
        f"{jobs} default fits of box_hole (16,384 points), started together; jobs per hour on this machine. "
        "Each process pays its own start (torch import, kernels loaded from torch.compile's disk cache).",
        "",
        "| layout | seconds for all | seconds per job (latency) | jobs per hour |",
        "|---|---|---|---|",
    ]
    for name, seconds in layouts.items():
        processes = 1 if name.startswith("1") else 2
        lines.append(f"| {name} | {seconds:.0f} | {seconds / (jobs / processes):.0f} | {jobs / seconds * 3600:.0f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
