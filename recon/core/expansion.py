"""Match-graph expansion: after matching, propose the pairs the match graph says overlap (`+expand:E`).

Appearance retrieval (`recon.core.retrieval`) ranks images by a global descriptor, and is
weakest on exactly the pairs this project exists for: two photos of one surface from very
different angles share few similar-looking features. The match graph carries evidence that
needs no appearance similarity: when image i matches k and k matches j, i and j probably see a
common part of the scene (co-visibility). So after the proposed pairs are matched, every pair
(i, j) not matched yet is scored by its common neighbours k,

    score(i, j) = sum over k of min(n_ik, n_kj),

where n_ab is the matches of pair (a, b) and only pairs with at least `min_matches` count as
edges (the verification threshold: a pair with fewer is not a link). A pair needs at least
`min_common` common neighbours. Each image proposes its `per_image` best-scored candidates, the
union (at most `per_image`·N pairs) is matched, and the next round scores again with the new
edges. Rounds stop when one proposes nothing, when fewer than `min_yield` of its pairs reach
`min_matches` (the graph has run out of overlapping pairs: more rounds would pay for pairs
that do not verify), or after `max_rounds`. So retrieval:K+expand:E proposes at most
(K + E·max_rounds)·N pairs: linear in N.

Why min(n_ik, n_kj): a chain is as strong as its weaker link; summing over k rewards pairs seen
together through many neighbours. Everything is deterministic: scores are integers and ties are
broken by image order. Pure functions over names and match counts; `expand` runs the rounds
with a caller's matching function (`recon.core.stages.match` matches on the run's executor,
`benchmarks/bench_expansion.py` reads an exhaustive run's counts), so both follow one logic.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

Pair = tuple[str, str]


@dataclass(frozen=True)
class ExpansionConfig:
    """Match-graph expansion (see module doc)."""

    per_image: int
    """E: each image proposes at most this many new partners per round (>= 1)."""
    max_rounds: int = 3
    """At most this many rounds of proposing and matching."""
    min_matches: int = 15
    """A matched pair is an edge of the graph with at least this many matches (COLMAP's default
    minimum of verified inliers, `recon`'s verified-pair threshold)."""
    min_common: int = 1
    """A candidate needs at least this many common neighbours."""
    min_yield: float = 0.5
    """Stop after a round in which fewer than this share of the new pairs reached `min_matches`."""

    def __post_init__(self) -> None:
        if self.per_image < 1 or self.max_rounds < 1 or self.min_matches < 1 or self.min_common < 1:
            raise ValueError("ExpansionConfig: per_image, max_rounds, min_matches and min_common must be >= 1")
        if not 0.0 <= self.min_yield <= 1.0:
            raise ValueError("ExpansionConfig.min_yield must be in [0, 1]")


def covisibility_scores(names: Sequence[str], matched: Mapping[Pair, int], min_matches: int,
                        min_common: int = 1) -> dict[tuple[int, int], int]:
    """{(i, j), i < j: score} for every pair not in `matched` with at least `min_common` common
    neighbours over the edges of `matched` (pairs of names -> matches, either order) with at least
    `min_matches` matches; i, j index `names`."""
    index = {n: i for i, n in enumerate(names)}
    nbrs: list[dict[int, int]] = [{} for _ in names]
    done: set[tuple[int, int]] = set()
    for (a, b), n in matched.items():
        if a not in index or b not in index or a == b:
            continue
        i, j = sorted((index[a], index[b]))
        done.add((i, j))
        if n >= min_matches:
            nbrs[i][j] = nbrs[j][i] = int(n)
    score: dict[tuple[int, int], int] = {}
    common: dict[tuple[int, int], int] = {}
    for nk in nbrs:  # each image k and its edges
        around = sorted(nk)
        for x, i in enumerate(around):
            for j in around[x + 1:]:
                if (i, j) in done:
                    continue
                score[(i, j)] = score.get((i, j), 0) + min(nk[i], nk[j])
                common[(i, j)] = common.get((i, j), 0) + 1
    return {p: s for p, s in score.items() if common[p] >= min_common}


def expansion_pairs(names: Sequence[str], matched: Mapping[Pair, int], cfg: ExpansionConfig) -> list[Pair]:
    """One round: each image's `cfg.per_image` best-scored unmatched partners (see module doc),
    as (name_i, name_j) with i < j in `names` order, sorted; [] when the graph proposes nothing."""
    scores = covisibility_scores(names, matched, cfg.min_matches, cfg.min_common)
    per_image: list[list[tuple[int, int]]] = [[] for _ in names]  # (-score, partner)
    for (i, j), s in scores.items():
        per_image[i].append((-s, j))
        per_image[j].append((-s, i))
    keys: set[tuple[int, int]] = set()
    for i, cands in enumerate(per_image):
        for _neg, j in sorted(cands)[:cfg.per_image]:
            keys.add((min(i, j), max(i, j)))
    return [(names[i], names[j]) for i, j in sorted(keys)]


def round_yield(counts: Sequence[int], min_matches: int) -> float:
    """Share of a round's new pairs with at least `min_matches` matches (1.0 for no pairs)."""
    return 1.0 if not counts else sum(1 for n in counts if n >= min_matches) / len(counts)


def expand(names: Sequence[str], matched: Mapping[Pair, int], match: Callable[[list[Pair]], list[int]],
           cfg: ExpansionConfig) -> list[list[Pair]]:
    """Run the expansion rounds (see module doc) from the already matched pairs `matched`
    ({pair: matches}); `match(new_pairs)` matches a round's pairs and returns their match counts
    in order. Returns the new pairs of each round, in order."""
    counts = dict(matched)
    rounds: list[list[Pair]] = []
    for _ in range(cfg.max_rounds):
        new = expansion_pairs(names, counts, cfg)
        if not new:
            break
        got = match(new)
        rounds.append(new)
        counts.update(zip(new, got))
        if round_yield(got, cfg.min_matches) < cfg.min_yield:
            break
    return rounds
