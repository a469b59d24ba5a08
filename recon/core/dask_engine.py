"""The Dask engine: pair matching (and per-image retrieval features) as tasks on worker processes.

`make_dask_executor(address, workers)` gives a `DaskEngine` whose `.executor` is a
`concurrent.futures.Executor` (`distributed.Client.get_executor`), so the pipeline's match loop
(`submit`, `wait(FIRST_COMPLETED)`, results in pair order) runs unchanged on it:

* no address: a `LocalCluster` of `workers` worker PROCESSES with one thread each
  (`processes=True, threads_per_worker=1`), OpenCV's own thread pool in each sized to
  cores // workers (`local_worker_env`),
  and the dashboard on a free port (`dashboard_address=":0"`, so two runs never collide);
* an address (`tcp://HOST:8786`): `Client(address)` on an existing scheduler.

`engine.dashboard_link` is the dashboard URL: print it (`recon: Dask dashboard at ...`) so a
user can watch the tasks. Every task is submitted with `retries=TASK_RETRIES` (an exception in a
task is retried) and Dask reschedules the tasks of a worker that dies (its nanny restarts it),
so a killed worker loses no pair (see `tests/test_dask_engine.py`).

Tasks are module-level functions of small picklable specs (no pipeline state crosses the wire):

* `match_pair_on_worker(PairTaskSpec) -> PairResult`: each worker process builds its matcher
  once (`matching.registry.get_matcher(method, **overrides)`, a module-level dict keyed by
  (method, overrides)) and opens one `FeatureStore` per shared cache folder, loads
  and downscales the two images exactly as the pipeline's loader does
  (`recon.core.scene._decode_one`, the function `scan_scene` uses) and matches. The result is in
  working-resolution pixels, exactly what the thread pool's `match_pair_task` returns; the driver
  converts it to full resolution, caches it and writes the database (only the driver writes).
  Same seed, byte-identical arrays to the thread pool.
* `image_descriptors_on_worker(ImageTaskSpec) -> NDArray`: the retrieval descriptors of one image
  (`recon.core.retrieval.image_descriptors`), leaving the original's SIFT in the shared cache for
  the matching tasks.

Worker processes are started with `spawn` (Dask's default), which imports the driver's main
module again: a script that calls `make_dask_executor(None, n)` must do so under
`if __name__ == "__main__":` (the `recon` console script does; `recon/__main__.py`, run by
`python -m recon`, needs that guard too before it can start a local cluster).

Several machines: start a scheduler on one machine and a worker on each machine, with the
scene folder and the output folder (its `cache/features`) on a shared filesystem mounted at the
same path everywhere, and the same environment (`pip install recon` with `dask[distributed]`):

    machine A$ dask scheduler                        # prints tcp://A:8786, dashboard :8787
    every machine$ dask worker tcp://A:8786 --nthreads 1 --nworkers 2
    machine A$ recon run SCENE --out /shared/out --engine dask:tcp://A:8786

Without a shared filesystem, workers still work (each computes the features it needs and keeps
them in its own cache folder); only the driver reads the images' pair results and writes
`OUT/`. Images are read by path, so the scene folder must be visible at the same path.
"""

from __future__ import annotations

import os
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from matching.errors import InputError
from matching.registry import PairMatcher, get_matcher
from matching.store import FeatureStore
from matching.types import PairResult

TASK_RETRIES = 3  # an exception inside a task is retried this many times (then it is the pair's error)
IMAGES_PER_WORKER = 32  # decoded images a worker keeps (LRU); features stay in the disk cache


# task specs -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PairTaskSpec:
    """What a worker needs to match one pair, rebuilding its own state (all picklable, small)."""

    name0: str
    """Image names as in the scene (the FeatureStore keys)."""
    name1: str
    path0: Path
    """Image files, readable at this path on the worker (shared filesystem)."""
    path1: Path
    max_size: int | None
    """Working resolution, longer side in px (the pipeline's `max_size or None`)."""
    method: str
    """Matcher name (`matching.registry.METHODS`)."""
    overrides: tuple[tuple[str, Any], ...]
    """Matcher config overrides as sorted (key, value) pairs (see `pipeline_overrides`)."""
    seed: int
    """Seed (already one of `overrides` for matchers with a seed; kept for the report)."""
    cache_dir: Path | None
    """Shared feature cache folder (OUT/cache/features), None = no disk cache."""


@dataclass(frozen=True)
class ImageTaskSpec:
    """What a worker needs to compute one image's retrieval descriptors."""

    name: str
    path: Path
    max_size: int | None
    cache_dir: Path | None
    retrieval: Any = None
    """A `recon.core.retrieval.RetrievalConfig` (None = its defaults)."""


def pipeline_overrides(method: str, seed: int) -> tuple[tuple[str, Any], ...]:
    """The overrides of the pipeline's matcher for `method` without user options
    (`recon.core.stages.match.matcher_overrides` with one thread inside), as sorted pairs."""
    from recon.core.stages.match import matcher_overrides

    return tuple(sorted(matcher_overrides(method, seed, inner_workers=1).items()))


def pair_task_specs(scene: Any, pairs: list[tuple[str, str]], method: str, seed: int, max_size: int | None,
                    cache_dir: Path | None, overrides: tuple[tuple[str, Any], ...] | None = None
                    ) -> list[PairTaskSpec]:
    """One PairTaskSpec per pair of a scanned `recon.core.scene.Scene` (image paths from the scene)."""
    ov = pipeline_overrides(method, seed) if overrides is None else overrides
    paths = {im.name: Path(im.path) for im in scene.images}
    return [PairTaskSpec(a, b, paths[a], paths[b], max_size or None, method, ov, int(seed),
                         None if cache_dir is None else Path(cache_dir)) for a, b in pairs]


# worker side ------------------------------------------------------------------------------------
@dataclass
class _WorkerStore:
    """This process's FeatureStore over one cache folder, with an LRU of decoded images."""

    store: FeatureStore
    loaded: OrderedDict[str, None] = field(default_factory=OrderedDict)
    pins: dict[str, int] = field(default_factory=dict)  # images a running task uses: never evicted
    lock: threading.Lock = field(default_factory=threading.Lock)


_STORES: dict[str | None, _WorkerStore] = {}
_MATCHERS: dict[tuple[str, str], PairMatcher] = {}
_GUARD = threading.Lock()


def _store(cache_dir: Path | None) -> _WorkerStore:
    """The process-wide store over `cache_dir`, opened once."""
    key = None if cache_dir is None else str(cache_dir)
    with _GUARD:
        if key not in _STORES:
            _STORES[key] = _WorkerStore(FeatureStore(cache_dir=cache_dir))
        return _STORES[key]


def _matcher(method: str, overrides: tuple[tuple[str, Any], ...]) -> PairMatcher:
    """The process-wide matcher for (method, overrides), built once."""
    key = (method, repr(overrides))
    with _GUARD:
        if key not in _MATCHERS:
            _MATCHERS[key] = get_matcher(method, **dict(overrides))
        return _MATCHERS[key]


def load_working_gray(path: Path, max_size: int | None) -> NDArray[np.uint8]:
    """The image at `path` as the pipeline loads it: 8-bit gray at the working resolution."""
    from recon.core.scene import _decode_one  # the loader scan_scene uses (one implementation)

    res = _decode_one(Path(path), max_size)
    if isinstance(res, str):
        raise InputError(f"{path}: {res}")
    return res[0]


def _ensure_image(st: _WorkerStore, name: str, path: Path, max_size: int | None) -> None:
    """Load `name` into the store unless it is there, and pin it (see `_unpin`); evict the least
    recently used unpinned images beyond IMAGES_PER_WORKER."""
    with st.lock:
        st.pins[name] = st.pins.get(name, 0) + 1
        if name in st.loaded:
            st.loaded.move_to_end(name)
            return
    try:
        gray = load_working_gray(path, max_size)
    except BaseException:
        _unpin(st, name)
        raise
    with st.lock:
        if name not in st.loaded:
            st.store.add_image(name, gray)
            st.loaded[name] = None
        excess = len(st.loaded) - IMAGES_PER_WORKER
        for old in [n for n in st.loaded if not st.pins.get(n)][:max(0, excess)]:
            del st.loaded[old]
            st.store.drop_image(old)


def _unpin(st: _WorkerStore, name: str) -> None:
    with st.lock:
        n = st.pins.get(name, 0) - 1
        if n > 0:
            st.pins[name] = n
        else:
            st.pins.pop(name, None)


def register_images(cache_dir: Path | None, grays: dict[str, NDArray[np.uint8]]) -> None:
    """Hand already decoded working-resolution images to this process's store over `cache_dir`,
    so `match_pair_on_worker` run in the driver's own threads (`--engine threads`) does not
    decode them again. Optional: a task loads any image it lacks."""
    st = _store(cache_dir)
    with st.lock:
        for name, gray in grays.items():
            if name not in st.loaded:
                st.store.add_image(name, gray)
                st.loaded[name] = None


def match_pair_on_worker(spec: PairTaskSpec) -> PairResult:
    """Match one pair in this (worker) process; the result is in working-resolution pixels."""
    st = _store(spec.cache_dir)
    matcher = _matcher(spec.method, spec.overrides)
    _ensure_image(st, spec.name0, spec.path0, spec.max_size)
    try:
        _ensure_image(st, spec.name1, spec.path1, spec.max_size)
        try:
            return matcher.match(st.store, spec.name0, spec.name1)
        finally:
            _unpin(st, spec.name1)
    finally:
        _unpin(st, spec.name0)


def image_descriptors_on_worker(spec: ImageTaskSpec) -> NDArray[np.float32]:
    """Retrieval descriptors of one image (`recon.core.retrieval.image_descriptors`)."""
    from recon.core.retrieval import RetrievalConfig, image_descriptors

    st = _store(spec.cache_dir)
    _ensure_image(st, spec.name, spec.path, spec.max_size)
    try:
        return image_descriptors(st.store, spec.name, spec.retrieval or RetrievalConfig())
    finally:
        _unpin(st, spec.name)


# driver side ------------------------------------------------------------------------------------
class DaskEngine:
    """A Dask client (and its LocalCluster, if it started one) with a concurrent.futures executor.

    Use as a context manager or call `close()`; `executor` submits with `retries=TASK_RETRIES`
    and `pure=False` (every submit is its own task, even for equal arguments).
    """

    def __init__(self, client: Any, cluster: Any = None):
        self.client = client
        self.cluster = cluster
        self.executor = client.get_executor(retries=TASK_RETRIES, pure=False)

    @property
    def dashboard_link(self) -> str | None:
        """The dashboard URL (None when the scheduler has no dashboard)."""
        try:
            return self.client.dashboard_link
        except Exception:
            return None

    @property
    def num_workers(self) -> int:
        return len(self.client.scheduler_info(n_workers=-1).get("workers", {}))

    def close(self) -> None:
        try:
            self.client.close()
        finally:
            if self.cluster is not None:
                self.cluster.close()

    def __enter__(self) -> DaskEngine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def parse_dask_engine(spec: str) -> str | None:
    """`dask` -> None (a local cluster), `dask:ADDRESS` -> ADDRESS; ValueError (one line) otherwise."""
    s = (spec or "").strip()
    if s == "dask":
        return None
    if s.startswith("dask:") and len(s) > len("dask:"):
        return s[len("dask:"):]
    raise ValueError(f"--engine {spec!r}: expected dask or dask:ADDRESS (e.g. dask:tcp://HOST:8786)")


def local_worker_env(workers: int, cpu_count: int | None = None,
                     environ: dict[str, str] | None = None) -> dict[str, str]:
    """Environment of a LocalCluster's worker processes: OpenCV's own thread pool sized to this
    machine's share per worker (`OPENCV_FOR_THREADS_NUM` = max(1, cores // workers)), unless the
    user set the variable. Dask already pins OMP/MKL/OpenBLAS to one thread per worker for the
    same reason; OpenCV's pthreads pool is not covered, and W workers each starting a pool of one
    thread per core put W x cores threads on the machine. OpenCV reads the variable on its first
    parallel call, so Nanny's `env` (applied before any task) is in time (a test checks it with a
    driver that imports cv2 first). On 2 cores it changes nothing measurable (orbit-50,
    retrieval:10, 2 workers: 228 s match stage by default, 226 s pinned to one thread each);
    it guards machines with many cores and workers."""
    env = dict(os.environ if environ is None else environ)
    if env.get("OPENCV_FOR_THREADS_NUM"):
        return {}
    cores = cpu_count or os.cpu_count() or 1
    return {"OPENCV_FOR_THREADS_NUM": str(max(1, cores // max(1, workers)))}


def make_dask_executor(address: str | None, workers: int) -> DaskEngine:
    """A DaskEngine: a LocalCluster of `workers` single-thread worker processes when `address`
    is None, else a client of the scheduler at `address`. Raises ImportError with the install
    hint when distributed is missing."""
    try:
        from distributed import Client, LocalCluster
    except ImportError as e:  # pragma: no cover - depends on the install
        raise ImportError("the dask engine needs dask[distributed]: pip install 'dask[distributed]'") from e
    if address:
        return DaskEngine(Client(address))
    n = max(1, int(workers))
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                           dashboard_address=":0", silence_logs=40, env=local_worker_env(n))
    try:
        return DaskEngine(Client(cluster), cluster)
    except BaseException:
        cluster.close()
        raise
