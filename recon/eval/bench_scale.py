"""`recon bench scale`: time, memory and accuracy of `recon run` against the number of photos.

What runs (`plan_runs`):

* **size sweep**: the rendered walk around a building (`scenes.presets.orbit`, 800x600, N views
  360/N deg apart, exact ground truth) for every N of `--sizes`, once per pair selection of
  `--pairs` (default `exhaustive` and `retrieval:10`), on `--engine`/`--workers`. Exhaustive
  above `--max-exhaustive` images is not run (N(N-1)/2 pairs: 19,900 at 200 views) and is
  reported as a `skipped` row, never estimated;
* **engine comparison**: on the `--engine-size` scene, `--engine-pairs`, every engine of
  `--engines` (`threads:W`, `dask:W` = a local cluster of W single-thread worker processes;
  `/cvT` pins OpenCV's own threads to T per process, e.g. `dask:2/cv1`: see EngineSpec);
* **real scenes** (`--real`: folders, or names under `$RECON_SHARED_DATA/scenes`, default
  castle_P30 and fox) with `--real-pairs` (default `auto`); a missing folder is a `skipped` row.

Each run is a fresh `python -m recon run SCENE --out OUT/runs/<scene>/<config> --overwrite
--clean-cache` subprocess: no feature or pair cache of an earlier run in the folder is reused, its
memory is its own and a Dask cluster is started and stopped inside it; its `report.json`
gives pairs, seconds per stage, registered images. Measured here:

* `wall_seconds`: the subprocess's wall time (includes interpreter start and, for Dask, the
  cluster's start and stop; `seconds_total` is the report's own, from load to export);
* `cpu_seconds`: user + system CPU seconds of the subprocess and all its descendants (wait4's
  rusage): unlike wall time, it does not grow when other work loads the machine;
* `peak_tree_mb`: the highest sum of resident memory (RSS, MB = 10^6 bytes) over the subprocess
  and all its descendants (Dask's nanny and worker processes), sampled with psutil every
  `SAMPLE_S` s. Summed RSS counts shared pages (libraries) once per process, so it is an upper
  bound; spikes shorter than the interval can be missed;
* `rot_err_deg_median` / `auc_5`: relative rotation error and pose AUC@5 deg of the model
  (`OUT/sparse/0`) against the scene's ground truth (`recon.eval.evaluate.evaluate_model`, as
  `recon compare`), when the scene has one.

`OUT/scale.json`: `config` (the options, `cpu_count`, how memory is measured), `rows` and
`summary` (`fits`, `engines`, `targets`). A row: `scene`, `kind`, `scene_dir`, `engine`, `workers`,
`group`, `pairs_spec`, `config`, `status` (ok, no_model, error, skipped) and `reason`; for a run:
`num_images`, `pairs` (proposed), `pairs_used` (exhaustive or retrieval: what `auto` chose),
`pairs_bound` ((K+1)*N, plus S*N with `+sequential:S`; null for exhaustive), `verified_pairs`
(>= 15 inliers), `registered`, `num_points3D`, `stages` (seconds per stage), `match_seconds`,
`seconds_total`, `wall_seconds`, `cpu_seconds`, `peak_tree_mb`, `report_peak_mb` (the driver
process alone, the report's own), `rot_err_deg_median`, `auc_5`, `out`, `returncode`.

A finished run leaves `OUT/runs/<scene>/<config>/bench_row.json`; a later `recon bench scale`
with the same run settings (scene, pairs, engine, workers, seed, max size) reuses it instead of
running again (`--recompute` runs everything again), so a long sweep can be done in pieces and
collected into one table. Results: `OUT/scale.json` (rows, fits, target checks) and, with
matplotlib, a log-log plot of total seconds against N.

`summarise` fits the growth exponent b of seconds ~ a*N^b by least squares in log-log over the
rendered sizes from 50 up (issue 10's 50 -> 200 target: b <= 1.2) and computes the engine ratios
(match-stage seconds of dask:1 over dask:2; dask:W over threads:W).
"""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from recon.core.jsonio import write_json_atomic
from recon.errors import UserError

DEFAULT_SIZES = (25, 50, 100, 200)
DEFAULT_PAIRS = ("exhaustive", "retrieval:10")
DEFAULT_ENGINES = ("threads:1", "threads:2", "dask:1", "dask:2")
DEFAULT_ENGINE_SIZE = 50
DEFAULT_ENGINE_PAIRS = "retrieval:10"
DEFAULT_MAX_EXHAUSTIVE = 50
DEFAULT_REAL = ("castle_P30", "fox")
DEFAULT_REAL_PAIRS = "auto"
SAMPLE_S = 0.5  # seconds between memory samples of the run's process tree
FIT_MIN_N = 50  # the growth exponent is fitted over rendered sizes from this many views up
ROW_FILE = "bench_row.json"
Log = Callable[[str], None]


# options ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class EngineSpec:
    """An executor and its number of parallel pair tasks (threads, or Dask worker processes)."""

    engine: str
    """`threads` or `dask` (a local cluster started by the run)."""
    workers: int
    """Parallel tasks: threads of the pool, or single-thread Dask worker processes."""
    opencv_threads: int = 0
    """OpenCV's own threads per process (`OPENCV_FOR_THREADS_NUM` of the run and its Dask
    workers); 0 = OpenCV's default (one per core). OpenCV parallelises SIFT and warps inside a
    task, so on a small machine one worker already keeps several cores partly busy; pinning it to
    1 (`dask:2/cv1`) measures the engine's own scaling, as on a cluster of single-core workers."""

    def __str__(self) -> str:
        return f"{self.engine}:{self.workers}" + (f"/cv{self.opencv_threads}" if self.opencv_threads else "")


def parse_sizes(text: str) -> list[int]:
    """`25,50,100` -> [25, 50, 100] (sorted, unique); `none` or empty -> []; UserError otherwise."""
    from scenes.presets import ORBIT_MAX_VIEWS, ORBIT_MIN_VIEWS

    if text.strip().lower() in ("", "none"):
        return []
    try:
        sizes = sorted({int(v) for v in text.split(",") if v.strip()})
    except ValueError:
        raise UserError(f"--sizes {text!r}: expected numbers of views, e.g. 25,50,100") from None
    bad = [n for n in sizes if not ORBIT_MIN_VIEWS <= n <= ORBIT_MAX_VIEWS]
    if bad:
        raise UserError(f"--sizes: {bad[0]} views; each size must be {ORBIT_MIN_VIEWS}-{ORBIT_MAX_VIEWS}")
    return sizes


def parse_pairs_modes(text: str, option: str = "--pairs") -> list[str]:
    """Comma-separated pair selections (exhaustive, auto, retrieval:K[+sequential:S]); UserError otherwise."""
    from recon.core.pairs import parse_pairs_spec

    modes = [m.strip() for m in text.split(",") if m.strip()]
    if not modes:
        raise UserError(f"{option} is empty: give exhaustive, auto or retrieval:K")
    out = []
    for m in modes:
        try:
            spec = parse_pairs_spec(m)
        except ValueError as e:
            raise UserError(str(e).replace("--pairs", option)) from None
        if spec.kind not in ("exhaustive", "retrieval", "auto"):
            raise UserError(f"{option} {m!r}: the scale benchmark takes exhaustive, auto or retrieval:K[+sequential:S]")
        out.append(str(spec))
    return list(dict.fromkeys(out))


def parse_engines(text: str, option: str = "--engines") -> list[EngineSpec]:
    """`threads:2,dask:1/cv1` -> [EngineSpec("threads", 2), EngineSpec("dask", 1, opencv_threads=1)];
    `none` -> []."""
    if text.strip().lower() in ("", "none"):
        return []
    out = []
    for item in (t.strip() for t in text.split(",")):
        if not item:
            continue
        m = re.fullmatch(r"(threads|dask):(\d+)(?:/cv(\d+))?", item)
        if not m or int(m.group(2)) < 1 or (m.group(3) is not None and int(m.group(3)) < 1):
            raise UserError(f"{option} {item!r}: expected threads:W or dask:W with W >= 1 workers, optionally "
                            f"/cvT for T >= 1 OpenCV threads per process, e.g. dask:2 or dask:2/cv1")
        out.append(EngineSpec(m.group(1), int(m.group(2)), int(m.group(3) or 0)))
    return list(dict.fromkeys(out))


def resolve_real(text: str, shared_root: Path | None = None) -> list[tuple[str, Path]]:
    """`--real`: comma-separated folders or names under SHARED/scenes -> [(label, folder)]
    (folders need not exist: missing ones become skipped rows); `none` or empty -> []."""
    if text.strip().lower() in ("", "none"):
        return []
    root = shared_root or Path(os.environ.get("RECON_SHARED_DATA") or Path(__file__).resolve().parents[2].parent
                               / "shared" / "data")
    out = []
    for item in (t.strip() for t in text.split(",")):
        if not item:
            continue
        p = Path(item).expanduser()
        if not (p.is_absolute() or item.startswith(".") or "/" in item):
            p = root / "scenes" / item
        out.append((p.name, p))
    return out


# the plan ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RunSpec:
    """One `recon run` of the benchmark."""

    scene: str
    """Label: `orbit-<N>` for a rendered scene, the folder name for a real one."""
    kind: str
    """`rendered` or `real`."""
    scene_dir: str
    """The scene folder (rendered into OUT/scenes/<scene> when `kind` is rendered)."""
    pairs: str
    """The `--pairs` selection."""
    engine: str
    """`threads` or `dask`."""
    workers: int
    """`--workers`: threads, or Dask worker processes."""
    group: str
    """Why it runs: `size` (the sweep), `engine` (the engine comparison) or `real`."""
    opencv_threads: int = 0
    """OpenCV threads per process (EngineSpec.opencv_threads); 0 = OpenCV's default."""

    @property
    def config(self) -> str:
        """A folder-safe name of (pairs, engine, workers), e.g. `retrieval-10_dask-2` (`_cv1` appended
        when OpenCV is pinned to one thread)."""
        return (re.sub(r"[^A-Za-z0-9]+", "-", self.pairs).strip("-") + f"_{self.engine}-{self.workers}"
                + (f"_cv{self.opencv_threads}" if self.opencv_threads else ""))


def plan_runs(out: Path, sizes: Sequence[int], pairs_modes: Sequence[str], engine: EngineSpec,
              engine_size: int, engine_pairs: str, engines: Sequence[EngineSpec],
              real: Sequence[tuple[str, Path]], real_pairs: str, max_exhaustive: int
              ) -> tuple[list[RunSpec], list[dict[str, Any]]]:
    """(runs to do, in order, without duplicates; rows of the runs skipped, with the reason)."""
    runs: list[RunSpec] = []
    skipped: list[dict[str, Any]] = []

    def add(spec: RunSpec) -> None:
        same = [r for r in runs if (r.scene, r.pairs, r.engine, r.workers, r.opencv_threads)
                == (spec.scene, spec.pairs, spec.engine, spec.workers, spec.opencv_threads)]
        if not same:
            runs.append(spec)

    def skip(scene: str, kind: str, n: int | None, pairs: str, eng: EngineSpec, group: str, reason: str) -> None:
        skipped.append({"scene": scene, "kind": kind, "num_images": n, "pairs_spec": pairs, "engine": eng.engine,
                        "workers": eng.workers, "opencv_threads": eng.opencv_threads, "group": group,
                        "status": "skipped", "reason": reason})

    def rendered(n: int) -> str:
        return str(out / "scenes" / f"orbit-{n}")

    for n in sizes:
        for mode in pairs_modes:
            if mode == "exhaustive" and n > max_exhaustive:
                skip(f"orbit-{n}", "rendered", n, mode, engine, "size",
                     f"exhaustive above --max-exhaustive {max_exhaustive} images ({n * (n - 1) // 2} pairs): not run")
                continue
            add(RunSpec(f"orbit-{n}", "rendered", rendered(n), mode, engine.engine, engine.workers, "size",
                        engine.opencv_threads))
    if engine_size and engines:
        for eng in engines:
            if engine_pairs == "exhaustive" and engine_size > max_exhaustive:
                skip(f"orbit-{engine_size}", "rendered", engine_size, engine_pairs, eng, "engine",
                     f"exhaustive above --max-exhaustive {max_exhaustive} images: not run")
                continue
            add(RunSpec(f"orbit-{engine_size}", "rendered", rendered(engine_size), engine_pairs, eng.engine,
                        eng.workers, "engine", eng.opencv_threads))
    for label, path in real:
        if not path.is_dir():
            skip(label, "real", None, real_pairs, engine, "real", f"{path}: no such folder (shared data absent)")
            continue
        add(RunSpec(label, "real", str(path), real_pairs, engine.engine, engine.workers, "real",
                    engine.opencv_threads))
    return runs, skipped


# one run ----------------------------------------------------------------------------------------
class TreePeak:
    """Peak summed RSS (MB) of a process and all its descendants, sampled every `interval` s."""

    def __init__(self, pid: int, interval: float = SAMPLE_S):
        self.pid = pid
        self.interval = interval
        self.peak_mb: float | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="recon-tree-peak", daemon=True)

    def __enter__(self) -> TreePeak:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def sample(self) -> float | None:
        """Summed RSS of the tree now (MB), None when the root is gone or psutil cannot tell."""
        try:
            import psutil

            root = psutil.Process(self.pid)
            procs = [root, *root.children(recursive=True)]
        except Exception:  # noqa: BLE001  the process ended, or psutil is refused: no sample
            return None
        total = 0
        for p in procs:
            try:
                total += p.memory_info().rss
            except Exception:  # noqa: BLE001  a child that just exited
                pass
        return total / 1e6

    def _loop(self) -> None:
        while True:
            mb = self.sample()
            if mb is not None and (self.peak_mb is None or mb > self.peak_mb):
                self.peak_mb = mb
            if self._stop.wait(self.interval):
                return


def fingerprint(spec: RunSpec, seed: int, max_size: int, image_size: tuple[int, int] = (800, 600)) -> dict[str, Any]:
    """What makes a finished run reusable: its scene (a rendered one by name and seed, so runs can be
    moved between OUT folders), options, seed and working resolution."""
    return {"scene": spec.scene, "scene_dir": spec.scene_dir if spec.kind == "real" else
            f"rendered {image_size[0]}x{image_size[1]}, seed {seed}",
            "pairs": spec.pairs, "engine": spec.engine,
            "workers": spec.workers, "seed": seed, "max_size": max_size,
            **({"opencv_threads": spec.opencv_threads} if spec.opencv_threads else {})}


def run_command(spec: RunSpec, run_dir: Path, seed: int, max_size: int) -> list[str]:
    """The `python -m recon run ...` command line of one benchmark run."""
    return [sys.executable, "-m", "recon", "run", spec.scene_dir, "--out", str(run_dir), "--overwrite", "--clean-cache",
            "--pairs", spec.pairs, "--engine", spec.engine, "--workers", str(spec.workers), "--seed", str(seed),
            "--max-size", str(max_size), "--no-progress"]


def _child_env(opencv_threads: int = 0) -> dict[str, str]:
    """This environment with the project root first on PYTHONPATH (the subprocess imports this
    checkout) and, when `opencv_threads` > 0, OpenCV pinned to that many threads in the run and
    in the Dask worker processes it starts (they inherit the environment)."""
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = os.pathsep.join([root, *[p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]])
    if opencv_threads:
        env["OPENCV_FOR_THREADS_NUM"] = str(opencv_threads)
    return env


def engine_label(row: dict[str, Any]) -> str:
    """`threads:2`, `dask:1/cv1`: a row's engine as `--engines` spells it."""
    cv = int(row.get("opencv_threads") or 0)
    return f"{row['engine']}:{row['workers']}" + (f"/cv{cv}" if cv else "")


def row_of(spec: RunSpec, report: dict[str, Any] | None, run_dir: Path, wall: float, peak_mb: float | None,
           returncode: int, error: str = "") -> dict[str, Any]:
    """The benchmark row of one run: the report's figures, the measured wall time and tree peak, GT metrics."""
    from recon.core.pairs import parse_pairs_spec

    row: dict[str, Any] = {**{k: v for k, v in asdict(spec).items() if k not in ("pairs",)}, "pairs_spec": spec.pairs,
                           "config": spec.config, "out": str(run_dir), "returncode": returncode,
                           "wall_seconds": round(wall, 1), "peak_tree_mb": None if peak_mb is None else round(peak_mb, 1)}
    if report is None:
        row.update(status="error", reason=error or f"recon run exited {returncode} without a report")
        return row
    stages = {k: round(float(v), 2) for k, v in (report.get("stages") or {}).items()}
    n = int(report.get("num_images") or 0)
    pairs = report.get("pairs") or []
    ps = parse_pairs_spec(spec.pairs)
    used = "exhaustive" if ps.kind == "exhaustive" or (ps.kind == "auto" and len(pairs) == n * (n - 1) // 2) \
        else "retrieval"
    k = ps.k if ps.kind == "retrieval" else None
    if ps.kind == "auto" and used == "retrieval":
        from recon.core.retrieval import AUTO_K

        k = AUTO_K
    row.update({
        "status": report.get("status", "error"), "reason": report.get("message", "") if report.get("status") != "ok"
        else "", "num_images": n, "pairs": len(pairs), "pairs_used": used,
        "pairs_bound": None if k is None else (k + 1 + ps.sequential) * n,
        "verified_pairs": sum(1 for p in pairs if int(p.get("verified_inliers", 0)) >= 15),
        "registered": int(report.get("registered_images") or 0), "num_points3D": int(report.get("num_points3D") or 0),
        "seconds_total": None if report.get("seconds_total") is None else round(float(report["seconds_total"]), 1),
        "stages": stages, "match_seconds": stages.get("match"), "report_peak_mb": report.get("peak_mb"),
        "rot_err_deg_median": None, "auc_5": None,
    })
    gt_eval(row, Path(spec.scene_dir), run_dir)
    return row


def gt_eval(row: dict[str, Any], scene_dir: Path, run_dir: Path) -> None:
    """Add the model's median relative rotation error and AUC@5 against the scene's GT, if any."""
    from recon.eval.compare import load_model
    from recon.eval.evaluate import evaluate_model
    from recon.eval.gt import find_gt

    try:
        gt = find_gt(scene_dir)
    except Exception as e:  # noqa: BLE001  unreadable GT: the row says so, the benchmark goes on
        row["gt_error"] = str(e)
        return
    if gt is None or row.get("status") != "ok":
        return
    rec = load_model(run_dir / "sparse" / "0")
    if rec is None:
        return
    ev = evaluate_model(rec, gt, with_pairs=False)
    row["rot_err_deg_median"] = ev.get("rel_rot_err_deg_median")
    row["auc_5"] = ev.get("auc_5")


def run_one(spec: RunSpec, out: Path, seed: int, max_size: int, recompute: bool, log: Log,
            image_size: tuple[int, int] = (800, 600), collect: bool = False) -> dict[str, Any]:
    """Run (or reuse) one benchmark run; its row (also OUT/runs/<scene>/<config>/bench_row.json).
    With `collect`, nothing runs: a run without a finished result is a `skipped` row."""
    run_dir = out / "runs" / spec.scene / spec.config
    fp = fingerprint(spec, seed, max_size, image_size)
    saved = run_dir / ROW_FILE
    if saved.is_file() and not recompute:
        try:
            prev = json.loads(saved.read_text(encoding="utf-8"))
            if prev.get("fingerprint") == fp and prev.get("row", {}).get("status") in ("ok", "no_model"):
                log(f"{spec.scene} {spec.config}: reusing {saved} (--recompute to run it again)")
                return {**prev["row"], "group": spec.group}
        except (OSError, ValueError):
            pass
    if collect:
        return {**{k: v for k, v in asdict(spec).items() if k != "pairs"}, "pairs_spec": spec.pairs,
                "num_images": int(spec.scene.removeprefix("orbit-")) if spec.kind == "rendered" else None,
                "config": spec.config, "status": "skipped", "reason": "not run (--collect: no finished result in OUT)"}
    cmd = run_command(spec, run_dir, seed, max_size)
    log(f"{spec.scene} {spec.config}: {' '.join(cmd[1:])}")
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(run_dir.parent / f"{spec.config}.log", "wb") as logf:
        proc = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, env=_child_env(spec.opencv_threads))
        with TreePeak(proc.pid) as peak:
            rc, cpu = _wait_with_cpu(proc)
    wall = time.perf_counter() - t0
    report = None
    rp = run_dir / "report.json"
    if rp.is_file() and rp.stat().st_mtime >= time.time() - wall - 5:
        try:
            report = json.loads(rp.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            report = None
    row = row_of(spec, report, run_dir, wall, peak.peak_mb, rc,
                 error=f"recon run exited {rc}; see {run_dir.parent / (spec.config + '.log')}")
    row["cpu_seconds"] = None if cpu is None else round(cpu, 1)
    if row.get("status") in ("ok", "no_model"):
        write_json_atomic(saved, {"fingerprint": fp, "row": row})
    log(f"{spec.scene} {spec.config}: {row.get('status')}, {row.get('registered', 0)}/{row.get('num_images', '?')} "
        f"registered, {row.get('pairs', '?')} pairs, {row.get('seconds_total')} s, tree peak {row.get('peak_tree_mb')} MB")
    return row


def _wait_with_cpu(proc: subprocess.Popen) -> tuple[int, float | None]:
    """(exit code, CPU seconds (user + system) of the process and every descendant it waited for,
    Dask workers included), from wait4's rusage; CPU time, unlike wall time, does not grow when
    other work loads the machine. (code, None) where wait4 is missing (Windows)."""
    if not hasattr(os, "wait4"):
        return proc.wait(), None
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, usage.ru_utime + usage.ru_stime


def ensure_scene(out: Path, n: int, seed: int, log: Log, image_size: tuple[int, int] = (800, 600)) -> Path:
    """OUT/scenes/orbit-<n>, rendered once (reused when its seed and size match)."""
    from scenes.render import render_scene

    d = out / "scenes" / f"orbit-{n}"
    meta = d / "gt" / "scene.json"
    if meta.is_file() and (d / "images").is_dir():
        try:
            m = json.loads(meta.read_text(encoding="utf-8"))
            if m.get("seed") == seed and m.get("image_size") == list(image_size):
                return d
        except (OSError, ValueError):
            pass
    log(f"rendering orbit-{n} -> {d}")
    render_scene(d, f"orbit-{n}", seed=seed, overwrite=True,
                 image_size=None if tuple(image_size) == (800, 600) else (int(image_size[0]), int(image_size[1])))
    return d


# summary ----------------------------------------------------------------------------------------
def fit_exponent(points: Sequence[tuple[float, float]]) -> float | None:
    """b of y = a*x^b by least squares in log-log; None with fewer than two distinct x."""
    pts = [(math.log(x), math.log(y)) for x, y in points if x > 0 and y and y > 0]
    if len({x for x, _ in pts}) < 2:
        return None
    mx = sum(x for x, _ in pts) / len(pts)
    my = sum(y for _, y in pts) / len(pts)
    sxx = sum((x - mx) ** 2 for x, _ in pts)
    return sum((x - mx) * (y - my) for x, y in pts) / sxx


def _ok(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    return [r for r in rows if r.get("status") in ("ok", "no_model")]


def summarise(rows: Sequence[dict[str, Any]], engine: EngineSpec) -> dict[str, Any]:
    """Growth exponents per pair selection, engine ratios and issue 10's target checks."""
    done = _ok(rows)
    sweep = [r for r in done if r["kind"] == "rendered" and engine_label(r) == str(engine)]
    fits: dict[str, Any] = {}
    for mode in dict.fromkeys(r["pairs_spec"] for r in sweep):
        pts = sorted((r["num_images"], r["seconds_total"]) for r in sweep if r["pairs_spec"] == mode)
        big = [p for p in pts if p[0] >= FIT_MIN_N]
        fits[mode] = {"sizes": [p[0] for p in pts], "exponent_all": _round(fit_exponent(pts), 3),
                      f"exponent_from_{FIT_MIN_N}": _round(fit_exponent(big), 3),
                      "sizes_from_50": [p[0] for p in big]}
    engines: dict[str, Any] = {}
    eng_rows = [r for r in done if r["kind"] == "rendered"]
    by_key: dict[tuple[str, str], dict[str, dict[str, Any]]] = {}
    for r in eng_rows:
        by_key.setdefault((r["scene"], r["pairs_spec"]), {})[engine_label(r)] = r
    for (scene, mode), d in by_key.items():
        if len(d) < 2:
            continue
        e: dict[str, Any] = {"runs": {k: {"match_seconds": v.get("match_seconds"), "seconds_total": v.get("seconds_total"),
                                         "wall_seconds": v.get("wall_seconds"), "peak_tree_mb": v.get("peak_tree_mb")}
                                     for k, v in d.items()}}
        for cv in sorted({lab.partition("/")[2] for lab in d}):  # "" (OpenCV's default), "cv1", ...
            suf = f"/{cv}" if cv else ""
            tag = f"_{cv}" if cv else ""
            if f"dask:1{suf}" in d and f"dask:2{suf}" in d:
                e[f"dask_2_over_1_match_speedup{tag}"] = _ratio(d[f"dask:1{suf}"].get("match_seconds"),
                                                                d[f"dask:2{suf}"].get("match_seconds"))
            for w in (1, 2):
                if f"dask:{w}{suf}" in d and f"threads:{w}{suf}" in d:
                    e[f"dask_over_threads_{w}_match{tag}"] = _ratio(d[f"dask:{w}{suf}"].get("match_seconds"),
                                                                    d[f"threads:{w}{suf}"].get("match_seconds"))
                    e[f"dask_over_threads_{w}_total{tag}"] = _ratio(d[f"dask:{w}{suf}"].get("seconds_total"),
                                                                    d[f"threads:{w}{suf}"].get("seconds_total"))
        engines[f"{scene} {mode}"] = e
    return {"fits": fits, "engines": engines, "targets": check_targets(done, fits, engines)}


def check_targets(done: Sequence[dict[str, Any]], fits: dict[str, Any], engines: dict[str, Any]) -> list[dict[str, Any]]:
    """Issue 10's scale targets, each {target, value, met} (met = None when not measured)."""
    out: list[dict[str, Any]] = []
    ret = [r for r in done if r.get("pairs_bound")]
    if ret:
        worst = max(ret, key=lambda r: r["pairs"] / r["pairs_bound"])
        out.append({"target": "retrieval proposes at most (K+1)*N pairs",
                    "value": f"max {worst['pairs']} / {worst['pairs_bound']} ({worst['scene']} {worst['pairs_spec']})",
                    "met": all(r["pairs"] <= r["pairs_bound"] for r in ret)})
    for mode, f in fits.items():
        b = f.get(f"exponent_from_{FIT_MIN_N}")
        if mode != "exhaustive" and b is not None:
            out.append({"target": f"total time {mode} from 50 to 200 views grows <= N^1.2",
                        "value": f"N^{b:.2f} over {f['sizes_from_50']}", "met": b <= 1.2})
    big = [r for r in done if r["kind"] == "rendered" and r.get("num_images") == 200]
    for r in big:
        secs = r.get("seconds_total") or 0.0
        mem = r.get("peak_tree_mb") or 0.0
        out.append({"target": f"200 views ({r['config']}): < 30 min, all registered, < 8 GiB",
                    "value": f"{secs / 60:.1f} min, {r['registered']}/{r['num_images']}, {mem / 1e3:.2f} GB",
                    "met": secs < 1800 and r["registered"] == r["num_images"] and mem * 1e6 < 8 * 2**30})
    for r in done:
        if r["scene"] == "fox":
            secs = r.get("seconds_total") or 0.0
            out.append({"target": "fox: >= 65/67 registered in < 20 min",
                        "value": f"{r['registered']}/{r['num_images']} in {secs / 60:.1f} min",
                        "met": r["registered"] >= 65 and secs < 1200})
        if r["scene"] == "castle_P30":
            out.append({"target": "castle_P30: 30/30 registered", "value": f"{r['registered']}/{r['num_images']}, "
                        f"rot. err. {_fmt(r.get('rot_err_deg_median'), '.3f')} deg", "met": r["registered"] == 30})
    for key, e in engines.items():
        for name, s in e.items():
            if name.startswith("dask_2_over_1_match_speedup") and s is not None:
                pinned = name.removeprefix("dask_2_over_1_match_speedup").strip("_")
                how = f", OpenCV pinned to {pinned.removeprefix('cv')} thread(s) per process" if pinned else ""
                out.append({"target": f"Dask 2 workers >= 1.8x one on the match stage ({key}{how})",
                            "value": f"{s:.2f}x", "met": s >= 1.8})
        for w in (1, 2):
            q = e.get(f"dask_over_threads_{w}_match")
            if q is not None:
                out.append({"target": f"dask <= 5 % slower than threads at {w} worker(s), match stage ({key})",
                            "value": f"{(q - 1) * 100:+.1f} %", "met": q <= 1.05})
    return out


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if not a or not b else round(a / b, 3)


def _round(v: float | None, nd: int) -> float | None:
    return None if v is None else round(v, nd)


def _fmt(v: Any, spec: str) -> str:
    return "-" if v is None else format(v, spec)


# the whole benchmark ----------------------------------------------------------------------------
def run_scale(out: str | Path, sizes: Sequence[int] = DEFAULT_SIZES, pairs_modes: Sequence[str] = DEFAULT_PAIRS,
              engine: EngineSpec = EngineSpec("threads", 2), engine_size: int = DEFAULT_ENGINE_SIZE,
              engine_pairs: str = DEFAULT_ENGINE_PAIRS, engines: Sequence[EngineSpec] = (),
              real: Sequence[tuple[str, Path]] = (), real_pairs: str = DEFAULT_REAL_PAIRS,
              max_exhaustive: int = DEFAULT_MAX_EXHAUSTIVE, seed: int = 0, max_size: int = 1600,
              recompute: bool = False, log: Log = lambda _m: None,
              image_size: tuple[int, int] = (800, 600), collect: bool = False) -> dict[str, Any]:
    """Render, run and measure everything `plan_runs` lists (with `collect`: only gather finished
    runs); {"config", "rows", "summary"} (also OUT/scale.json,
    rewritten after every run so an interrupted sweep keeps its finished runs)."""
    out = Path(out).expanduser().resolve()
    out.mkdir(parents=True, exist_ok=True)
    if engine_size and engines and engine_size not in sizes:
        sizes_to_render = sorted({*sizes, engine_size})
    else:
        sizes_to_render = list(sizes)
    runs, skipped = plan_runs(out, sizes, pairs_modes, engine, engine_size, engine_pairs, engines, real, real_pairs,
                              max_exhaustive)
    config = {"sizes": list(sizes), "pairs": list(pairs_modes), "engine": str(engine), "engine_size": engine_size,
              "engine_pairs": engine_pairs, "engines": [str(e) for e in engines],
              "real": [str(p) for _, p in real], "real_pairs": real_pairs, "max_exhaustive": max_exhaustive,
              "seed": seed, "max_size": max_size, "image_size": list(image_size), "cpu_count": os.cpu_count(),
              "memory": f"peak_tree_mb: summed RSS of the run's process tree (Dask workers included), sampled every "
                        f"{SAMPLE_S} s; MB = 10^6 bytes",
              "collect": collect, "started": time.strftime("%Y-%m-%dT%H:%M:%S")}
    rendered = {n for n in sizes_to_render if any(r.scene == f"orbit-{n}" for r in runs)}
    for n in sorted(rendered) if not collect else ():
        ensure_scene(out, n, seed, log, image_size)
    rows: list[dict[str, Any]] = []
    result = {"config": config, "rows": rows + skipped, "summary": summarise(rows, engine)}
    for spec in runs:
        rows.append(run_one(spec, out, seed, max_size, recompute and not collect, log, image_size, collect))
        result = {"config": config, "rows": rows + skipped, "summary": summarise(rows, engine)}
        write_json_atomic(out / "scale.json", result)
    write_json_atomic(out / "scale.json", result)
    return result


# output -----------------------------------------------------------------------------------------
STAGE_COLUMNS = (("features", "features"), ("pairs", "pairs"), ("match", "match"), ("sfm", "sfm"))


def scale_table(result: dict[str, Any]) -> Any:
    """A rich Table: one line per run (skipped ones say why)."""
    from rich.table import Table

    t = Table(title="recon bench scale (seconds per stage; other = load, tracks, database, verify, export; "
                    "peak = summed RSS of the run's process tree, MB)")
    for col in ("scene", "N", "pairs", "engine", "proposed", "verified", *(c for c, _ in STAGE_COLUMNS), "other",
                "total", "wall", "CPU s", "peak MB", "registered", "rot. err °"):
        t.add_column(col, justify="left" if col in ("scene", "pairs", "engine") else "right")
    for r in sorted(result["rows"], key=_row_order):
        eng = engine_label(r)
        if r.get("status") == "skipped" or r.get("status") == "error":
            t.add_row(r["scene"], _fmt(r.get("num_images"), "d"), r["pairs_spec"], eng,
                      f"[dim]{r['status']}: {r.get('reason', '')}[/dim]", *[""] * 12)
            continue
        st = r.get("stages") or {}
        t.add_row(r["scene"], str(r["num_images"]), r["pairs_spec"], eng, str(r["pairs"]), str(r["verified_pairs"]),
                  *(_fmt(st.get(k), ".1f") for _, k in STAGE_COLUMNS), _fmt(_other_seconds(r), ".1f"),
                  _fmt(r.get("seconds_total"), ".1f"),
                  _fmt(r.get("wall_seconds"), ".1f"), _fmt(r.get("cpu_seconds"), ".0f"), _fmt(r.get("peak_tree_mb"), ".0f"),
                  f"{r['registered']}/{r['num_images']}", _fmt(r.get("rot_err_deg_median"), ".3f"))
    return t


def _other_seconds(r: dict[str, Any]) -> float | None:
    """Seconds of the stages without a column of their own (load, tracks, database, verify, export)."""
    st = r.get("stages") or {}
    return sum(v for k, v in st.items() if k not in {key for _, key in STAGE_COLUMNS}) if st else None


def _row_order(r: dict[str, Any]) -> tuple:
    return (r["kind"] != "rendered", r.get("num_images") or 0, r["scene"], r["pairs_spec"], r["engine"], r["workers"],
            int(r.get("opencv_threads") or 0))


def targets_lines(result: dict[str, Any]) -> list[str]:
    """One line per target check: `met` / `MISSED` / `not measured`."""
    lines = []
    for t in result["summary"]["targets"]:
        verdict = "met" if t["met"] else "MISSED" if t["met"] is not None else "not measured"
        lines.append(f"{verdict:>7}  {t['target']}: {t['value']}")
    for mode, f in result["summary"]["fits"].items():
        lines.append(f"    fit  {mode}: total seconds ~ N^{_fmt(f['exponent_all'], '.2f')} over {f['sizes']}, "
                     f"N^{_fmt(f.get(f'exponent_from_{FIT_MIN_N}'), '.2f')} from {FIT_MIN_N} views")
    return lines


def plot_scale(result: dict[str, Any], path: Path) -> Path | None:
    """Log-log plot of total seconds against N per pair selection (rendered sweep) and the real scenes;
    None when matplotlib is not installed."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    cfg = result["config"]
    done = [r for r in _ok(result["rows"]) if r.get("seconds_total")]
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    sweep = [r for r in done if r["kind"] == "rendered" and engine_label(r) == cfg["engine"]]
    for mode in dict.fromkeys(r["pairs_spec"] for r in sweep):
        pts = sorted((r["num_images"], r["seconds_total"]) for r in sweep if r["pairs_spec"] == mode)
        b = fit_exponent(pts)
        ax.plot(*zip(*pts), "o-", label=f"rendered, {mode}" + (f" (~N^{b:.2f})" if b is not None else ""))
    for r in done:
        if r["kind"] == "real":
            ax.plot([r["num_images"]], [r["seconds_total"]], "s", label=f"{r['scene']}, {r['pairs_spec']} "
                                                                        f"({r['pairs_used']})")
    series = {m: sorted((r["num_images"], r["seconds_total"]) for r in sweep if r["pairs_spec"] == m)
              for m in dict.fromkeys(r["pairs_spec"] for r in sweep)}
    longest = max(series.values(), key=len, default=[])
    if len(longest) >= 2:  # reference slopes from the first point of the longest series
        (lo, y0), hi = longest[0], longest[-1][0]
        for e, style in ((1.2, ":"), (2.0, "--")):
            ax.plot([lo, hi], [y0, y0 * (hi / lo) ** e], "k" + style, lw=0.8, label=f"N^{e:g}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("images N")
    ax.set_ylabel("total seconds (recon run, load to export)")
    ax.set_title(f"recon run time against N ({cfg['engine']}, {cfg.get('cpu_count')} cores)",
                 fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
