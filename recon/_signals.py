"""Ctrl-C (SIGINT) and SIGTERM for the `recon` program: one line, cleanup, exit 130 / 143.

Standard library only, so `recon/__init__.py` can install it first thing when the process is
the `recon` program (`install_early`; never for a library user). Two modes:

* deferred (from the first import until `recon.cli.main` takes over): a signal is only
  recorded, so Ctrl-C while the heavy modules import gives no `KeyboardInterrupt` traceback;
  `main` then exits with one line at once;
* raising (inside `main`, `install`): SIGINT raises `KeyboardInterrupt` and SIGTERM
  `Terminated` (a subclass) in the main thread, so every `finally` runs (temporary files,
  locks) and `main` prints one line.

SIGTERM never reaches a C handler: pycolmap's import installs glog's failure handler, which
answers SIGTERM with a 30-line C stack dump (from whichever thread the kernel picks). So the
program blocks SIGTERM before any other thread exists (every thread inherits the mask), a
watcher thread takes it with `sigwait` and forwards it to the main thread as `FORWARD`
(SIGUSR2, which glog leaves alone), whose Python handler acts as for SIGTERM. Child processes
(the Rerun viewer) are started inside `unblocked_for_children()` so that they can be
terminated normally.

While a native package imports (`DEFER_DURING_IMPORT`), a signal is held until the import is
complete: an exception inside a pybind11 module's initialisation becomes an ImportError that a
package may swallow. A second signal exits at once (`os._exit`). A signal the parent set to be
ignored (`nohup`, a shell's background job) stays ignored. A signal that arrives while Python itself starts (the
first ~50 ms, before any recon code runs) gets Python's default behaviour.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

FORWARD = signal.SIGUSR2  # SIGTERM, forwarded by the watcher thread to the main thread
# native packages whose import must not be interrupted half-way: pybind11 turns an exception in
# a module's initialisation into ImportError, which a package may swallow (pycolmap without
# pyceres) or turn into a misleading "Cannot import the C++ backend"
DEFER_DURING_IMPORT = ("pycolmap", "pyceres", "open3d", "rerun", "rerun_bindings", "cv2", "pyarrow")
received: int | None = None  # the first SIGINT / SIGTERM of this command
_raising = False
_deferring = 0  # > 0 while one of DEFER_DURING_IMPORT imports
_previous: dict[int, object] = {}
_watcher: threading.Thread | None = None


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that every `finally` (temporary files, locks) runs."""


def _note(signum: int) -> None:
    global received
    if received is not None:  # a second signal: the user insists
        try:
            os.write(2, b"recon: interrupted again; exiting now\n")
        finally:
            os._exit(128 + signum)
    received = signum
    if _raising and not _deferring:
        raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


def _on_sigint(signum: int, _frame: object) -> None:
    _note(signal.SIGINT)


def _on_sigterm(signum: int, _frame: object) -> None:  # FORWARD, or SIGTERM itself when not blocked
    _note(signal.SIGTERM)


def is_program_entry() -> bool:
    """True when this process is the `recon` program: the console script or `python -m recon`."""
    argv = list(getattr(sys, "orig_argv", None) or [])
    if "-m" in argv:
        i = argv.index("-m")
        return i + 1 < len(argv) and argv[i + 1] == "recon"
    main_file = str(getattr(sys.modules.get("__main__"), "__file__", "") or "")
    return os.path.basename(main_file) == "recon" or os.path.basename(sys.argv[0] or "") == "recon"


def _set(sig: int, handler) -> None:
    prev = signal.signal(sig, handler)
    _previous.setdefault(sig, prev)


def _watch_sigterm() -> None:
    """The watcher thread: the first SIGTERM goes to the main thread (see module doc); a second
    one ends the process from here, even when the main thread is busy inside C++ code (whose
    Python handler would only run when that call returns)."""
    main_id = threading.main_thread().ident
    while True:
        try:
            signal.sigwait({signal.SIGTERM})
        except Exception:  # interpreter shutting down
            return
        if received is not None:
            try:
                os.write(2, b"recon: terminated again; exiting now\n")
            finally:
                os._exit(128 + signal.SIGTERM)
        try:
            signal.pthread_kill(main_id, FORWARD)  # type: ignore[arg-type]
        except (ProcessLookupError, OSError, TypeError):
            return


def install_early() -> None:
    """The program's first step (see module doc): deferred handlers, SIGTERM blocked in every
    thread to come and taken by the watcher thread. Main thread only."""
    global _watcher
    if threading.current_thread() is not threading.main_thread():
        return
    install(raising=False)
    if signal.getsignal(signal.SIGTERM) is signal.SIG_IGN or _watcher is not None:
        return
    try:
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    except (AttributeError, OSError, ValueError):
        return
    _set(FORWARD, _on_sigterm)
    _watcher = threading.Thread(target=_watch_sigterm, name="recon-sigterm", daemon=True)
    _watcher.start()


def install(raising: bool) -> None:
    """Our handlers in the given mode (main thread only; elsewhere a no-op)."""
    global _raising
    _raising = raising
    if threading.current_thread() is not threading.main_thread():
        return
    for sig, handler in ((signal.SIGINT, _on_sigint), (signal.SIGTERM, _on_sigterm)):
        current = signal.getsignal(sig)
        if current is signal.SIG_IGN and sig not in _previous:
            continue
        _set(sig, handler)
    if _watcher is not None:
        _set(FORWARD, _on_sigterm)
    if not any(isinstance(f, _DeferDuringImport) for f in sys.meta_path):
        sys.meta_path.insert(0, _DeferDuringImport())


def restore() -> None:
    """Put back the handlers found before `install` (a library caller of `main`, e.g. tests)."""
    global _raising
    for sig, prev in list(_previous.items()):
        try:
            signal.signal(sig, prev)  # type: ignore[arg-type]
        except (ValueError, OSError, TypeError):
            pass
    _previous.clear()
    _raising = False


def reset() -> None:
    global received
    received = None


@contextmanager
def unblocked_for_children() -> Iterator[None]:
    """Start child processes inside this block: they inherit the caller's signal mask, and a
    child with SIGTERM blocked could not be terminated. In the main thread SIGTERM is briefly
    unblocked (our Python handler set again first: pycolmap's import may have replaced it)."""
    if _watcher is None or threading.current_thread() is not threading.main_thread():
        yield
        return
    try:
        signal.signal(signal.SIGTERM, _on_sigterm)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
    except (OSError, ValueError):
        pass
    try:
        yield
    finally:
        try:
            signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
        except (OSError, ValueError):
            pass


class _DeferDuringImport:
    """Import hook: a signal that arrives while one of `DEFER_DURING_IMPORT` imports is recorded
    and raised once that import is complete (see the note at `DEFER_DURING_IMPORT`)."""

    def find_spec(self, fullname: str, path=None, target=None):
        if fullname not in DEFER_DURING_IMPORT:
            return None
        import importlib.util

        sys.meta_path[:] = [f for f in sys.meta_path if f is not self]
        try:
            spec = importlib.util.find_spec(fullname)
        finally:
            sys.meta_path.insert(0, self)
        loader = getattr(spec, "loader", None)
        if spec is None or loader is None or not hasattr(loader, "exec_module"):
            return spec
        exec_module = loader.exec_module

        def deferred_exec(module) -> None:
            global _deferring
            _deferring += 1
            try:
                exec_module(module)
            finally:
                _deferring -= 1
            if received is not None and _raising and not _deferring:
                raise Terminated() if received == signal.SIGTERM else KeyboardInterrupt()

        loader.exec_module = deferred_exec  # type: ignore[method-assign]
        return spec
