"""Process-wide settings of the fitting core, made once by the program that runs it.

A library call such as ``core.fit.fit`` changes nothing outside its own objects. What belongs to
the whole process (torch's thread count, whether the network's kernels are compiled, how glibc's
malloc keeps freed memory) is set here, by the entry points: ``edgerecon fit`` and the worker
call ``configure`` once at start. A program that never calls it gets torch's own thread count,
compiled kernels and glibc's default malloc.
"""

from __future__ import annotations

import ctypes

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # from glibc's malloc.h


def configure(*, compile: bool, threads: int | None = None, tune_malloc: bool = True) -> None:
    """Set up this process for fitting.

    ``compile``: compile the network's element-wise kernels with ``torch.compile`` at their first
    use (25-45 s the first time on a machine, about 5 s from the disk cache), or run them
    eagerly. ``threads``: torch's thread count (None leaves it). ``tune_malloc``: keep freed
    memory for reuse (``keep_freed_memory``).
    """
    import torch

    from core.network import use_compiled_kernels

    if threads is not None:
        torch.set_num_threads(threads)
    use_compiled_kernels(compile)
    if tune_malloc:
        keep_freed_memory()


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
