"""`benchmarks/mapper_seeds.py`: a finished database mapped again per seed through the sfm stage."""

from __future__ import annotations

import importlib.util
import json

import pytest

from shared_paths import REPO

_spec = importlib.util.spec_from_file_location("mapper_seeds", REPO / "benchmarks" / "mapper_seeds.py")
assert _spec is not None and _spec.loader is not None
mapper_seeds = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(mapper_seeds)


def test_seed_0_reproduces_the_runs_model_and_the_rows_are_written(corner_sift_run, corner_scene, tmp_path, capsys):
    out, rep, _ = corner_sift_run
    js = tmp_path / "seeds.json"
    assert mapper_seeds.main([str(corner_scene), "--db", f"sift={out / 'database.db'}", "--seeds", "2",
                              "--json", str(js)]) == 0
    rows = json.loads(js.read_text())["rows"]
    assert [(r["db"], r["seed"]) for r in rows] == [("sift", 0), ("sift", 1)]
    first = rows[0]  # the run's own options and seed: its model
    assert first["registered"] == rep.registered_images and first["points"] == rep.num_points3D
    assert first["rot_err_deg"] is not None and first["rot_err_deg"] < 1.0
    assert "sift: rotation error median" in capsys.readouterr().out


def test_bad_arguments_exit_2(corner_scene, tmp_path):
    for argv in ([str(corner_scene)], [str(corner_scene), "--db", "x"],
                 [str(corner_scene), "--db", f"x={tmp_path / 'missing.db'}"]):
        with pytest.raises(SystemExit) as e:
            mapper_seeds.main(argv)
        assert e.value.code == 2
