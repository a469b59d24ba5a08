"""Stage `pairs`: which image pairs are matched (`recon.core.pairs`).

Needs: `scene` (retrieval reads the originals' SIFT from the run's `store` when there is one,
so the match stage reuses them). Makes: `pairs`, in a fixed order (results are always collected in this order). Key: none,
it always runs (instant for exhaustive, sequential and files; retrieval costs one SIFT per image,
which matching needs anyway). Options: `pairs.spec` (`auto`, `exhaustive`, `sequential:K`,
`retrieval:K[+sequential:S]`, or a file of name pairs; pairs naming unusable images are dropped
with a warning).
"""

from __future__ import annotations

from typing import Any

from matching.store import FeatureStore
from recon.core.context import Run
from recon.core.pairs import make_pairs, parse_pairs_spec
from recon.core.retrieval import store_pairs
from recon.errors import UserError


class Pairs:
    name = "pairs"
    needs = ("scene",)
    makes = ("pairs",)

    def key(self, run: Run) -> str | None:
        return None

    def reuse(self, run: Run, record: dict[str, Any]) -> bool:
        return False

    @staticmethod
    def _store(run: Run) -> FeatureStore:
        """The run's FeatureStore (retrieval's SIFT is then reused by matching), or, where a stage
        list has none (the stock comparison), an in-memory one over the decoded photos."""
        if run.data.store is not None:
            return run.data.store
        store = FeatureStore()
        for name, gray in (run.data.grays or {}).items():
            store.add_image(name, gray)
        return store

    def run(self, run: Run) -> None:
        spec = run.cfg.pairs.spec
        pairs, warnings = make_pairs(parse_pairs_spec(spec), run.data.scene.names,
                                     retrieve=lambda s, names: store_pairs(s, self._store(run), names))
        for w in warnings:
            run.warn(w)
        if not pairs:
            raise UserError(f"--pairs {spec}: no pair of usable images to match")
        run.data.pairs = pairs
        return None
