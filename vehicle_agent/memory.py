"""How an agent process keeps the memory it frees.

Every interval an agent allocates and frees the same large arrays: its scan's rays
and cells, the stacked points of ~300 received objects (~34 000 points, 0.8 MB per
copy, several copies per pass of fusion), the bundles' bytes. glibc's malloc serves
such blocks with ``mmap`` and gives them back with ``munmap`` (or trims its heap), so
the next interval faults the same pages in again, each zeroed by the kernel: measured
at ~190 page faults per interval in fusion alone, a quarter of its CPU time. Raising
the thresholds keeps freed blocks in the process for reuse; what an agent holds stays
bounded by its largest interval's working set.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging

log = logging.getLogger(__name__)

M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters (malloc.h)
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024  # glibc's largest (HEAP_MAX_SIZE / 2 on 64-bit)
TRIM_THRESHOLD_BYTES = 256 * 1024 * 1024


def keep_freed_memory() -> bool:
    """Serve blocks up to 32 MB from the heap and never trim it (glibc ``mallopt``);
    False, and nothing changed, where the C library has no ``mallopt``."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        log.debug("no mallopt: freed memory goes back to the system as the C library decides")
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(mallopt(M_TRIM_THRESHOLD,
                                                                                  TRIM_THRESHOLD_BYTES))
