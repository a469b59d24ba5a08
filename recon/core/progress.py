"""Console progress for long stages: rich bars on stderr, or nothing (tests, --no-progress).

The bars share `recon.log.console()` with the log lines, so a warning printed while they are
drawn lands above them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


class Progress:
    """One bar per stage that asks for one (`task`), labelled with the stage's name."""

    def __init__(self, enabled: bool):
        self._p: Any = None
        if enabled:
            from rich.progress import BarColumn, MofNCompleteColumn, SpinnerColumn, TextColumn, TimeElapsedColumn
            from rich.progress import Progress as RichProgress

            from recon.log import console

            self._p = RichProgress(SpinnerColumn(), TextColumn("{task.description:<10}"), BarColumn(),
                                   MofNCompleteColumn(), TimeElapsedColumn(), console=console(), transient=False)

    def __enter__(self) -> Progress:
        if self._p is not None:
            self._p.__enter__()
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._p is not None:
            self._p.__exit__(*exc)

    def task(self, desc: str, total: int | None) -> Callable[..., None]:
        """A bar of `total` steps (None: unknown); returns `advance(n=1, done=False)`."""
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
