"""The Dockerfile's build-time commands, run as plain processes (there is no Docker engine here)."""

from __future__ import annotations

import os
import re
import subprocess
import sys

from tests.helpers import ROOT

# A second process's view of the cache: fits of other clouds with the kernels compiled (a tiny one
# extracted, and a default one of more than 8,192 points to its first steps compiled whole), and
# how many compiled graphs came from the cache (hit) or had to be compiled (miss).
_CACHE_USE = """
from torch._dynamo.utils import counters
from core.runtime import configure
configure(compile=True)
from core.errors import Cancelled
from core.fit import EAGER_STEPS, fit
from core.params import FitParams
from core.reconstruct import reconstruct
from evaluation.shapes import sample_shape
points = sample_shape('sphere', n_points=3000, seed=5).points
dense = sample_shape('cube', n_points=9000, seed=5).points
for encoding in ('never', 'always'):
    reconstruct(points, FitParams(iterations=3, resolution=40, encoding=encoding))
    steps = []
    try:
        fit(dense, FitParams(encoding=encoding), lambda update: steps.append(1), lambda: len(steps) > EAGER_STEPS + 1)
    except Cancelled:
        pass
print(counters["inductor"]["fxgraph_cache_hit"], counters["inductor"]["fxgraph_cache_miss"])
"""


def _python_commands() -> list[str]:
    """The code of every ``RUN python -c "..."`` of the Dockerfile, its line continuations joined."""
    text = (ROOT / "Dockerfile").read_text().replace("\\\n", "")
    return re.findall(r'^RUN python -c "(.*)"$', text, flags=re.MULTILINE)


def test_the_image_compiles_every_kernel_a_job_uses_at_build_time(tmp_path):
    commands = _python_commands()
    assert len(commands) == 1
    env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": str(tmp_path / "inductor"), "OMP_NUM_THREADS": "1"}
    env.pop("EDGERECON_COMPILE", None)
    subprocess.run([sys.executable, "-c", commands[0]], cwd=ROOT, env=env, check=True, timeout=600)
    # A job of another size in a new process finds every kernel compiled.
    used = subprocess.run(
        [sys.executable, "-c", _CACHE_USE], cwd=ROOT, env=env, check=True, timeout=600, capture_output=True, text=True
    )
    hits, misses = map(int, used.stdout.split()[-2:])
    assert hits > 0 and misses == 0, used.stdout
