"""The process's memory allocator, set up for a live loop: freed memory is kept for reuse.

numpy allocates every temporary afresh. glibc's malloc gives freed memory back to the
system once more than M_TRIM_THRESHOLD (128 kB) lies free at the top of the heap, and
serves blocks over M_MMAP_THRESHOLD with pages of their own: so each frame's temporaries
(a few kB to a megabyte: a frame, the band fit's strips under 60 parameter sets) fault
freshly zeroed pages in again, which costs more than the arithmetic done in them. Keeping
freed memory for reuse cut the band fit's coverage model from 0.54 to 0.10 ms and a
frame's detection by about a third on this machine. The price is that the process keeps
its peak heap resident (tens of MB for the loop).

``keep_freed_memory`` is called once by the command line (every ``vservo`` command, the
controller process among them); a library user running the loop elsewhere may call it
too. Where the C library has no ``mallopt`` (not glibc) nothing changes.
"""

from __future__ import annotations

import ctypes
import ctypes.util

#: mallopt parameters (glibc malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: Free memory kept at the heap's top before any is given back.
TRIM_THRESHOLD_BYTES = 256 << 20
#: Blocks from this size on get pages of their own (glibc's largest setting on 64-bit):
#: below it every array comes from the heap, and its pages are reused.
MMAP_THRESHOLD_BYTES = 32 << 20


def keep_freed_memory() -> bool:
    """Make malloc keep freed memory for reuse; True when the C library took the settings."""
    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c")).mallopt
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)) and bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES))
