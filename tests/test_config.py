"""`recon.config`: one source for every option. The `recon run` CLI is generated from RunConfig
(defaults and help equal the dataclass), `--preset` / `--config` / `--set` reach every stage
including the matcher, bad keys are one-line errors (exit 2), and the seed reaches the matcher,
COLMAP's two-view RANSAC and the mapper however the config is built; `-v` lets COLMAP's log
through."""

from __future__ import annotations

import dataclasses
import json
import logging
import typing
from pathlib import Path

import pytest

from recon.cli import main
from recon.config import DEFAULT_MAX_SIZE, PRESETS, MatchConfig, RunConfig, build_run_config, field_docs, preset, run_options
from recon.core.report import RunReport
from recon.core.stages.match import make_matcher
from recon.errors import UserError


def _click_command(name: str, group: str | None = None):
    import typer

    from recon.cli import _register_commands, app

    _register_commands()
    cmd = typer.main.get_command(app)
    if group:
        cmd = cmd.commands[group]  # type: ignore[attr-defined]
    return cmd.commands[name]  # type: ignore[attr-defined]


def _get(obj, path: str):
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


# the CLI is the dataclass -------------------------------------------------------------------------
def test_cli_defaults_and_help_equal_the_dataclass():
    params = {p.name: p for p in _click_command("run").params}
    defaults = RunConfig()
    flagged = []
    for owner in [RunConfig] + [t for t in typing.get_type_hints(RunConfig).values() if dataclasses.is_dataclass(t)]:
        docs = field_docs(owner)
        for f in dataclasses.fields(owner):
            assert f.name in docs or dataclasses.is_dataclass(typing.get_type_hints(owner)[f.name]), \
                f"{owner.__name__}.{f.name} has no docstring"
            if "flag" in f.metadata:
                flagged.append(f.metadata["flag"])
    assert len(run_options()) == len(flagged) >= 12
    for o in run_options():
        p = params[o.name]
        assert p.default == _get(defaults, o.path) == o.default, o.path
        section, _, leaf = o.path.rpartition(".")
        owner = type(_get(defaults, section)) if section else RunConfig
        assert p.help == o.help == " ".join(field_docs(owner)[leaf].split()), o.path
        assert o.flag.split("/")[0] in p.opts, o.flag
    assert params["max_size"].default == DEFAULT_MAX_SIZE == RunConfig().load.max_size
    # the other commands' --max-size come from the same constant
    assert {p.name: p.default for p in _click_command("compare").params}["max_size"] == DEFAULT_MAX_SIZE
    assert {p.name: p.default for p in _click_command("scenes", "bench").params}["max_size"] == DEFAULT_MAX_SIZE


def test_every_preset_builds_and_differs_where_documented():
    assert set(PRESETS) >= {"default", "fast"}
    assert preset("default") == RunConfig()
    assert preset("fast").load.max_size == 800 and preset("fast").match == RunConfig().match
    assert preset("sift").match.method == "sift"
    with pytest.raises(UserError, match="default, fast"):
        preset("ultra")


# --set, --config, precedence ---------------------------------------------------------------------------
@pytest.fixture
def captured(monkeypatch):
    """`recon run` up to the library call: the RunConfig it would run with."""
    import recon.core.pipeline

    seen: list[RunConfig] = []

    def fake_run_scene(scene_dir, cfg, **kw):
        seen.append(cfg)
        return RunReport(scene=str(scene_dir), out=str(cfg.output.out or scene_dir))

    monkeypatch.setattr(recon.core.pipeline, "run_scene", fake_run_scene)
    return seen


def _cli(tmp_path, capsys, *args) -> tuple[int, list[str]]:
    for name in ("a.png", "b.png"):  # the CLI checks for image files before the run starts
        (tmp_path / name).touch()
    rc = main(["run", str(tmp_path), "--no-progress", "--rerun", "none", *map(str, args)])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return rc, [ln for ln in err.splitlines() if ln.startswith("recon: error:")]


def test_set_reaches_the_matcher(tmp_path, capsys, captured):
    assert make_matcher(RunConfig().match).cfg.fine_top_k == 2  # the multi-view default
    rc, _ = _cli(tmp_path, capsys, "--set", "matcher.fine_top_k=1", "--set", "matcher.coarse.rank_by=matches",
                 "--set", "tracks.merge_px=0.5")
    assert rc == 0
    cfg = captured[-1]
    assert cfg.match.matcher == {"fine_top_k": 1, "coarse.rank_by": "matches"} and cfg.tracks.merge_px == 0.5
    m = make_matcher(cfg.match, cfg.seed)
    assert m.cfg.fine_top_k == 1 and m.cfg.coarse.rank_by == "matches"
    assert m.cfg.final_homography is False and m.cfg.guided_epipolar  # still the multi-view variant


@pytest.mark.parametrize("setting, text", [
    ("matcher.nope=1", "fine_top_k"),  # names the valid matcher options
    ("matcher.fine_top_k=many", "expected int"),
    ("matcher.coarse.rank_by=votes", "matches, inliers"),
    ("matcher.seed=3", "--seed"),
    ("tracks.radius=3", "tracks.merge_px"),
    ("nonsense=1", "load.max_size"),
    ("load.max_size=10", "--max-size"),
    ("novalue", "KEY=VALUE"),
    ("match.engine=ray", "threads"),
    ("sfm.final_ba_loss=tukey", "cauchy, soft_l1"),
    ("sfm.final_ba_scale_px=-1", "sfm.final_ba_scale_px"),
    ("sfm.final_ba_outlier_scales=-1", "sfm.final_ba_outlier_scales"),
    ("sfm.final_ba_principal_point=maybe", "fixed, refine, auto"),
    ("tracks.conflict_order=random", "pairs, distance, support"),
])
def test_bad_set_is_one_line_exit_2(tmp_path, capsys, captured, setting, text):
    rc, lines = _cli(tmp_path, capsys, "--set", setting)
    assert rc == 2 and len(lines) == 1 and text in lines[0], lines
    assert not captured


def test_config_file_and_precedence(tmp_path, capsys, captured):
    toml = tmp_path / "recon.toml"
    toml.write_text('seed = 4\n[load]\nmax_size = 800\n[tracks]\nmerge_px = 1.0\n'
                    '[matcher]\nfine_top_k = 3\n[matcher.coarse]\nrank_by = "matches"\n', encoding="utf-8")
    assert _cli(tmp_path, capsys, "--config", toml)[0] == 0
    cfg = captured[-1]
    assert (cfg.seed, cfg.load.max_size, cfg.tracks.merge_px) == (4, 800, 1.0)
    assert cfg.match.matcher == {"fine_top_k": 3, "coarse.rank_by": "matches"}
    m = make_matcher(cfg.match, cfg.seed)
    assert m.cfg.fine_top_k == 3 and m.cfg.coarse.rank_by == "matches" and m.cfg.seed == 4
    # preset < file < flags given on the command line < --set; flags left at their default do not count
    assert _cli(tmp_path, capsys, "--preset", "sift", "--config", toml, "--max-size", "640",
                "--set", "tracks.merge_px=0.5", "--set", "matcher.fine_top_k=1")[0] == 2  # sift has no fine_top_k
    assert _cli(tmp_path, capsys, "--preset", "fast", "--config", toml, "--max-size", "640",
                "--set", "tracks.merge_px=0.5")[0] == 0
    cfg = captured[-1]
    assert (cfg.seed, cfg.load.max_size, cfg.tracks.merge_px, cfg.match.matcher["fine_top_k"]) == (4, 640, 0.5, 3)
    # the same in JSON, nested as report.json's config
    js = tmp_path / "recon.json"
    js.write_text(json.dumps({"load": {"max_size": 700}, "match": {"matcher": {"fine_top_k": 1}}}), encoding="utf-8")
    assert _cli(tmp_path, capsys, "--config", js)[0] == 0
    assert captured[-1].load.max_size == 700 and captured[-1].match.matcher == {"fine_top_k": 1}


@pytest.mark.parametrize("content, suffix, text", [
    ("[load]\nmax_px = 3\n", ".toml", "load.max_size"),
    ("[load\n", ".toml", "--config"),
    ('{"seed": "x"}', ".json", "expected int"),
    ('{"matcher": {"fine_top_k": true}}', ".json", "expected int"),
])
def test_bad_config_file_is_one_line_exit_2(tmp_path, capsys, captured, content, suffix, text):
    f = tmp_path / f"c{suffix}"
    f.write_text(content, encoding="utf-8")
    rc, lines = _cli(tmp_path, capsys, "--config", f)
    assert rc == 2 and len(lines) == 1 and text in lines[0], lines
    rc, lines = _cli(tmp_path, capsys, "--config", tmp_path / "missing.toml")
    assert rc == 2 and len(lines) == 1


def test_run_config_defaults_give_the_final_adjustments_defaults():
    """`sfm.final_ba_*` restate `recon.core.sfm.FinalBaConfig`'s defaults (the config layer does not
    import pycolmap): the stage must build the same adjustment from a default run."""
    from recon.core.sfm import FinalBaConfig
    from recon.core.stages.sfm import final_ba_config

    built, core = final_ba_config(RunConfig(), 1.0), FinalBaConfig()
    for name in ("loss", "scale_px", "max_iterations", "outlier_scales", "principal_point"):
        assert getattr(built, name) == getattr(core, name), name


def test_report_config_round_trips(tmp_path):
    cfg = build_run_config("fast", None, {"pairs.spec": "sequential:2"}, ["matcher.fine_top_k=3", "seed=9"])
    assert RunConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg


# the seed ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("build", [
    lambda: RunConfig(seed=7),
    lambda: RunConfig.from_options(seed=7, method="extra-affine"),
    lambda: RunConfig.from_dict({"seed": 7}),
    lambda: build_run_config("fast", settings=["seed=7", "matcher.fine_top_k=1"]),
])
def test_the_seed_reaches_the_matcher_and_colmap(build):
    from recon.core.stages.sfm import mapping_options
    from recon.core.stages.verify import verify_options
    from recon.eval.stock import verification_options

    cfg = build()
    m = make_matcher(cfg.match, cfg.seed).cfg
    assert m.seed == 7  # the one seed of every matching stage (matching.config)
    assert verify_options(cfg, 2.0).ransac.random_seed == 7
    o = mapping_options(cfg, 2.0)
    assert o.random_seed == o.mapper.random_seed == o.triangulation.random_seed == 7
    assert verification_options(cfg.seed).ransac.random_seed == 7  # the stock comparison's verification
    assert make_matcher(MatchConfig(method="sift"), cfg.seed).cfg.seed == 7  # baselines too


# logging -----------------------------------------------------------------------------------------
def test_verbose_lets_colmap_log_through(capfd):
    """COLMAP logs from C++ straight to fd 2: silenced by default, let through with -v."""
    import pycolmap

    from recon.log import quiet_colmap, setup_logging

    try:
        setup_logging(verbose=False)
        with quiet_colmap():
            pycolmap.logging.info("colmap-quiet-marker")
        logging.getLogger("recon.test").debug("recon-quiet-debug")
        setup_logging(verbose=True)
        with quiet_colmap():
            pycolmap.logging.info("colmap-verbose-marker")
        logging.getLogger("recon.test").debug("recon-verbose-debug")
        logging.getLogger("matching.test").warning("a long warning " * 20)
    finally:
        setup_logging(verbose=False)
    err = capfd.readouterr().err
    assert "colmap-verbose-marker" in err and "colmap-quiet-marker" not in err
    assert "recon-verbose-debug" in err and "recon-quiet-debug" not in err
    warn = [ln for ln in err.splitlines() if "a long warning" in ln]
    assert len(warn) == 1 and warn[0].startswith("recon: warning: a long warning") and warn[0].count("long") == 20


@pytest.mark.slow
def test_cli_verbose_shows_colmap_log(tmp_path):
    """`recon -v run` on a small rendered scene: COLMAP's mapper log reaches stderr; without -v
    it does not (subprocesses: COLMAP writes to the file descriptor)."""
    import os
    import subprocess
    import sys

    from scenes.render import render_scene

    scene = tmp_path / "s"
    render_scene(scene, "corner", seed=0, image_size=(320, 240))
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    errs = {}
    for flag in ([], ["-v"]):
        cmd = [sys.executable, "-m", "recon", *flag, "run", str(scene), "--out", str(tmp_path / f"o{len(flag)}"),
               "--method", "sift", "--no-progress", "--rerun", "none"]
        p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
        assert p.returncode == 0, p.stderr
        errs[bool(flag)] = p.stderr
    assert "incremental_pipeline" in errs[True] and "stage match" in errs[True]
    assert "incremental_pipeline" not in errs[False] and "stage match" not in errs[False]
