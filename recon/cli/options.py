"""Options shared by several commands, declared once so every `--help` spells and explains them alike.

`recon run` generates its options from `recon.config.RunConfig`; the other commands take these
factories (`Annotated[int, workers_option()]`), and `tests/test_cli_help.py` checks that every
command offering one of them lists it with the same flag. Flags (booleans) get an empty metavar
so `--help` shows no `<bool>` column entry; choices are Enums or Literals so `--help` lists them.
"""

from __future__ import annotations

import sys
from enum import Enum
from typing import Any

import typer

WORKERS_HELP = "Parallel tasks (0 = all cores)."
SEED_HELP = "Seed of every RANSAC and of the matcher (results are deterministic per seed)."
PROGRESS_HELP = "Progress bars on stderr."
STOCK_PRESETS_HELP = "Stock COLMAP presets, comma-separated: default, high (e.g. default,high)."
HELP_OPTION_NAMES = ["-h", "--help"]
CONTEXT_SETTINGS: dict[str, Any] = {"help_option_names": HELP_OPTION_NAMES}


class StockPreset(str, Enum):
    """COLMAP's stock matching presets (`recon.eval.stock.PRESETS`)."""

    default = "default"
    high = "high"


def choices_metavar(choices: Any) -> str:
    """`<a|b|c>`: how --help shows a str option's choices. The option stays a str (checked by the
    code, which raises UserError: one line, exit 2) rather than a click Choice, whose usage error
    takes four lines."""
    return "<" + "|".join(map(str, choices)) + ">"


def workers_option(help: str = WORKERS_HELP) -> Any:
    return typer.Option("--workers", help=help)


def seed_option(help: str = SEED_HELP) -> Any:
    """`--seed`, checked while the command line is parsed: COLMAP's and OpenCV's RANSAC seeds are
    32-bit signed integers (`recon.cli._options.SEED_MAX`)."""
    from recon.cli._options import SEED_MAX

    return typer.Option("--seed", min=0, max=SEED_MAX, help=help)


def progress_option(help: str = PROGRESS_HELP) -> Any:
    return typer.Option("--progress/--no-progress", help=help, metavar="")


def flag(*names: str, help: str) -> Any:
    """A boolean flag without the `<bool>` type column in `--help`."""
    return typer.Option(*names, help=help, metavar="")


SIMULATE_HELP = ("Which pairs our pipeline simulates views for: auto (recon run's default: needed above "
                 "match.adaptive_above images, else all), all (every pair) or needed (every pair's originals "
                 "first, then only the weak pairs the scene needs).")
SET_HELP = "A `recon run --set KEY=VALUE` for our pipeline (repeatable)."


def simulate_option() -> Any:
    """`--simulate auto|all|needed` of the commands that run our pipeline beside stock COLMAP."""
    from recon.config import SIMULATE

    return typer.Option("--simulate", help=SIMULATE_HELP, metavar=choices_metavar(SIMULATE))


def set_option() -> Any:
    return typer.Option("--set", help=SET_HELP, metavar="KEY=VALUE")


def our_settings(simulate: str, settings: list[str] | None) -> list[str]:
    """`--simulate` and `--set` as `recon run --set` strings (`--set` last: it wins)."""
    return [f"match.simulate={simulate}", *(settings or [])]


def stock_presets_option() -> Any:
    return typer.Option("--stock-presets", help=STOCK_PRESETS_HELP,
                        metavar=choices_metavar(p.value for p in StockPreset) + ",...")


def deprecated_stock_preset_option() -> Any:
    """The old `--stock-preset` spelling of `recon compare`: hidden, still accepted, with a warning."""
    return typer.Option("--stock-preset", hidden=True, help="Deprecated: use --stock-presets.")


def stock_presets(value: str, deprecated: str | None = None) -> list[str]:
    """The preset names of `--stock-presets` (or of the deprecated `--stock-preset`, with a warning);
    UserError naming the valid presets for an unknown one."""
    from recon.errors import UserError

    if deprecated is not None:
        print("recon: warning: --stock-preset is deprecated; use --stock-presets", file=sys.stderr)
        value = deprecated
    names = [p.strip() for p in value.split(",") if p.strip()]
    valid = [p.value for p in StockPreset]
    bad = [p for p in names if p not in valid]
    if bad or not names:
        raise UserError(f"--stock-presets {value!r}: choose from {', '.join(valid)} (comma-separated)")
    return list(dict.fromkeys(names))


def image_size(text: str | None, option: str = "--image-size") -> tuple[int, int] | None:
    """`WxH` (e.g. 800x600) as (width, height) px, each at least 64; None for None."""
    from recon.errors import UserError

    if text is None:
        return None
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise UserError(f"{option} {text!r}: expected WxH, e.g. 800x600") from None
    if min(w, h) < 64:
        raise UserError(f"{option} {text!r}: expected WxH, each at least 64 px")
    return w, h
