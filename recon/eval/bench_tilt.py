"""Synthetic tilt benchmark: every method on rendered frontal/oblique pairs with exact homographies.

The shared pairs carry ground truths that are themselves 2.6-6.7 px off on five EVD pairs
(`benchmarks/gt_alignment.py`), and are only eight: a matcher tuned to them proves little. Here
the pairs are rendered (`scenes.tilt`): each texture (the procedural one of `scenes.texture`, or
a photo pasted on the plane) is seen frontally and from each viewing angle x azimuth, so the
homography is exact and the tilt is known. `run_tilt_bench` writes the pairs under OUT (so they
can be inspected and rerun with `recon match`), runs `recon.eval.bench_pairs.run_bench` on them
and adds the view's angle, tilt and azimuth to each row; `tilt_table` shows, per viewing angle,
how many pairs each method solved (the pair benchmark's criterion: precision >= 50 % at sqrt(3)
px with >= 20 correct) and its median correct matches and seconds.
"""

from __future__ import annotations

import statistics
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from matching.registry import PairMatcher
from recon.errors import UserError
from recon.eval.bench_pairs import GtPair, run_bench, solved
from scenes.texture import photo_texture, procedural_texture
from scenes.tilt import Photometry, TiltView, render_tilt_pair

IMAGE_SIZE = (800, 600)
TEXTURE_SIZE = (1600, 1200)  # twice the images: the frontal view reads 2 texture px per pixel
DEFAULT_ROLL = 20.0


@dataclass(frozen=True)
class TextureSpec:
    """`procedural:SEED` (the project's texture) or the path of a photo."""

    label: str
    seed: int | None = None
    path: Path | None = None

    def load(self) -> np.ndarray:
        w, h = TEXTURE_SIZE
        if self.path is not None:
            return photo_texture(self.path, w, h)
        return procedural_texture(8.0, 6.0, w / 8.0, int(self.seed or 0))


def parse_textures(text: str) -> list[TextureSpec]:
    """Comma-separated `procedural:SEED` or image paths; UserError for a missing file or bad seed."""
    out: list[TextureSpec] = []
    for item in (s.strip() for s in text.split(",")):
        if not item:
            continue
        if item.startswith("procedural"):
            _, _, seed = item.partition(":")
            try:
                n = int(seed or 0)
            except ValueError:
                raise UserError(f"--textures {item!r}: expected procedural:SEED with an integer seed") from None
            out.append(TextureSpec(f"procedural-{n}", seed=n))
        else:
            p = Path(item).expanduser()
            if not p.is_file():
                raise UserError(f"--textures {item!r}: no such image file")
            label = f"{p.parent.name}-{p.stem}" if p.parent.name else p.stem
            out.append(TextureSpec(label, path=p))
    if not out:
        raise UserError("--textures: give at least one texture (procedural:SEED or an image path)")
    labels = [t.label for t in out]
    if len(set(labels)) != len(labels):
        raise UserError(f"--textures: two textures share a name ({', '.join(labels)})")
    return out


def parse_floats(text: str, option: str, lo: float, hi: float) -> list[float]:
    """Comma-separated numbers in [lo, hi); UserError otherwise."""
    try:
        vals = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise UserError(f"{option} {text!r}: expected comma-separated numbers") from None
    bad = [v for v in vals if not lo <= v < hi]
    if not vals or bad:
        raise UserError(f"{option} {text!r}: every value must lie in [{lo:g}, {hi:g})")
    return list(dict.fromkeys(vals))


def tilt_views(angles: Sequence[float], azimuths: Sequence[float], roll: float = DEFAULT_ROLL,
               zooms: Sequence[float] = (1.0,)) -> list[TiltView]:
    return [TiltView(a, az, roll, z) for z in zooms for a in angles for az in azimuths]


def write_pairs(out: Path, textures: Sequence[TextureSpec], views: Sequence[TiltView],
                photometry: Photometry | None = None) -> tuple[list[GtPair], dict[str, dict[str, Any]]]:
    """Render every (texture, view) pair into OUT/<texture>/<view>/{0.png, 1.png, H_1_from_0.txt};
    the GtPairs and, per pair name, the fields added to its rows. The oblique image's noise is
    seeded by the pair's name, so a rerun writes the same bytes."""
    pairs: list[GtPair] = []
    info: dict[str, dict[str, Any]] = {}
    for spec in textures:
        tex = spec.load()
        for v in views:
            seed = zlib.crc32(f"{spec.label} {v.name}".encode())
            img0, img1, H = render_tilt_pair(tex, v, IMAGE_SIZE, photometry=photometry, seed=seed)
            d = out / spec.label / v.name.replace(" ", "_")
            d.mkdir(parents=True, exist_ok=True)
            p0, p1 = d / "0.png", d / "1.png"
            for p, img in ((p0, img0), (p1, img1)):
                if not cv2.imwrite(str(p), img):
                    raise UserError(f"cannot write {p}")
            np.savetxt(d / "H_1_from_0.txt", H)
            name = f"{spec.label} {v.name}"
            pairs.append(GtPair(name, p0, p1, H, "tilt"))
            info[name] = {"texture": spec.label, "angle_deg": v.angle_deg, "tilt": round(v.tilt, 3),
                          "azimuth_deg": v.azimuth_deg, "roll_deg": v.roll_deg, "zoom": v.zoom,
                          "photometry": None if photometry is None else vars(photometry)}
    return pairs, info


def run_tilt_bench(out: Path, textures: Sequence[TextureSpec], views: Sequence[TiltView], methods: Sequence[str],
                   matchers: dict[str, PairMatcher], json_path: Path | None = None, progress: bool = True,
                   log: Callable[[str], None] | None = None, photometry: Photometry | None = None
                   ) -> list[dict[str, Any]]:
    """Render the pairs, run every method on every pair (one process), one row per (pair, method);
    with `json_path` the rows so far are rewritten after each pair (an interrupted run keeps them)."""
    pairs, info = write_pairs(out, textures, views, photometry)
    if log:
        log(f"{len(pairs)} rendered pairs under {out}")

    def annotate(row: dict[str, Any]) -> None:
        row.update(info[row["pair"]])

    return run_bench(pairs, methods, json_path=json_path, progress=progress, matchers=matchers, on_row=annotate)


def tilt_summary(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (zoom, viewing angle, method): pairs, solved, median correct, median seconds."""
    out = []
    for zoom, angle in sorted({(r["zoom"], r["angle_deg"]) for r in rows}):
        for m in dict.fromkeys(r["method"] for r in rows):
            rs = [r for r in rows if r["angle_deg"] == angle and r["zoom"] == zoom and r["method"] == m]
            out.append({"zoom": zoom, "angle_deg": angle, "tilt": rs[0]["tilt"], "method": m, "pairs": len(rs),
                        "solved": sum(map(solved, rs)),
                        "median_correct": statistics.median(r["correct"] for r in rs),
                        "median_seconds": statistics.median(r["seconds"] for r in rs)})
    return out


def tilt_table(rows: Sequence[dict[str, Any]]):
    """A rich Table: one line per (zoom, viewing angle), 'solved / pairs, median correct, median s'
    per method (`tilt_summary`), and a last line of all pairs solved per method."""
    from rich.table import Table

    methods = list(dict.fromkeys(r["method"] for r in rows))
    t = Table(title="Rendered tilt pairs (solved: precision >= 50 % at sqrt(3) px with >= 20 correct; "
                    "solved/pairs, median correct, median s)")
    t.add_column("zoom", justify="right", no_wrap=True)
    t.add_column("angle (tilt)", justify="right", no_wrap=True)
    for m in methods:
        t.add_column(m, justify="right", no_wrap=True)
    cells: dict[tuple[float, float], dict[str, dict[str, Any]]] = {}
    for c in tilt_summary(rows):  # already in (zoom, angle) order
        cells.setdefault((c["zoom"], c["angle_deg"]), {})[c["method"]] = c
    for (zoom, angle), by_method in cells.items():
        t.add_row(f"{zoom:g}", f"{angle:g}° ({by_method[methods[0]]['tilt']:.2f})",
                  *[f"{c['solved']}/{c['pairs']}, {c['median_correct']:g}, {c['median_seconds']:.2f}"
                    for c in (by_method[m] for m in methods)])
    tot = [f"{sum(map(solved, rs))}/{len(rs)}" for rs in ([r for r in rows if r['method'] == m] for m in methods)]
    t.add_row("all", "", *tot)
    return t
