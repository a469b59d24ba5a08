"""The feature store's disk cache (matching.store.FeatureStore with a cache_dir): features written
once, reloaded identical by a new store over the same folder, and a damaged or foreign cache file
recomputed, never trusted."""

from __future__ import annotations

import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from matching.features import DetectorConfig, Features, detect
from matching.store import FeatureStore

SIFT = DetectorConfig("sift", max_features=500)


def _texture(seed: int = 0) -> np.ndarray:
    """A 240 x 320 blurred random texture: a few hundred SIFT keypoints."""
    rng = np.random.default_rng(seed)
    return cv2.resize(rng.integers(0, 255, (60, 80), dtype=np.uint8), (320, 240), interpolation=cv2.INTER_CUBIC)


class Counting:
    """compute() for get_or_compute that counts its calls."""

    def __init__(self, img: np.ndarray, cfg: DetectorConfig = SIFT):
        self.img, self.cfg, self.calls = img, cfg, 0

    def __call__(self) -> Features:
        self.calls += 1
        return detect(self.img, self.cfg)


def _cache_files(d: Path) -> list[Path]:
    return sorted(p for p in d.rglob("*") if p.is_file())


def _same(a: Features, b: Features) -> None:
    for name in ("kpts", "sizes", "angles", "descriptors", "responses"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_array_equal(x, y, err_msg=name)
            assert x.dtype == y.dtype, name


def test_features_are_written_once_and_reloaded_identical(tmp_path):
    img = _texture()
    first = FeatureStore(tmp_path / "cache")
    first.add_image("a.png", img)
    compute = Counting(img)
    f1 = first.get_or_compute("a.png", SIFT.key, compute)
    assert compute.calls == 1 and len(f1) > 100
    assert first.get_or_compute("a.png", SIFT.key, compute) is f1 and compute.calls == 1  # memory
    (cached,) = _cache_files(tmp_path / "cache")
    assert cached.suffix == ".npz"
    written = cached.stat().st_mtime_ns

    again = FeatureStore(tmp_path / "cache")  # a new run over the same folder
    again.add_image("a.png", img.copy())
    compute2 = Counting(img)
    f2 = again.get_or_compute("a.png", SIFT.key, compute2)
    assert compute2.calls == 0 and again.hits == 1 and again.misses == 0
    _same(f1, f2)
    assert _cache_files(tmp_path / "cache") == [cached] and cached.stat().st_mtime_ns == written


def test_the_cache_is_keyed_by_image_content_and_key_not_by_name(tmp_path):
    store = FeatureStore(tmp_path)
    img = _texture()
    store.add_image("a.png", img)
    store.get_or_compute("a.png", SIFT.key, Counting(img))
    orb = DetectorConfig("orb", max_features=300)
    store.get_or_compute("a.png", orb.key, Counting(img, orb))  # another key: another file
    assert len(_cache_files(tmp_path)) == 2

    renamed = FeatureStore(tmp_path)  # the same pixels under another name: reused
    renamed.add_image("b.png", img)
    c = Counting(img)
    renamed.get_or_compute("b.png", SIFT.key, c)
    assert c.calls == 0

    changed = FeatureStore(tmp_path)  # other pixels under the old name: recomputed
    other = _texture(1)
    changed.add_image("a.png", other)
    c = Counting(other)
    f = changed.get_or_compute("a.png", SIFT.key, c)
    assert c.calls == 1
    _same(f, detect(other, SIFT))
    assert len(_cache_files(tmp_path)) == 3


@pytest.mark.parametrize("damage", ["truncated", "garbage", "empty", "other_key"])
def test_a_damaged_cache_file_is_recomputed_not_trusted(tmp_path, damage):
    img = _texture()
    store = FeatureStore(tmp_path)
    store.add_image("a.png", img)
    good = store.get_or_compute("a.png", SIFT.key, Counting(img))
    (path,) = _cache_files(tmp_path)
    data = path.read_bytes()
    if damage == "truncated":  # a file cut short (a full disk, a copy interrupted)
        path.write_bytes(data[: len(data) // 2])
    elif damage == "garbage":
        path.write_bytes(b"\x00not a numpy archive" * 50)
    elif damage == "empty":
        path.write_bytes(b"")
    else:  # a well-formed archive of another entry under this file name (a hash collision, a stray copy)
        np.savez(path, key=np.array("orb300"), kpts=np.zeros((3, 2), np.float32), sizes=np.ones(3, np.float32),
                 angles=np.zeros(3, np.float32), descriptors=np.zeros((3, 32), np.uint8))

    fresh = FeatureStore(tmp_path)
    fresh.add_image("a.png", img)
    c = Counting(img)
    f = fresh.get_or_compute("a.png", SIFT.key, c)
    assert c.calls == 1 and fresh.misses == 1
    _same(f, good)
    # the recomputed entry replaced the bad file: the next run loads it
    third = FeatureStore(tmp_path)
    third.add_image("a.png", img)
    c3 = Counting(img)
    _same(third.get_or_compute("a.png", SIFT.key, c3), good)
    assert c3.calls == 0
    assert not [p for p in tmp_path.rglob("*.tmp.npz")]  # no temporary file left


def test_no_cache_dir_or_persist_false_writes_nothing(tmp_path):
    img = _texture()
    mem = FeatureStore()
    mem.add_image("a.png", img)
    c = Counting(img)
    mem.get_or_compute("a.png", SIFT.key, c)
    assert c.calls == 1 and mem.cache_dir is None

    store = FeatureStore(tmp_path / "cache")
    store.add_image("a.png", img)
    store.get_or_compute("a.png", "views-only", Counting(img), persist=False)
    assert _cache_files(tmp_path / "cache") == []


def test_concurrent_requests_compute_once_and_write_one_file(tmp_path):
    img = _texture()
    store = FeatureStore(tmp_path)
    store.add_image("a.png", img)
    compute = Counting(img)
    results: list[Features] = []
    threads = [threading.Thread(target=lambda: results.append(store.get_or_compute("a.png", SIFT.key, compute)))
               for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert compute.calls == 1 and len(results) == 6 and all(r is results[0] for r in results)
    assert len(_cache_files(tmp_path)) == 1
