"""The stages of `recon run`, one module each, in the order they run:

    load -> features -> pairs -> match -> tracks -> database -> verify -> sfm -> export

| stage      | needs                         | makes                  | key (skipped when unchanged)            |
|------------|-------------------------------|------------------------|-----------------------------------------|
| `load`     | -                             | scene, grays           | none: always runs (pixel digests)       |
| `features` | scene, grays                  | store                  | none (the store caches per image+kind)  |
| `pairs`    | scene                         | pairs                  | none                                    |
| `match`    | scene, store, pairs           | results, cached        | none (the pair cache resumes per pair)  |
| `tracks`   | scene, pairs, results         | merged, keypoints      | none                                    |
| `database` | scene, pairs, merged, keypts  | image_ids, num_keypts  | camera mode, images, keypoints, matches |
| `verify`   | ... image_ids                 | verified               | database key + two-view options         |
| `sfm`      | scene, image_ids              | reconstruction         | verify key + mapper options             |
| `export`   | scene, reconstruction         | -                      | none                                    |

`recon.core.orchestrator.run_stages` runs them; the stock comparison (`recon.eval.stock`) swaps
`features` / `match` for COLMAP's own and drops `tracks` / `verify` (COLMAP verifies while matching).
"""

from __future__ import annotations

from typing import Any

from recon.core.stages.database import Database
from recon.core.stages.export import Export
from recon.core.stages.features import Features
from recon.core.stages.load import Load
from recon.core.stages.match import Match
from recon.core.stages.pairs import Pairs
from recon.core.stages.sfm import Sfm
from recon.core.stages.tracks import Tracks
from recon.core.stages.verify import Verify

__all__ = ["Database", "Export", "Features", "Load", "Match", "Pairs", "Sfm", "Tracks", "Verify", "scene_stages"]


def scene_stages() -> list[Any]:
    """The stages of `recon run`, in order."""
    return [Load(), Features(), Pairs(), Match(), Tracks(), Database(), Verify(), Sfm(), Export()]
