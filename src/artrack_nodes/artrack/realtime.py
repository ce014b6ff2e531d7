"""Process settings for steady per-frame cost.

numpy allocates its large temporaries (the particle filter's particles x capsules x points
arrays, ~13 MB each) afresh every frame. glibc serves allocations
above its mmap threshold with fresh pages and returns freed heap above its trim threshold to
the system, so a frame can pay for zeroing tens of megabytes in the kernel, and which frame
does depends on the heap's history: in `bench/particles.py` a third of the CPU time was
system time and single frames took 3x the median. Keeping freed memory in the process (as
real-time guidelines advise: no trimming, large blocks from the heap) makes every frame do the
same work (there: system time 12 % -> 2 %, frame time cv 0.3-0.5 -> 0.1, the machine's timing
noise). The blob tracker's closed loop does not gain (12.1 vs 11.7 frames/s), so only the
particle tracker and its bench call :func:`keep_freed_memory`, once at process start; it is a
no-op where the C library is not glibc.
"""

from __future__ import annotations

import ctypes
import ctypes.util

__all__ = ["keep_freed_memory"]

_M_TRIM_THRESHOLD = -1      # glibc malloc.h
_M_MMAP_THRESHOLD = -3
_MMAP_THRESHOLD_MAX = 32 * 1024 * 1024   # glibc's upper limit on 64-bit systems


def keep_freed_memory() -> bool:
    """Serve blocks up to 32 MiB from the heap and never trim it. True if glibc took both."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    trim = mallopt(_M_TRIM_THRESHOLD, 2**31 - 1)
    mmap = mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_MAX)
    return bool(trim) and bool(mmap)
