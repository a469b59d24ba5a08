"""`recon bench scale` (issue 10): the orbit scenes it renders, a tiny real run's JSON, option errors."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from recon.errors import UserError
from recon.eval.bench_scale import EngineSpec, fit_exponent, parse_engines, parse_pairs_modes, parse_sizes, plan_runs, run_scale
from recon.eval.gt import find_gt
from scenes.presets import PRESETS, get_preset, orbit
from scenes.render import render_scene

REPO = Path(__file__).resolve().parents[1]


def test_orbit_preset_spreads_n_views_all_around():
    p = get_preset("orbit-12")
    az = np.asarray(p.cameras.azimuths_deg)
    assert len(az) == 12 and p.image_size == (800, 600)
    assert np.allclose(np.diff(az), 30.0)  # evenly spaced over the full circle
    assert "orbit-12" not in PRESETS  # parametrised, the named presets are unchanged
    with pytest.raises(ValueError, match="orbit"):
        get_preset("orbit-2")
    with pytest.raises(ValueError):
        orbit(5000)


def test_orbit_render_gives_n_views_with_ground_truth(tmp_path):
    scene = render_scene(tmp_path / "s", "orbit-5", image_size=(160, 120))
    assert [p.name for p in scene.image_paths] == [f"view_0{i}.png" for i in range(5)]
    gt = find_gt(tmp_path / "s")
    assert gt is not None and sorted(gt) == [p.name for p in scene.image_paths]
    # opposite views see opposite walls: a walk all around, not an arc
    assert "south" in scene.viewing_angles_deg[0] and "south" not in scene.viewing_angles_deg[2]
    centres = np.array([-P[:, :3].T @ P[:, 3] for P in scene.cam_from_world])
    assert np.ptp(np.linalg.norm(centres[:, :2], axis=1)) < 1e-9  # all on one circle about the building
    assert np.allclose(centres.mean(axis=0)[:2], 0.0, atol=1e-9)


def test_view_names_keep_view_order_above_100_views():
    from scenes.render import view_names

    names = view_names(120)
    assert names[0] == "view_000.png" and names[-1] == "view_119.png" and names == sorted(names)
    assert view_names(30)[-1] == "view_29.png"  # the existing presets' names are unchanged


def test_option_parsers():
    assert parse_sizes("50,25,50") == [25, 50]
    assert parse_sizes("none") == []
    assert parse_pairs_modes("exhaustive, retrieval:10") == ["exhaustive", "retrieval:10"]
    assert parse_engines("threads:2,dask:1") == [EngineSpec("threads", 2), EngineSpec("dask", 1)]
    for bad in ("2", "a,b", "3000"):
        with pytest.raises(UserError):
            parse_sizes(bad)
    with pytest.raises(UserError):
        parse_pairs_modes("sequential:2")
    with pytest.raises(UserError):
        parse_engines("dask")


def test_plan_skips_exhaustive_above_the_cap_and_missing_real_scenes(tmp_path):
    runs, skipped = plan_runs(tmp_path, [25, 200], ["exhaustive", "retrieval:10"], EngineSpec("threads", 2),
                              25, "retrieval:10", [EngineSpec("threads", 2), EngineSpec("dask", 2)],
                              [("nowhere", tmp_path / "nowhere")], "auto", 50)
    got = {(r.scene, r.pairs, f"{r.engine}:{r.workers}") for r in runs}
    assert got == {("orbit-25", "exhaustive", "threads:2"), ("orbit-25", "retrieval:10", "threads:2"),
                   ("orbit-200", "retrieval:10", "threads:2"), ("orbit-25", "retrieval:10", "dask:2")}
    assert len(runs) == len(got)  # the engine comparison reuses the sweep's threads:2 run
    reasons = {(s["scene"], s["pairs_spec"]): s["reason"] for s in skipped}
    assert "19900 pairs" in reasons[("orbit-200", "exhaustive")]
    assert "no such folder" in reasons[("nowhere", "auto")]


def test_fit_exponent_recovers_a_power_law():
    assert fit_exponent([(n, 3.0 * n ** 1.3) for n in (50, 100, 200)]) == pytest.approx(1.3)
    assert fit_exponent([(50, 10.0)]) is None


def test_tiny_bench_writes_json_with_its_documented_keys(tmp_path):
    """A real, small sweep: 5 views at 320x240, retrieval:1, 2 threads; the exhaustive run is skipped (cap 4)."""
    res = run_scale(tmp_path / "b", sizes=[5], pairs_modes=["retrieval:1", "exhaustive"], engine=EngineSpec("threads", 2),
                    engine_size=0, max_exhaustive=4, image_size=(320, 240), max_size=320)
    data = json.loads((tmp_path / "b" / "scale.json").read_text())
    assert data == json.loads(json.dumps(res))
    assert data["config"]["image_size"] == [320, 240]
    rows = {r["pairs_spec"]: r for r in data["rows"]}
    assert rows["exhaustive"]["status"] == "skipped"
    r = rows["retrieval:1"]
    assert r["status"] in ("ok", "no_model"), r
    assert set(r) >= {"scene", "kind", "engine", "workers", "pairs_spec", "status", "num_images", "pairs",
                      "pairs_used", "pairs_bound", "verified_pairs", "registered", "stages", "match_seconds",
                      "seconds_total", "wall_seconds", "cpu_seconds", "peak_tree_mb", "rot_err_deg_median", "auc_5"}
    assert set(data) == {"config", "rows", "summary"} and set(data["summary"]) == {"fits", "engines", "targets"}
    assert r["num_images"] == 5 and r["pairs_bound"] == 10
    assert 3 <= r["pairs"] <= 5  # each image with its nearest other: at least N/2 (mutual), at most N pairs
    assert 0 <= r["registered"] <= 5
    assert r["seconds_total"] > 0 and r["wall_seconds"] >= r["seconds_total"]
    assert r["cpu_seconds"] > 1.0  # interpreter, OpenCV, SIFT and matching of the child process
    assert set(r["stages"]) >= {"features", "pairs", "match", "sfm"} and r["match_seconds"] == r["stages"]["match"]
    assert r["peak_tree_mb"] > 50  # a python process with numpy and OpenCV loaded
    assert r["rot_err_deg_median"] is None or 0 <= r["rot_err_deg_median"] < 180
    assert Path(r["out"], "report.json").is_file()
    fits = data["summary"]["fits"]["retrieval:1"]
    assert fits["sizes"] == [5] and fits["exponent_all"] is None
    # a second call reuses the finished run instead of running it again
    again = run_scale(tmp_path / "b", sizes=[5], pairs_modes=["retrieval:1"], engine=EngineSpec("threads", 2),
                      engine_size=0, image_size=(320, 240), max_size=320)
    assert again["rows"][0]["wall_seconds"] == r["wall_seconds"]


@pytest.mark.parametrize("args, message", [
    (["--sizes", "2"], "--sizes"),
    (["--pairs", "sequential:3"], "--pairs"),
    (["--engines", "dask:0"], "--engines"),
    (["--engine", "gpu:2"], "--engine"),
    (["--max-exhaustive", "-1"], "--max-exhaustive"),
    (["--image-size", "10x10"], "--image-size"),
])
def test_bad_options_are_one_line_and_exit_2(tmp_path, args, message):
    p = subprocess.run([sys.executable, "-m", "recon", "bench", "scale", "--out", str(tmp_path / "o"), *args],
                       capture_output=True, text=True, cwd=REPO)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], p.stderr
    assert not (tmp_path / "o").exists()


def test_collect_runs_nothing_and_lists_missing_runs_as_not_run(tmp_path):
    res = run_scale(tmp_path / "c", sizes=[25], pairs_modes=["retrieval:10"], engine=EngineSpec("threads", 2),
                    engine_size=0, collect=True)
    (row,) = res["rows"]
    assert row["status"] == "skipped" and "not run" in row["reason"] and row["num_images"] == 25
    assert not (tmp_path / "c" / "scenes").exists() and not (tmp_path / "c" / "runs").exists()
    assert res["summary"]["targets"] == []
