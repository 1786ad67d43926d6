"""Keep freed memory in the process for reuse, instead of handing it back to the kernel.

Why: XLA:CPU takes each call's temporary buffers from ``malloc`` and frees them when the call
returns (about 50 MiB for one paper-size calibrator window). glibc serves every block above
its mmap threshold (128 KiB, growing to at most 32 MiB) with fresh pages from ``mmap`` and
unmaps them on ``free``, so the next call's buffers are new pages again: the kernel zeroes and
maps each on first touch, one 4 KiB page fault at a time. Measured on one paper-size window
(``experiments/bench_calibrator.py``, 2-core CPU): 12-18 thousand minor faults and 26 ms of
system time per call; with :func:`keep_freed_memory` 0-20 faults and 25-30 % less wall time.
This is the job tcmalloc or jemalloc do for PyTorch CPU inference, done here with glibc's own
switches: no ``mmap`` for large blocks (they come from the heap) and no trimming of the heap's
free top below 1 GiB.

Cost: the process's resident memory no longer shrinks after a peak (freed blocks wait in the
heap for the next call). So it is for processes that make many similar calls -- the ``uavcal``
command and the benchmarks call it at start; importing the library changes nothing.
``UAVCAL_KEEP_FREED_MEMORY=0`` turns it off.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

__all__ = ["keep_freed_memory"]

# glibc <malloc.h>
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
#: The heap's free top is returned to the kernel only above this size, bytes.
TRIM_THRESHOLD = 1 << 30


def keep_freed_memory() -> bool:
    """Switch glibc ``malloc`` to keep freed large blocks for reuse (see the module
    docstring). Returns whether it was applied: ``False`` where the C library is not glibc
    (nothing changes there) or ``UAVCAL_KEEP_FREED_MEMORY=0``."""
    if os.environ.get("UAVCAL_KEEP_FREED_MEMORY", "1") == "0":
        return False
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
        libc.gnu_get_libc_version  # noqa: B018 - present in glibc only
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
