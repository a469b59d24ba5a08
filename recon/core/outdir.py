"""Output folders: checked, owned, locked, and cleaned of our own files only.

Every command that writes a folder (`run`, `compare`, `bench`; `render-scene` has its own
marker, see `scenes.render`) goes through the same three steps:

1. `check_output_folder(out)` (read-only, nothing is created): refused with one line when `out`
   is a file, when a component of its path is a file (`--out FILE/sub`: "not a folder"), when it
   is read-only, or when it exists, is not empty and carries no recon marker. A folder with
   COLMAP's own `database.db` / `sparse/` but no marker is named as such and never modified,
   with or without `--overwrite`.
2. `output_lock(out)`: `fcntl.flock` on `OUT/.recon.lock` (non-blocking), held for the whole
   command; a second run into the same folder gets "another recon run is using OUT (pid N)".
   Re-entrant within one process (a CLI command and the library call inside it may both take
   it). Releasing it removes this process's temporary files from the folder, and a folder that
   the command created and left holding nothing but bookkeeping is removed again
   (`claim_output` does all of this as one context manager).
3. A marker says the folder is ours: `OUT/.recon_scene.json` for `recon run` (scene path and
   image file names, written by `prepare_out`), `OUT/.recon_owner.json` for the others.

`recon run` folders are tied to their scene: a different scene is refused without
`--overwrite`. A different image list of the same scene is accepted (and re-pinned) unless the
folder holds a finished model of the old list (then `--overwrite` is needed): fixing a scene
after a failed run (adding a photo, removing a corrupt one) just works, and the content-
addressed caches (`cache/features`, `cache/pairs`, keyed by pixels and options) stay valid.

`--overwrite` deletes only the names in `OWN_OUTPUTS` (and temporary leftovers), never other
files, and keeps the content-addressed caches unless `clean_cache` (`--clean-cache`).
"""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
import stat
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from recon.core.jsonio import remove_quietly, write_json_atomic
from recon.errors import UserError

SCENE_MARKER = ".recon_scene.json"  # a `recon run` output folder
OWNER_MARKER = ".recon_owner.json"  # any other recon output folder (compare, bench)
LOCK_NAME = ".recon.lock"
MARKERS = (SCENE_MARKER, OWNER_MARKER)
BOOKKEEPING = (LOCK_NAME, SCENE_MARKER, OWNER_MARKER)
OWN_OUTPUTS = ("cache", "recording.rrd", "database.db", "database.db.tmp", "database.db-journal", "database.db-wal",
               "database.db-shm", "database.db.tmp-journal", "sparse", "points.ply", "report.json", SCENE_MARKER)
# content-addressed caches (keyed by image pixels and matcher options): valid for any image list
CONTENT_CACHES = ("cache/features", "cache/pairs")
# what COLMAP itself leaves in a project folder: such a folder without our marker is never touched
COLMAP_SIGNS = ("database.db", "sparse", "dense", "project.ini")
# temporary files of our atomic writers: `.NAME.tmp-PID[...]`, `.NAME.old-PID`, `.NAME.PID.TID.tmp.npz`
# (pair cache), `NAME.PID.TID.tmp.npz` (feature cache), `.NAME.sfm-tmp-PID`, `database.db.tmp*`
_TEMP_RE = re.compile(r"(\.tmp-(?P<pid1>\d+)|\.old-(?P<pid2>\d+)|\.(?P<pid3>\d+)\.\d+\.tmp\.npz$|"
                      r"^database\.db\.tmp(-journal|-wal|-shm)?$)")


# checks (read-only) -------------------------------------------------------------------------------
def _no_write_bits(p: Path) -> bool:
    try:
        return not (p.stat().st_mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))
    except OSError:
        return False


def _first_existing(p: Path) -> Path:
    while not p.exists() and p.parent != p:
        p = p.parent
    return p


def has_marker(out: Path) -> bool:
    return any((out / m).is_file() for m in MARKERS)


def is_ours(out: Path) -> bool:
    """True when `out` does not exist, is empty (bookkeeping aside) or carries a recon marker."""
    if not out.exists():
        return True
    if not out.is_dir():
        return False
    return has_marker(out) or not _foreign_entries(out)


def _foreign_entries(out: Path) -> list[str]:
    try:
        return sorted(p.name for p in out.iterdir()
                      if p.name not in BOOKKEEPING and not p.name.startswith(".write-test"))
    except OSError:
        return []


def check_output_folder(out: Path, *, option: str = "--out", default_out: bool = False,
                        legacy: tuple[str, ...] = ()) -> None:
    """UserError (one line) unless recon may write into `out` (see module doc, step 1).

    Creates nothing. `option` names the flag in messages; `default_out` says `out` was not given
    by the user (the hint then suggests passing one); `legacy`: glob patterns of files that mark
    an output folder of an older recon (made before markers existed, e.g. `compare.json`),
    accepted too.
    """
    hint = f"pass {option} DIR to write elsewhere" if default_out else f"choose another {option}"
    if out.exists() and not out.is_dir():
        raise UserError(f"{option} {out}: exists and is not a folder; {hint}")
    probe = _first_existing(out)
    if not probe.is_dir():
        raise UserError(f"{option} {out}: {probe} is a file, not a folder; {hint}")
    if out.is_dir() and not has_marker(out) and not any(next(out.glob(pat), None) for pat in legacy):
        stray = _foreign_entries(out)
        colmap = [n for n in COLMAP_SIGNS if (out / n).exists()]
        if colmap:
            shown = ", ".join(n + ("/" if (out / n).is_dir() else "") for n in colmap)
            raise UserError(f"{out} looks like a COLMAP project ({shown}) that recon did not make; recon never "
                            f"writes into it (with or without --overwrite); {hint}")
        if stray:
            raise UserError(f"{out} is not empty and is not a recon output folder (found {stray[0]}); {hint}")
    if not os.access(probe, os.W_OK | os.X_OK) or _no_write_bits(probe):
        # a folder without any write permission bit counts as read-only even for root
        raise UserError(f"cannot write to {out}: {probe} is read-only; {hint}")


# the lock ------------------------------------------------------------------------------------------
_held: dict[str, list] = {}  # resolved path -> [fd, depth]
_held_guard = threading.Lock()


def lock_holder(out: Path) -> int | None:
    """The pid of another process holding `OUT/.recon.lock`, or None when the folder is free
    (or locked by this process)."""
    import fcntl

    path = Path(out) / LOCK_NAME
    key = str(Path(out).resolve())
    with _held_guard:
        if key in _held:
            return None
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return _read_pid(fd) or -1
        except OSError:
            return None
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def _read_pid(fd: int) -> int | None:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        return int(os.read(fd, 32).decode().strip() or 0) or None
    except (OSError, ValueError):
        return None


def _busy(out: Path, pid: int | None) -> UserError:
    who = f" (pid {pid})" if pid and pid > 0 else ""
    return UserError(f"another recon run is using {out}{who}; wait for it to finish or choose another --out")


@contextmanager
def output_lock(out: Path) -> Iterator[None]:
    """Hold the folder's lock for the block (see module doc, step 2); `out` must exist.

    UserError "another recon run is using OUT (pid N)" when another process holds it. On a file
    system without flock support the block runs unlocked. On release, this process's temporary
    files left in `out` (an interrupted writer) are removed.
    """
    import fcntl

    out = Path(out)
    key = str(out.resolve())
    with _held_guard:
        if key in _held:
            _held[key][1] += 1
            entered = True
        else:
            entered = False
    if entered:
        try:
            yield
        finally:
            with _held_guard:
                _held[key][1] -= 1
        return
    path = out / LOCK_NAME
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        pid = _read_pid(fd)
        os.close(fd)
        raise _busy(out, pid) from None
    except OSError:  # no flock here (some network file systems): run unlocked
        pass
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
    except OSError:
        pass
    with _held_guard:
        _held[key] = [fd, 1]
    try:
        yield
    finally:
        with _held_guard:
            _held.pop(key, None)
        try:
            sweep_temp_files(out, only_pid=os.getpid())
        finally:
            os.close(fd)  # closing the descriptor releases the flock


def _only_bookkeeping(out: Path) -> bool:
    """True when `out` holds nothing but our lock/markers and empty folders."""
    for dirpath, _dirs, files in os.walk(out):
        for f in files:
            if Path(dirpath) != out or f not in BOOKKEEPING:
                return False
    return True


@contextmanager
def claim_output(out: Path, command: str, *, option: str = "--out", default_out: bool = False,
                 marker: bool = True, legacy: tuple[str, ...] = ()) -> Iterator[Path]:
    """Check, create and lock an output folder for one command; yields the resolved folder.

    `marker`: write `OUT/.recon_owner.json` (compare, bench; `recon run` leaves it to
    `prepare_out`, which writes the scene marker); `legacy` as in `check_output_folder`. When
    the block fails and the folder was
    created here and holds only bookkeeping, it is removed again: a refused or failed command
    leaves nothing behind.
    """
    out = Path(out).expanduser().absolute()
    check_output_folder(out, option=option, default_out=default_out, legacy=legacy)
    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UserError(f"cannot create {option} {out}: {e.strerror or e}") from None
    ok = False
    try:
        with output_lock(out):
            check_output_folder(out, option=option, default_out=default_out, legacy=legacy)  # again, now exclusive
            if marker and not (out / OWNER_MARKER).is_file():
                write_json_atomic(out / OWNER_MARKER, {"command": command, "created": time.strftime("%Y-%m-%dT%H:%M:%S")})
            yield out.resolve()
            ok = True
    finally:
        if not ok and created and out.is_dir() and _only_bookkeeping(out):
            shutil.rmtree(out, ignore_errors=True)


# cleaning --------------------------------------------------------------------------------------------
def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


def sweep_temp_files(out: Path, only_pid: int | None = None) -> list[Path]:
    """Delete temporary files of our atomic writers under `out` (see `_TEMP_RE`): those of
    `only_pid`, or (None) those of processes that no longer run plus pid-less ones. Only call
    it while holding the folder's lock. Returns what was removed."""
    removed: list[Path] = []
    if not out.is_dir():
        return removed
    for dirpath, dirs, files in os.walk(out):
        for name in list(files) + list(dirs):
            m = _TEMP_RE.search(name)
            if not m:
                continue
            pid_s = m.group("pid1") or m.group("pid2") or m.group("pid3")
            pid = int(pid_s) if pid_s else None
            if only_pid is not None and pid != only_pid:
                continue
            if only_pid is None and pid is not None and _pid_alive(pid) and pid != os.getpid():
                continue
            p = Path(dirpath) / name
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
                if name in dirs:
                    dirs.remove(name)
            else:
                remove_quietly(p)
            removed.append(p)
    return removed


def remove_outputs(out: Path, names: tuple[str, ...] = OWN_OUTPUTS, keep: tuple[str, ...] = ()) -> None:
    """Delete the named outputs in `out` and the temporary leftovers of killed runs, nothing else.

    `keep`: relative paths inside a named folder to spare (e.g. `CONTENT_CACHES` inside
    `cache`): the folder's other entries are deleted, the kept ones stay as they are.
    """
    for name in names:
        p = out / name
        spared = [k for k in keep if k.startswith(name + "/")]
        if spared and p.is_dir() and not p.is_symlink():
            for child in p.iterdir():
                rel = f"{name}/{child.name}"
                if any(k == rel or k.startswith(rel + "/") for k in spared):
                    continue
                if child.is_dir() and not child.is_symlink():
                    shutil.rmtree(child, ignore_errors=True)
                else:
                    child.unlink(missing_ok=True)
        elif p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        elif p.exists() or p.is_symlink():
            p.unlink()
    for p in out.glob(".*tmp-*"):  # leftovers of a killed run: .sfm-tmp-<pid>, .report.json.tmp-<pid>, ...
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)


def clean_content_cache(out: Path) -> None:
    """`--clean-cache`: delete the content-addressed caches of a recon output folder (only one
    that carries our marker)."""
    if has_marker(out):
        remove_outputs(out, ("cache",))


def discard_unsound_database(out: Path) -> str | None:
    """Delete `OUT/database.db` (and its SQLite side files) when it fails
    `database.database_is_sound`, so the pipeline rebuilds it instead of trusting a matching
    fingerprint; returns the reason, or None when it is absent or sound."""
    from recon.core.database import database_problem, remove_database

    db = out / "database.db"
    if not db.exists():
        return None
    why = database_problem(db)
    if why is None:
        return None
    remove_database(db)
    return why


# `recon run` folders ---------------------------------------------------------------------------------
def _finished_model_of_marker(out: Path) -> bool:
    """True when OUT/report.json says "ok" and was written after the current marker (the model
    in the folder belongs to the pinned image list)."""
    rep, marker = out / "report.json", out / SCENE_MARKER
    try:
        if rep.stat().st_mtime < marker.stat().st_mtime:
            return False
        return json.loads(rep.read_text(encoding="utf-8")).get("status") == "ok"
    except (OSError, ValueError, AttributeError):
        return False


def prepare_out(out: Path, root: Path, candidates: list[str], overwrite: bool, default_out: bool,
                clean_cache: bool = False) -> list[str]:
    """Check, create and claim a `recon run` output folder for this scene (see module doc).

    Returns notes for the user (one line each: a re-pinned image list, a rebuilt database).
    Raises UserError when the folder is refused or locked by another run.
    """
    from recon.core.scene import find_image_dir

    notes: list[str] = []
    out = Path(out)
    marker = out / SCENE_MARKER
    check_output_folder(out, default_out=default_out)
    pid = lock_holder(out) if out.is_dir() else None
    if pid is not None:
        raise _busy(out, pid)
    if marker.is_file():
        try:
            rec = json.loads(marker.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            rec = {}
        if not isinstance(rec, dict):
            rec = {}
        if not overwrite and rec.get("scene") != str(root):
            raise UserError(f"{out} holds the reconstruction of another scene ({rec.get('scene', '?')}); "
                            f"pass --overwrite to replace it or choose another --out")
        old = rec.get("images")
        if not overwrite and old != candidates:
            added = sorted(set(candidates) - set(old or []))
            gone = sorted(set(old or []) - set(candidates))
            change = f"{len(added)} image(s) added, {len(gone)} removed"
            if _finished_model_of_marker(out):
                raise UserError(f"{out} holds a finished model of a different image list of this scene ({change}); "
                                f"pass --overwrite to rebuild it (matched pairs are reused) or choose another --out")
            notes.append(f"the image list changed since the last (unfinished) run ({change}); cached matches of "
                         f"unchanged images are reused")
    try:
        out.mkdir(parents=True, exist_ok=True)
        t = out / f".write-test-{os.getpid()}"
        t.write_bytes(b"")
        t.unlink()
    except OSError as e:
        hint = "pass --out DIR to write the reconstruction elsewhere" if default_out else "choose another --out DIR"
        if e.errno in (errno.ENOSPC, errno.EDQUOT):
            raise
        raise UserError(f"cannot write to {out}: {e.strerror or e}; {hint}") from None
    if overwrite:
        remove_outputs(out, keep=() if clean_cache else CONTENT_CACHES)
    elif clean_cache:
        remove_outputs(out, ("cache",))
    sweep_temp_files(out)
    why = discard_unsound_database(out)
    if why:
        notes.append(f"{out / 'database.db'} was damaged ({why}); it is rebuilt")
    write_json_atomic(marker, {"scene": str(root), "image_dir": str(find_image_dir(root)), "images": candidates})
    return notes
