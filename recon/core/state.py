"""Resume state: `OUT/cache/state.json` holds, per keyed stage, the key it was built with.

A stage's key is a fingerprint (`fingerprint`) of everything its output depends on: its options
and its inputs (the upstream stage's key, or the content itself, e.g. the merged keypoints). So
a change anywhere upstream changes every key downstream, and an unchanged key means the stage
would produce the same output. Next to the key, a stage keeps a small JSON record of what later
stages need from it (e.g. the image ids of the database) so a reused stage can restore it
without recomputing. The file is rewritten atomically after every change, so a killed run
leaves either the old or the new state, never half of one.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np

from recon.core.jsonio import write_json_atomic

STATE_VERSION = "2"  # 2: one entry per stage (1: db_fingerprint / sfm_fingerprint)


def fingerprint(*parts: Any) -> str:
    """sha1 over the parts: arrays by shape and bytes, anything else by repr."""
    h = hashlib.sha1()
    for p in parts:
        if isinstance(p, np.ndarray):
            h.update(str(p.shape).encode())
            h.update(np.ascontiguousarray(p).tobytes())
        else:
            h.update(repr(p).encode())
        h.update(b"\0")
    return h.hexdigest()


class StageState:
    """The keys and records of finished stages; `path=None` keeps nothing (no resuming)."""

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self.data: dict[str, Any] = {"version": STATE_VERSION, "stages": {}}
        if path is not None and path.is_file():
            try:
                data = json.loads(path.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                data = {}
            if isinstance(data, dict) and data.get("version") == STATE_VERSION:
                self.data = data

    def record(self, stage: str, key: str) -> dict[str, Any] | None:
        """The record of `stage` if it was built with `key`, else None."""
        entry = self.data["stages"].get(stage)
        return entry.get("record", {}) if isinstance(entry, dict) and entry.get("key") == key else None

    def forget(self, stage: str) -> None:
        """Before a stage rebuilds its outputs: a kill half-way must not leave them trusted."""
        if self.data["stages"].pop(stage, None) is not None:
            self._save()

    def put(self, stage: str, key: str, record: dict[str, Any]) -> None:
        self.data["stages"][stage] = {"key": key, "record": record}
        self._save()

    def _save(self) -> None:
        if self.path is not None:
            write_json_atomic(self.path, self.data)
