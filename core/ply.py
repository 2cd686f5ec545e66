"""Reading point clouds from PLY files (ASCII or binary, any endianness), without torch.

plyfile parses the header. ASCII bodies are read by plyfile, which rejects malformed rows; in a
binary body the vertex rows are viewed in place with the dtype plyfile gives them, after checking
that every declared element fits in the file, so nothing is allocated for a lying header. Only
the ``x y z`` vertex properties are used: other vertex properties and elements (faces) are ignored.
"""

from __future__ import annotations

import io
import os
import re

import numpy as np

from core.errors import PointCloudError

MIN_POINTS = 100
MAX_POINTS = 5_000_000
_MAX_HEADER_BYTES = 64 * 1024


def read_points(
    source: bytes | str | os.PathLike, *, min_points: int = MIN_POINTS, max_points: int = MAX_POINTS
) -> np.ndarray:
    """Return the vertex positions of a PLY file as an (N, 3) float64 array, in file order.

    ``source`` is the file's content or its path. Raises ``PointCloudError`` with a message a
    user understands when the file is not a usable cloud (see ``check_points``).
    """
    if isinstance(source, (bytes, bytearray, memoryview)):
        data = bytes(source)
    else:
        with open(source, "rb") as handle:
            data = handle.read()
    ply, body_start = _parse_header(data)
    vertex = ply["vertex"] if "vertex" in ply else None
    if vertex is None:
        raise PointCloudError("the PLY file has no 'vertex' element")
    missing = [axis for axis in "xyz" if axis not in [prop.name for prop in vertex.properties]]
    if missing:
        raise PointCloudError(f"the vertex element has no {', '.join(missing)} property")
    if ply.text:
        vertices = _read_ascii_vertices(data, body_start, ply)
    else:
        vertices = _read_binary_vertices(data, body_start, ply)
    points = np.stack([np.asarray(vertices[axis], dtype=np.float64) for axis in "xyz"], axis=1)
    return check_points(points, min_points=min_points, max_points=max_points)


def check_points(points: np.ndarray, *, min_points: int = MIN_POINTS, max_points: int = MAX_POINTS) -> np.ndarray:
    """Validate an (N, 3) array of positions and return it as float64.

    Rejects non-finite coordinates, fewer than ``min_points`` or more than ``max_points``
    points, and clouds that span fewer than two dimensions (all points equal, or collinear).
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise PointCloudError(f"expected points with 3 coordinates, got an array of shape {points.shape}")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise PointCloudError(f"{int(bad.sum())} points have NaN or infinite coordinates (the first is vertex {first})")
    if len(points) < min_points:
        raise PointCloudError(f"the cloud has {len(points)} points; at least {min_points} are needed")
    if len(points) > max_points:
        raise PointCloudError(f"the cloud has {len(points)} points; at most {max_points} are accepted")
    # The spread along the principal axes: a cloud on a line (or a point) has no surface to fit.
    spread = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov(points.T)), 0.0))[::-1]
    if spread[0] == 0.0 or spread[1] <= 1e-6 * spread[0]:
        raise PointCloudError("the points are all equal or lie on one line: there is no surface to fit")
    return points


def _parse_header(data: bytes):
    """The header as plyfile parses it (elements, counts, format) and where the body starts."""
    from plyfile import PlyData, PlyHeaderParseError

    if not data:
        raise PointCloudError("the file is empty")
    if not data.startswith(b"ply"):
        raise PointCloudError("not a PLY file: it must start with the line 'ply'")
    if re.search(rb"end_header[ \t]*\r?\n", data[:_MAX_HEADER_BYTES]) is None:
        raise PointCloudError("the PLY header has no 'end_header' line (file truncated?)")
    stream = io.BytesIO(data)
    try:
        ply = PlyData._parse_header(stream)  # plyfile's own header parser; it reads no data
    except (PlyHeaderParseError, UnicodeDecodeError, ValueError) as error:
        raise PointCloudError(f"malformed PLY header: {error}") from None
    return ply, stream.tell()


def _read_ascii_vertices(data: bytes, body_start: int, ply) -> np.ndarray:
    from plyfile import PlyData, PlyParseError

    # plyfile allocates every element at its declared size before reading it; an ASCII row is a
    # line, so a header that declares more rows than the file has lines is refused up front.
    body = memoryview(data)[body_start:]
    lines = data.count(b"\n", body_start) + (0 if data.endswith(b"\n") or not body else 1)
    declared = sum(element.count for element in ply)
    if declared > lines:
        raise PointCloudError(f"the header declares {declared} rows but the file holds only {lines} lines")
    try:
        return PlyData.read(io.BytesIO(data))["vertex"].data
    except (PlyParseError, ValueError, KeyError, UnicodeDecodeError) as error:
        raise PointCloudError(f"malformed ASCII PLY: {error}") from None


def _read_binary_vertices(data: bytes, body_start: int, ply) -> np.ndarray:
    """The vertex rows as a structured array viewed on ``data``; other elements are skipped.

    Every element must fit in the file (at its smallest row size for rows with lists), so a
    truncated file or a huge declared count is refused without allocating anything.
    """
    from plyfile import PlyListProperty

    offset, vertices, exact = body_start, None, True
    for element in ply:
        has_lists = any(isinstance(prop, PlyListProperty) for prop in element.properties)
        if element.name == "vertex":
            if has_lists:
                raise PointCloudError("the vertex element has list properties, which are not supported")
            dtype = element.dtype(ply.byte_order)
            if offset + element.count * dtype.itemsize > len(data):
                raise PointCloudError(
                    f"malformed binary PLY: the file is truncated (it declares {element.count} vertices)"
                )
            vertices = np.frombuffer(data, dtype=dtype, count=element.count, offset=offset)
        elif has_lists and vertices is None:
            raise PointCloudError(f"the '{element.name}' element before the vertices has lists; not supported")
        size = element.count * _smallest_row_bytes(element, ply.byte_order)
        if offset + size > len(data):
            raise PointCloudError(
                f"malformed binary PLY: the file is truncated (it declares {element.count} '{element.name}' rows)"
            )
        offset += size  # exact for elements without lists, a lower bound after them
        exact = exact and not has_lists
    if exact and offset != len(data):
        raise PointCloudError(
            f"malformed binary PLY: the file holds {len(data) - offset} bytes more than its header declares"
        )
    return vertices


def _smallest_row_bytes(element, byte_order: str) -> int:
    from plyfile import PlyListProperty

    sizes = [
        np.dtype(
            prop.list_dtype(byte_order)[0] if isinstance(prop, PlyListProperty) else prop.dtype(byte_order)
        ).itemsize
        for prop in element.properties
    ]
    return sum(sizes)
