"""Reading point clouds from PLY files (ASCII or binary, any endianness), without torch.

The header is parsed here (``parse_header``), and only the vertex element's rows are read: of
them only the ``x y z`` properties are kept, and other elements (faces) are skipped, never
parsed. Binary vertex rows are viewed in place with a dtype built from the header, after
checking that every declared element fits in the file, so nothing is allocated for a lying
header. An ASCII row is one line, so a header that declares more rows than the file has lines is
refused up front; the vertex lines are then parsed by numpy, and checked row by row only to say
which row is wrong.
"""

from __future__ import annotations

import io
import os
import re
import warnings
from dataclasses import dataclass

import numpy as np

from core.errors import PointCloudError

MIN_POINTS = 100
MAX_POINTS = 5_000_000
_MAX_HEADER_BYTES = 64 * 1024
_CHUNK_BYTES = 1 << 20  # ASCII lines are counted and parsed a chunk at a time, so memory stays bounded
_ROWS_PER_BLOCK = 1 << 18  # rows per block of the checks on a cloud

_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}
# PLY's type names, the sized names many writers use, and numpy's codes, which some writers use too.
_TYPES = {
    **dict.fromkeys(("char", "int8", "i1"), "i1"),
    **dict.fromkeys(("uchar", "uint8", "u1"), "u1"),
    **dict.fromkeys(("short", "int16", "i2"), "i2"),
    **dict.fromkeys(("ushort", "uint16", "u2"), "u2"),
    **dict.fromkeys(("int", "int32", "i4"), "i4"),
    **dict.fromkeys(("uint", "uint32", "u4"), "u4"),
    **dict.fromkeys(("float", "float32", "f4"), "f4"),
    **dict.fromkeys(("double", "float64", "f8"), "f8"),
}
# A number as an ASCII row may write it (what the row-by-row check accepts).
_NUMBER = re.compile(rb"[+-]?(?:\d+\.?\d*(?:[eE][+-]?\d+)?|\.\d+(?:[eE][+-]?\d+)?|nan|inf|infinity)", re.IGNORECASE)


@dataclass(frozen=True)
class Property:
    """One property of an element: its name, its numpy type code (``"f4"``...) and, for a list,
    the type code of its length (None for a plain value)."""

    name: str
    type: str
    length_type: str | None = None


@dataclass(frozen=True)
class Element:
    name: str
    count: int
    properties: tuple[Property, ...]

    @property
    def has_lists(self) -> bool:
        return any(prop.length_type is not None for prop in self.properties)


@dataclass(frozen=True)
class Header:
    """A PLY header: ``format`` is ``ascii``, ``binary_little_endian`` or ``binary_big_endian``;
    the body starts at byte ``body_start``."""

    format: str
    elements: tuple[Element, ...]
    body_start: int

    def element(self, name: str) -> Element | None:
        return next((element for element in self.elements if element.name == name), None)


def read_points(
    source: bytes | bytearray | memoryview | str | os.PathLike[str],
    *,
    min_points: int = MIN_POINTS,
    max_points: int = MAX_POINTS,
    compact: bool = False,
) -> np.ndarray:
    """Return the vertex positions of a PLY file as an (N, 3) float64 array, in file order.

    ``source`` is the file's content or its path. Raises ``PointCloudError`` with a message a
    user understands when the file is not a usable cloud (see ``check_points``). ``compact``
    returns float32 when every coordinate is declared float32 or a 1- or 2-byte integer (float32
    holds those exactly), to halve the memory of a large cloud (the API stores it so).
    """
    if isinstance(source, (bytes, bytearray, memoryview)):
        data = bytes(source)
    else:
        with open(source, "rb") as handle:
            data = handle.read()
    header = parse_header(data)
    vertex = header.element("vertex")
    if vertex is None:
        raise PointCloudError("the PLY file has no 'vertex' element")
    types = {prop.name: prop.type for prop in vertex.properties}
    missing = [axis for axis in "xyz" if axis not in types]
    if missing:
        raise PointCloudError(f"the vertex element has no {', '.join(missing)} property")
    if vertex.has_lists:
        raise PointCloudError("the vertex element has list properties, which are not supported")
    if header.format == "ascii":
        _check_ascii_lines(data, header)
    else:
        vertices = _read_binary_vertices(data, header)  # a view on data: checks the layout, allocates nothing
    _check_count(vertex.count, min_points, max_points)  # before the points are allocated
    exact_in_float32 = all(types[axis] in ("f4", "i1", "u1", "i2", "u2") for axis in "xyz")
    points = np.empty((vertex.count, 3), np.float32 if compact and exact_in_float32 else np.float64)
    with np.errstate(all="ignore"):  # values are checked explicitly, below and in check_points
        if header.format == "ascii":
            _read_ascii_vertices(data, header, vertex, points)
        else:
            for index, axis in enumerate("xyz"):
                points[:, index] = vertices[axis]
            del vertices
    del data  # the file's bytes (and any view on them) go before the checks allocate
    return check_points(points, min_points=min_points, max_points=max_points)


def _check_count(count: int, min_points: int, max_points: int) -> None:
    if count < min_points:
        raise PointCloudError(f"the cloud has {count} points; at least {min_points} are needed")
    if count > max_points:
        raise PointCloudError(f"the cloud has {count} points; at most {max_points} are accepted")


def check_points(points: np.ndarray, *, min_points: int = MIN_POINTS, max_points: int = MAX_POINTS) -> np.ndarray:
    """Validate an (N, 3) array of positions and return it (float32 stays float32, else float64).

    Rejects non-finite coordinates, fewer than ``min_points`` or more than ``max_points``
    points, and clouds that span fewer than two dimensions (all points equal, or collinear).
    The checks work a block of rows at a time, so they add little memory to a large cloud.
    """
    points = np.asarray(points)
    if points.dtype != np.float32:
        points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise PointCloudError(f"expected points with 3 coordinates, got an array of shape {points.shape}")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise PointCloudError(f"{int(bad.sum())} points have NaN or infinite coordinates (the first is vertex {first})")
    _check_count(len(points), min_points, max_points)
    # The spread along the principal axes: a cloud on a line (or a point) has no surface to fit.
    # Computed on the cloud scaled into the unit box, so that huge coordinates cannot overflow.
    low, high = points.min(axis=0).astype(np.float64), points.max(axis=0).astype(np.float64)
    center, scale = low / 2 + high / 2, float(np.max(high / 2 - low / 2)) or 1.0  # halves: no overflow
    mean, scatter = np.zeros(3), np.zeros((3, 3))
    for start in range(0, len(points), _ROWS_PER_BLOCK):
        mean += ((points[start : start + _ROWS_PER_BLOCK] - center) / scale).sum(axis=0)
    mean /= len(points)
    for start in range(0, len(points), _ROWS_PER_BLOCK):
        block = (points[start : start + _ROWS_PER_BLOCK] - center) / scale - mean
        scatter += block.T @ block
    spread = np.sqrt(np.maximum(np.linalg.eigvalsh(scatter / len(points)), 0.0))[::-1]
    if spread[0] == 0.0 or spread[1] <= 1e-6 * spread[0]:
        raise PointCloudError("the points are all equal or lie on one line: there is no surface to fit")
    return points


def parse_header(data: bytes) -> Header:
    """The header of a PLY file: its format, its elements with their properties, where the body starts."""
    if not data:
        raise PointCloudError("the file is empty")
    if not data.startswith(b"ply"):
        raise PointCloudError("not a PLY file: it must start with the line 'ply'")
    if re.search(rb"end_header[ \t]*\r?\n", data[:_MAX_HEADER_BYTES]) is None:
        raise PointCloudError("the PLY header has no 'end_header' line (file truncated?)")
    fmt: str | None = None
    elements: list[tuple[str, int, list[Property]]] = []
    position, number = 0, 0
    while True:
        newline = data.find(b"\n", position, _MAX_HEADER_BYTES)
        if newline < 0:  # "end_header" was in a comment
            raise PointCloudError("the PLY header has no 'end_header' line (file truncated?)")
        line, position, number = data[position:newline], newline + 1, number + 1
        words = line.decode("ascii", "replace").split()
        keyword = words[0] if words else ""
        if number == 1:
            if words != ["ply"]:
                raise _header_error(number, "expected 'ply'")
        elif keyword in ("comment", "obj_info"):
            continue
        elif not line.isascii():
            raise _header_error(number, "not ASCII text")
        elif keyword == "format":
            if fmt is not None or elements or len(words) != 3 or words[1] not in _FORMATS:
                raise _header_error(number, f"expected 'format {'|'.join(_FORMATS)} 1.0', once, before the elements")
            if words[2] != "1.0":
                raise _header_error(number, f"unknown PLY version '{words[2]}' (expected 1.0)")
            fmt = words[1]
        elif keyword == "element":
            if fmt is None:
                raise _header_error(number, "an element before the format line")
            if len(words) != 3:
                raise _header_error(number, "expected 'element <name> <count>'")
            if not words[2].isdigit():
                raise _header_error(number, f"the count of element '{words[1]}' is not a whole number: '{words[2]}'")
            if any(name == words[1] for name, _, _ in elements):
                raise _header_error(number, f"a second element called '{words[1]}'")
            elements.append((words[1], int(words[2]), []))
        elif keyword == "property":
            if not elements:
                raise _header_error(number, "a property before any element")
            prop = _property(words[1:])
            if prop is None:
                types = ", ".join(sorted(set(_TYPES) - set(_TYPES.values())))
                raise _header_error(
                    number,
                    f"expected 'property <type> <name>' or 'property list <length type> <type> <name>' ({types})",
                )
            name, _, properties = elements[-1]
            if any(known.name == prop.name for known in properties):
                raise _header_error(number, f"a second property called '{prop.name}' in element '{name}'")
            properties.append(prop)
        elif words == ["end_header"]:
            if fmt is None:
                raise _header_error(number, "no 'format' line before end_header")
            return Header(fmt, tuple(Element(n, c, tuple(props)) for n, c, props in elements), position)
        else:
            raise _header_error(number, f"unknown keyword '{keyword}'")


def _header_error(line: int, problem: str) -> PointCloudError:
    return PointCloudError(f"malformed PLY header: line {line}: {problem}")


def _property(words: list[str]) -> Property | None:
    """The property that a header line declares (``words`` after ``property``); None if malformed."""
    if len(words) == 2 and words[0] in _TYPES:
        return Property(words[1], _TYPES[words[0]])
    if len(words) == 4 and words[0] == "list" and words[2] in _TYPES and _TYPES.get(words[1], "f")[0] in "iu":
        return Property(words[3], _TYPES[words[2]], _TYPES[words[1]])
    return None


def _read_binary_vertices(data: bytes, header: Header) -> dict[str, np.ndarray]:
    """The vertex properties by name, viewed on ``data`` (nothing is copied); other elements are skipped.

    Every element must fit in the file (at its smallest row size for rows with lists), so a
    truncated file or a huge declared count is refused without allocating anything.
    """
    order = _FORMATS[header.format]
    offset, vertices, exact = header.body_start, None, True
    for element in header.elements:
        if element.name == "vertex":
            dtype = np.dtype([(prop.name, order + prop.type) for prop in element.properties])
            if offset + element.count * dtype.itemsize > len(data):
                raise PointCloudError(
                    f"malformed binary PLY: the file is truncated (it declares {element.count} vertices)"
                )
            vertices = np.frombuffer(data, dtype=dtype, count=element.count, offset=offset)
        elif element.has_lists and vertices is None:
            raise PointCloudError(f"the '{element.name}' element before the vertices has lists; not supported")
        size = element.count * sum(np.dtype(prop.length_type or prop.type).itemsize for prop in element.properties)
        if offset + size > len(data):
            raise PointCloudError(
                f"malformed binary PLY: the file is truncated (it declares {element.count} '{element.name}' rows)"
            )
        offset += size  # exact for elements without lists, a lower bound after them
        exact = exact and not element.has_lists
    if exact and offset != len(data):
        raise PointCloudError(
            f"malformed binary PLY: the file holds {len(data) - offset} bytes more than its header declares"
        )
    assert vertices is not None  # read_points checked that there is a vertex element
    return {name: vertices[name] for name in vertices.dtype.names or ()}


def _read_ascii_vertices(data: bytes, header: Header, vertex: Element, out: np.ndarray) -> None:
    """Parse the vertex rows of an ASCII body into ``out`` (N, 3: x y z), about a megabyte at a time.

    Rows are lines, whatever their element, so the lines of the elements before the vertices are
    skipped unread, and nothing after them is read at all. Parsing a block at a time keeps the
    memory bounded whatever the number of properties per row.
    """
    start = header.body_start
    for element in header.elements[: header.elements.index(vertex)]:
        start = _after_lines(data, start, element.count)
    stop = _after_lines(data, start, vertex.count)
    names = [prop.name for prop in vertex.properties]
    xyz = [names.index(axis) for axis in "xyz"]
    row = 0
    while start < stop:
        end = data.rfind(b"\n", start, min(start + _CHUNK_BYTES, stop)) + 1
        if end <= start or stop - start <= _CHUNK_BYTES:  # the last block, or one line longer than a block
            end = stop if stop - start <= _CHUNK_BYTES else data.find(b"\n", start, stop) + 1 or stop
        block = data[start:end]
        count = block.count(b"\n") + (0 if block.endswith(b"\n") else 1)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # a block of blank lines: "input contained no data"
                table = np.loadtxt(io.BytesIO(block), dtype=np.float64, comments=None, ndmin=2)
        except ValueError as error:
            raise PointCloudError(
                f"malformed ASCII PLY: element 'vertex': {_bad_row(block, vertex, row) or error}"
            ) from None
        if table.shape != (count, len(names)):  # blank lines (numpy skips them) or a column too many
            raise PointCloudError(f"malformed ASCII PLY: element 'vertex': {_bad_row(block, vertex, row)}")
        for index, prop in enumerate(vertex.properties):
            column = table[:, index]
            if prop.type[0] in "iu":  # an integer property holds integers in its type's range
                limits = np.iinfo(prop.type)
                wrong = np.flatnonzero((column != np.round(column)) | (column < limits.min) | (column > limits.max))
                if len(wrong):
                    raise PointCloudError(
                        f"malformed ASCII PLY: element 'vertex': row {row + int(wrong[0])}: property '{prop.name}': "
                        f"not a valid {np.dtype(prop.type).name}"
                    )
        for axis, index in enumerate(xyz):  # through the declared type, as a binary file would hold it
            out[row : row + count, axis] = table[:, index].astype(vertex.properties[index].type)
        row, start = row + count, end
    if row != vertex.count:
        raise PointCloudError(f"malformed ASCII PLY: element 'vertex': {_bad_row(b'', vertex, row)}")


def _check_ascii_lines(data: bytes, header: Header) -> None:
    """An ASCII row is a line: refuse a header that declares more rows than the file has lines."""
    start = header.body_start
    lines = data.count(b"\n", start) + (0 if data.endswith(b"\n") or start == len(data) else 1)
    declared = sum(element.count for element in header.elements)
    if declared > lines:
        raise PointCloudError(f"the header declares {declared} rows but the file holds only {lines} lines")


def _bad_row(rows: bytes, vertex: Element, first: int) -> str | None:
    """Where the first malformed row of ``rows`` (vertex lines from row ``first``) goes wrong, as
    plyfile said it."""
    names = [prop.name for prop in vertex.properties]
    for row, line in enumerate(rows.split(b"\n")[: vertex.count - first], first):
        words = line.split()
        for name, word in zip(names, words):
            if not _NUMBER.fullmatch(word):
                return f"row {row}: property '{name}': malformed input"
        if len(words) < len(names):
            return f"row {row}: property '{names[len(words)]}': early end-of-line"
        if len(words) > len(names):
            return f"row {row}: expected end-of-line"
    if first < vertex.count:
        return f"row {first}: property '{names[0]}': early end-of-line"
    return None


def _after_lines(data: bytes, start: int, count: int) -> int:
    """The offset just past ``count`` lines from ``start`` (the end of ``data`` if it has fewer)."""
    position = start
    while count > 0 and position < len(data):
        end = min(position + _CHUNK_BYTES, len(data))
        found = data.count(b"\n", position, end)
        if found >= count:
            newlines = np.flatnonzero(np.frombuffer(data, np.uint8, end - position, position) == ord("\n"))
            return position + int(newlines[count - 1]) + 1
        count -= found
        position = end
    return position
