"""`recon match IMG_A IMG_B`: match one pair and explain the matcher's decisions."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from matching.config import VARIANTS
from matching.io import load_color, load_gray, read_homography
from matching.metrics import DEFAULT_TH, gt_reference, precision
from matching.registry import METHODS, get_matcher, match_at_size
from matching.types import PairResult
from recon.cli._options import image_file, json_file
from recon.cli.options import choices_metavar, seed_option, workers_option
from recon.config import DEFAULT_MAX_SIZE

console = Console(stderr=False, highlight=False)


def summarize(result: PairResult, names: tuple[str, str], gt=None, th: float = DEFAULT_TH) -> dict:
    """JSON-ready summary of a pair result (and its precision against a GT homography)."""
    out: dict = {
        "image0": names[0], "image1": names[1], "method": result.method,
        "matches": result.num_matches, "inliers": result.num_inliers,
        "reference": None if result.reference is None else names[result.reference],
        "reference_index": result.reference, "reference_reason": result.reference_reason,
        "f0": result.f0, "f1": result.f1,
        "best_views": [{"t": v.t, "phi": v.phi, "s": v.s} for v in result.best_views],
        "coarse_scores": [{"t": c.view.t, "phi": c.view.phi, "s": c.view.s, "matches": c.matches,
                           "inliers": c.inliers, "score": c.score} for c in result.coarse_scores],
        "escalation": result.escalation, "path": result.path, "path_reason": result.path_reason,
        "finishing": result.finishing, "reason": result.reason, "timings_s": result.timings,
        "H_1_from_0": None if result.H_1_from_0 is None else result.H_1_from_0.tolist(),
    }
    p0, p1 = result.matched_points(inliers_only=True)
    out["points0"] = p0.tolist()
    out["points1"] = p1.tolist()
    if gt is not None and result.image_sizes is not None:
        rep = precision(result, gt, th)
        ref_gt = gt_reference(gt, result.image_sizes[0])
        out.update(points=rep.points, correct=rep.correct, precision=rep.precision, th=th,
                   gt_reference=ref_gt,
                   ref_correct=None if ref_gt is None or result.reference is None else ref_gt == result.reference)
    return out


def _print(summary: dict, result: PairResult) -> None:
    t = Table(show_header=False, box=None, pad_edge=False)
    t.add_column(style="bold")
    t.add_column()
    t.add_row("method", summary["method"])
    if result.reference is not None:
        t.add_row("reference", f"{summary['reference']}  ({summary['reference_reason']})")
        if result.f0 is not None:
            t.add_row("Eq. 1 f0 / f1", f"{result.f0:.1f} / {result.f1:.1f}")
    if result.best_views:
        t.add_row("best (t, phi, s)", ", ".join(f"({v.t:.2f}, {v.phi:.1f}°, {v.s:.2f})" for v in result.best_views))
    if result.path:
        t.add_row("path", f"{result.path} ({result.path_reason})")
    if result.escalation:
        t.add_row("escalation", result.escalation)
    if result.finishing:
        t.add_row("finishing", result.finishing)
    scales = summary.get("working_scale", [1.0, 1.0])
    if scales != [1.0, 1.0]:
        t.add_row("working size", f"{scales[0]:.3g}x / {scales[1]:.3g}x the originals (--max-size; points in "
                                  "the originals' pixels)")
    t.add_row("matches / inliers", f"{summary['matches']} / {summary['inliers']}")
    if "precision" in summary:
        ok = {True: "agrees with GT", False: "DISAGREES with GT", None: "GT scales within 10 %"}[summary["ref_correct"]]
        t.add_row("precision", f"{summary['precision'] * 100:.2f} %  ({summary['correct']} of {summary['points']} "
                               f"within {summary['th']:.3g} px); reference {ok}")
    t.add_row("time", "  ".join(f"{k} {v:.2f}s" for k, v in result.timings.items()))
    if result.reason:
        t.add_row("note", result.reason)
    console.print(t)


def match_command(
    img_a: Path = typer.Argument(..., help="First image (image 0).", metavar="IMG_A"),
    img_b: Path = typer.Argument(..., help="Second image (image 1).", metavar="IMG_B"),
    method: str = typer.Option("extra-affine", "--method", "-m", help="Pair matcher.",
                               metavar=choices_metavar(METHODS)),
    gt: Optional[Path] = typer.Option(None, "--gt", help="Ground-truth homography file (image 0 -> image 1)."),
    save_vis: Optional[Path] = typer.Option(None, "--save-vis", callback=image_file,
                                            help="Write the matches drawn side by side, with a legend and counts "
                                                 "(PNG/JPG)."),
    json_out: Optional[Path] = typer.Option(None, "--json", callback=json_file,
                                            help="Write the result summary and matched points as JSON."),
    th: float = typer.Option(DEFAULT_TH, "--th", help="Precision threshold in pixels (paper: sqrt(3))."),
    max_size: int = typer.Option(DEFAULT_MAX_SIZE, "--max-size",
                                 help="Match at this working resolution (longer side, px; 0 = full): results, "
                                      "--gt and drawings stay in the originals' pixels."),
    variant: str = typer.Option("default", "--variant", metavar=choices_metavar(VARIANTS),
                                help="extra-affine only: the default (planar pairs), the paper's plain reading, "
                                     "`recon run`'s preset, or 3d (two photos of a 3D scene: no final homography, "
                                     "covariant SIFT on the originals, every escalation level)."),
    seed: Annotated[int, seed_option()] = 0,
    workers: Annotated[int, workers_option("Threads of the extra-affine matcher's views (0 = all cores).")] = 0,
    rerun: str = typer.Option("none", "--rerun", help="Log the pair to Rerun: save:PATH, spawn, connect[:URL] or none."),
) -> None:
    """Match two images and report the reference choice, best view, matches and timings."""
    from recon.core.jsonio import write_json_atomic
    from recon.errors import UserError
    from recon.viz.vis import draw_matches, write_image_atomic

    if method not in METHODS:
        raise UserError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if variant not in VARIANTS:
        raise UserError(f"unknown variant {variant!r}; choose one of {', '.join(VARIANTS)}")
    if not (th > 0 and np.isfinite(th)):
        raise UserError(f"--th {th}: must be a positive number of pixels")
    if workers < 0:
        raise UserError(f"--workers {workers}: must be >= 0 (0 = all cores)")
    if max_size != 0 and max_size < 64:
        raise UserError(f"--max-size {max_size}: must be 0 (full resolution) or at least 64 px")
    from recon.viz.rerun_log import find_viewer, log_single_pair, parse_sink

    try:
        sink = parse_sink(rerun)
    except ValueError as e:
        raise UserError(str(e)) from None
    if sink.kind == "spawn" and find_viewer() is None:
        raise UserError("--rerun spawn: the Rerun viewer (`rerun`) is not installed; use --rerun save:PATH")
    H_gt = read_homography(gt) if gt is not None else None
    gray = [load_gray(img_a), load_gray(img_b)]
    names = (str(img_a), str(img_b))
    overrides: dict = {"seed": seed}
    if method == "extra-affine":
        overrides["workers"] = workers
        if variant != "default":
            overrides["variant"] = variant
    matcher = get_matcher(method, **overrides)
    from recon.log import quiet_colmap

    with quiet_colmap():  # the multiview preset's covariant SIFT would log each extraction
        result, (scale0, scale1) = match_at_size(matcher, gray[0], gray[1], max_size, names)
    summary = summarize(result, names, H_gt, th)
    summary["working_scale"] = [scale0, scale1]
    _print(summary, result)
    if result.num_matches == 0:
        console.print(f"no match: {result.reason or 'the images share no features'}")
    if save_vis is not None:
        write_image_atomic(save_vis, draw_matches(load_color(img_a), load_color(img_b), result, legend=True))
        console.print(f"wrote {save_vis}")
    if json_out is not None:
        write_json_atomic(json_out, summary)
        console.print(f"wrote {json_out}")
    if sink.enabled:
        saved = log_single_pair(sink, img_a, img_b, result)
        if saved is not None:
            console.print(f"wrote {saved}")


def register(app: typer.Typer) -> None:
    app.command("match")(match_command)
