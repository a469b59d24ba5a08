"""Stage `pairs`: which image pairs are matched (`recon.core.pairs`).

Needs: `scene`. Makes: `pairs`, in a fixed order (results are always collected in this order).
Key: none, it always runs (instant). Options: `pairs.spec` (`exhaustive`, `sequential:K`, or
a file of name pairs; pairs naming unusable images are dropped with a warning).
"""

from __future__ import annotations

from typing import Any

from recon.core.context import Run
from recon.core.pairs import make_pairs, parse_pairs_spec
from recon.errors import UserError


class Pairs:
    name = "pairs"
    needs = ("scene",)
    makes = ("pairs",)

    def key(self, run: Run) -> str | None:
        return None

    def reuse(self, run: Run, record: dict[str, Any]) -> bool:
        return False

    def run(self, run: Run) -> None:
        spec = run.cfg.pairs.spec
        pairs, warnings = make_pairs(parse_pairs_spec(spec), run.data.scene.names)
        for w in warnings:
            run.warn(w)
        if not pairs:
            raise UserError(f"--pairs {spec}: no pair of usable images to match")
        run.data.pairs = pairs
        return None
