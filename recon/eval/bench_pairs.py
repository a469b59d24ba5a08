"""Pair benchmark with ground-truth homographies (the paper's Table I), for every method.

`discover_pairs(root)` finds the GT pairs under a data root, `run_bench(pairs, methods)` runs
every method on every pair in this one process and returns one row (dict) per (pair, method),
`print_report` draws the table and per-method summary, `write_json` saves the rows atomically.

Layouts recognised (at the root itself, or one or two folder levels below it):
- Oxford: `<set>/img1.<ext> .. img6.<ext>` + `H1to{k}p` (img1 -> img{k}); pairs "graf 1-2".
- HPatches: `<seq>/1.<ext> .. 6.<ext>` + `H_1_{k}` (1 -> k); sequences without any H file are
  skipped; pairs "v_dogman 1-4".
- EVD: `1/<n>.<ext>`, `2/<n>.<ext>`, `h/<n>.txt` (image 1 -> image 2, normalised by H[2,2]);
  pairs "evd adam".
"""

from __future__ import annotations

import json
import math
import os
import re
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from matching.io import load_gray, read_homography
from matching.memory import PeakRss
from matching.metrics import DEFAULT_TH, gt_reference, inlier_ratio, precision, reference_correct
from matching.registry import PairMatcher, get_matcher
from matching.store import FeatureStore

IMAGE_EXTS = (".png", ".ppm", ".pgm", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
SOLVED_MIN_PRECISION = 0.5  # a pair counts as solved with precision >= 50 % ...
SOLVED_MIN_CORRECT = 20  # ... and at least this many correct matches
LOOSE_TH = 5.0  # px: `correct_5px` counts final matches this close to the ground truth, for pairs whose
# ground truth is itself a few px off at textured patches (benchmarks/gt_alignment.py: EVD mag, fox, grand)


@dataclass(frozen=True, eq=False)
class GtPair:
    """Two images and the true homography mapping image 0 (path0) to image 1 (path1)."""

    name: str  # "graf 1-2", "v_dogman 1-4", "evd adam"
    path0: Path
    path1: Path
    H_1_from_0: NDArray[np.float64]
    dataset: str = ""  # "oxford", "hpatches", "evd"


def solved(row: dict[str, Any]) -> bool:
    """Whether a result row counts as solved (`SOLVED_MIN_PRECISION`, `SOLVED_MIN_CORRECT`)."""
    return row["precision"] >= SOLVED_MIN_PRECISION and row["correct"] >= SOLVED_MIN_CORRECT


# discovery --------------------------------------------------------------------------------------
def _image(folder: Path, stem: str) -> Path | None:
    for ext in IMAGE_EXTS:
        for cand in (folder / f"{stem}{ext}", folder / f"{stem}{ext.upper()}"):
            if cand.is_file():
                return cand
    return None


def _numbered(folder: Path, pattern: str) -> list[tuple[int, Path]]:
    """(k, file) for the files of `folder` whose name fully matches `pattern` (one int group), by k."""
    out = []
    for p in folder.iterdir():
        m = re.fullmatch(pattern, p.name)
        if m and p.is_file():
            out.append((int(m.group(1)), p))
    return sorted(out)


def _one_to_k(folder: Path, first: str, h_pattern: str, image_k: str, kind: str) -> list[GtPair]:
    """Pairs (image `first`, image k) with homography files matching `h_pattern` (k as its group);
    `image_k` names image k (`{k}` is replaced)."""
    img1 = _image(folder, first)
    if img1 is None:
        return []
    out = []
    for k, hp in _numbered(folder, h_pattern):
        imgk = _image(folder, image_k.format(k=k))
        if imgk is not None:
            out.append(GtPair(f"{folder.name} 1-{k}", img1, imgk, read_homography(hp), kind))
    return out


def _oxford(folder: Path) -> list[GtPair]:
    return _one_to_k(folder, "img1", r"H1to(\d+)p", "img{k}", "oxford")


def _hpatches(folder: Path) -> list[GtPair]:
    return _one_to_k(folder, "1", r"H_1_(\d+)", "{k}", "hpatches")


def _evd(folder: Path) -> list[GtPair]:
    d1, d2, dh = folder / "1", folder / "2", folder / "h"
    if not (d1.is_dir() and d2.is_dir() and dh.is_dir()):
        return []
    out = []
    for hp in sorted(dh.glob("*.txt")):
        p0, p1 = _image(d1, hp.stem), _image(d2, hp.stem)
        if p0 is not None and p1 is not None:
            out.append(GtPair(f"evd {hp.stem}", p0, p1, read_homography(hp), "evd"))
    return out


def discover_pairs(data_root: Path) -> list[GtPair]:
    """Every ground-truth pair under `data_root` (see the module doc for the layouts).

    Folders are visited in sorted order (root, then children, then grandchildren), so the list
    is stable. A malformed homography file raises `InputError` naming it.
    """
    root = Path(data_root)
    if not root.is_dir():
        return []
    folders = [root]
    children = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    for c in children:
        folders.append(c)
        folders.extend(sorted(p for p in c.iterdir() if p.is_dir() and not p.name.startswith(".")))
    pairs: list[GtPair] = []
    seen: set[str] = set()
    for f in folders:
        for pair in _oxford(f) + _hpatches(f) + _evd(f):
            key = f"{pair.path0}|{pair.path1}"
            if key not in seen:
                seen.add(key)
                pairs.append(pair)
    order = {"oxford": 0, "hpatches": 1, "evd": 2}
    return sorted(pairs, key=lambda p: order.get(p.dataset, 3))  # stable: keeps discovery order


# running ----------------------------------------------------------------------------------------
def _clean(v: Any) -> Any:
    """JSON-safe: numpy scalars to Python, non-finite floats to None."""
    if isinstance(v, dict):
        return {str(k): _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def run_pair(pair: GtPair, img0: NDArray[np.uint8], img1: NDArray[np.uint8], method: str,
             matcher: PairMatcher, th: float = DEFAULT_TH) -> dict[str, Any]:
    """Run one matcher on one pair with a fresh FeatureStore; one result row."""
    store = FeatureStore()
    store.add_image("0", img0)
    store.add_image("1", img1)
    with PeakRss() as mem:
        t = time.perf_counter()
        result = matcher.match(store, "0", "1")
        seconds = time.perf_counter() - t
    size0 = (int(img0.shape[1]), int(img0.shape[0]))
    rep = precision(result, pair.H_1_from_0, th)
    loose = precision(result, pair.H_1_from_0, LOOSE_TH)
    bv = result.best_view
    row = {
        "pair": pair.name,
        "dataset": pair.dataset,
        "method": method,
        "points": rep.points,
        "correct": rep.correct,
        "precision": rep.precision,
        "correct_5px": loose.correct,
        "seconds": seconds,
        "peak_mb": mem.peak_mb,
        "peak_rss_mb": mem.total_mb,
        "rss_before_mb": mem.before_mb,
        "ref_correct": reference_correct(result, pair.H_1_from_0, size0),
        "reference": result.reference,
        "gt_reference": gt_reference(pair.H_1_from_0, size0),
        "reference_reason": result.reference_reason,
        "matches": result.num_matches,
        "inliers": result.num_inliers,
        "inlier_ratio": inlier_ratio(result),
        "homography": result.H_1_from_0 is not None,
        "escalation": result.escalation,
        "path": result.path,
        "path_reason": result.path_reason,
        "best_view": None if bv is None else {"t": bv.t, "phi": bv.phi, "s": bv.s, "key": bv.key},
        "reason": result.reason,
        "timings": dict(result.timings),
        "th": th,
        "path0": str(pair.path0),
        "path1": str(pair.path1),
    }
    return _clean(row)


def write_json(path: Path, rows: list[dict[str, Any]]) -> None:
    """Write rows as a JSON list atomically (temporary file in the same folder + os.replace)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump([_clean(r) for r in rows], f, indent=1)
        f.write("\n")
    os.replace(tmp, path)


def run_bench(pairs: Sequence[GtPair], methods: Sequence[str], th: float = DEFAULT_TH,
              json_path: Path | None = None, progress: bool = True,
              matchers: dict[str, PairMatcher] | None = None,
              on_row: Callable[[dict[str, Any]], None] | None = None) -> list[dict[str, Any]]:
    """Every method on every pair, in this process; one row per (pair, method).

    Each pair's images are loaded once; each (pair, method) gets a fresh FeatureStore so
    `seconds` includes feature extraction (the paper's "extraction plus matching"). With
    `json_path` the rows so far are rewritten (atomically) after each pair, so an interrupted run
    keeps what it measured. A matcher that raises is a bug: the exception propagates.
    """
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    matchers = dict(matchers or {})
    for m in methods:
        if m not in matchers:
            matchers[m] = get_matcher(m)
    rows: list[dict[str, Any]] = []
    console = Console(stderr=True)
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), console=console, transient=True, disable=not progress) as prog:
        task = prog.add_task("bench", total=len(pairs) * len(methods))
        for pair in pairs:
            img0, img1 = load_gray(pair.path0), load_gray(pair.path1)
            for m in methods:
                prog.update(task, description=f"{pair.name} [bold]{m}[/]")
                row = run_pair(pair, img0, img1, m, matchers[m], th)
                rows.append(row)
                if on_row is not None:
                    on_row(row)
                prog.advance(task)
            if json_path is not None:
                write_json(json_path, rows)
    return rows


# reporting --------------------------------------------------------------------------------------
def summarize(rows: Sequence[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per-method summary: pairs, solved, median seconds, mean precision, median peak MB, ref accuracy."""
    out: dict[str, dict[str, Any]] = {}
    for m in dict.fromkeys(r["method"] for r in rows):
        rs = [r for r in rows if r["method"] == m]
        mems = [r["peak_mb"] for r in rs if r.get("peak_mb") is not None]
        refs = [r["ref_correct"] for r in rs if r.get("ref_correct") is not None]
        out[m] = {
            "pairs": len(rs),
            "solved": sum(map(solved, rs)),
            "median_seconds": statistics.median(r["seconds"] for r in rs),
            "mean_precision": statistics.fmean(r["precision"] for r in rs),
            "median_peak_mb": statistics.median(mems) if mems else None,
            "ref_decided": len(refs),
            "ref_accuracy": (sum(refs) / len(refs)) if refs else None,
        }
    return out


def ratio_line(summary: dict[str, dict[str, Any]], ours: str = "extra-affine", base: str = "asift") -> str | None:
    """"extra-affine median time = X x faster than asift, peak memory = Y % of asift", or None."""
    if ours not in summary or base not in summary:
        return None
    a, b = summary[ours], summary[base]
    parts = []
    if a["median_seconds"] > 0:
        parts.append(f"{ours} median time = {b['median_seconds'] / a['median_seconds']:.2f} x faster than {base}")
    if a["median_peak_mb"] is not None and b["median_peak_mb"]:
        parts.append(f"peak memory = {100.0 * a['median_peak_mb'] / b['median_peak_mb']:.0f} % of {base}")
    parts.append(f"mean precision {100 * a['mean_precision']:.1f} % vs {100 * b['mean_precision']:.1f} %")
    return ", ".join(parts)


def _fmt(v: Any, spec: str, none: str = "-") -> str:
    return none if v is None else format(v, spec)


def _ref(v: bool | None) -> str:
    return "-" if v is None else ("yes" if v else "[red]no[/]")


def print_report(rows: Sequence[dict[str, Any]], th: float = DEFAULT_TH, console=None) -> None:
    """Table I-style table (pair x method) plus a per-method summary and the ratio line."""
    from rich.console import Console
    from rich.table import Table

    if console is None:
        console = Console()
        if not console.is_terminal:  # piped / redirected: do not squeeze the table into 80 columns
            console = Console(width=140)
    t = Table(title=f"Pairs with ground truth (Th = {th:.3g} px)", show_lines=False)
    for col, just in [("pair", "left"), ("method", "left"), ("points", "right"), ("correct", "right"),
                      ("precision %", "right"), ("seconds", "right"), ("peak MB", "right"),
                      ("ref ok", "center"), ("escalation", "left")]:
        t.add_column(col, justify=just, no_wrap=True)  # type: ignore[arg-type]
    prev = None
    for r in rows:
        if prev is not None and r["pair"] != prev:
            t.add_section()
        prev = r["pair"]
        prec = 100 * r["precision"]
        style = "green" if solved(r) else ""
        t.add_row(r["pair"], r["method"], str(r["points"]), str(r["correct"]),
                  f"[{style}]{prec:.2f}[/]" if style else f"{prec:.2f}", f"{r['seconds']:.2f}",
                  _fmt(r.get("peak_mb"), ".0f"), _ref(r.get("ref_correct")), r.get("escalation") or "")
    console.print(t)

    summary = summarize(rows)
    s = Table(title=f"Summary (solved: precision >= {100 * SOLVED_MIN_PRECISION:.0f} % and "
                    f">= {SOLVED_MIN_CORRECT} correct)")
    for col in ["method", "solved", "median s", "mean precision %", "median peak MB", "ref accuracy"]:
        s.add_column(col, justify="left" if col == "method" else "right", no_wrap=True)
    for m, v in summary.items():
        ref = "-" if v["ref_accuracy"] is None else f"{100 * v['ref_accuracy']:.0f} % ({v['ref_decided']})"
        s.add_row(m, f"{v['solved']}/{v['pairs']}", f"{v['median_seconds']:.2f}",
                  f"{100 * v['mean_precision']:.2f}", _fmt(v["median_peak_mb"], ".0f"), ref)
    console.print(s)
    line = ratio_line(summary)
    if line:
        console.print(line)
