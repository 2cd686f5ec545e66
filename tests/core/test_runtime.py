"""core.runtime: what is process-wide is set once by configure, and a fit changes none of it."""

from __future__ import annotations

import ctypes
import subprocess
import sys

import numpy as np
import pytest
import torch

from core import network, runtime
from core.fit import fit
from core.params import FitParams
from evaluation.shapes import sample_shape
from tests.helpers import ROOT

MIB = 1024 * 1024


class _FakeLibc:
    def __init__(self, calls: list):
        self.calls = calls

    def mallopt(self, option: int, value: int) -> int:
        self.calls.append((option, value))
        return 1


@pytest.fixture
def process_state(monkeypatch):
    """Restores torch's thread count and the kernels' switch after the test; records mallopt calls."""
    calls: list[tuple[int, int]] = []
    monkeypatch.setattr(ctypes, "CDLL", lambda name, *args, **kwargs: _FakeLibc(calls))
    monkeypatch.setattr(network._kernels, "compiled", network._kernels.compiled)
    threads = torch.get_num_threads()
    yield calls
    torch.set_num_threads(threads)


def test_configure_sets_the_threads_the_kernels_and_glibcs_malloc(process_state):
    runtime.configure(compile=False, threads=1)
    assert torch.get_num_threads() == 1
    assert network._kernels.compiled is False
    assert process_state == [(-3, 32 * MIB), (-1, 1024 * MIB)]  # M_MMAP_THRESHOLD, M_TRIM_THRESHOLD
    runtime.configure(compile=True)
    assert network._kernels.compiled is True


# A fresh process: how many of a million denormal floats (1e-39) survive a multiplication by one,
# which torch splits between its two threads, after configure or without it.
_DENORMALS_LEFT = """
import sys, torch
from core.runtime import configure
if sys.argv[1] == "configure":
    configure(compile=False, threads=2, tune_malloc=False)
torch.set_num_threads(2)
print(int((torch.full((1 << 20,), 1e-39) * 1.0 != 0).sum()))
"""


def test_configure_flushes_denormals_in_every_thread_torch_computes_on():
    left = {
        how: int(
            subprocess.run(
                [sys.executable, "-c", _DENORMALS_LEFT, how], cwd=ROOT, capture_output=True, text=True, check=True
            ).stdout
        )
        for how in ("configure", "plain")
    }
    assert left == {"configure": 0, "plain": 1 << 20}


def test_configure_leaves_threads_and_malloc_alone_when_asked(process_state):
    threads = torch.get_num_threads()
    runtime.configure(compile=False, tune_malloc=False)
    assert torch.get_num_threads() == threads and process_state == []


def test_a_fit_changes_nothing_outside_its_own_objects(process_state):
    points = sample_shape("cube", n_points=500, seed=0).points
    params = FitParams(iterations=3, width=16, depth=1, batch_points=64, precision="float32")
    network._kernels.compiled = False  # eager: this test is not about compiling
    before = (torch.get_num_threads(), torch.get_default_dtype(), torch.random.get_rng_state().clone())
    numpy_state = np.random.get_state()[1].copy()
    fit(points, params)
    assert process_state == []  # no mallopt
    assert network._kernels.compiled is False
    assert torch.get_num_threads() == before[0] and torch.get_default_dtype() == before[1]
    assert torch.equal(torch.random.get_rng_state(), before[2])
    assert np.array_equal(np.random.get_state()[1], numpy_state)
