"""core.ply.read_points: every accepted layout, every rejected input, and no torch import."""

from __future__ import annotations

import subprocess
import sys
import time
import tracemalloc

import numpy as np
import pytest

from core.errors import PointCloudError
from core.ply import MAX_POINTS, MIN_POINTS, read_points
from tests.helpers import EXAMPLE_CLOUD

HUGE = 10**12
N = 200
POINTS = np.random.default_rng(0).normal(size=(N, 3))
XYZ_FLOAT = ("float x", "float y", "float z")
FACE_LIST = "element face {n}\nproperty list uchar int vertex_indices\n"


def header(fmt: str, n: int = N, props=XYZ_FLOAT, extra: str = "", vertex: str = "vertex") -> bytes:
    lines = ["ply", f"format {fmt} 1.0", "comment made by test_ply", f"element {vertex} {n}"]
    lines += [f"property {p}" for p in props]
    return ("\n".join(lines) + "\n" + extra + "end_header\n").encode()


def ascii_rows(points: np.ndarray) -> bytes:
    return "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in points.tolist()).encode()


def ascii_ply(points: np.ndarray = POINTS, **kw) -> bytes:
    return header("ascii", len(points), **kw) + ascii_rows(points)


def binary_ply(points: np.ndarray = POINTS, dtype: str = "<f4", n: int | None = None, extra: str = "") -> bytes:
    kind = {"f4": "float", "f8": "double"}[dtype[1:]]
    fmt = "binary_little_endian" if dtype[0] == "<" else "binary_big_endian"
    props = tuple(f"{kind} {axis}" for axis in "xyz")
    return header(fmt, len(points) if n is None else n, props, extra) + points.astype(dtype).tobytes()


def triangles(count: int, size: int = 3) -> bytes:
    return (np.array([size], np.uint8).tobytes() + np.arange(size, dtype="<i4").tobytes()) * count


def assert_points(result: np.ndarray, expected: np.ndarray = POINTS, float32: bool = True) -> None:
    assert result.dtype == np.float64 and result.shape == expected.shape
    if float32:
        np.testing.assert_array_equal(result, expected.astype(np.float32).astype(np.float64))
    else:
        np.testing.assert_array_equal(result, expected)


def expect_error(data: bytes, phrase: str, **kw) -> str:
    with pytest.raises(PointCloudError) as info:
        read_points(data, **kw)
    message = str(info.value)
    assert phrase.lower() in message.lower(), message
    assert "\n" not in message and len(message) < 300
    return message


# --- accepted layouts ----------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", ["<f4", ">f4", "<f8", ">f8"])
def test_binary_endianness_and_precision(dtype):
    assert_points(read_points(binary_ply(dtype=dtype)), float32=dtype.endswith("f4"))


@pytest.mark.parametrize("kind", ["float", "double", "float32", "float64"])
def test_ascii_float_and_double(kind):
    data = header("ascii", props=tuple(f"{kind} {a}" for a in "xyz")) + ascii_rows(POINTS)
    assert_points(read_points(data), float32=kind.startswith("float") and kind != "float64")


def test_binary_extra_vertex_properties_interleaved():
    """Normals and colours around and between x, y, z are skipped; order of x y z is by name."""
    names = ["nx", "x", "y", "red", "z", "green", "blue", "ny"]
    types = ["<f4", "<f4", "<f4", "u1", "<f4", "u1", "u1", "<f4"]
    rows = np.zeros(N, dtype=list(zip(names, types)))
    rows["x"], rows["y"], rows["z"] = POINTS.T
    rows["nx"], rows["ny"], rows["red"], rows["green"], rows["blue"] = 1.0, -1.0, 255, 7, 9
    props = ("float nx", "float x", "float y", "uchar red", "float z", "uchar green", "uchar blue", "float ny")
    assert_points(read_points(header("binary_little_endian", props=props) + rows.tobytes()))


def test_binary_axes_out_of_order():
    props = ("float z", "float x", "float y")
    data = header("binary_little_endian", props=props) + POINTS[:, [2, 0, 1]].astype("<f4").tobytes()
    assert_points(read_points(data))


def test_ascii_extra_vertex_properties():
    props = ("float nx", "float x", "float y", "uchar red", "float z", "float ny")
    body = "".join(f"0.5 {x!r} {y!r} 200 {z!r} -0.25\n" for x, y, z in POINTS.tolist()).encode()
    assert_points(read_points(header("ascii", props=props) + body))


def test_binary_with_faces_keeps_vertices_in_order():
    data = binary_ply(extra=FACE_LIST.format(n=5)) + triangles(5)
    assert_points(read_points(data))


def test_ascii_with_faces_keeps_vertices_in_order():
    data = ascii_ply(extra=FACE_LIST.format(n=3)) + b"3 0 1 2\n4 0 1 2 3\n3 5 6 7\n"
    assert_points(read_points(data))


def test_binary_with_mixed_triangles_and_quads():
    data = binary_ply(extra=FACE_LIST.format(n=2)) + triangles(1, 3) + triangles(1, 4)
    assert_points(read_points(data))


def test_ascii_crlf_line_ends():
    assert_points(read_points(ascii_ply().replace(b"\n", b"\r\n")))


def test_binary_crlf_header():
    data = binary_ply()
    head, body = data.split(b"end_header\n")
    assert_points(read_points(head.replace(b"\n", b"\r\n") + b"end_header\r\n" + body))


def test_path_str_and_bytes_input(tmp_path):
    path = tmp_path / "cloud.ply"
    path.write_bytes(binary_ply())
    for source in (path, str(path), path.read_bytes(), bytearray(path.read_bytes())):
        assert_points(read_points(source))


def test_minimum_and_maximum_point_counts_are_inclusive():
    assert len(read_points(binary_ply(POINTS[:MIN_POINTS]))) == MIN_POINTS
    assert len(read_points(binary_ply(), max_points=N)) == N
    assert MIN_POINTS <= 1000 and MAX_POINTS >= 1_000_000


# --- rejected inputs -------------------------------------------------------------------------------


def test_empty_file():
    expect_error(b"", "empty")


@pytest.mark.parametrize("data", [b"hello world\n", b"\x89PNG\r\n\x1a\n" + bytes(100), b"OFF\n3 1 0\n"])
def test_not_a_ply(data):
    expect_error(data, "not a PLY")


def test_header_without_end():
    expect_error(header("ascii").replace(b"end_header\n", b""), "end_header")


@pytest.mark.parametrize(
    "data",
    [
        pytest.param(header("binary_little_endian"), id="binary-header-only"),
        pytest.param(binary_ply()[:-7], id="binary-cut-in-a-row"),
        pytest.param(binary_ply()[:-1200], id="binary-cut-rows"),
        pytest.param(binary_ply(dtype="<f8")[: len(header("binary_little_endian")) + 12], id="binary-one-row"),
    ],
)
def test_truncated_binary(data):
    message = expect_error(data, "binary PLY")
    assert "truncated" in message


@pytest.mark.parametrize(
    "data, phrase",
    [
        pytest.param(header("ascii"), "declares 200 rows", id="ascii-header-only"),
        pytest.param(header("ascii") + ascii_rows(POINTS[:150]), "holds only 150 lines", id="ascii-missing-rows"),
        pytest.param(ascii_ply()[:-20], "early end-of-line", id="ascii-cut-in-a-row"),
    ],
)
def test_truncated_ascii(data, phrase):
    expect_error(data, phrase)


def test_binary_trailing_garbage():
    expect_error(binary_ply() + bytes(100), "100 bytes more than its header declares")


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_no_vertex_element(fmt):
    data = header(fmt, vertex="point") + (ascii_rows(POINTS) if fmt == "ascii" else POINTS.astype("<f4").tobytes())
    expect_error(data, "no 'vertex' element")


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
@pytest.mark.parametrize("missing", ["x", "z"])
def test_missing_coordinate(fmt, missing):
    props = tuple(f"float {'w' if a == missing else a}" for a in "xyz")
    body = ascii_rows(POINTS) if fmt == "ascii" else POINTS.astype("<f4").tobytes()
    message = expect_error(header(fmt, props=props) + body, "no ")
    assert f" {missing}" in message


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("fmt", ["ascii", "binary"])
def test_non_finite_coordinates(value, fmt):
    points = POINTS.copy()
    points[5, 1] = value
    points[17, 2] = value
    data = ascii_ply(points) if fmt == "ascii" else binary_ply(points)
    message = expect_error(data, "NaN or infinite")
    assert "2 points" in message and "vertex 5" in message


def test_too_few_points():
    message = expect_error(binary_ply(POINTS[: MIN_POINTS - 1]), "at least")
    assert str(MIN_POINTS) in message and str(MIN_POINTS - 1) in message


def test_too_many_points():
    message = expect_error(binary_ply(), "at most", max_points=150)
    assert "150" in message and str(N) in message


def test_all_points_equal():
    expect_error(binary_ply(np.full((N, 3), 0.25)), "no surface to fit")


def test_collinear_points():
    line = np.outer(np.linspace(-1, 1, N), [0.3, -2.0, 1.0]) + [5.0, 6.0, 7.0]
    expect_error(ascii_ply(line), "one line")
    # A thin but genuinely planar strip is a surface and is accepted.
    strip = line + np.outer(np.resize([0.0, 1e-3], N), [1.0, 0.0, 0.0])
    assert len(read_points(ascii_ply(strip))) == N


def _fails_fast(data: bytes, phrase: str) -> None:
    """Raises the error quickly and without allocating anything near the declared size."""
    tracemalloc.start()
    started = time.perf_counter()
    try:
        expect_error(data, phrase)
    finally:
        elapsed = time.perf_counter() - started
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert elapsed < 0.5, elapsed
    assert peak < 5 * 2**20, peak


@pytest.mark.parametrize("count", [10**7, HUGE, 2**64])
def test_huge_vertex_count_binary(count):
    _fails_fast(binary_ply(n=count), "binary PLY")


@pytest.mark.parametrize("count", [10**7, HUGE])
def test_huge_vertex_count_ascii(count):
    _fails_fast(header("ascii", count) + ascii_rows(POINTS), f"declares {count} rows")


@pytest.mark.parametrize("count", [10**7, HUGE])
def test_huge_face_count_ascii(count):
    data = ascii_ply(extra=FACE_LIST.format(n=count)) + b"3 0 1 2\n"
    _fails_fast(data, f"declares {count + N} rows")


@pytest.mark.parametrize("count", [10**7, HUGE])
def test_huge_face_count_binary(count):
    _fails_fast(binary_ply(extra=FACE_LIST.format(n=count)) + triangles(2), "binary PLY")


def test_huge_face_count_binary_without_face_data():
    _fails_fast(binary_ply(extra=FACE_LIST.format(n=HUGE)), "binary PLY")


@pytest.mark.parametrize("bad", ["1.2.3", "abc", "0x1p3", "--1"])
def test_malformed_number(bad):
    rows = ascii_rows(POINTS).split(b"\n")
    rows[3] = f"{bad} 0.5 0.5".encode()
    expect_error(header("ascii") + b"\n".join(rows), "malformed ASCII PLY")


def test_extra_column_in_ascii_row():
    rows = ascii_rows(POINTS).split(b"\n")
    rows[42] += b" 7.0"
    message = expect_error(header("ascii") + b"\n".join(rows), "malformed ASCII PLY")
    assert "row 42" in message


def test_missing_column_in_ascii_row():
    rows = ascii_rows(POINTS).split(b"\n")
    rows[9] = b"0.5 0.5"
    message = expect_error(header("ascii") + b"\n".join(rows), "malformed ASCII PLY")
    assert "row 9" in message


def test_binary_with_comment_mentioning_format_ascii():
    data = binary_ply().replace(b"end_header", b"comment converted from format ascii\nend_header")
    assert_points(read_points(data))


# --- shared sample data and imports --------------------------------------------------------------


def test_shared_binary_and_ascii_read_identically(shared_data):
    folders = sorted(p for p in shared_data.iterdir() if (p / "points.ply").exists())
    assert folders
    for folder in folders:
        binary = read_points(folder / "points.ply")
        assert binary.shape == (16_384, 3)
        np.testing.assert_array_equal(binary, read_points(folder / "points_ascii.ply"))
        labels = np.load(folder / "labels.npz")
        np.testing.assert_array_equal(binary, labels["points"].astype(np.float64))


def test_shared_mesh_vertices_in_file_order(shared_data):
    import trimesh

    path = shared_data / "sphere" / "gt.ply"
    mesh = trimesh.load(path, process=False)
    assert len(mesh.faces) > 0
    np.testing.assert_array_equal(read_points(path), mesh.vertices)


def test_reading_and_params_do_not_import_torch():
    code = (
        "import sys, core.ply, core.params, core.errors;"
        "from core.params import FitParams; FitParams();"
        "core.ply.read_points(open(sys.argv[1], 'rb').read());"
        "print('torch' in sys.modules)"
    )
    command = [sys.executable, "-c", code, str(EXAMPLE_CLOUD)]
    result = subprocess.run(command, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "False"


# --- bounded cost, and only our own error on any input -------------------------------------------


def test_huge_coordinates_are_checked_without_overflow():
    """Finite but huge doubles once overflowed the covariance into LinAlgError (a 500 in the API)."""
    points = POINTS * 1e300
    assert read_points(binary_ply(points, dtype="<f8")).shape == (N, 3)
    expect_error(binary_ply(np.outer(np.arange(N), [1e300, 1e300, 0]), dtype="<f8"), "one line")


def test_compact_keeps_float32_clouds_in_float32_and_doubles_in_float64():
    assert read_points(binary_ply(), compact=True).dtype == np.float32
    np.testing.assert_array_equal(read_points(binary_ply(), compact=True), read_points(binary_ply()))
    assert read_points(binary_ply(dtype="<f8"), compact=True).dtype == np.float64
    assert read_points(ascii_ply(), compact=True).dtype == np.float32


def test_a_list_typed_coordinate_is_refused():
    for fmt in ("ascii", "binary_little_endian"):
        props = ("list uchar float x", "float y", "float z")
        expect_error(header(fmt, props=props) + b"1 0.5 0.5 0.5\n" * N, "list properties")


def test_ascii_vertices_with_many_properties_are_parsed_in_bounded_memory():
    """200 one-digit properties per row: a whole-table parse holds 8 bytes per digit (32 MB here); a
    parse a block at a time holds about ten times a block's text, whatever the file's size."""
    rows = np.random.default_rng(1).integers(0, 10, size=(20_000, 203))
    props = ("float x", "float y", "float z", *(f"uchar p{i}" for i in range(200)))
    data = header("ascii", len(rows), props=props) + "".join(" ".join(map(str, row)) + "\n" for row in rows).encode()
    tracemalloc.start()
    try:
        points = read_points(data)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    np.testing.assert_array_equal(points, rows[:, :3])
    assert peak < 16 * 2**20, f"{peak / 2**20:.1f} MiB for {len(data) / 2**20:.1f} MiB of text"


def _seeds() -> list[bytes]:
    """Valid files in every format, with an extra vertex property and a face element after the vertices."""
    props = ("float x", "double y", "float z", "uchar red")
    faces = FACE_LIST.format(n=2)
    rows = "".join(f"{x:.5f} {y:.5f} {z:.5f} 7\n" for x, y, z in POINTS.tolist()).encode()
    seeds = [header("ascii", props=props, extra=faces) + rows + b"3 0 1 2\n4 0 1 2 3\n"]
    for order, fmt in (("<", "binary_little_endian"), (">", "binary_big_endian")):
        vertices = np.zeros(N, [("x", order + "f4"), ("y", order + "f8"), ("z", order + "f4"), ("red", "u1")])
        vertices["x"], vertices["y"], vertices["z"] = POINTS.T
        seeds.append(header(fmt, props=props, extra=faces) + vertices.tobytes() + triangles(2, 3).replace(b"<", b""))
    return seeds


_TOKENS = [b"list", b"uchar", b"int", b"double", b"-1", b"0", b"99999999999999999999", b"1e400", b"nan", b"x"]
_TOKENS += [b"vertex", b"element", b"property", b"\n", b" ", b"\r\n", b"\x00", b"\xff", b"end_header", b"2"]


def _mutate(data: bytes, rng: np.random.Generator) -> bytes:
    """``data`` truncated, with bytes flipped, tokens inserted, header words replaced or bytes cut."""
    out = bytearray(data)
    for _ in range(int(rng.integers(1, 5))):
        at = int(rng.integers(0, len(out) + 1))
        kind = int(rng.integers(0, 5))
        token = _TOKENS[int(rng.integers(0, len(_TOKENS)))]
        if kind == 0:
            del out[at:]
        elif kind == 1 and out:
            out[min(at, len(out) - 1)] = int(rng.integers(0, 256))
        elif kind == 2:
            out[at:at] = token
        elif kind == 3:  # a word of the header
            starts = [i + 1 for i in range(max(out.find(b"end_header"), 0)) if out[i] in b" \n"]
            if starts:
                start = starts[int(rng.integers(0, len(starts)))]
                end = start
                while end < len(out) and out[end] not in b" \n":
                    end += 1
                out[start:end] = token
        else:
            del out[at : at + int(rng.integers(1, 20))]
    return bytes(out)


@pytest.mark.parametrize("seed", range(4))
def test_any_truncation_or_mutation_raises_only_point_cloud_error(seed):
    """Fuzzing (5,000 mutants per seed, about a second): the reader accepts a file or raises its own
    typed error, never anything else (which the API would answer 500 and the command print as a traceback)."""
    rng = np.random.default_rng(seed)
    seeds = _seeds()
    for seed_file in seeds:
        assert read_points(seed_file, min_points=1).shape == (N, 3)
    for _ in range(5000):
        mutant = _mutate(seeds[int(rng.integers(0, len(seeds)))], rng)
        try:
            read_points(mutant, min_points=1)
        except PointCloudError as error:
            assert "\n" not in str(error) and str(error), mutant[:200]
        except Exception as error:
            pytest.fail(f"{type(error).__name__}: {error} on {mutant[:300]!r}")
