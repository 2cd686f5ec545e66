"""The ``edgerecon fit`` command, run as a user runs it (a subprocess), on the example cloud.

The cloud is moved and scaled first (x100, shifted) so that the outputs' mapping back to the
input's coordinates is checked too. The network is kept small and torch on one thread so the run
takes seconds on a shared two-core machine.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from core.mesh_formats import convert_obj
from core.ply import read_points
from evaluation.shapes import write_ply
from tests.helpers import EXAMPLE_CLOUD as EXAMPLE

SCALE, SHIFT = 100.0, np.array([10.0, -5.0, 3.0])
FAST = ["--iterations", "30", "--resolution", "32", "--width", "64", "--depth", "2", "--batch-points", "512"]


def command() -> list[str]:
    script = Path(sys.executable).parent / "edgerecon"
    return [str(script)] if script.exists() else [sys.executable, "-m", "service.cli"]


def run(*args, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    return subprocess.run([*command(), *map(str, args)], cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def moved_cloud(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("input") / "part.ply"
    write_ply(path, read_points(EXAMPLE) * SCALE + SHIFT)
    return path


@pytest.fixture(scope="module")
def fitted(moved_cloud, tmp_path_factory):
    """One successful run, shared by the checks of its three outputs."""
    parent = tmp_path_factory.mktemp("run")
    result = run("fit", moved_cloud, "--out", parent / "out", "--tau", "2", "--extraction", "mc", *FAST, cwd=parent)
    assert result.returncode == 0, result.stderr
    return parent, result


def test_help_lists_the_commands(tmp_path):
    result = run("--help", cwd=tmp_path)
    assert result.returncode == 0 and "fit" in result.stdout
    result = run("fit", "--help", cwd=tmp_path)
    assert result.returncode == 0 and "--tau" in result.stdout and "--no-edge-sampling" in result.stdout


def test_fit_writes_exactly_the_three_outputs(fitted):
    parent, result = fitted
    assert sorted(p.name for p in parent.iterdir()) == ["out"], "a staging folder was left behind"
    assert sorted(p.name for p in (parent / "out").iterdir()) == ["edges.json", "mesh.obj", "normals.json"]
    assert "wrote" in result.stdout and "mesh.obj" in result.stdout
    assert "Traceback" not in result.stderr


def test_mesh_loads_in_input_coordinates(fitted, moved_cloud):
    import trimesh

    mesh = trimesh.load(fitted[0] / "out" / "mesh.obj", force="mesh", process=False)
    assert len(mesh.faces) > 500 and len(mesh.vertices) > 250
    points = read_points(moved_cloud)
    low, high = points.min(axis=0), points.max(axis=0)
    slack = 0.15 * SCALE  # the grid's margin and rounding, in input units
    assert (mesh.bounds[0] >= low - slack).all() and (mesh.bounds[1] <= high + slack).all()
    assert np.linalg.norm(mesh.vertices.mean(axis=0) - SHIFT) < 0.2 * SCALE


def test_normals_one_unit_vector_per_point_mostly_outward(fitted, moved_cloud):
    normals = np.array(json.loads((fitted[0] / "out" / "normals.json").read_text())["normals"])
    points = read_points(moved_cloud)
    assert normals.shape == points.shape
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    # 30 steps from the initial sphere: the normals already point away from the cube's centre.
    outward = ((points - SHIFT) * normals).sum(axis=1) > 0
    assert outward.mean() > 0.9


def test_edges_json_follows_the_design(fitted, moved_cloud):
    edges = json.loads((fitted[0] / "out" / "edges.json").read_text())
    assert set(edges) == {"tau", "count", "indices", "points", "laplacian", "curves"}
    assert edges["tau"] == 2.0 and edges["curves"] == []  # marching cubes: edges by |Δf| > tau, no curves
    points = read_points(moved_cloud)
    indices = np.array(edges["indices"], dtype=np.int64)
    assert 0 < edges["count"] == len(indices) == len(edges["points"]) == len(edges["laplacian"]) < len(points)
    assert (np.diff(indices) > 0).all() and indices[0] >= 0 and indices[-1] < len(points)
    np.testing.assert_allclose(np.array(edges["points"]), points[indices], rtol=0, atol=1e-9)
    assert (np.array(edges["laplacian"]) > edges["tau"] - 1e-3).all()


def _write(kind: str, folder: Path) -> Path:
    path = folder / f"{kind}.ply"
    if kind == "nan":
        points = read_points(EXAMPLE)[:300].copy()
        points[12, 1] = np.nan
        write_ply(path, points)
    elif kind == "not_a_ply":
        path.write_text("x y z\n0 0 0\n1 0 0\n")
    elif kind == "too_few":
        write_ply(path, read_points(EXAMPLE)[:20])
    elif kind == "list_x":  # once a ValueError and a traceback
        header = "ply\nformat ascii 1.0\nelement vertex 200\nproperty list uchar float x\nproperty float y\n"
        path.write_bytes((header + "property float z\nend_header\n").encode() + b"1 0.5 0.25 0.125\n" * 200)
    return path


@pytest.mark.parametrize(
    "kind, options, code, phrase",
    [
        ("nan", [], 1, "NaN or infinite"),
        ("not_a_ply", [], 1, "not a PLY"),
        ("too_few", [], 1, "at least"),
        ("list_x", [], 1, "list properties"),
        ("missing", [], 1, "No such file"),
        ("good", ["--iterations", "0"], 2, "--iterations"),
        ("good", ["--resolution", "8"], 2, "--resolution"),
        ("good", ["--tau", "nan"], 2, "--tau"),
        ("good", ["--lambda2", "-1"], 2, "--lambda2"),
    ],
)
def test_errors_exit_nonzero_with_one_line_and_no_output(tmp_path, kind, options, code, phrase):
    if kind == "good":
        shutil.copy(EXAMPLE, tmp_path / "good.ply")
        source = tmp_path / "good.ply"
    elif kind == "missing":
        source = tmp_path / "missing.ply"
    else:
        source = _write(kind, tmp_path)
    before = sorted(p.name for p in tmp_path.iterdir())
    result = run("fit", source, "--out", tmp_path / "out", *options, cwd=tmp_path)
    assert result.returncode == code, result.stderr
    assert "Traceback" not in result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("edgerecon") and phrase.lower() in lines[0].lower()
    assert sorted(p.name for p in tmp_path.iterdir()) == before, "an output or staging folder was left"


def test_a_bad_setting_in_the_environment_exits_2_with_one_line_naming_it(tmp_path):
    env = {**os.environ, "EDGERECON_COMPILE": "perhaps", "PYTHONWARNINGS": "ignore"}
    result = subprocess.run(
        [*command(), "fit", str(EXAMPLE), "--out", str(tmp_path / "out")], env=env, capture_output=True, text=True
    )
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.strip().startswith("edgerecon: EDGERECON_COMPILE: ") and len(result.stderr.splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_unparsable_option_value_is_an_argparse_error(tmp_path):
    result = run("fit", EXAMPLE, "--out", tmp_path / "out", "--resolution", "abc", cwd=tmp_path)
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert "invalid int value: 'abc'" in result.stderr.splitlines()[-1]
    assert not (tmp_path / "out").exists()


def test_failure_after_fitting_leaves_no_staging_folder(tmp_path, monkeypatch, capsys):
    """In-process: the output path is an existing file, so writing fails after the fit."""
    from core import network
    from service import cli

    monkeypatch.setenv("EDGERECON_COMPILE", "0")  # the command configures the process: eager kernels
    monkeypatch.setattr(network._kernels, "compiled", network._kernels.compiled)  # restored afterwards
    (tmp_path / "out").write_text("in the way")
    tiny = ["--iterations", "2", "--resolution", "32", "--width", "16", "--depth", "1", "--batch-points", "64"]
    code = cli.main(["fit", str(EXAMPLE), "--out", str(tmp_path / "out"), *tiny])
    assert code == 1
    assert "edgerecon:" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    assert (tmp_path / "out").read_text() == "in the way"


def test_format_writes_the_mesh_in_each_format_asked_with_the_same_counts(tmp_path, monkeypatch, capsys):
    """In-process, on a tiny fit: ``--format ply,stl,glb,obj`` writes the four meshes through the one
    writer, and ``--preview`` adds preview.json (which a plain fit does not write)."""
    import trimesh

    from core import network
    from service import cli

    monkeypatch.setenv("EDGERECON_COMPILE", "0")
    monkeypatch.setattr(network._kernels, "compiled", network._kernels.compiled)
    tiny = ["--iterations", "2", "--resolution", "32", "--width", "16", "--depth", "1", "--batch-points", "64"]
    code = cli.main(
        ["fit", str(EXAMPLE), "--out", str(tmp_path / "out"), "--format", "ply,STL, glb,obj", "--preview", *tiny]
    )
    assert code == 0, capsys.readouterr().err
    written = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert written == ["edges.json", "mesh.glb", "mesh.obj", "mesh.ply", "mesh.stl", "normals.json", "preview.json"]
    preview = json.loads((tmp_path / "out" / "preview.json").read_text())
    assert preview["total"] == len(preview["points"]) == len(read_points(EXAMPLE))
    assert "mesh.ply, mesh.stl, mesh.glb, mesh.obj" in capsys.readouterr().out
    obj = trimesh.load(tmp_path / "out" / "mesh.obj", process=False, force="mesh")
    for fmt in ("ply", "stl", "glb"):
        mesh = trimesh.load(tmp_path / "out" / f"mesh.{fmt}", force="mesh")  # STL stores triangles: merged here
        assert (len(mesh.vertices), len(mesh.faces)) == (len(obj.vertices), len(obj.faces)), fmt
        np.testing.assert_allclose(mesh.bounds, obj.bounds, atol=1e-5)
        # The files the API serves for the same job: made from the stored OBJ.
        assert (tmp_path / "out" / f"mesh.{fmt}").read_bytes() == convert_obj(
            (tmp_path / "out" / "mesh.obj").read_bytes(), fmt
        ), fmt


def test_a_cloud_with_stray_points_says_how_many_were_left_out_of_the_fit(tmp_path, monkeypatch, capsys):
    """In-process, on a tiny fit: the example cloud with 30 points scattered round it (core.strays)."""
    from core import network
    from service import cli

    monkeypatch.setenv("EDGERECON_COMPILE", "0")
    monkeypatch.setattr(network._kernels, "compiled", network._kernels.compiled)
    points = read_points(EXAMPLE)
    low, high = points.min(axis=0), points.max(axis=0)
    size = (high - low).max()
    scattered = np.random.default_rng(0).uniform(low - 0.3 * size, high + 0.3 * size, size=(30, 3))
    write_ply(tmp_path / "strays.ply", np.concatenate([points, scattered]))
    tiny = ["--iterations", "2", "--resolution", "32", "--width", "16", "--depth", "1", "--batch-points", "64"]
    assert cli.main(["fit", str(tmp_path / "strays.ply"), "--out", str(tmp_path / "out"), *tiny]) == 0
    out = capsys.readouterr().out
    assert "stray points left out of the fit" in out, out
    assert cli.main(["fit", str(EXAMPLE), "--out", str(tmp_path / "clean"), *tiny]) == 0
    assert "left out of the fit" not in capsys.readouterr().out


def test_an_unknown_format_is_refused_before_anything_runs(tmp_path):
    result = run("fit", EXAMPLE, "--out", tmp_path / "out", "--format", "obj,fbx", cwd=tmp_path)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "'obj,fbx': expected formats among obj, ply, stl, glb" in result.stderr.splitlines()[-1]
    assert not (tmp_path / "out").exists()


def test_a_fit_that_starts_again_with_features_says_so_and_writes_its_outputs(tmp_path, monkeypatch, capsys):
    """In-process, on a tiny fit made to pass the residual limits: one line on stderr, the outputs."""
    from core import fit, network
    from service import cli

    monkeypatch.setenv("EDGERECON_COMPILE", "0")
    monkeypatch.setattr(network._kernels, "compiled", network._kernels.compiled)
    monkeypatch.setattr(fit, "CHECKED_ITERATIONS", 4)
    monkeypatch.setattr(fit, "residual_tail", lambda model, points, neighbours: (float("inf"), float("inf")))
    tiny = ["--iterations", "4", "--resolution", "32", "--width", "16", "--depth", "1", "--batch-points", "64"]
    code = cli.main(["fit", str(EXAMPLE), "--out", str(tmp_path / "out"), "--features", "4", *tiny])
    err = capsys.readouterr().err
    assert code == 0, err
    assert err.count("starting again with Fourier features") == 1
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["edges.json", "mesh.obj", "normals.json"]
