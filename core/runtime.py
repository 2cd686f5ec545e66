"""Process-wide settings of the fitting core, made once by the program that runs it.

A library call such as ``core.fit.fit`` changes nothing outside its own objects. What belongs to
the whole process (torch's thread count, whether the network's kernels are compiled, how glibc's
malloc keeps freed memory, whether denormal floats are flushed) is set here, by the entry points:
``edgerecon fit`` and the worker call ``configure`` once at start, before any torch work. A program
that never calls it gets torch's own thread count, compiled kernels, glibc's default malloc and
denormal arithmetic.
"""

from __future__ import annotations

import ctypes
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # from glibc's malloc.h


def configure(*, compile: bool, threads: int | None = None, tune_malloc: bool = True) -> None:
    """Set up this process for fitting.

    ``compile``: compile the network's element-wise kernels with ``torch.compile`` at their first
    use (25-45 s the first time on a machine, about 5 s from the disk cache), or run them
    eagerly. ``threads``: torch's thread count (None leaves it). ``tune_malloc``: keep freed
    memory for reuse (``keep_freed_memory``). Denormal floats are flushed to zero
    (``flush_denormals``), which must come before torch's first parallel operation.
    """
    import torch

    from core.network import use_compiled_kernels

    flush_denormals()
    if threads is not None:
        torch.set_num_threads(threads)
    use_compiled_kernels(compile)
    if tune_malloc:
        keep_freed_memory()


def flush_denormals() -> None:
    """Treat denormal floats (below 1.2e-38 in float32) as zero, in this thread and the threads
    started after it.

    With β = 200 a hidden unit's β-scaled pre-activation reaches ±100, where σ(u), e^u and their
    products are denormal, and each operation on one takes the CPU's slow path: the compiled
    kernels ran up to 3 times slower and a default fit 14 % (docs/benchmarks.md). Flushed, such a
    value is 0, as it nearly is already.
    The flag is per thread and a new thread inherits it: torch's OpenMP pool starts at its first
    parallel operation, after which a call here reaches only the calling thread.
    """
    import torch

    torch.set_flush_denormal(True)


def flushing_denormals() -> bool:
    """Whether this thread flushes denormal floats now (a denormal times 1 comes out 0)."""
    return bool((np.array([5e-324]) * 1.0)[0] == 0.0)


@contextmanager
def denormals_kept() -> Iterator[None]:
    """Denormal arithmetic in this thread (and threads started in the block) for the block, then the
    flag as it was.

    For C code that was not written for flushed denormals: scipy's k-d tree (balanced, compact
    nodes: its defaults) recursed until the process crashed (SIGSEGV) while building a tree over
    points of which many have a coordinate exactly 0, such as an exactly sampled part with a face
    on a plane of the normalised frame, when the flag was set as ``configure`` sets it."""
    if not flushing_denormals():
        yield
        return
    import torch

    torch.set_flush_denormal(False)
    try:
        yield
    finally:
        torch.set_flush_denormal(True)


def keep_freed_memory() -> None:
    """Let glibc reuse freed blocks of up to 32 MB instead of unmapping them.

    Every step allocates and frees tensors of 5-20 MB; by default glibc maps each one afresh
    and the kernel zero-fills every page on first touch, which cost 20-30 % of a step here.
    """
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:  # not glibc: nothing to tune
        return
    libc.mallopt(_M_MMAP_THRESHOLD, 32 * 1024 * 1024)
    libc.mallopt(_M_TRIM_THRESHOLD, 1024 * 1024 * 1024)
