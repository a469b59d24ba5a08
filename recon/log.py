"""Logging: one logger per package, one stderr console, and COLMAP's own log level.

Library modules log with `logging.getLogger(__name__)` (so under "recon" or "matching") and never
print diagnostics. Nothing is configured on import: a Python caller gets the standard library's
behaviour (warnings on stderr, the rest silent) until it configures logging itself. The CLI
calls `setup_logging(verbose)` once per command (the `-v/--verbose` flag of `recon`):

* warnings and errors: one line, `recon: warning: ...` (never wrapped, so a script can grep it);
* with `-v`: debug and info records too, drawn by rich's `RichHandler`, and COLMAP's own log
  (which `quiet_colmap` otherwise keeps to fatal messages).

`console()` is the one rich Console on stderr that log lines and the progress bars share, so a
warning printed while bars are drawn lands above them instead of through them.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

LOGGERS = ("recon", "matching")
_console: Any = None


def console() -> Any:
    """The shared rich Console on stderr (resolves `sys.stderr` at each write)."""
    global _console
    if _console is None:
        from rich.console import Console

        _console = Console(stderr=True, highlight=False)
    return _console


def _handler_class() -> type:
    from rich.logging import RichHandler

    class CliHandler(RichHandler):
        """Warnings and errors as one `recon: <level>: message` line; lower levels as rich log lines."""

        def emit(self, record: logging.LogRecord) -> None:
            if record.levelno < logging.WARNING:
                super().emit(record)
                return
            try:
                msg = " ".join(self.format(record).split("\n")[:1]) if record.exc_info else record.getMessage()
                self.console.print(f"recon: {record.levelname.lower()}: {msg}", markup=False, highlight=False,
                                   soft_wrap=True)
            except Exception:
                self.handleError(record)

    return CliHandler


def setup_logging(verbose: bool = False) -> None:
    """Configure the "recon" and "matching" loggers for the CLI (idempotent: replaces the
    handler an earlier call installed). verbose: debug records and COLMAP's own log."""
    handler = _handler_class()(console=console(), show_path=verbose, rich_tracebacks=False, markup=False)
    handler.set_name("recon-cli")
    for name in LOGGERS:
        logger = logging.getLogger(name)
        for h in [h for h in logger.handlers if h.get_name() == "recon-cli"]:
            logger.removeHandler(h)
        logger.addHandler(handler)
        logger.setLevel(logging.DEBUG if verbose else logging.WARNING)
        logger.propagate = False  # the CLI owns stderr: no second copy through the root logger


def colmap_verbose() -> bool:
    """Whether COLMAP's own log should reach stderr: when "recon" logs at debug level (`-v`)."""
    return logging.getLogger("recon").isEnabledFor(logging.DEBUG)


@contextmanager
def quiet_colmap() -> Iterator[None]:
    """COLMAP logs every step (and its own failures, e.g. "Failed to create any sparse model")
    to stderr; a run reports everything itself on one line, so keep only fatal messages unless
    `colmap_verbose()` (`recon -v`)."""
    import pycolmap

    old = pycolmap.logging.minloglevel
    if not colmap_verbose():
        pycolmap.logging.minloglevel = 3
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old
