"""The Dask engine: worker-side pair tasks equal the thread pool's, and a killed worker loses no pair."""

from __future__ import annotations

import os
import signal
import time
from concurrent.futures import ThreadPoolExecutor, wait

import numpy as np
import pytest

pytest.importorskip("distributed")

from matching.store import FeatureStore  # noqa: E402
from recon.core import dask_engine as D  # noqa: E402
from recon.core.scene import scan_scene  # noqa: E402

PAIRS6 = [("view_00.png", "view_01.png"), ("view_00.png", "view_02.png"), ("view_01.png", "view_02.png"),
          ("view_01.png", "view_03.png"), ("view_02.png", "view_03.png"), ("view_03.png", "view_04.png")]


def test_parse_dask_engine():
    assert D.parse_dask_engine("dask") is None
    assert D.parse_dask_engine("dask:tcp://10.0.0.1:8786") == "tcp://10.0.0.1:8786"
    for bad in ("dask:", "threads", "dusk:x", ""):
        with pytest.raises(ValueError) as e:
            D.parse_dask_engine(bad)
        assert "\n" not in str(e.value)


@pytest.mark.parametrize("method", ["extra-affine", "sift"])
def test_pipeline_overrides_build_the_pipeline_matcher(method):
    from matching.registry import get_matcher
    from recon.core.stages.match import make_matcher, matcher_identity

    ov = D.pipeline_overrides(method, 7)
    assert matcher_identity(get_matcher(method, **dict(ov))) == matcher_identity(make_matcher(method, 7, 1))


@pytest.fixture(scope="module")
def scene5(tmp_path_factory):
    """A 5-view facade sweep at 320x240 and the thread pool's results for six pairs (the reference)."""
    from recon.core.pipeline import make_matcher, match_pair_task
    from scenes.render import render_scene

    out = tmp_path_factory.mktemp("facade5")
    render_scene(out, "facade-5x40", image_size=(320, 240))
    scene, grays = scan_scene(out, max_size=1600)
    store = FeatureStore(cache_dir=out / "threads-cache")
    for n in scene.names:
        store.add_image(n, grays[n])
    matcher = make_matcher("extra-affine", seed=3, inner_workers=1)
    with ThreadPoolExecutor(2) as ex:
        ref = list(ex.map(lambda p: match_pair_task(store, matcher, *p), PAIRS6))
    return scene, ref, out


def _same(a, b) -> None:
    for f in ("kpts0", "kpts1", "matches", "distances"):
        x, y = np.asarray(getattr(a, f)), np.asarray(getattr(b, f))
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), f
    assert (a.reference, a.best_views, a.reason, a.escalation) == (b.reference, b.best_views, b.reason, b.escalation)


def test_worker_task_in_threads_equals_pipeline_task(scene5, tmp_path):
    """The worker function itself (here in this process's threads) reproduces the pipeline's task."""
    scene, ref, _ = scene5
    specs = D.pair_task_specs(scene, PAIRS6[:2], "extra-affine", 3, 1600, tmp_path / "cache")
    grays = {im.name: D.load_working_gray(im.path, 1600) for im in scene.images[:2]}
    D.register_images(tmp_path / "cache", grays)  # view_02 is loaded by the task itself
    assert D._store(tmp_path / "cache").store.image("view_00.png") is grays["view_00.png"]
    with ThreadPoolExecutor(2) as ex:
        got = list(ex.map(D.match_pair_on_worker, specs))
    for a, b in zip(ref[:2], got):
        _same(a, b)
    assert any(r.num_matches > 50 for r in got)


def test_user_matcher_options_reach_the_workers(scene5, tmp_path):
    """`--set matcher.*` options travel in the task spec: a worker builds the driver's matcher
    (same identity, so the same pair cache key) and returns the driver's result."""
    from recon.config import MatchConfig
    from recon.core.stages.match import make_matcher, match_pair_task, matcher_identity, matcher_overrides

    scene, _, _ = scene5
    cfg = MatchConfig(method="extra-affine", engine="dask",
                      matcher={"fine_top_k": 1, "coarse.rank_by": "matches", "escalation.steep.candidates": 3})
    ov = tuple(sorted(matcher_overrides(cfg, 3, inner_workers=1).items()))
    driver = make_matcher(cfg, 3, inner_workers=1)
    assert matcher_identity(D._matcher("extra-affine", ov)) == matcher_identity(driver)
    assert matcher_identity(driver) != matcher_identity(make_matcher("extra-affine", 3, 1))  # the options count
    spec = D.pair_task_specs(scene, PAIRS6[1:2], "extra-affine", 3, 1600, tmp_path / "cache", ov)[0]
    store = FeatureStore()
    for im in scene.images[:3]:
        store.add_image(im.name, D.load_working_gray(im.path, 1600))
    _same(match_pair_task(store, driver, *PAIRS6[1]), D.match_pair_on_worker(spec))


def test_first_pass_matcher_reaches_the_workers(scene5, tmp_path):
    """`--simulate needed`'s first pass (originals only) on a Dask worker: the spec carries its
    extra overrides, so the worker builds the driver's first-pass matcher (same identity, same
    pair cache key) and returns the driver's result."""
    from recon.config import MatchConfig
    from recon.core.stages.match import (
        first_pass_overrides,
        make_matcher,
        match_pair_task,
        matcher_identity,
        matcher_overrides,
    )

    scene, _, _ = scene5
    cfg = MatchConfig(method="extra-affine", engine="dask", simulate="needed")
    extra = first_pass_overrides(cfg)
    ov = tuple(sorted({**matcher_overrides(cfg, 3, inner_workers=1), **extra}.items()))
    driver = make_matcher(cfg, 3, inner_workers=1, extra=extra)
    assert not driver.cfg.simulate
    assert matcher_identity(D._matcher("extra-affine", ov)) == matcher_identity(driver)
    assert matcher_identity(driver) != matcher_identity(make_matcher(cfg, 3, inner_workers=1))
    spec = D.pair_task_specs(scene, PAIRS6[1:2], "extra-affine", 3, 1600, tmp_path / "cache", ov)[0]
    store = FeatureStore()
    for im in scene.images[:3]:
        store.add_image(im.name, D.load_working_gray(im.path, 1600))
    here, there = match_pair_task(store, driver, *PAIRS6[1]), D.match_pair_on_worker(spec)
    _same(here, there)
    assert there.path in ("originals", "deferred") and there.coarse_scores == []


def _opencv_threads() -> int:
    import cv2

    return int(cv2.getNumThreads())


def test_local_workers_share_the_cores_between_their_opencv_pools():
    assert D.local_worker_env(2, cpu_count=2, environ={}) == {"OPENCV_FOR_THREADS_NUM": "1"}
    assert D.local_worker_env(1, cpu_count=8, environ={}) == {"OPENCV_FOR_THREADS_NUM": "8"}
    assert D.local_worker_env(3, cpu_count=8, environ={}) == {"OPENCV_FOR_THREADS_NUM": "2"}
    assert D.local_worker_env(16, cpu_count=8, environ={}) == {"OPENCV_FOR_THREADS_NUM": "1"}
    # the user's own setting wins (the workers inherit it)
    assert D.local_worker_env(2, cpu_count=8, environ={"OPENCV_FOR_THREADS_NUM": "3"}) == {}


_DRIVER_IMPORTING_CV2 = """
import cv2  # at the top, as `python -m recon` does: a spawned worker re-imports this module
from recon.core.dask_engine import make_dask_executor


def opencv_threads():
    import cv2

    return cv2.getNumThreads()


if __name__ == "__main__":
    with make_dask_executor(None, 2) as engine:
        print(sorted(engine.client.run(opencv_threads).values()))
"""


@pytest.mark.slow
def test_local_workers_opencv_pools_when_the_driver_imported_cv2_first(tmp_path):
    """The workers' OpenCV pools are their share of the cores even when the driver's main module
    imports cv2, which a spawned worker re-imports before Nanny applies its `env` (OpenCV reads
    the variable on its first parallel call, so the variable must reach the workers before any
    task; without `env=local_worker_env(n)` this fails on a machine of 2 or more cores)."""
    import subprocess
    import sys
    from pathlib import Path

    script = tmp_path / "driver.py"
    script.write_text(_DRIVER_IMPORTING_CV2)
    env = {k: v for k, v in os.environ.items() if k != "OPENCV_FOR_THREADS_NUM"}
    env["PYTHONPATH"] = os.pathsep.join([str(Path(__file__).resolve().parents[1]), env.get("PYTHONPATH", "")])
    out = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    want = max(1, (os.cpu_count() or 1) // 2)
    assert out.stdout.strip().splitlines()[-1] == str([want, want])


@pytest.mark.slow
def test_dask_equals_threads_and_survives_a_killed_worker(scene5, tmp_path):
    scene, ref, out = scene5
    specs = D.pair_task_specs(scene, PAIRS6, "extra-affine", 3, 1600, tmp_path / "cache")
    with D.make_dask_executor(None, 2) as engine:
        assert engine.dashboard_link and engine.dashboard_link.startswith("http")
        assert engine.num_workers == 2
        # 0. each worker's OpenCV pool is its share of the cores (no oversubscription)
        want = int(os.environ.get("OPENCV_FOR_THREADS_NUM") or max(1, (os.cpu_count() or 1) // 2))
        assert set(engine.client.run(_opencv_threads).values()) == {want}
        # 1. same seed, byte-identical results to the thread pool
        futs = [engine.executor.submit(D.match_pair_on_worker, s) for s in specs]
        got = [f.result(timeout=600) for f in futs]
        for a, b in zip(ref, got):
            _same(a, b)

        # 2. kill a busy worker process mid-run: every pair still comes back, unchanged
        pids = engine.client.run(os.getpid)  # {worker address: pid}
        specs2 = D.pair_task_specs(scene, PAIRS6, "extra-affine", 3, 1600, tmp_path / "cache2")
        futs = [engine.executor.submit(D.match_pair_on_worker, s) for s in specs2]
        victim = None
        deadline = time.monotonic() + 120
        while victim is None and time.monotonic() < deadline:
            busy = [w for w, keys in engine.client.processing().items() if keys]
            if busy:
                victim = pids[sorted(busy)[0]]
            else:
                time.sleep(0.05)
        assert victim is not None, "no worker ever became busy"
        assert not all(f.done() for f in futs)
        os.kill(victim, signal.SIGKILL)
        done, not_done = wait(futs, timeout=600)
        assert not not_done
        for a, f in zip(ref, futs):
            _same(a, f.result())
        assert victim not in engine.client.run(os.getpid).values()  # the nanny started a new process

        # 3. per-image retrieval descriptors as tasks equal the local computation
        from recon.core.retrieval import RetrievalConfig, image_descriptors

        cfg = RetrievalConfig(views=())
        im = scene.images[0]
        spec = D.ImageTaskSpec(im.name, im.path, 1600, tmp_path / "cache", cfg)
        remote = engine.executor.submit(D.image_descriptors_on_worker, spec).result(timeout=300)
        local_store = FeatureStore()
        local_store.add_image(im.name, D.load_working_gray(im.path, 1600))
        assert np.array_equal(remote, image_descriptors(local_store, im.name, cfg))


def test_worker_store_evicts_only_unpinned_images(scene5, tmp_path, monkeypatch):
    monkeypatch.setattr(D, "IMAGES_PER_WORKER", 2)
    ims = scene5[0].images[:4]
    st = D._store(tmp_path / "lru")
    D._ensure_image(st, ims[0].name, ims[0].path, 1600)  # stays pinned: a task is using it
    for im in ims[1:]:
        D._ensure_image(st, im.name, im.path, 1600)
        D._unpin(st, im.name)
    assert list(st.loaded) == [ims[0].name, ims[3].name]
    assert ims[0].name in st.store and ims[1].name not in st.store
    D._unpin(st, ims[0].name)
    assert st.pins == {}
