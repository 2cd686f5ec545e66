"""The ``edgerecon`` command: ``fit`` runs a reconstruction in-process; ``serve`` and ``worker`` run the service."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal, cast, get_args, get_origin

from pydantic import ValidationError

from core.errors import EdgereconError
from core.outputs import MESH_FORMATS
from core.params import FitParams
from core.progress import Progress, Stage


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="edgerecon", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    fit_parser = commands.add_parser(
        "fit", help="reconstruct a PLY cloud into DIR/mesh.obj (or --format), normals.json, edges.json"
    )
    fit_parser.add_argument("input", type=Path, help="the point cloud, a PLY file")
    fit_parser.add_argument("--out", type=Path, required=True, help="output folder (created)")
    fit_parser.add_argument(
        "--format",
        type=_mesh_formats,
        default=("obj",),
        help=f"the mesh's formats, comma-separated, of {','.join(MESH_FORMATS)} (default obj): DIR/mesh.<format> each",
    )
    fit_parser.add_argument(
        "--preview",
        action="store_true",
        help="also write DIR/preview.json: a sample of at most 50,000 input points, their normals and edge flags",
    )
    _add_param_options(fit_parser)
    serve_parser = commands.add_parser(
        "serve", help="start the service: the API, N workers, and its own Redis when REDIS_URL is unset"
    )
    serve_parser.add_argument("--host", default="127.0.0.1", help="address the API listens on (default 127.0.0.1)")
    serve_parser.add_argument("--port", type=int, default=8000, help="port the API listens on (default 8000)")
    serve_parser.add_argument(
        "--workers",
        type=int,
        default=1,
        help="worker processes to start (default 1, on every core; N: cores // N each)",
    )
    serve_parser.add_argument(
        "--data-dir",
        type=Path,
        default=None,
        help="folder of the embedded Redis's data, kept across restarts (default EDGERECON_DATA_DIR, "
        "else $XDG_DATA_HOME/edgerecon or ~/.local/share/edgerecon)",
    )
    commands.add_parser("worker", help="start one more worker against REDIS_URL")
    args = parser.parse_args(argv)
    if args.command == "fit":
        return _fit(args)
    if args.command == "serve":
        from service.serve import serve

        return serve(args.host, args.port, args.workers, args.data_dir)
    if args.command == "worker":
        from worker.process import main as run_worker

        return run_worker()
    return 2


def _mesh_formats(text: str) -> tuple[str, ...]:
    """``--format``: a comma-separated list of mesh formats, in the order given, without repeats."""
    formats = tuple(dict.fromkeys(name.strip().lower() for name in text.split(",") if name.strip()))
    unknown = [name for name in formats if name not in MESH_FORMATS]
    if unknown or not formats:
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected formats among {', '.join(MESH_FORMATS)}, comma-separated (e.g. obj,ply,glb)"
        )
    return formats


def _add_param_options(parser: argparse.ArgumentParser) -> None:
    """One option per FitParams field, named after it; unset options keep the model's default."""
    for name, field in FitParams.model_fields.items():
        flag = "--" + name.replace("_", "-")
        help_text = f"{field.description} (default {field.default})"
        if field.annotation is bool:
            parser.add_argument(flag, dest=name, action=argparse.BooleanOptionalAction, default=None, help=help_text)
        elif get_origin(field.annotation) is Literal:
            parser.add_argument(flag, dest=name, choices=get_args(field.annotation), default=None, help=help_text)
        else:
            parser.add_argument(
                flag, dest=name, type=cast(Callable[[str], Any], field.annotation), default=None, help=help_text
            )


def _fit(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from worker.settings import Settings

    given = {name: getattr(args, name) for name in FitParams.model_fields if getattr(args, name) is not None}
    try:
        params = FitParams(**given)
    except ValidationError as error:
        for problem in error.errors():
            print(f"edgerecon: --{problem['loc'][0]}: {problem['msg']}", file=sys.stderr)
        return 2
    try:
        settings = Settings()
    except ValidationError as error:
        for problem in error.errors():
            print(f"edgerecon: EDGERECON_{str(problem['loc'][0]).upper()}: {problem['msg']}", file=sys.stderr)
        return 2
    try:
        from core.ply import read_points
        from core.reconstruct import reconstruct, write_outputs
        from core.runtime import configure

        configure(compile=settings.compile)
        points = read_points(args.input)
        bar = tqdm(total=params.iterations, unit="it", desc="fitting", dynamic_ncols=True)

        def progress(update: Progress) -> None:
            if update.stage == Stage.FITTING:
                if update.total != bar.total:  # the only fit whose steps grow: encoding=auto's restart
                    restart = "the residuals halfway show points the fit misses: starting again with Fourier features"
                    bar.write(restart, sys.stderr)
                    bar.total = update.total
                bar.update(update.iteration - bar.n)
                if update.losses and (update.iteration % 50 == 0 or update.iteration == update.total):
                    bar.set_postfix(loss=f"{update.losses['total']:.4f}", edges=f"{update.edge_share or 0:.1%}")
            else:
                bar.close()
                print("extracting the mesh, normals and edges...", file=sys.stderr)

        try:
            result = reconstruct(points, params, progress=progress)
        finally:
            bar.close()
        names = [*(f"mesh.{fmt}" for fmt in args.format), "normals.json", "edges.json"]
        names += ["preview.json"] if args.preview else []
        write_outputs(result, args.out, names)
    except (EdgereconError, OSError) as error:
        print(f"edgerecon: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("edgerecon: interrupted", file=sys.stderr)
        return 130
    summary = result.summary()
    meshes = ", ".join(f"mesh.{fmt}" for fmt in args.format)
    print(
        f"wrote {args.out}/{meshes} ({summary['vertices']} vertices, {summary['faces']} faces), "
        f"normals.json, edges.json ({summary['edge_points']} edge points){', preview.json' if args.preview else ''} "
        f"in {summary['timings']['fit_seconds']:.1f} s fit + {summary['timings']['extract_seconds']:.1f} s extraction"
        + (f"; {summary['stray_points']} stray points left out of the fit" if summary.get("stray_points") else "")
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
