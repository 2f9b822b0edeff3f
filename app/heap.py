"""The serving process's C heap, kept from growing with the browsers that came and went.

Each browser that connects is sent the page's state: messages of tens to hundreds of kB,
built and freed again. glibc's malloc serves a block that large from the heap once its
mmap threshold has risen (it rises to the largest block freed, up to 32 MB), and a heap
cut up by such blocks between long-lived small ones keeps its pages: the process grew by
about 100 kB for every browser that left. With the threshold held at 128 kB, such blocks
are mapped on their own and unmapped when freed.

Elsewhere than on glibc (musl, macOS) nothing is changed.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging

log = logging.getLogger("vservo.app")

M_MMAP_THRESHOLD = -3  # glibc's mallopt parameter (malloc.h)
MMAP_THRESHOLD_BYTES = 128 * 1024  # glibc's own starting value, held there


def hold_the_mmap_threshold() -> bool:
    """Hold glibc's mmap threshold at 128 kB (no dynamic rise); whether it was set."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
        mallopt = getattr(libc, "mallopt", None)
    except OSError:
        mallopt = None
    if mallopt is None or not hasattr(libc, "gnu_get_libc_version"):
        return False
    done = bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES))
    if not done:
        log.warning("mallopt(M_MMAP_THRESHOLD) refused: the heap may grow with browsers that left")
    return done
