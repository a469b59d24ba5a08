"""Process memory: give large freed buffers back to the OS at once, and measure peaks.

The one memory helper of the project: `return_large_buffers_to_os` (below), `PeakRss` (peak
resident growth during a block, sampled) and `peak_rss_mb` (the process's peak so far).

glibc serves large allocations (OpenCV's image pyramids, SIFT's scale space) with mmap only
above a threshold that *grows* to the largest block freed so far; after the first SIFT, its
buffers come from per-thread heap arenas and stay resident once freed, so with view threads
each holding an arena the resident peak grows with the threads. Pinning the threshold keeps
large buffers mmapped and returned on free, for a little time (page faults on fresh buffers);
4 MB (the default) sits below SIFT's first-octave layers of an 800 px image. Figures in
docs/decisions.md.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import sys
import threading
import time

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


# peak memory -----------------------------------------------------------------------------------------
def _rss_bytes() -> int | None:
    """Resident set size of this process (psutil; None where psutil cannot tell)."""
    try:
        return int(_process().memory_info().rss)
    except Exception:  # noqa: BLE001  psutil missing or refusing (sandboxes): no measurement, no crash
        return None


_proc = None


def _process():
    """This process's psutil handle, made once (psutil caches per-process state in it)."""
    global _proc
    if _proc is None:
        import psutil

        _proc = psutil.Process()
    return _proc


def _release_free_memory() -> None:
    """Give freed heap back to the OS so the next measurement starts from a clean baseline."""
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


RUN_INTERVAL_S = 0.05
"""`PeakRss` sampling interval for whole runs (seconds to minutes): their peaks last far longer,
and at the 5 ms default the sampler thread took about 6 % of a `recon run` profile's samples
(a Python thread waking 200 times a second competes with the pair threads for the GIL)."""


class PeakRss:
    """Peak resident-set growth during a `with` block, sampled with psutil.

    Why RSS and not tracemalloc: tracemalloc sees only Python's allocator, not OpenCV's C++
    buffers (image pyramids, simulated views, descriptors), which are most of the memory here.
    A background thread samples the process RSS every `interval` s (OpenCV releases the GIL
    in its calls, so sampling continues while they run); `peak_mb` is the highest sample minus
    the RSS just before the block, in MB (2^20 bytes). Freed heap is trimmed (`malloc_trim`)
    before the block so memory left over by an earlier method does not hide the growth.
    Limits: spikes shorter than the interval can be missed, and the process baseline
    (interpreter, numpy, OpenCV, the two loaded images: `before_mb`) is excluded; `total_mb`
    is the absolute peak. Where psutil cannot read the RSS, all three are None.
    psutil's RSS is the one /proc/self/statm gives (the former reader; identical values, 26 vs
    33 us per sample) and also works on macOS and Windows. Child processes (the covariant-SIFT
    extractors of `matching.colmap_sift.extraction_processes`) count too: their RSS is added to
    each sample (the list of children is refreshed every `children_every` s; shared library
    pages count once per process, so the sum errs high).
    """

    def __init__(self, interval: float = 0.005, children_every: float = 0.25):
        self.interval = interval
        self.children_every = children_every
        self.before: int | None = None
        self.peak: int | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._children: list = []
        self._children_at = -1.0

    def _children_rss(self) -> int:
        """Summed RSS of this process's descendants (0 where psutil cannot tell)."""
        now = time.monotonic()
        if now - self._children_at >= self.children_every:
            self._children_at = now
            try:
                self._children = _process().children(recursive=True)
            except Exception:  # noqa: BLE001  psutil missing or refusing: own RSS only
                self._children = []
        total = 0
        for child in self._children:
            try:
                total += int(child.memory_info().rss)
            except Exception:  # noqa: BLE001  a child that just exited
                pass
        return total

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            r = _rss_bytes()
            if r is not None:
                r += self._children_rss()
                if self.peak is None or r > self.peak:
                    self.peak = r

    def __enter__(self) -> PeakRss:
        _release_free_memory()
        self.before = _rss_bytes()
        self.peak = self.before
        if self.before is not None:
            self._thread = threading.Thread(target=self._run, name="peak-rss", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        r = _rss_bytes()
        if r is not None and self.peak is not None and r > self.peak:
            self.peak = r

    @property
    def peak_mb(self) -> float | None:
        if self.before is None or self.peak is None:
            return None
        return max(0, self.peak - self.before) / 2**20

    @property
    def total_mb(self) -> float | None:
        return None if self.peak is None else self.peak / 2**20

    @property
    def before_mb(self) -> float | None:
        return None if self.before is None else self.before / 2**20


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MB (0.0 where the OS does not say)."""
    try:
        import resource
    except ImportError:  # Windows
        return 0.0
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KB on Linux, bytes on macOS
    return float(r) / (1024.0 * 1024.0) if sys.platform == "darwin" else float(r) / 1024.0
