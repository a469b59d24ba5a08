"""Rerun views and recordings (issue 14, item 3): the pair view as line strips, the labelled heat
map, the rebuilt growth replay, stale recordings, --clean-cache, `recon view --web` and the
headless hint."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

pytest.importorskip("rerun")

from matching.types import PairResult  # noqa: E402
from recon.cli import main  # noqa: E402
from recon.viz.rerun_log import (  # noqa: E402
    MAX_STRIPS,
    Sink,
    heatmap_figure,
    heatmap_image,
    log_single_pair,
    match_strips,
    pair_entity,
    replay_steps,
)


def _batches(rrd: Path) -> dict[str, list]:
    """{entity path: [record batches]} of a recording."""
    from rerun.chunk import RrdReader

    out: dict[str, list] = {}
    for c in RrdReader(rrd).stream().to_chunks():
        out.setdefault(str(c.entity_path), []).append(c.to_record_batch())
    return out


def _column(batches: list, name: str) -> list:
    return [v for b in batches if name in b.schema.names for v in b.column(name).to_pylist()]


def _instances(batches: list, name: str) -> list:
    """The instances of a component over all rows (each row holds a list of them)."""
    return [x for row in _column(batches, name) for x in row]


def _result(n_in: int, n_out: int, seed: int = 0) -> PairResult:
    rng = np.random.default_rng(seed)
    n = n_in + n_out
    k0 = rng.uniform(0, 600, (n, 2)).astype(np.float32)
    k1 = rng.uniform(0, 400, (n, 2)).astype(np.float32)
    return PairResult("test", k0, k1, np.stack([np.arange(n), np.arange(n)], 1).astype(np.int32),
                      np.zeros(n, np.float32), inlier_mask=np.arange(n) < n_in)


def test_pair_view_draws_inliers_and_outliers_as_separate_line_strips(tmp_path):
    """Two photos (800x600 and 400x400), 40 inliers and 12 outliers: the recording holds the two
    images side by side without lines, and one strip per match in two entities, at the
    keypoints scaled to the picture (+0.5: Rerun's pixel centres)."""
    p0, p1 = tmp_path / "a.png", tmp_path / "b.png"
    cv2.imwrite(str(p0), np.full((600, 800, 3), 90, np.uint8))
    cv2.imwrite(str(p1), np.full((400, 400, 3), 160, np.uint8))
    r = _result(40, 12)
    rrd = log_single_pair(Sink("save", str(tmp_path / "pair.rrd")), p0, p1, r)
    assert rrd is not None
    ent = "/" + pair_entity("a.png", "b.png") + "/matches"
    b = _batches(rrd)
    blob = _column(b[f"{ent}/images"], "EncodedImage:blob")[0]
    picture = cv2.imdecode(np.asarray(blob, np.uint8).ravel(), cv2.IMREAD_COLOR)
    assert picture.shape[:2] == (400, 512 + 400)  # 800x600 -> 512x384 (PAIR_PX), 400x400 as is
    assert abs(int(picture[:384, :512].mean()) - 90) < 3 and abs(int(picture[:, 512:].mean()) - 160) < 3
    assert not picture[390:, :500].any()  # black below the shorter image; no lines burnt in anywhere
    inl = _instances(b[f"{ent}/inliers"], "LineStrips2D:strips")
    out = _instances(b[f"{ent}/outliers"], "LineStrips2D:strips")
    assert len(inl) == 40 and len(out) == 12
    s0 = 512 / 800
    np.testing.assert_allclose(inl[0][0], (r.kpts0[0] + 0.5) * s0, atol=1e-3)
    np.testing.assert_allclose(inl[0][1], r.kpts1[0] + 0.5 + [512, 0], atol=1e-3)
    np.testing.assert_allclose(out[0][0], (r.kpts0[40] + 0.5) * s0, atol=1e-3)
    assert _instances(b[f"{ent}/inliers"], "LineStrips2D:labels")[:2] == ["match 0", "match 1"]
    colors = {str(_instances(b[f"{ent}/{k}"], "LineStrips2D:colors")) for k in ("inliers", "outliers")}
    assert len(colors) == 2  # two colours


def test_line_strips_are_limited_per_class():
    r = _result(1000, 5)
    strips = match_strips(r, 1.0, 1.0, 600.0)
    assert len(strips["inliers"][0]) == MAX_STRIPS and len(strips["outliers"][0]) == 5
    idx = strips["inliers"][1]
    assert (np.diff(idx) > 0).all() and idx.max() < 1000  # a sorted sample of the inliers
    np.testing.assert_array_equal(idx, match_strips(r, 1.0, 1.0, 600.0)["inliers"][1])  # seeded


def test_heat_map_figure_has_labels_and_a_colour_scale():
    grid = np.array([[1.0, 2.0, np.nan], [3.0, 10.0, 5.0]], np.float32)
    labels = ["t=1.00", "t=2.00"]
    cells = heatmap_image(grid, [(1, 1)], 28)
    fig = heatmap_figure(grid, labels, [(1, 1)], 28)
    assert fig.shape[0] > cells.shape[0] + 40 and fig.shape[1] > cells.shape[1] + 100
    # the cells sit inside the figure, unchanged
    ys, xs = np.where((fig == cells[0, 0]).all(axis=2))
    assert len(ys)
    # the colour bar: a column whose top is viridis' yellow end and whose bottom its purple end
    yellow = cv2.cvtColor(cv2.applyColorMap(np.array([[255]], np.uint8), cv2.COLORMAP_VIRIDIS), cv2.COLOR_BGR2RGB)[0, 0]
    purple = cv2.cvtColor(cv2.applyColorMap(np.array([[0]], np.uint8), cv2.COLORMAP_VIRIDIS), cv2.COLOR_BGR2RGB)[0, 0]
    cols = [x for x in range(cells.shape[1], fig.shape[1])
            if (np.abs(fig[:, x].astype(int) - yellow).max(axis=1) < 10).any()
            and (np.abs(fig[:, x].astype(int) - purple).max(axis=1) < 10).any()]
    assert cols, "no colour bar"
    # dark text in the left margin (the tilt labels) and below the cells (the longitude axis)
    assert (fig[:, :30] < 100).any() and (fig[-30:] < 100).any()


class _Img(SimpleNamespace):
    pass


class _Model:
    """The part of a pycolmap.Reconstruction that replay_steps reads."""

    def __init__(self, names: list[str]) -> None:
        self._names = names

    def reg_image_ids(self):
        return list(range(1, len(self._names) + 1))

    def image(self, i: int):
        return _Img(name=self._names[i - 1])


def test_replay_steps_from_schema_2_and_schema_1_growth():
    model = _Model(["a", "b", "c", "d"])
    v2 = [{"step": 0, "model": 0, "image": "c", "registered_images": 2, "initial_pair": ["a", "c"]},
          {"step": 1, "model": 0, "image": "b", "registered_images": 3, "initial_pair": None},
          {"step": 2, "model": 0, "image": "x", "registered_images": 4, "initial_pair": None},  # later dropped
          {"step": 3, "model": 0, "image": "d", "registered_images": 5, "initial_pair": None}]
    assert replay_steps(model, v2) == [(0, ["a", "c"], "c"), (1, ["a", "c", "b"], "b"), (2, ["a", "c", "b"], "x"),
                                       (3, ["a", "c", "b", "d"], "d")]
    v1 = [{k: v for k, v in g.items() if k != "initial_pair"} for g in v2]  # the first image: the unnamed one
    assert replay_steps(model, v1)[0] == (0, ["a", "c"], "c")
    # two models: the one the kept model's images belong to
    other = [{"step": 0, "model": 0, "image": "y", "registered_images": 2, "initial_pair": ["z", "y"]}]
    shifted = [dict(g, model=1, step=g["step"] + 1) for g in v2]
    assert replay_steps(model, other + shifted)[0] == (1, ["a", "c"], "c")
    assert replay_steps(model, []) == []


def test_a_stale_recording_is_renamed_or_deleted(tmp_path, capsys):
    from recon.cli.run import STALE_RECORDING_NAME, retire_stale_recording

    rec = tmp_path / "recording.rrd"
    new_model, reused = SimpleNamespace(model_reused=False), SimpleNamespace(model_reused=True)
    rec.write_bytes(b"old")
    assert retire_stale_recording(rec, None, reused, False) is None and rec.is_file()  # same model: kept
    assert retire_stale_recording(rec, rec, new_model, False) is None and rec.is_file()  # this run wrote it
    old = retire_stale_recording(rec, None, new_model, False)  # --rerun none, a new model
    assert old == tmp_path / STALE_RECORDING_NAME and old.read_bytes() == b"old" and not rec.exists()
    assert "renamed" in capsys.readouterr().err
    rec.write_bytes(b"old2")
    assert retire_stale_recording(rec, tmp_path / "elsewhere.rrd", reused, True) is None and not rec.exists()


def test_view_without_a_display_hints_at_web(tmp_path, monkeypatch, capsys):
    (tmp_path / "recording.rrd").write_bytes(b"RRF2" + bytes(60))  # a recording by its first bytes
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.setattr("recon.viz.rerun_log.find_viewer", lambda: "/bin/true")
    assert main(["view", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "recon view --web" in err and "no display" in err


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.slow
def test_view_web_serves_the_web_viewer(tmp_path):
    """`recon view --web` (a real `rerun --serve-web`): the printed address answers with the web
    viewer's page. Needs the `rerun` executable (rerun-sdk)."""
    from recon.viz.rerun_log import find_viewer

    if find_viewer() is None:
        pytest.skip("the Rerun viewer executable is not installed")
    p0, p1 = tmp_path / "a.png", tmp_path / "b.png"
    cv2.imwrite(str(p0), np.full((60, 80, 3), 90, np.uint8))
    cv2.imwrite(str(p1), np.full((60, 80, 3), 160, np.uint8))
    rrd = log_single_pair(Sink("save", str(tmp_path / "recording.rrd")), p0, p1, _result(5, 2))
    port, grpc = _free_port(), _free_port()
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    cli = "import sys; from recon.cli import main; sys.exit(main(sys.argv[1:]))"
    proc = subprocess.Popen([sys.executable, "-c", cli, "view", "--web", str(tmp_path), "--port", str(port),
                             "--grpc-port", str(grpc)], stderr=subprocess.PIPE, env=env, text=True,
                            start_new_session=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:  # (SIGINT at its default in the child: a background test run inherits it ignored)
        page, deadline = "", time.monotonic() + 60
        while time.monotonic() < deadline and not page:
            try:
                page = urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2).read().decode("utf-8", "replace")
            except OSError:
                time.sleep(0.5)
        assert "<html" in page.lower() and "rerun" in page.lower()
    finally:  # Ctrl-C to the whole group, as a terminal does: recon and the rerun it started
        os.killpg(proc.pid, signal.SIGINT)
        try:
            err = proc.communicate(timeout=30)[1]
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            err = proc.communicate()[1]
    assert proc.returncode in (0, 130) and "Traceback" not in err, err  # Ctrl-C: 130, one line (recon.cli)
    assert f"http://localhost:{port}/?url=rerun%2Bhttp%3A%2F%2Flocalhost%3A{grpc}%2Fproxy" in err
    assert rrd is not None and rrd.is_file()


@pytest.mark.slow
def test_clean_cache_and_a_new_model_retire_the_old_recording(corner_scene, tmp_path):
    """Run 1 records (default sink) and keeps its cache; run 2 changes an option (a new model)
    with --rerun none --clean-cache: the old recording is renamed, OUT/cache is gone, the
    outputs stay."""
    scene = tmp_path / "corner"
    shutil.copytree(corner_scene, scene)
    out = tmp_path / "out"
    base = ["run", str(scene), "--out", str(out), "--method", "sift", "--no-progress"]
    assert main(base) == 0
    assert (out / "recording.rrd").is_file() and (out / "cache").is_dir()
    assert main([*base, "--merge-px", "1.5", "--rerun", "none", "--clean-cache"]) == 0
    report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    assert not report["model_reused"] and report["config"]["tracks"]["merge_px"] == 1.5
    assert not (out / "recording.rrd").exists() and (out / "recording.previous.rrd").is_file()
    assert not (out / "cache").exists()
    assert (out / "database.db").is_file() and (out / "sparse" / "0").is_dir() and (out / "points.ply").is_file()
