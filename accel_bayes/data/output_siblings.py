"""The hidden siblings of an output target: its lock, and what killed runs into it leave behind.

Every name a run puts beside a target NAME starts with ``.NAME.``: the lock ``.NAME.lock``, the
temporary files of :func:`accel_bayes.data.outputs.atomic_path` (``.NAME.<pid>-<hex8>.tmp``) and,
for an ``--out DIR`` set (:mod:`accel_bayes.data.output_sets`), the staging folder
``.NAME.partial-<pid>-<hex8>`` and the previous set moved aside ``.NAME.old-<pid>-<hex8>``.
:func:`hidden_siblings` finds those of a target by parsing each name exactly.

Locks
    A target being written is locked by a sibling file ``.NAME.lock`` created with ``O_EXCL``
    and holding ``<pid> <host>``; a second run into the same target is refused with one line.
    Stale-lock rule: a lock whose process no longer exists on this host (or an unreadable lock
    older than :data:`STALE_UNREADABLE_S` seconds) is removed and taken over.
"""
from __future__ import annotations

import os
import re
import socket
import time
from contextlib import contextmanager
from pathlib import Path

from ..errors import UserError

__all__ = ["STALE_UNREADABLE_S", "lock_path", "pid_alive", "acquire_lock", "hold_lock", "hidden_siblings"]

# A lock file is written in one small write right after its O_EXCL creation; one that still
# cannot be parsed after this long belongs to a process that died in between.
STALE_UNREADABLE_S = 60.0


# ---------------------------------------------------------------- locks

def lock_path(target) -> Path:
    """The lock file of an output target: ``.NAME.lock`` beside it."""
    target = Path(target)
    return target.parent / f".{target.name}.lock"


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this host (it may belong to another user)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def _lock_owner(lock: Path):
    """(pid, host) written in ``lock``, or None when it cannot be read or parsed."""
    try:
        pid, host = lock.read_text(encoding="utf-8").split()[:2]
        return int(pid), host
    except (OSError, ValueError):
        return None


def _is_stale(lock: Path) -> bool:
    owner = _lock_owner(lock)
    if owner is None:
        try:
            return time.time() - lock.stat().st_mtime > STALE_UNREADABLE_S
        except FileNotFoundError:
            return True
    pid, host = owner
    return host == socket.gethostname() and not pid_alive(pid)


def acquire_lock(target: Path, flag: str) -> Path:
    """Create the lock of ``target`` (taking over a stale one) and return its path; another live
    run's lock is refused with one line naming ``flag``."""
    lock = lock_path(target)
    for _ in range(2):  # a second try after removing a stale lock
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            if _is_stale(lock):
                lock.unlink(missing_ok=True)
                continue
            owner = _lock_owner(lock)
            who = f"pid {owner[0]} on {owner[1]}" if owner else "another process"
            raise UserError(f"{flag}: {target} is being written by another accel-bayes run ({who}); "
                            f"wait for it, or delete {lock} if that run is gone") from None
        except OSError as exc:
            raise UserError(f"{flag}: cannot write in {lock.parent} ({exc.strerror or exc})") from None
        try:
            os.write(fd, f"{os.getpid()} {socket.gethostname()}\n".encode())
        except OSError as exc:
            os.close(fd)
            lock.unlink(missing_ok=True)
            raise UserError(f"{flag}: cannot write in {lock.parent} ({exc.strerror or exc})") from None
        os.close(fd)
        return lock
    raise UserError(f"{flag}: {target} is being written by another accel-bayes run; lock {lock}")


@contextmanager
def hold_lock(target, flag: str = "--out"):
    """Hold the lock of ``target`` for the duration of the block (what a running command does)."""
    lock = acquire_lock(Path(target), flag)
    try:
        yield lock
    finally:
        lock.unlink(missing_ok=True)


# ---------------------------------------------------------------- leftovers of killed runs

def hidden_siblings(target: Path, kinds, suffix: str = ""):
    """(path, pid) of the hidden siblings this package's writers make for ``target``:
    ``.NAME.<kind><pid>-<hex8><suffix>`` for each kind in ``kinds`` (e.g. "partial-", "old-", or ""
    for the temporary files of :func:`atomic_path`).  The directory is listed and each name parsed
    exactly (NAME escaped), never globbed: a NAME holding ``*`` or ``[`` matches only itself, and a
    name without a pid is never taken for ours."""
    alts = "|".join(re.escape(k) for k in kinds)
    pat = re.compile(rf"\.{re.escape(target.name)}\.(?:{alts})([0-9]+)-[0-9a-f]{{8}}{re.escape(suffix)}")
    try:
        names = os.listdir(target.parent)
    except OSError:
        return []
    return [(target.parent / n, int(m.group(1))) for n in names if (m := pat.fullmatch(n))]
