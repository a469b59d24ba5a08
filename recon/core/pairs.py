"""Which image pairs to match: `exhaustive`, `sequential:K`, or a file of name pairs.

* `exhaustive` (default): every unordered pair, (i, j) with i < j in name order.
* `sequential:K`: each image with the next K images in name order (video or walk-around
  captures, where only neighbours overlap).
* `retrieval:K`, `retrieval:K+sequential:S`, `auto`: appearance retrieval (see
  `recon.core.retrieval`); `make_pairs` needs its `retrieve` argument for them. `+expand:E`
  adds match-graph expansion after matching (`recon.core.expansion`, run by the match stage).
* anything else is a path to a text file (UTF-8) with one pair per line (`read_pairs_file`):

  - two image names separated by whitespace: `a.jpg b.jpg`; extra columns (retrieval scores)
    are ignored;
  - a name with spaces is quoted, with double or single quotes: `"my photo.jpg" 'b c.jpg'`. A
    quote counts only at the start of a name, so apostrophes inside one need nothing
    (`l'église.jpg`); there is no escaping inside quotes;
  - or the line is tab-separated (it holds a tab): each field is a name taken verbatim
    (spaces, quotes and `#` inside included), surrounding spaces stripped, and one pair of
    quotes around the whole field removed;
  - `#` starts a comment only at the start of a line or after whitespace (`# note`,
    `a.jpg b.jpg  # note`, a field starting with `#`); inside a name (`photo#2.jpg`) it is part
    of the name. A name that starts with `#` must be quoted;
  - blank lines are ignored.

  Syntax errors name the file and line (InputError). `check_pairs_names` checks the names against
  the scene's image files before any image is decoded: a file naming no pair of them is refused
  up front. Pairs naming an image that is not in the scene (or was skipped as corrupt or
  duplicate) are dropped with one warning, as are self-pairs and repeats ((a, b) after (a, b)
  or (b, a)).

Pairs come out in a deterministic order (the generator's order, or the file's), and the
pipeline writes results in that order whatever order the matching finished in.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from matching.errors import InputError

Pair = tuple[str, str]


@dataclass(frozen=True)
class PairsSpec:
    kind: str  # "exhaustive" | "sequential" | "file" | "retrieval" | "auto"
    k: int = 0  # sequential window; for retrieval / auto: neighbours per image
    path: Path | None = None  # file of pairs
    sequential: int = 0  # retrieval: also the next `sequential` images in name order
    expand: int = 0  # retrieval: match-graph expansion, new partners per image and round (recon.core.expansion)

    def __str__(self) -> str:
        if self.kind == "sequential":
            return f"sequential:{self.k}"
        if self.kind == "file":
            return str(self.path)
        if self.kind == "retrieval":
            return (f"retrieval:{self.k}" + (f"+sequential:{self.sequential}" if self.sequential else "")
                    + (f"+expand:{self.expand}" if self.expand else ""))
        return self.kind


def parse_pairs_spec(spec: str) -> PairsSpec:
    """Parse `--pairs`; raises ValueError with a one-line message when it is malformed."""
    s = (spec or "").strip()
    if s == "exhaustive":
        return PairsSpec("exhaustive")
    # --- retrieval specs (issue 10): parsed by recon.core.retrieval ---
    from recon.core.retrieval import is_retrieval_spec, parse_retrieval_spec

    if is_retrieval_spec(s):
        r = parse_retrieval_spec(s)
        return PairsSpec("auto" if r.auto else "retrieval", k=r.k, sequential=r.sequential,
                         expand=r.expand)
    # ---
    if s.startswith("sequential"):
        _, sep, k = s.partition(":")
        try:
            kk = int(k) if sep else 0
        except ValueError:
            kk = 0
        if kk < 1:
            raise ValueError(f"--pairs {spec!r}: expected sequential:K with an integer K >= 1")
        return PairsSpec("sequential", k=kk)
    if not s:
        raise ValueError("--pairs is empty: use exhaustive, sequential:K or a pairs file")
    p = Path(s).expanduser()
    if not p.is_file():
        raise ValueError(f"--pairs {spec!r}: not 'exhaustive', 'sequential:K', 'retrieval:K', 'auto' or an existing pairs file")
    return PairsSpec("file", path=p)


def exhaustive_pairs(names: list[str]) -> list[Pair]:
    return [(names[i], names[j]) for i in range(len(names)) for j in range(i + 1, len(names))]


def sequential_pairs(names: list[str], k: int) -> list[Pair]:
    return [(names[i], names[j]) for i in range(len(names)) for j in range(i + 1, min(len(names), i + 1 + k))]


def split_pairs_line(line: str) -> list[str]:
    """The names on one line of a pairs file (see module doc); ValueError when malformed."""
    if "\t" in line:
        names = []
        for field in line.split("\t"):
            f = field.strip()
            if f.startswith("#"):  # a comment: at the line's start or after a tab
                break
            if len(f) >= 2 and f[0] == f[-1] and f[0] in "\"'":  # quoted anyway
                f = f[1:-1]
            if f:
                names.append(f)
        return names
    names, i, n = [], 0, len(line)
    while i < n:
        if line[i].isspace():
            i += 1
            continue
        c = line[i]
        if c == "#":  # at a name's start: a comment to the end of the line
            break
        if c in "\"'":
            j = line.find(c, i + 1)
            if j < 0:
                raise ValueError(f"no closing {c} for the name starting at column {i + 1}")
            if j + 1 < n and not line[j + 1].isspace():
                raise ValueError(f"a quoted name must be followed by a space (column {j + 2})")
            if j == i + 1:
                raise ValueError(f"empty quoted name at column {i + 1}")
            names.append(line[i + 1:j])
            i = j + 1
            continue
        j = i
        while j < n and not line[j].isspace():
            j += 1
        names.append(line[i:j])
        i = j
    return names


def read_pairs_file(path: Path) -> list[Pair]:
    """The (name0, name1) rows of a pairs file; InputError naming the file and line when malformed."""
    try:
        text = Path(path).read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: cannot read pairs file ({getattr(e, 'strerror', None) or e})") from None
    out: list[Pair] = []
    for lineno, line in enumerate(text.splitlines(), 1):
        try:
            parts = split_pairs_line(line)
        except ValueError as e:
            raise InputError(f"{path}:{lineno}: malformed pairs line ({e})") from None
        if not parts:
            continue
        if len(parts) < 2:
            raise InputError(f"{path}:{lineno}: expected two image names, got {line.strip()!r}")
        out.append((parts[0], parts[1]))  # extra columns (scores from retrieval) are ignored
    return out


def check_pairs_names(spec: PairsSpec, candidates: list[str]) -> None:
    """Before any image is decoded: a pairs file must parse and name at least one pair of the
    scene's image files (`candidates`, from `scene.list_candidates`); InputError otherwise.
    Other specs always pass. (Unknown names in a usable file are dropped later, with a warning.)"""
    if spec.kind != "file":
        return
    assert spec.path is not None
    rows = read_pairs_file(spec.path)
    if not rows:
        raise InputError(f"{spec.path}: the pairs file lists no pair")
    known = set(candidates)
    if not any(a in known and b in known and a != b for a, b in rows):
        unknown = next((n for a, b in rows for n in (a, b) if n not in known), None)
        detail = (f"{unknown!r} is not an image file of the scene" if unknown is not None
                  else "every pair names one image twice")
        raise InputError(f"{spec.path}: no line names two different images of the scene ({detail}; names are "
                         f"file names relative to the image folder)")


def make_pairs(spec: PairsSpec, names: list[str],
               retrieve: Callable[[PairsSpec, list[str]], list[Pair]] | None = None,
               ) -> tuple[list[Pair], list[str]]:
    """(pairs, warnings) for the scene's usable image names (in name order).

    `retrieve(spec, names)` computes retrieval / auto pairs (e.g. `recon.core.retrieval.
    store_pairs` over the run's FeatureStore); ValueError when such a spec needs it and it is
    missing (`auto` on a small scene is exhaustive and does not).
    """
    if spec.kind == "exhaustive":
        return exhaustive_pairs(names), []
    if spec.kind in ("retrieval", "auto"):  # issue 10: appearance retrieval
        from recon.core.retrieval import AUTO_EXHAUSTIVE_MAX_IMAGES

        if spec.kind == "auto" and len(names) <= AUTO_EXHAUSTIVE_MAX_IMAGES:
            return exhaustive_pairs(names), []  # small scenes: no features needed
        if retrieve is None:
            raise ValueError(f"--pairs {spec}: retrieval needs image features (pass `retrieve`)")
        return retrieve(spec, names), []
    if spec.kind == "sequential":
        return sequential_pairs(names, spec.k), []
    assert spec.path is not None
    raw = read_pairs_file(spec.path)
    known = set(names)
    seen: set[frozenset[str]] = set()
    out: list[Pair] = []
    unknown: list[str] = []
    dropped_self = dropped_dup = 0
    for a, b in raw:
        if a not in known or b not in known:
            unknown.extend(n for n in (a, b) if n not in known)
            continue
        if a == b:
            dropped_self += 1
            continue
        key = frozenset((a, b))
        if key in seen:
            dropped_dup += 1
            continue
        seen.add(key)
        out.append((a, b))
    warnings = []
    if unknown:
        u = sorted(set(unknown))
        shown = ", ".join(u[:5]) + (f" and {len(u) - 5} more" if len(u) > 5 else "")
        warnings.append(f"{spec.path}: dropped pairs naming images not in the scene (or skipped): {shown}")
    if dropped_self or dropped_dup:
        warnings.append(f"{spec.path}: dropped {dropped_self} self-pair(s) and {dropped_dup} repeated pair(s)")
    return out, warnings
