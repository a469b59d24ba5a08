"""`recon.core.orchestrator`: stages run in order, keyed stages are skipped while their key and
outputs are unchanged and rerun (with everything after them) when an option changes; the
observer protocol's events arrive in order. Unit tests on toy stages, then the real stages on a
small rendered scene (SIFT, 400x300 px)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from recon.config import RunConfig
from recon.core.context import Run
from recon.core.observer import BaseRunObserver, CompositeObserver, as_observer
from recon.core.orchestrator import run_stages
from recon.core.report import RunReport
from recon.core.state import StageState, fingerprint


# toy stages -------------------------------------------------------------------------------------
class Toy:
    """A stage keyed on `option` and on the previous stage's key; its output is a file."""

    def __init__(self, name: str, option: int, upstream: str | None, calls: list[str]) -> None:
        self.name, self.option, self.upstream, self.calls = name, option, upstream, calls
        self.needs: tuple[str, ...] = ()
        self.makes: tuple[str, ...] = ()

    def key(self, run: Run) -> str | None:
        return fingerprint(self.name, self.option, run.keys.get(self.upstream) if self.upstream else None)

    def _file(self, run: Run) -> Path:
        return run.out / f"{self.name}.txt"

    def run(self, run: Run) -> dict:
        self.calls.append(self.name)
        self._file(run).write_text(str(self.option))
        return {"option": self.option}

    def reuse(self, run: Run, record: dict) -> bool:
        return self._file(run).is_file() and record == {"option": self.option}


class Events(BaseRunObserver):
    def __init__(self) -> None:
        self.events: list[tuple] = []

    def on_stage_start(self, stage):
        self.events.append(("start", stage))

    def on_stage_end(self, stage, seconds, reused):
        self.events.append(("end", stage, reused))

    def on_pair(self, index, name0, name1, result, cached):
        self.events.append(("pair", index, cached))

    def on_sfm_step(self, step, live):
        self.events.append(("sfm", step.step, live.num_reg_images()))

    def on_model(self, model, report):
        self.events.append(("model", None if model is None else model.num_reg_images(), report.status))

    def on_warning(self, message):
        self.events.append(("warning", message))


def _toy_run(out: Path, options: tuple[int, int, int], observer=None) -> tuple[RunReport, list[str]]:
    calls: list[str] = []
    stages = [Toy("a", options[0], None, calls), Toy("b", options[1], "a", calls), Toy("c", options[2], "b", calls)]
    cfg = RunConfig.from_options(progress=False)
    run = Run(cfg, out, out, RunReport(scene="", out=str(out)), as_observer(observer),
              StageState(out / "cache" / "state.json"))
    return run_stages(run, stages), calls


def test_unchanged_keys_are_skipped_and_a_changed_option_reruns_from_there(tmp_path):
    rep, calls = _toy_run(tmp_path, (1, 1, 1))
    assert calls == ["a", "b", "c"] and rep.stages_reused == [] and list(rep.stages) == ["a", "b", "c"]
    rep, calls = _toy_run(tmp_path, (1, 1, 1))
    assert calls == [] and rep.stages_reused == ["a", "b", "c"]
    rep, calls = _toy_run(tmp_path, (1, 2, 1))  # b's option: b and c (whose key holds b's) rerun
    assert calls == ["b", "c"] and rep.stages_reused == ["a"]
    (tmp_path / "c.txt").unlink()  # an output gone: that stage reruns although its key is unchanged
    rep, calls = _toy_run(tmp_path, (1, 2, 1))
    assert calls == ["c"] and rep.stages_reused == ["a", "b"]
    assert json.loads((tmp_path / "report.json").read_text())["stages_reused"] == ["a", "b"]


def test_a_stage_killed_half_way_is_not_trusted(tmp_path):
    class Dies(Toy):
        def run(self, run):
            self._file(run).write_text("half")
            raise KeyboardInterrupt

    _toy_run(tmp_path, (1, 1, 1))
    calls: list[str] = []
    stages = [Toy("a", 1, None, calls), Dies("b", 2, "a", calls), Toy("c", 1, "b", calls)]
    run = Run(RunConfig.from_options(progress=False), tmp_path, tmp_path, RunReport(scene="", out=""),
              as_observer(None), StageState(tmp_path / "cache" / "state.json"))
    with pytest.raises(KeyboardInterrupt):
        run_stages(run, stages)
    state = json.loads((tmp_path / "cache" / "state.json").read_text())
    assert "b" not in state["stages"]  # forgotten before it started rewriting its output
    _, calls = _toy_run(tmp_path, (1, 2, 1))
    assert calls == ["b", "c"]


def test_stage_events_in_order_and_composite_fans_out(tmp_path):
    one, two = Events(), Events()
    _toy_run(tmp_path, (1, 1, 1), observer=[one, two])
    expected = [("start", "a"), ("end", "a", False), ("start", "b"), ("end", "b", False),
                ("start", "c"), ("end", "c", False), ("model", None, "ok")]
    assert one.events == expected and two.events == expected
    assert isinstance(as_observer(one), CompositeObserver)


def test_every_stage_input_is_made_by_an_earlier_stage():
    from recon.core.context import RunData
    from recon.core.stages import scene_stages
    from recon.eval.stock import stock_stages

    fields = set(RunData.__dataclass_fields__)
    for stages in (scene_stages(), stock_stages("default")):
        made: set[str] = set()
        for s in stages:
            assert set(s.needs) <= made, (s.name, set(s.needs) - made)
            assert set(s.makes) <= fields, s.name
            made |= set(s.makes)
    assert [s.name for s in scene_stages()] == ["load", "features", "pairs", "match", "tracks", "database",
                                                "verify", "sfm", "export"]


# the real stages on a small rendered scene ------------------------------------------------------
@pytest.fixture(scope="module")
def corner(tmp_path_factory) -> Path:
    from scenes.render import render_scene

    d = tmp_path_factory.mktemp("orch") / "corner"
    render_scene(d, "corner", seed=0, image_size=(400, 300))
    return d


def _run(scene: Path, out: Path, observer=None, **options):
    from recon.core.pipeline import run_scene

    return run_scene(scene, RunConfig.from_options(out=out, method="sift", progress=False, **options),
                     observer=observer)


@pytest.mark.slow
def test_real_stages_resume_and_rerun_from_a_changed_option(corner, tmp_path):
    out = tmp_path / "out"
    first = _run(corner, out)
    assert first.ok and first.stages_reused == [] and first.pairs_computed == len(first.pairs)
    assert list(first.stages) == ["load", "features", "pairs", "match", "tracks", "database", "verify", "sfm",
                                  "export"]
    again = _run(corner, out)
    assert again.stages_reused == ["database", "verify", "sfm"] and again.pairs_cached == len(again.pairs)
    assert again.database_reused and again.model_reused
    assert (again.registered_images, again.num_points3D) == (first.registered_images, first.num_points3D)
    assert again.mean_reprojection_error == pytest.approx(first.mean_reprojection_error, rel=1e-9)  # read back
    # a verification option: the database (keypoints, raw matches) is reused, verify and sfm rerun
    stricter = _run(corner, out, **{"verify.min_num_inliers": 30})
    assert stricter.stages_reused == ["database"] and stricter.pairs_cached == len(stricter.pairs)
    # a tracks option: the merged keypoints change, so database, verify and sfm all rerun
    unmerged = _run(corner, out, merge_px=0)
    assert unmerged.stages_reused == [] and unmerged.merge["merge_px"] == 0.0
    assert unmerged.merge["num_keypoints"] != first.merge["num_keypoints"]
    # and back: the pair cache still serves every pair, the keyed stages rebuild and agree
    back = _run(corner, out)
    assert back.pairs_cached == len(back.pairs) and back.stages_reused == []
    assert [p.verified_inliers for p in back.pairs] == [p.verified_inliers for p in first.pairs]
    assert back.num_points3D == first.num_points3D


@pytest.mark.slow
def test_observer_events_arrive_in_order(corner, tmp_path):
    ev = Events()
    rep = _run(corner, tmp_path / "out", observer=ev, seed=3)
    kinds = [e[0] for e in ev.events]
    stages = [e[1] for e in ev.events if e[0] == "start"]
    assert stages == list(rep.stages)
    assert kinds[-1] == "model" and ev.events[-1] == ("model", rep.registered_images, "ok")

    def span(stage: str) -> tuple[int, int]:
        return ev.events.index(("start", stage)), next(i for i, e in enumerate(ev.events)
                                                       if e[:2] == ("end", stage))

    pairs = [i for i, e in enumerate(ev.events) if e[0] == "pair"]
    steps = [i for i, e in enumerate(ev.events) if e[0] == "sfm"]
    m0, m1 = span("match")
    s0, s1 = span("sfm")
    assert len(pairs) == len(rep.pairs) and all(m0 < i < m1 for i in pairs)
    assert sorted(ev.events[i][1] for i in pairs) == list(range(len(rep.pairs)))  # each pair once (as it finishes)
    assert len(steps) == len(rep.sfm_growth) == rep.registered_images - 1 and all(s0 < i < s1 for i in steps)
    assert [ev.events[i][2] for i in steps] == list(range(2, rep.registered_images + 1))  # the model grows
    # the seed reached the verification RANSAC and the mapper (report: pycolmap's own todict())
    assert rep.colmap_options["verification"]["ransac"]["random_seed"] == 3
    assert rep.sfm_options["random_seed"] == rep.sfm_options["mapper"]["random_seed"] == 3
    assert rep.sfm_options["triangulation"]["random_seed"] == 3
    assert rep.config["seed"] == 3
