"""How long a cancel takes to stop a reconstruction, at each moment of its set-up and first steps.

For a cloud of N points (a noisy cube's surface), ``reconstruct`` is started again and again with a
cancel check that turns true ``delay`` seconds after the start; the latency is the time from that
moment to ``Cancelled``. This is the core's part of a cancel; a worker adds at most its
``EDGERECON_PROGRESS_INTERVAL`` (0.5 s), the period at which it reads the job's status.

    .venv/bin/python bench/cancel_latency.py --points 1000000 5000000
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from core.errors import Cancelled
from core.params import FitParams
from core.reconstruct import reconstruct
from core.runtime import configure


def noisy_cube(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    points = rng.uniform(-1, 1, (n, 3))
    axis = rng.integers(0, 3, n)
    points[np.arange(n), axis] = np.sign(points[np.arange(n), axis])
    return points + rng.normal(0, 0.002, points.shape)


def latency(points: np.ndarray, delay: float) -> tuple[float, bool]:
    """Seconds from the cancel (``delay`` s after the start) to ``Cancelled``; False if the fit ended first."""
    started = time.perf_counter()
    params = FitParams(iterations=100_000, resolution=32, width=32, depth=2, batch_points=256)
    try:
        reconstruct(points, params, should_cancel=lambda: time.perf_counter() - started >= delay)
    except Cancelled:
        return time.perf_counter() - started - delay, True
    return 0.0, False


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, nargs="+", default=[1_000_000, 5_000_000])
    parser.add_argument("--delays", type=float, nargs="+", default=[0.0, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0])
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    configure(compile=False, threads=args.threads)
    print("| points | cancel after (s) | latency (s) |\n|---|---|---|")
    for n in args.points:
        points = noisy_cube(n)
        worst = 0.0
        for delay in args.delays:
            seconds, canceled = latency(points, delay)
            worst = max(worst, seconds)
            print(f"| {n:,} | {delay:g} | {seconds:.3f} |" if canceled else f"| {n:,} | {delay:g} | finished |")
        print(f"| {n:,} | worst | {worst:.3f} |")


if __name__ == "__main__":
    main()
