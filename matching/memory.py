"""Process-level memory behaviour: give large freed buffers back to the OS at once.

glibc serves large allocations (OpenCV's image pyramids, SIFT's scale space: ~120 MB for an
800 px image) with mmap only above a threshold that *grows* to the largest block freed so far;
after the first SIFT, its buffers come from per-thread heap arenas and stay resident once
freed, so with view threads each holding an arena the resident peak of a graf pair grew from
123 MB (one thread) to 197 MB (two). Pinning the threshold keeps large buffers mmapped and
returned on free. Measured on graf 1-2..1-6 (median time per pair / peak of 1-4):
unpinned 0.95 s / 197 MB; 1 MB 1.15 s / 140 MB (page faults on every fresh buffer);
4 MB (default: SIFT's first-octave layers of an 800 px image are 8 MB) 1.07 s / 149 MB.
"""

from __future__ import annotations

import ctypes
import ctypes.util

M_MMAP_THRESHOLD = -3  # glibc's mallopt parameter number
_done = False


def return_large_buffers_to_os(threshold_bytes: int = 4 << 20) -> bool:
    """Pin glibc's mmap threshold (see module doc); True if applied, False off glibc."""
    global _done
    if _done:
        return True
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        _done = bool(libc.mallopt(M_MMAP_THRESHOLD, int(threshold_bytes)))
    except (OSError, AttributeError):
        _done = False
    return _done
