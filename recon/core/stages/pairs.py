"""Stage `pairs`: which image pairs are matched (`recon.core.pairs`).

Needs: `scene`, `store` (retrieval reads the originals' SIFT from it; the match stage reuses
them). Makes: `pairs`, in a fixed order (results are always collected in this order). Key: none,
it always runs (instant for exhaustive, sequential and files; retrieval costs one SIFT per image,
which matching needs anyway). Options: `pairs.spec` (`auto`, `exhaustive`, `sequential:K`,
`retrieval:K[+sequential:S]`, or a file of name pairs; pairs naming unusable images are dropped
with a warning).
"""

from __future__ import annotations

from typing import Any

from recon.core.context import Run
from recon.core.pairs import make_pairs, parse_pairs_spec
from recon.core.retrieval import store_pairs
from recon.errors import UserError


class Pairs:
    name = "pairs"
    needs = ("scene", "store")
    makes = ("pairs",)

    def key(self, run: Run) -> str | None:
        return None

    def reuse(self, run: Run, record: dict[str, Any]) -> bool:
        return False

    def run(self, run: Run) -> None:
        spec = run.cfg.pairs.spec
        store = run.data.store
        pairs, warnings = make_pairs(parse_pairs_spec(spec), run.data.scene.names,
                                     retrieve=lambda s, names: store_pairs(s, store, names))
        for w in warnings:
            run.warn(w)
        if not pairs:
            raise UserError(f"--pairs {spec}: no pair of usable images to match")
        run.data.pairs = pairs
        return None
