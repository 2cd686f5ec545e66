"""Stray points: a scanner's returns far from every surface, left out of the fit.

A fit passes f = 0 through every point it is given, so a point far from the surface gets a small
closed surface of its own: one percent of l_bracket's cloud scattered through its box gave a mesh of
15 extra components (genus -14) and an exact Hausdorff distance of 0.565 (docs/benchmarks.md). A
point of a surface has its nearest neighbours on that surface around it, as near to it as they are
to theirs; a stray's nearest neighbours lie on the nearest surface or are other strays, and much
farther from it than from their own. The test is local, so a cloud sampled eight times as densely at
one end as at the other keeps every point, and a stray near a dense face is found as one near a
sparse face is.
"""

from __future__ import annotations

import numpy as np

from core.trees import kd_tree

NEIGHBOURS = 8
# A point is a stray where its NEIGHBOURS-th nearest neighbour lies more than STRAY_RATIO times as
# far as that of its own neighbours (their median) and as the cloud's median (a cluster of repeated
# points has neighbours at distance 0), or more than FAR_RATIO times as far as the cloud's median:
# strays far from every surface are one another's neighbours, as far apart as they are from the
# surface (of 163 strays in l_bracket's box, the first test alone found 33, both 106; the 57 left
# lie within 0.06 of the surface, twelve noise widths). A region sampled 36
# times more sparsely than the cloud's median would pass for strays. Of 38 clouds of
# docs/benchmarks.md (the shapes and their variants, the twelve parts, five public models, two
# clouds eight times as dense at one end as at the other) no point is a stray.
STRAY_RATIO = 3.0
FAR_RATIO = 6.0
# Strays that are one another's neighbours hide one another from the first test; read without the
# strays found, they are found (on a cube with 160 strays in its box, two 4.8 spacings off its
# surface were missed in one reading).
PASSES = 3


def strays(points: np.ndarray, workers: int = 1) -> np.ndarray:
    """(n,) bool: which of ``points`` (n, 3) are strays, far from the surface their neighbours
    sample (``STRAY_RATIO``, ``FAR_RATIO``), read again without those found (``PASSES``). None of
    a cloud of ``NEIGHBOURS`` + 1 points or fewer."""
    kept = np.arange(len(points))
    for _ in range(PASSES):
        found = _strays_among(points[kept], workers)
        if not found.any():
            break
        kept = kept[~found]
    stray = np.ones(len(points), dtype=bool)
    stray[kept] = False
    return stray


def _strays_among(points: np.ndarray, workers: int) -> np.ndarray:
    """(n,) bool: one reading of ``strays``."""
    if len(points) <= NEIGHBOURS + 1:
        return np.zeros(len(points), dtype=bool)
    distances, nearest = kd_tree(points).query(points, k=NEIGHBOURS + 1, workers=workers)
    reach = distances[:, -1]
    around = np.median(reach[nearest[:, 1:]], axis=1)
    typical = np.median(reach)
    return (reach > STRAY_RATIO * np.maximum(around, typical)) | (reach > FAR_RATIO * typical)
