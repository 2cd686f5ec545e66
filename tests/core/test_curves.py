"""core.curves.without_isolated: which edge curves count as a part's edges and which as a smooth
surface's lone creases. (The curves of analytic shapes are tested with the extraction, in test_dual.)"""

from __future__ import annotations

import numpy as np
import pytest

from core.curves import Curve, without_isolated
from tests.helpers import flooded

GAP, LENGTH, KEEP_DIHEDRAL = 0.05, 0.06, 120.0


def segment(start: list[float], end: list[float], samples: int = 5, dihedral: float = 140.0) -> Curve:
    """A straight curve from ``start`` to ``end`` whose faces meet at ``dihedral`` degrees (its side
    normals do not matter here): 140, as shallow as a scan's creases, unless said."""
    points = np.linspace(start, end, samples)
    normals = np.tile([0.0, 0.0, 1.0], (samples, 1))
    return Curve(points, normals, normals, dihedral, True)


def loop(centre: list[float], radius: float, samples: int = 40) -> Curve:
    """A closed circle (first and last point the same) whose faces meet at 140°."""
    angle = np.linspace(0.0, 2 * np.pi, samples)
    points = np.asarray(centre) + radius * np.stack([np.cos(angle), np.sin(angle), np.zeros_like(angle)], axis=1)
    normals = np.tile([0.0, 0.0, 1.0], (samples, 1))
    return Curve(points, normals, normals, 140.0, True)


def kept(curves: list[Curve]) -> list[int]:
    survivors = without_isolated(curves, GAP, LENGTH, KEEP_DIHEDRAL)
    return [i for i, curve in enumerate(curves) if any(curve is s for s in survivors)]


def test_a_lone_short_crease_is_dropped_and_a_long_one_kept():
    assert kept([segment([0, 0, 0], [0.04, 0, 0]), segment([1, 0, 0], [1.07, 0, 0])]) == [1]


def test_a_lone_short_edge_whose_faces_meet_at_less_than_the_keep_angle_stays():
    # A poor fit finds a part's right-angled edge in lone pieces; a scan's creases are shallower.
    assert kept([segment([0, 0, 0], [0.03, 0, 0], dihedral=90.0)]) == [0]
    assert kept([segment([0, 0, 0], [0.03, 0, 0], dihedral=125.0)]) == []


def test_pieces_of_one_edge_count_together_across_a_gap():
    # Two pieces of 0.035 whose ends are 0.03 apart make an edge of 0.07; 0.08 apart, two creases.
    near = [segment([0, 0, 0], [0.035, 0, 0]), segment([0.065, 0, 0], [0.1, 0, 0])]
    far = [segment([0, 0, 0], [0.035, 0, 0]), segment([0.115, 0, 0], [0.15, 0, 0])]
    assert kept(near) == [0, 1]
    assert kept(far) == []


def test_groups_are_linked_transitively_at_either_end():
    # a-b linked at a's end and b's start, b-c at both ends' last points: 0.025 + 0.025 + 0.03.
    a = segment([0, 0, 0], [0.025, 0, 0])
    b = segment([0.03, 0, 0], [0.055, 0, 0])
    c = segment([0.13, 0, 0], [0.1, 0, 0])  # its end, not its start, is near b's end
    assert kept([a, b, c]) == [0, 1, 2]
    assert kept([a, b]) == []  # 0.05 in all


@pytest.mark.parametrize("radius, survives", [(0.011, True), (0.009, False)])
def test_a_shallow_loop_counts_by_its_circumference(radius, survives):
    # 2π r: 0.069 for a loop of radius 0.011, 0.057 for 0.009. (A small hole's rim is a right
    # angle and stays whatever its size: the keep angle.)
    assert kept([loop([0, 0, 0], radius)]) == ([0] if survives else [])


def test_no_curves():
    assert without_isolated([], GAP, LENGTH, KEEP_DIHEDRAL) == []


@pytest.mark.parametrize("seed", range(5))
def test_without_isolated_matches_a_brute_force_grouping(seed):
    # Reference: groups by a breadth-first search over every pair of ends within the gap.
    rng = np.random.default_rng(seed)
    curves = []
    for _ in range(60):
        start = rng.uniform(0, 0.5, 3)
        dihedral = float(rng.choice([90.0, 140.0], p=[0.2, 0.8]))
        curves.append(segment(list(start), list(start + rng.normal(0, 0.03, 3)), dihedral=dihedral))
    ends = [(curve.points[0], curve.points[-1]) for curve in curves]
    linked = [
        [j for j in range(len(curves)) if min(np.linalg.norm(p - q) for p in ends[i] for q in ends[j]) <= GAP]
        for i in range(len(curves))
    ]
    group = flooded(linked)
    total = {g: sum(c.length for c, h in zip(curves, group) if h == g) for g in set(group)}
    expected = [i for i in range(len(curves)) if total[group[i]] >= LENGTH or curves[i].dihedral < KEEP_DIHEDRAL]
    assert 0 < len(expected) < len(curves)  # the draw has both kinds
    assert kept(curves) == expected
