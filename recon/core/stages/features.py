"""Stage `features`: the per-image feature store every pair task reads from.

Needs: `scene`, `grays`. Makes: `store`, a `matching.store.FeatureStore` holding every usable
image. Features are computed lazily, by the match stage, the first time a pair asks for them
(which ones depend on the pair: the extra-affine matcher simulates views chosen per pair), then
shared by every other pair of that image and persisted under `OUT/cache/features` (one file per
image digest and feature kind: that is this stage's cache key, kept by the store itself). So
this stage always runs and takes no time; the features' own time is inside `match`.
(The stock pipeline has its own `features` stage: COLMAP's SIFT extraction, `recon.eval.stock`.)
"""

from __future__ import annotations

from typing import Any

from matching.store import FeatureStore
from recon.core.context import Run


class Features:
    name = "features"
    needs = ("scene", "grays")
    makes = ("store",)

    def key(self, run: Run) -> str | None:
        return None

    def reuse(self, run: Run, record: dict[str, Any]) -> bool:
        return False

    def run(self, run: Run) -> None:
        store = FeatureStore(cache_dir=run.cache / "features")
        grays = run.data.grays or {}
        for name in run.data.scene.names:
            store.add_image(name, grays[name])
        run.data.store, run.data.grays = store, None  # the store holds the images now
        return None
