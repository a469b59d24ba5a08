"""Pair discovery, the bench runner and `recon bench pairs`."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from matching.memory import PeakRss
from recon.eval.bench_pairs import discover_pairs, ratio_line, summarize, write_json
from shared_paths import SHARED_DATA as DATA

needs_data = pytest.mark.requires_shared("oxford/graf/img1.png", "oxford/graf/img2.png", "oxford/graf/H1to2p")

REQUIRED = {"pair", "method", "points", "correct", "precision", "seconds", "peak_mb", "ref_correct"}


@pytest.mark.requires_shared("oxford/graf", "hpatches/v_dogman", "hpatches/v_adam_noH", "evd/1", "evd/2", "evd/h")
def test_discover_shared_data():
    pairs = discover_pairs(DATA)
    names = [p.name for p in pairs]
    assert [n for n in names if n.startswith("graf ")] == [f"graf 1-{k}" for k in range(2, 7)]
    assert [n for n in names if n.startswith("v_dogman ")] == [f"v_dogman 1-{k}" for k in range(2, 7)]
    evd = [n for n in names if n.startswith("evd ")]
    assert len(evd) == 8 and "evd adam" in evd
    assert not any("v_adam" in n for n in names)  # no homography files: skipped
    assert len(pairs) == 18
    for p in pairs:
        assert p.H_1_from_0.shape == (3, 3) and p.H_1_from_0[2, 2] == pytest.approx(1.0)
        assert p.path0.is_file() and p.path1.is_file()
    adam = pairs[names.index("evd adam")]
    assert adam.path0 == DATA / "evd" / "1" / "adam.png" and adam.path1 == DATA / "evd" / "2" / "adam.png"
    # the set folder itself is also a valid root
    assert [p.name for p in discover_pairs(DATA / "oxford" / "graf")] == [f"graf 1-{k}" for k in range(2, 7)]


def test_discover_nothing(tmp_path):
    assert discover_pairs(tmp_path) == []
    assert discover_pairs(tmp_path / "missing") == []


def _tiny_root(root: Path, scale: float = 0.5) -> Path:
    """oxford/graf with img1, img2 downscaled and H1to2p adjusted for the scaling."""
    d = root / "oxford" / "graf"
    d.mkdir(parents=True)
    for k in (1, 2):
        img = cv2.imread(str(DATA / "oxford" / "graf" / f"img{k}.png"), cv2.IMREAD_GRAYSCALE)
        small = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(d / f"img{k}.png"), small)
    H = np.loadtxt(DATA / "oxford" / "graf" / "H1to2p")
    # pixel centres: x_small = (x + 0.5) * scale - 0.5
    S = np.array([[scale, 0, 0.5 * scale - 0.5], [0, scale, 0.5 * scale - 0.5], [0, 0, 1.0]])
    np.savetxt(d / "H1to2p", S @ H @ np.linalg.inv(S))
    return root


def _synthetic_root(root: Path) -> Path:
    """An oxford/graf-shaped folder (img1, img2, H1to2p) of a random texture and its shifted copy."""
    d = root / "oxford" / "graf"
    d.mkdir(parents=True)
    rng = np.random.default_rng(0)
    img = cv2.resize(rng.integers(0, 255, (60, 80), dtype=np.uint8), (320, 240), interpolation=cv2.INTER_CUBIC)
    cv2.imwrite(str(d / "img1.png"), img)
    cv2.imwrite(str(d / "img2.png"), np.roll(img, 5, axis=1))
    np.savetxt(d / "H1to2p", np.array([[1.0, 0, 5], [0, 1, 0], [0, 0, 1]]))
    return root


@needs_data
def test_cli_bench_pairs_writes_json(tmp_path, capsys):
    from recon.cli import main

    root = _tiny_root(tmp_path / "data")
    out = tmp_path / "out" / "out.json"
    rc = main(["bench", "pairs", str(root), "--methods", "sift,orb", "--json", str(out), "--no-progress"])
    assert rc == 0
    rows = json.loads(out.read_text())
    assert [(r["pair"], r["method"]) for r in rows] == [("graf 1-2", "sift"), ("graf 1-2", "orb")]
    for r in rows:
        assert REQUIRED <= set(r)
        assert r["ref_correct"] is None  # baselines choose no reference
        assert r["gt_reference"] == 0
        assert r["seconds"] > 0 and 0 <= r["precision"] <= 1
        assert r["correct"] <= r["correct_5px"] <= r["points"]
    sift = rows[0]
    assert sift["points"] >= 100 and sift["precision"] >= 0.7  # the scaled H is right
    assert not [p for p in out.parent.iterdir() if p.name != "out.json"]  # no temp file left
    text = capsys.readouterr().out
    assert "graf 1-2" in text and "sift" in text and "Summary" in text


def test_cli_unknown_method_is_one_line(tmp_path, capsys):
    from recon.cli import main

    rc = main(["bench", "pairs", str(tmp_path), "--methods", "sift,surf"])
    assert rc == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "surf" in err and "extra-affine" in err


def test_cli_no_pairs_is_one_line(tmp_path, capsys):
    from recon.cli import main

    rc = main(["bench", "pairs", str(tmp_path), "--methods", "sift"])
    assert rc == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no ground-truth pairs" in err
    assert main(["bench", "pairs", str(tmp_path / "nope"), "--methods", "sift"]) == 2


def test_cli_only_filter_matches_nothing(tmp_path, capsys):
    from recon.cli import main

    root = _synthetic_root(tmp_path / "data")
    assert [p.name for p in discover_pairs(root)] == ["graf 1-2"]
    assert main(["bench", "pairs", str(root), "--methods", "orb", "--only", "boat"]) == 2
    assert "boat" in capsys.readouterr().err


def _row(method, pair, prec, correct, sec, mb, ref=None):
    return {"pair": pair, "method": method, "points": correct, "correct": correct, "precision": prec,
            "seconds": sec, "peak_mb": mb, "ref_correct": ref}


def test_summary_and_ratio_line():
    rows = [_row("extra-affine", "a", 0.9, 300, 1.0, 100, True), _row("asift", "a", 0.8, 900, 5.0, 400),
            _row("extra-affine", "b", 0.4, 300, 3.0, 100, False), _row("asift", "b", 0.9, 10, 5.0, 400),
            _row("extra-affine", "c", 0.95, 30, 2.0, 200, None), _row("asift", "c", 0.9, 50, 5.0, 400)]
    s = summarize(rows)
    assert s["extra-affine"]["solved"] == 2 and s["asift"]["solved"] == 2
    assert s["extra-affine"]["median_seconds"] == 2.0 and s["asift"]["median_peak_mb"] == 400
    assert s["extra-affine"]["ref_accuracy"] == 0.5 and s["extra-affine"]["ref_decided"] == 2
    assert s["asift"]["ref_accuracy"] is None
    line = ratio_line(s)
    assert "2.50 x faster than asift" in line and "peak memory = 25 % of asift" in line
    assert ratio_line(summarize([r for r in rows if r["method"] == "asift"])) is None


def test_write_json_atomic(tmp_path):
    p = tmp_path / "r.json"
    write_json(p, [{"a": np.float32(1.5), "b": float("nan"), "c": np.int64(3)}])
    assert json.loads(p.read_text()) == [{"a": 1.5, "b": None, "c": 3}]
    assert [x.name for x in tmp_path.iterdir()] == ["r.json"]


@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="RSS sampling needs /proc")
def test_peak_rss_sees_native_allocations():
    with PeakRss() as mem:
        a = cv2.resize(np.zeros((100, 100), np.float64), (6000, 6000))  # 288 MB allocated by OpenCV
        a[:] = 1.0
        del a
    assert mem.peak_mb is not None and mem.peak_mb > 200
    assert mem.total_mb >= mem.before_mb + mem.peak_mb - 1


@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="RSS sampling needs /proc")
def test_peak_rss_counts_child_processes():
    """A child's memory (the covariant-SIFT extractors run in children) is part of the peak."""
    import subprocess
    import sys

    code = "import numpy as np, time; a = np.ones(300 * 2**20 // 8); time.sleep(1.5)"
    with PeakRss() as mem:
        subprocess.run([sys.executable, "-c", code], check=True)
    assert mem.peak_mb is not None and mem.peak_mb > 250
