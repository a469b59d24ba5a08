"""Atomic JSON writing and JSON-safe conversion of numpy values."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np


def to_jsonable(x: Any) -> Any:
    """numpy scalars/arrays, dataclasses, Paths, tuples -> plain JSON types (NaN/inf -> None)."""
    if is_dataclass(x) and not isinstance(x, type):
        return to_jsonable(asdict(x))
    if isinstance(x, dict):
        return {str(k): to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return to_jsonable(x.tolist())
    if isinstance(x, (np.bool_, bool)):
        return bool(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating, float)):
        f = float(x)
        return f if math.isfinite(f) else None
    if isinstance(x, Path):
        return str(x)
    return x


def write_json_atomic(path: str | Path, data: Any) -> None:
    """Write JSON (numpy-safe, UTF-8) to `.<name>.tmp-<pid>` beside `path`, fsync, rename.

    On any failure (a full disk, Ctrl-C) the temporary file is removed and the OSError names
    `path` (`filename`), so the CLI can say which file could not be written.
    """
    path = Path(path)
    with replaced_atomically(path, path.with_name(f".{path.name}.tmp-{os.getpid()}")) as tmp:
        path.parent.mkdir(parents=True, exist_ok=True)
        text = json.dumps(to_jsonable(data), indent=1, ensure_ascii=False, default=str)
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())


@contextmanager
def replaced_atomically(path: Path, tmp: Path) -> Iterator[Path]:
    """Write `tmp` inside the block; on success it replaces `path` (one rename), on any failure
    (a full disk, Ctrl-C) it is removed and an OSError names `path` (`filename`), so the CLI can
    say which file could not be written. Every atomic writer of the project goes through here."""
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException as e:
        remove_quietly(tmp)
        if isinstance(e, OSError) and e.filename is None:
            e.filename = str(path)
        raise


def remove_quietly(path: str | Path) -> None:
    """Delete a file if it exists; never raises (cleanup of temporary files on a failure path)."""
    try:
        os.unlink(path)
    except OSError:
        pass
