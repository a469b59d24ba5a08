"""`recon run SCENE_DIR`: photos to a COLMAP sparse model (see `recon.core.pipeline`).

The options are generated from `recon.config.RunConfig` (every field with a `flag`, its
attribute docstring as the help, its default as the default), so they cannot drift from the
library. On top of them: `--preset NAME`, `--config FILE`, `--set KEY=VALUE` (any option, and
the matcher's own as `matcher.KEY`) and `--rerun SINK`. Precedence: preset < config file <
flags given on the command line < --set.
"""

from __future__ import annotations

import inspect
import typing
from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from recon.cli.options import choices_metavar
from recon.config import PRESETS, run_options

CLI_TYPES = {bool, int, float, str, Path}


def _cli_type(t: Any) -> Any:
    """The type typer parses: Literal choices and other types as str (checked by the config,
    which raises UserError: one line, exit 2), `X | None` as Optional[X]."""
    args = [a for a in typing.get_args(t) if a is not type(None)]
    if args and len(args) < len(typing.get_args(t)):
        return Optional[_cli_type(args[0])]  # noqa: UP045 (typer needs typing.Optional here)
    return t if t in CLI_TYPES else str


def metavar(t: Any, choices: tuple[str, ...]) -> str | None:
    """--help's type column: the choices (`<a|b|c>`), nothing for a flag, else typer's own."""
    if choices:
        return choices_metavar(choices)
    return "" if t is bool else None


def _signature() -> inspect.Signature:
    """run()'s parameters: the scene folder, the generated config options, then the CLI's own."""
    P = inspect.Parameter
    params = [
        P("ctx", P.KEYWORD_ONLY, annotation=typer.Context),
        P("scene_dir", P.KEYWORD_ONLY, annotation=Annotated[Path, typer.Argument(
            help="Scene folder: photos in SCENE_DIR/images/ or SCENE_DIR.", metavar="SCENE_DIR")]),
    ]
    for o in run_options():
        params.append(P(o.name, P.KEYWORD_ONLY, default=o.default,
                        annotation=Annotated[_cli_type(o.type), typer.Option(
                            o.flag, help=o.help, metavar=metavar(o.type, o.choices))]))
    params += [
        P("preset", P.KEYWORD_ONLY, default="default", annotation=Annotated[str, typer.Option(
            "--preset", help="Named configuration (see recon.config.PRESETS).", metavar=choices_metavar(PRESETS))]),
        P("config", P.KEYWORD_ONLY, default=None, annotation=Annotated[Optional[Path], typer.Option(  # noqa: UP045
            "--config", help="TOML or JSON file of options (nested as report.json's config; the matcher's "
                             "options in a matcher table).")]),
        P("set_", P.KEYWORD_ONLY, default=None, annotation=Annotated[Optional[list[str]], typer.Option(  # noqa: UP045
            "--set", help="KEY=VALUE, repeatable: any option (e.g. tracks.merge_px=1.5) or the matcher's own "
                          "(e.g. matcher.fine_top_k=3, matcher.coarse.rank_by=matches).")]),
        P("rerun", P.KEYWORD_ONLY, default="save", annotation=Annotated[str, typer.Option(
            "--rerun", help="Rerun recording: save (OUT/recording.rrd, default), save:PATH, spawn (open the "
                            "viewer), connect[:URL] (stream to a running viewer) or none.")]),
    ]
    return inspect.Signature(params)


def build_config(ctx: typer.Context, kw: dict[str, Any]) -> Any:
    """The RunConfig of this command line: preset < --config < flags given < --set."""
    from recon.config import build_run_config

    def given_on_command_line(name: str) -> bool:  # by name: click's enum or typer's vendored copy
        source = ctx.get_parameter_source(name)
        return source is not None and source.name != "DEFAULT"

    given = {o.path: kw[o.name] for o in run_options() if given_on_command_line(o.name)}
    return build_run_config(kw["preset"], kw["config"], given, kw["set_"])


STALE_RECORDING_NAME = "recording.previous.rrd"


def retire_stale_recording(recording: Path, saved: Path | None, report: Any, overwrite: bool) -> Path | None:
    """A recording never outlives the model it shows: when this run wrote a new model (or none)
    and did not write `recording` itself (`--rerun none`, or save:PATH elsewhere), an older
    OUT/recording.rrd is deleted (--overwrite) or renamed to recording.previous.rrd, so `recon
    view OUT` cannot show a different run. Returns the renamed file, if any."""
    import sys

    if saved == recording or not recording.is_file() or (report.model_reused and not overwrite):
        return None
    if overwrite:
        recording.unlink()
        return None
    old = recording.with_name(STALE_RECORDING_NAME)
    recording.replace(old)
    print(f"recon: {recording.name} showed an older model; renamed to {old.name}", file=sys.stderr)
    return old


def run(**kw: Any) -> None:
    """Match the photos of a scene, write a COLMAP database and reconstruct a sparse model."""
    import sys

    from rich.console import Console

    from recon.core.outdir import claim_output, clean_content_cache
    from recon.core.pairs import check_pairs_names, parse_pairs_spec
    from recon.core.pipeline import run_scene
    from recon.core.report import summary_table
    from recon.core.scene import require_images
    from recon.errors import UserError
    from recon.viz.rerun_log import RECORDING_NAME, RerunLogger, find_viewer, parse_sink

    scene_dir: Path = kw["scene_dir"]
    cfg = build_config(kw["ctx"], kw)
    # the same output folder run_scene uses; the logger opens its sink lazily, after
    # run_scene has checked and claimed the folder
    out_dir = (cfg.output.out or scene_dir.expanduser() / "recon").absolute()
    try:
        sink = parse_sink(kw["rerun"], out_dir / RECORDING_NAME)
    except ValueError as e:
        raise UserError(str(e)) from None
    if sink.kind == "spawn" and find_viewer() is None:
        raise UserError("--rerun spawn: the Rerun viewer (`rerun`) is not installed; "
                        "use --rerun save and open the file elsewhere")
    # the inputs first (no image decoded, nothing created): scene folder, image files, pairs file
    image_dir, candidates = require_images(scene_dir.expanduser())
    check_pairs_names(parse_pairs_spec(cfg.pairs.spec), candidates)
    image_dir = image_dir.resolve()
    logger = RerunLogger(sink, lambda name: image_dir / name) if sink.enabled else None
    ok = False
    # one run per output folder (OUT/.recon.lock); a foreign folder is refused before anything is written
    with claim_output(out_dir, "run", default_out=cfg.output.out is None, marker=False):
        if cfg.output.overwrite and not cfg.output.keep_cache:  # --overwrite --clean-cache: from scratch
            clean_content_cache(out_dir)
        try:
            report = run_scene(scene_dir, cfg, observer=[logger] if logger else None)
            ok = True
        finally:  # Ctrl-C too: `recon.cli.main` prints the one line and the exit code
            saved = logger.close(ok) if logger else None
    retire_stale_recording(out_dir / RECORDING_NAME, saved, report, cfg.output.overwrite)
    Console().print(summary_table(report))
    if saved is not None:
        print(f"recon: Rerun recording {saved} ({saved.stat().st_size / 1e6:.1f} MB); "
              f"open it with: recon view {saved}", file=sys.stderr)
    if not report.ok:
        print(f"recon: error: {report.message}", file=sys.stderr)
        # SystemExit, not typer.Exit: click (standalone_mode=False) would turn Exit into a
        # return value that `recon.cli.main` does not look at
        raise SystemExit(1)


run.__signature__ = _signature()  # type: ignore[attr-defined]


def register(app: typer.Typer) -> None:
    app.command("run")(run)
