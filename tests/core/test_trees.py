"""core.trees and core.runtime.denormals_kept: k-d trees that build in a process flushing denormals."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np

from core.runtime import denormals_kept, flush_denormals, flushing_denormals
from core.trees import nearest_others
from tests.helpers import ROOT


def test_a_tree_over_a_face_on_a_coordinate_plane_builds_and_answers_exactly_with_denormals_flushed():
    # In a child process: before core.trees, this build crashed the process (SIGSEGV); 3,000 of the
    # 20,000 points have x exactly 0, as an exactly sampled part's face on a plane of the frame.
    script = textwrap.dedent(
        """
        import numpy as np
        from core.runtime import flush_denormals, flushing_denormals
        from core.trees import kd_tree

        rng = np.random.default_rng(0)
        points = rng.uniform(-0.5, 0.5, (20000, 3))
        points[:3000, 0] = 0.0
        flush_denormals()
        tree = kd_tree(points)
        assert flushing_denormals(), "the flag is not back after the build"
        queries = rng.uniform(-0.6, 0.6, (300, 3))
        queries[:100, 0] = 0.0
        distance, index = tree.query(queries)
        brute = np.linalg.norm(queries[:, None] - points[None], axis=2)
        assert np.array_equal(distance, brute.min(axis=1)) and np.array_equal(index, brute.argmin(axis=1))
        print("ok")
        """
    )
    run = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.strip() == "ok"


def test_denormals_kept_turns_flushing_off_for_its_block_only_and_leaves_an_unflushed_thread_alone():
    assert not flushing_denormals()
    with denormals_kept():
        assert not flushing_denormals()
    assert not flushing_denormals()
    flush_denormals()
    assert flushing_denormals()
    with denormals_kept():
        assert not flushing_denormals()
    assert flushing_denormals()  # the autouse fixture turns it off after the test


def test_the_nearest_others_are_each_points_nearest_but_itself():
    points = np.random.default_rng(2).normal(size=(400, 3))
    rows = nearest_others(points, 8, workers=2)
    distances = np.linalg.norm(points[:, None] - points[None], axis=-1)
    np.fill_diagonal(distances, np.inf)
    assert np.array_equal(np.sort(rows, axis=1), np.sort(np.argsort(distances, axis=1)[:, :8], axis=1))
    assert nearest_others(points[:3], 8).shape == (3, 2)
