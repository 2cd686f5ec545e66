"""k-d trees over points, built the one way that is safe in a process that flushes denormals."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from core.runtime import denormals_kept


def kd_tree(points: np.ndarray) -> cKDTree:
    """The balanced k-d tree of ``points`` (n, d), built with denormal arithmetic on.

    Why not ``cKDTree(points)`` directly: after ``core.runtime.configure`` flushes denormals, scipy's
    build recursed until it crashed on points with many coordinates exactly 0 (an exactly sampled
    part with a face on a plane of the normalised frame: ``edgerecon fit`` died with SIGSEGV).
    Queries are not affected."""
    with denormals_kept():
        return cKDTree(points, balanced_tree=True)


def nearest_others(points: np.ndarray, count: int, workers: int = 1) -> np.ndarray:
    """(n, count): the rows of each of ``points``' (n, 3) ``count`` nearest other points (fewer in
    a cloud of fewer), queried on ``workers`` threads."""
    count = min(count, len(points) - 1)
    _, rows = kd_tree(points).query(points, k=count + 1, workers=workers)
    return np.asarray(rows).reshape(len(points), -1)[:, 1:]
