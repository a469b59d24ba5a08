"""The difficulty curve: azimuth step between neighbouring views against registration and accuracy.

`run_difficulty(out, views=(3, 4, 5, 7, 9, 13), max_azimuth_deg=78)` renders the stepped facade
(`scenes.presets.facade_sweep`) seen from N cameras spread evenly over ±`max_azimuth_deg`, so the
step between neighbours is 2·max_azimuth / (N − 1) (78° for N = 3 down to 13° for N = 13) while
the extreme viewing angles stay the same; then runs `recon.eval.compare.compare_scene` (stock COLMAP
`default` and `high`, and ours, same images and pairs) on each and collects, per step and method:
registered images, median relative rotation and translation-direction errors against the
rendered ground truth, AUC@5°, verified pairs, mean verified inliers per verified pair, and
time; the mean number of those correspondences that are right (`correct_per_pair`: distinct
verified correspondences within `gt_planes.CORRECT_PX` of the exact transfer through the
rendered planes, `recon.eval.gt_planes`; COLMAP's count also holds matches that fit the
epipolar geometry at the wrong place along a line) and their median distance from it
(`correct_median_px`: how precisely they are localised); and these means split by the pair's
azimuth separation (`by_baseline`: neighbours, two steps apart, ...), which says where two
methods part (`baseline_table`). A scene that does not register fully still counts: its
rotation error is over the pairs it did register (and `registered` says how many), AUC counts
unregistered pairs as failures.

Outputs (under OUT): `scenes/<preset>/` (rendered once, reused when the same seed and size are
already there), `runs/<preset>/` (each `compare` output), `difficulty.json` (rows + config,
rewritten atomically after every scene, so an interrupted sweep keeps its finished scenes and
the next run re-uses their `compare.json` unless --recompute), and, when matplotlib is installed
(the `bench` extra), `difficulty.png`: registered fraction and rotation error against the step.
"""

from __future__ import annotations

import functools
import json
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from recon.config import DEFAULT_MAX_SIZE
from recon.core.jsonio import write_json_atomic
from recon.eval.compare import OURS_KEY, compare_scene
from recon.eval.gt_planes import correct_counts, correct_error_median, correct_per_pair, transfer_errors

DEFAULT_VIEWS = (3, 4, 5, 7, 9, 13)
DEFAULT_MAX_AZIMUTH = 78.0
DEFAULT_PRESETS = ("default", "high")
Log = Callable[[str], None]


def step_deg(num_views: int, max_azimuth_deg: float) -> float:
    return 2.0 * max_azimuth_deg / (num_views - 1)


def _scene(out: Path, preset: str, seed: int, image_size: tuple[int, int] | None, log: Log,
           name: str | None = None, textures: list[Path] | None = None) -> tuple[Path, bool]:
    """(scene folder OUT/scenes/<name, default the preset>, whether it was (re-)rendered now:
    earlier runs on it are then stale). `textures`: photos pasted on the planes (None: the
    procedural textures); a finished render is reused only with the same seed, size and textures."""
    from scenes.render import render_scene, textures_label

    d = out / "scenes" / (name or preset)
    meta_path = d / "gt" / "scene.json"
    want_textures = textures_label(textures)
    if meta_path.is_file():
        try:
            meta = json.loads(meta_path.read_text(encoding="utf-8"))
            same = (meta.get("seed") == seed and (image_size is None or list(image_size) == meta.get("image_size"))
                    and meta.get("textures", "procedural") == want_textures)
        except (OSError, ValueError):
            same = False
        if same and (d / "images").is_dir():
            return d, False
    log(f"rendering {preset} -> {d}")
    render_scene(d, preset, textures=textures, seed=seed, image_size=image_size, overwrite=True)
    return d, True


def rows_of(res: dict[str, Any], num_views: int, step: float) -> list[dict[str, Any]]:
    """One row per method of one `compare_scene` result (correct correspondences from each
    method's database and the scene's ground truth, when both are still there)."""
    rows = []
    for name, m in res["methods"].items():
        errors = transfer_errors(m.get("out"), res.get("scene"))
        correct = correct_counts(errors)
        rows.append({
            "views": num_views, "step_deg": round(step, 2), "method": "ours" if name == OURS_KEY else name,
            "status": m.get("status"), "registered": m.get("registered_images", 0), "images": m.get("num_images", 0),
            "rot_err_deg": m.get("rel_rot_err_deg_median"), "trans_err_deg": m.get("rel_trans_err_deg_median"),
            "auc_5": m.get("auc_5"), "verified_pairs": m.get("verified_pairs", 0), "pairs": m.get("num_pairs", 0),
            "inliers_per_pair": m.get("inliers_per_pair_mean", 0.0),
            "distinct_per_pair": m.get("distinct_inliers_per_pair_mean", 0.0), "points": m.get("num_points3D", 0),
            "correct_per_pair": correct_per_pair(m.get("pairs") or [], correct),
            "correct_median_px": correct_error_median(errors),
            "seconds": m.get("seconds_total"),
            "by_baseline": by_baseline(m.get("pairs") or [], step, correct),
        })
    return rows


def by_baseline(pairs: Sequence[dict[str, Any]], step: float,
                correct: dict[tuple[str, str], int] | None = None) -> list[dict[str, Any]]:
    """Verified inliers per verified pair (COLMAP's raw count and the distinct one) grouped by
    the pair's azimuth separation in degrees, narrowest first: `pairs` are a run report's pair
    rows (`image0`, `image1`, `verified_inliers`, `distinct_inliers`); the sweep's views are
    named in azimuth order `step` degrees apart (`scenes.presets.facade_sweep`), so a pair's
    separation is its name-rank difference times `step`. Pairs without verified inliers are
    counted in `pairs` only (as `verified_pairs` counts them out of the means). With `correct`
    (`gt_planes.correct_counts`) each group also gets `correct_per_pair`."""
    names = sorted({p[k] for p in pairs for k in ("image0", "image1")})
    rank = {n: i for i, n in enumerate(names)}
    groups: dict[int, list[dict[str, Any]]] = {}
    for p in pairs:
        groups.setdefault(abs(rank[p["image0"]] - rank[p["image1"]]), []).append(p)
    out = []
    for gap in sorted(groups):
        verified = [p for p in groups[gap] if p.get("verified_inliers", 0) > 0]
        n = len(verified)
        out.append({"separation_deg": round(gap * step, 2), "pairs": len(groups[gap]), "verified_pairs": n,
                    "inliers_per_pair": sum(p["verified_inliers"] for p in verified) / n if n else 0.0,
                    "distinct_per_pair": sum(p.get("distinct_inliers", 0) for p in verified) / n if n else 0.0,
                    "correct_per_pair": correct_per_pair(groups[gap], correct)})
    return out


def run_difficulty(out: str | Path, views: Sequence[int] = DEFAULT_VIEWS, max_azimuth_deg: float = DEFAULT_MAX_AZIMUTH,
                   presets: Sequence[str] = DEFAULT_PRESETS, seed: int = 0, image_size: tuple[int, int] | None = None,
                   max_size: int = DEFAULT_MAX_SIZE, recompute: bool = False, log: Log = lambda _m: None,
                   workers: int = 0, progress: bool = False, textures: Sequence[Path] | None = None) -> dict[str, Any]:
    """Render and compare every sweep scene; returns {"config", "rows"} (also OUT/difficulty.json).
    `textures`: photos pasted on the facade's planes instead of the procedural textures."""
    from recon.errors import UserError
    from scenes.presets import get_preset
    from scenes.render import textures_label

    views = sorted({int(v) for v in views})
    if not views or views[0] < 3:
        raise UserError("--views: give view counts of at least 3 (e.g. 3,4,5,7)")
    if not 0 < max_azimuth_deg <= 85:
        raise UserError("--max-azimuth: degrees in (0, 85]")
    out = Path(out).expanduser().resolve()
    out.mkdir(parents=True, exist_ok=True)
    config = {"views": views, "max_azimuth_deg": max_azimuth_deg, "presets": list(presets), "seed": seed,
              "image_size": list(image_size) if image_size else list(get_preset(f"facade-3x{max_azimuth_deg:g}").image_size),
              "max_size": max_size, "textures": textures_label(textures),
              "cpu_count": os.cpu_count(), "started": time.strftime("%Y-%m-%dT%H:%M:%S")}
    rows: list[dict[str, Any]] = []
    for n in views:
        preset = f"facade-{n}x{max_azimuth_deg:g}"
        scene, rendered = _scene(out, preset, seed, image_size, log, textures=list(textures) if textures else None)
        run_dir = out / "runs" / preset
        res = None
        cj = run_dir / "compare.json"
        if cj.is_file() and not recompute and not rendered:
            try:
                res = json.loads(cj.read_text(encoding="utf-8"))
                if (res.get("config", {}).get("stock_presets") != list(presets)
                        or res["config"].get("max_size") != max_size or res["config"].get("seed") != seed):
                    res = None
            except (OSError, ValueError, KeyError):
                res = None
            if res is not None:
                log(f"{preset}: reusing {cj} (--recompute to run it again)")
        if res is None:
            res = compare_scene(scene, run_dir, presets=presets, max_size=max_size, seed=seed, strict=False,
                                workers=workers, progress=progress,
                                log=log, on_warning=functools.partial(_warn_with, log, preset))
        rows += rows_of(res, n, step_deg(n, max_azimuth_deg))
        write_json_atomic(out / "difficulty.json", {"config": config, "rows": rows})
    return {"config": config, "rows": rows}


def difficulty_table(data: dict[str, Any]):
    """A rich table: one row per step, per method `registered` / `rot err` / `inliers per pair`."""
    from rich.table import Table

    rows = data["rows"]
    methods = list(dict.fromkeys(r["method"] for r in rows))
    cfg = data["config"]
    t = Table(title=f"Difficulty curve: stepped facade over ±{cfg['max_azimuth_deg']:g}° "
                    f"({cfg['image_size'][0]}x{cfg['image_size'][1]} px)", header_style="bold")
    t.add_column("views", justify="right")
    t.add_column("step °", justify="right")
    for m in methods:
        t.add_column(f"{m}\nregistered", justify="right")
        t.add_column(f"{m}\nrot err ° med", justify="right")
        t.add_column(f"{m}\ninliers/pair\n(distinct, correct)", justify="right")
    for n in dict.fromkeys(r["views"] for r in rows):
        by = {r["method"]: r for r in rows if r["views"] == n}
        cells = [str(n), f"{next(iter(by.values()))['step_deg']:.1f}"]
        for m in methods:
            r = by.get(m)
            if r is None:
                cells += ["-", "-", "-"]
                continue
            full = r["registered"] == r["images"]
            reg = f"{r['registered']}/{r['images']}"
            cells += [reg if full else f"[red]{reg}[/red]",
                      "-" if r["rot_err_deg"] is None else f"{r['rot_err_deg']:.2f}",
                      _counts(r)]
        t.add_row(*cells)
    return t


def baseline_table(data: dict[str, Any], views: int | None = None):
    """A rich table of one sweep (`views`, default the densest): verified inliers per verified
    pair, raw (distinct, correct), per azimuth separation and method (`by_baseline`)."""
    from rich.table import Table

    rows = data["rows"]
    views = views if views is not None else max(r["views"] for r in rows)
    by = {r["method"]: {b["separation_deg"]: b for b in r.get("by_baseline") or []}
          for r in rows if r["views"] == views}
    seps = sorted({s for b in by.values() for s in b})
    t = Table(title=f"Verified inliers per pair by azimuth separation, {views} views: raw (distinct, correct)",
              header_style="bold")
    t.add_column("separation °", justify="right")
    t.add_column("pairs", justify="right")
    for m in by:
        t.add_column(m, justify="right")
    for sep in seps:
        cells = [f"{sep:g}", str(max((b[sep]["pairs"] for b in by.values() if sep in b), default=0))]
        for m in by:
            b = by[m].get(sep)
            cells.append("-" if b is None or not b["verified_pairs"] else _counts(b))
        t.add_row(*cells)
    return t


def _counts(r: dict[str, Any]) -> str:
    """"raw (distinct, correct)" verified inliers per pair (no correct count: "raw (distinct)")."""
    c = r.get("correct_per_pair")
    tail = "" if c is None else f", {c:.0f}"
    return f"{r['inliers_per_pair']:.0f} ({r.get('distinct_per_pair', 0.0):.0f}{tail})"


def plot_difficulty(data: dict[str, Any], path: str | Path) -> Path | None:
    """difficulty.png (registered fraction, rotation error, inliers per pair against the step);
    None when matplotlib (the `bench` extra) is not installed."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    rows = data["rows"]
    # distinct line styles and marker sizes: curves that coincide (e.g. all registered) stay visible
    style = {"ours": ("tab:blue", "o", "-", 9), "stock-default": ("tab:orange", "s", "--", 7),
             "stock-high": ("tab:purple", "^", ":", 6)}
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for m in dict.fromkeys(r["method"] for r in rows):
        rs = sorted((r for r in rows if r["method"] == m), key=lambda r: r["step_deg"])
        c, mk, ls, ms = style.get(m, ("tab:gray", "x", "-.", 6))
        kw = dict(marker=mk, color=c, linestyle=ls, markersize=ms, label=m, linewidth=2, zorder=20 - ms)
        x = [r["step_deg"] for r in rs]
        axes[0].plot(x, [r["registered"] / max(r["images"], 1) for r in rs], **kw)
        axes[1].plot(x, [float("nan") if r["rot_err_deg"] is None else r["rot_err_deg"] for r in rs], **kw)
        axes[2].plot(x, [r.get("distinct_per_pair") or r["inliers_per_pair"] for r in rs], **kw)
    axes[0].set_ylabel("registered images (fraction)")
    axes[0].set_ylim(-0.05, 1.05)
    axes[1].set_ylabel("median relative rotation error (°)")
    axes[1].set_ylim(bottom=0)
    axes[2].set_ylabel("distinct verified inliers per pair")
    axes[2].set_ylim(bottom=0)
    for ax in axes:
        ax.set_xlabel("azimuth step between neighbouring views (°)")
        ax.grid(alpha=0.3)
    axes[0].legend()
    cfg = data["config"]
    fig.suptitle(f"Stepped facade, views over ±{cfg['max_azimuth_deg']:g}° azimuth: stock COLMAP vs extra-affine")
    fig.tight_layout()
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)
    return path


def _warn_with(log: Callable[[str], None], label: str, message: str) -> None:
    """A run's warning in the log, prefixed with what it belongs to (preset)."""
    log(f"{label}: warning: {message}")
