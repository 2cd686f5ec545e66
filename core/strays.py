"""Stray points: a scanner's returns far from every surface, left out of the fit.

A fit passes f = 0 through every point it is given, so a point far from the surface gets a small
closed surface of its own: one percent of l_bracket's cloud scattered through its box gave a mesh of
15 extra components (genus -14) and an exact Hausdorff distance of 0.565 (docs/benchmarks.md). A
point of a surface has its nearest neighbours on that surface around it, as near to it as they are
to theirs; a stray's nearest neighbours lie on the nearest surface or are other strays, and much
farther from it than from their own. The test is local, so a cloud sampled eight times as densely at
one end as at the other keeps every point, and a stray near a dense face is found as one near a
sparse face is. Strays in a clump are one another's neighbours and pass that test; they are a
group of points whose nearest points are their own, too small to be a part (``GROUP_SHARE``).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from core.trees import kd_tree, nearest_others

NEIGHBOURS = 8
# A point is a stray where its NEIGHBOURS-th nearest neighbour lies more than STRAY_RATIO times as
# far as that of its own neighbours (their median) and as the cloud's median (a cluster of repeated
# points has neighbours at distance 0), or more than FAR_RATIO times as far as the cloud's median:
# strays far from every surface are one another's neighbours, as far apart as they are from the
# surface (of 163 strays in l_bracket's box, the first test alone found 33, both 106; the 57 left
# lie within 0.06 of the surface, twelve noise widths). A region sampled 36
# times more sparsely than the cloud's median would pass for strays. Of 51 clouds of
# docs/benchmarks.md (the shapes and their variants, the twelve parts, eight public models, twelve
# clouds eight times as dense at one end as at the other) no point is a stray, by either test.
STRAY_RATIO = 3.0
FAR_RATIO = 6.0
# Strays that are one another's neighbours hide one another from the first test; read without the
# strays found, they are found (on a cube with 160 strays in its box, two 4.8 spacings off its
# surface were missed in one reading).
PASSES = 3
# Each point is linked to its NEIGHBOURS nearest, and a linked group of less than GROUP_SHARE of the
# points is strays: a clump of stray returns, more than NEIGHBOURS together, has its nearest points
# among its own and no other point's among them, so the tests above pass it, and the fit would
# close a small surface round it as it did round each lone stray. A surface's points, however
# unevenly sampled, have some of theirs beyond any small patch of it.
GROUP_SHARE = 0.005


def strays(points: np.ndarray, workers: int = 1) -> np.ndarray:
    """(n,) bool: which of ``points`` (n, 3) are strays, far from the surface their neighbours
    sample (``STRAY_RATIO``, ``FAR_RATIO``), read again without those found (``PASSES``), and then
    in a small group apart from the rest (``GROUP_SHARE``). None of a cloud of
    ``NEIGHBOURS`` + 1 points or fewer."""
    kept = np.arange(len(points))
    for _ in range(PASSES):
        found = _strays_among(points[kept], workers)
        if not found.any():
            break
        kept = kept[~found]
    kept = kept[~_small_groups(points[kept], workers)]
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


def _small_groups(points: np.ndarray, workers: int) -> np.ndarray:
    """(n,) bool: which of ``points`` (n, 3) lie in a linked group of less than ``GROUP_SHARE`` of
    them, each point linked to its ``NEIGHBOURS`` nearest and they to it. Repeated points are taken
    as one, so that a point repeated many times is not a group of its own."""
    unique, inverse = np.unique(points, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    if len(unique) <= NEIGHBOURS + 1:
        return np.zeros(len(points), dtype=bool)
    nearest = nearest_others(unique, NEIGHBOURS, workers)
    rows = np.repeat(np.arange(len(unique)), NEIGHBOURS)
    links = coo_matrix((np.ones(len(rows), dtype=bool), (rows, nearest.reshape(-1))), shape=(len(unique),) * 2)
    _, group = connected_components(links, directed=False)
    sizes = np.bincount(group[inverse])  # each point counted, repeats too
    return sizes[group[inverse]] < GROUP_SHARE * len(points)
