"""Console progress for long stages (rich bars on stderr, or nothing) and COLMAP's log level."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager


class Progress:
    """rich progress bars on stderr, or nothing (tests, --no-progress)."""

    def __init__(self, enabled: bool):
        self._p = None
        if enabled:
            from rich.console import Console
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress, SpinnerColumn,
                                       TextColumn, TimeElapsedColumn)

            self._p = Progress(SpinnerColumn(), TextColumn("{task.description:<10}"), BarColumn(),
                               MofNCompleteColumn(), TimeElapsedColumn(),
                               console=Console(stderr=True), transient=False)

    def __enter__(self):
        if self._p is not None:
            self._p.__enter__()
        return self

    def __exit__(self, *exc):
        if self._p is not None:
            self._p.__exit__(*exc)

    def task(self, desc: str, total: int | None) -> Callable[..., None]:
        if self._p is None:
            return lambda *a, **k: None
        tid = self._p.add_task(desc, total=total)
        p = self._p

        def advance(n: int = 1, done: bool = False) -> None:
            if done:
                t = p.tasks[[t.id for t in p.tasks].index(tid)]
                p.update(tid, total=t.completed or 1, completed=t.completed or 1)
            else:
                p.advance(tid, n)

        return advance

    def print(self, msg: str) -> None:
        if self._p is not None:
            self._p.console.print(msg, markup=False, highlight=False)
        else:
            print(msg, file=sys.stderr)


@contextmanager
def quiet_colmap() -> Iterator[None]:
    """COLMAP logs every step (and its own failures, e.g. "Failed to create any sparse model")
    to stderr; the pipeline reports everything itself on one line, so keep only fatal messages."""
    import pycolmap

    old = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 3
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old
