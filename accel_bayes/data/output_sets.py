"""``--out DIR`` targets (:class:`OutputDir`): the results of a run written as one consistent set
(DESIGN §7.5), what a set is on disk (its marker) and what a run may remove.

Checked before any computation (not a file, no file on the way, writable parent; a non-empty
DIR is refused without ``--overwrite``, except ``--resume`` of the run in it).  What a run may
remove from DIR is exactly: the files listed in the ``files`` of its marker
:data:`SET_MARKER`, the marker, the ``keep`` files (``checkpoint.pt``) and the temporary files
of their killed writers.  **Anything else in DIR — a user's file, hidden file, folder or link —
makes the run refuse** (with or without ``--overwrite``, also with ``--resume``), in one line
naming it, before any computation and again just before the swap; nothing is kept aside.  A
DIR that contains an input of the run is refused too.  ``--out .`` (or ``..``) is taken as the
directory's absolute path, so its lock and staging folder lie beside it, not in it.
The results are written into a staging directory beside DIR (``.DIR.partial-<pid>-<hex8>``),
the marker is added last, and the set is moved into place only when complete: DIR (if any) is
renamed aside (``.DIR.old-<pid>-<hex8>``), the staging directory renamed to DIR, and the listed
files of the old set deleted.  A run killed at any moment therefore leaves either the previous
set, or no DIR at all, plus possibly those hidden siblings.  Files that must survive a killed
run (calibrate's ``checkpoint.pt``) live in DIR itself and are carried into the new set.

Leftovers.  The next run into a target removes the hidden siblings of dead runs into *that*
target only: the parent folder is listed and each name parsed against the exact schemes above
(``.NAME.partial-<pid>-<hex8>``, ``.NAME.old-<pid>-<hex8>``, ``.NAME.<pid>-<hex8>.tmp``, NAME
escaped; :func:`accel_bayes.data.output_siblings.hidden_siblings`) — never a glob built from
NAME — and only when that pid no longer runs.  A hidden folder without a pid is never ours.  A
staging folder is removed whole (only its run wrote into it); an old set loses only what its
marker lists, so a file put there survives.

The files of a set are written with :mod:`accel_bayes.data.outputs`' atomic writers, which also
keep the set's staging directory out of the paths shown to the user (``display_path``).  Refusals
are :class:`~accel_bayes.errors.UserError` with one line naming ``--out``.
"""
from __future__ import annotations

import contextlib
import json
import os
import re
import secrets
import shutil
import signal
import time
from contextlib import contextmanager
from pathlib import Path

from .. import interrupts
from ..errors import UserError
from .output_siblings import acquire_lock, hidden_siblings, pid_alive
from .outputs import OPEN_TARGETS, Target, fsync_dir, write_json

__all__ = ["SET_MARKER", "SET_SCHEMA", "OVERWRITE_DIR_HELP", "is_output_set", "OutputDir"]

# Written last into every committed --out DIR: what --overwrite is allowed to replace.
SET_MARKER = ".accel-bayes-set.json"
SET_SCHEMA = "accel_bayes.output_set/1"

# The --overwrite help of every --out DIR command (one wording everywhere).
OVERWRITE_DIR_HELP = ("replace the earlier results in a non-empty --out DIR (only a set written by accel-bayes; "
                      "refused otherwise)")


def is_output_set(d) -> bool:
    """Whether directory ``d`` holds an output set committed by :class:`OutputDir` (its marker)."""
    try:
        return json.loads((Path(d) / SET_MARKER).read_text(encoding="utf-8")).get("schema") == SET_SCHEMA
    except (OSError, ValueError, AttributeError):
        return False


@contextmanager
def _signals_held():
    # The two renames of a commit are not interrupted half-way; a Ctrl-C or SIGTERM arriving
    # meanwhile is delivered right after.
    sigs = {signal.SIGINT, signal.SIGTERM}
    try:
        old = signal.pthread_sigmask(signal.SIG_BLOCK, sigs)
    except (AttributeError, OSError, ValueError):
        yield
        return
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _nearest_existing(p: Path) -> Path:
    for a in (p, *p.parents):
        if a.exists():
            return a
    return Path(".")


def _set_files(d: Path) -> set[str]:
    """The files the marker of the output set in ``d`` lists (relative POSIX paths); empty when
    ``d`` holds no valid marker."""
    try:
        doc = json.loads((d / SET_MARKER).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return set()
    files = doc.get("files") if isinstance(doc, dict) and doc.get("schema") == SET_SCHEMA else None
    return {f for f in files if isinstance(f, str)} if isinstance(files, list) else set()


def _ours(d: Path, keep) -> tuple[set[str], list[str]]:
    """Split the content of directory ``d`` into what this package may remove — the files its set
    marker lists, the marker, the ``keep`` files and the temporary files of their killed writers —
    and the rest (sorted relative paths; an empty folder the set does not need ends in "/").
    Symbolic links are entries, never followed."""
    listed = _set_files(d) | set(keep) | {SET_MARKER}
    ours, other = set(), []
    for root, dirs, files in os.walk(d):
        rel = Path(os.path.relpath(root, d))
        links = [x for x in dirs if os.path.islink(os.path.join(root, x))]
        for name in files + links:
            r = (rel / name).as_posix()
            tmp = re.fullmatch(r"\.(.+)\.[0-9]+-[0-9a-f]{8}\.tmp", name)
            if r in listed or (tmp and (rel / tmp.group(1)).as_posix() in listed):
                ours.add(r)
            else:
                other.append(r)
        if not files and not dirs and rel != Path("."):
            r = rel.as_posix()
            if not any(f.startswith(r + "/") for f in listed):
                other.append(r + "/")
    return ours, sorted(other)


def _remove_set(d: Path, keep=()) -> list[str]:
    """Remove from ``d`` what :func:`_ours` says is ours, then the folders that became empty and
    ``d`` itself if empty; returns what was left (files this package did not write)."""
    if d.is_symlink():  # a DIR given as a link was moved aside as the link: its target is not ours
        d.unlink(missing_ok=True)
        return []
    ours, other = _ours(d, keep)
    for r in ours:
        (d / r).unlink(missing_ok=True)
    for root, _, _ in sorted(os.walk(d, topdown=False), key=lambda w: -len(w[0])):
        with contextlib.suppress(OSError):
            os.rmdir(root)  # only empty ones go
    return other


class OutputDir(Target):
    """An ``--out DIR`` target written as one consistent set (see the module docstring).

    ``keep`` names files that live in DIR itself during the run (``checkpoint.pt``) and are
    carried into the committed set; ``resume`` allows a non-empty DIR that holds one of them.
    ``inputs`` are the run's input files: a DIR that contains one is never replaced.
    After :meth:`open`, write into :attr:`staging` (or ``self / "name"``); :meth:`commit` moves
    the set into place; :meth:`final` maps a staged path to its place in DIR."""

    def __init__(self, path, *, overwrite: bool = False, resume: bool = False, keep=(), inputs=(),
                 flag: str = "--out"):
        self.target = Path(path)
        if self.target.name in ("", ".", ".."):
            # "--out ." names the directory by its own name in its parent, where the lock and the
            # staging folder go (inside it they would make it "not empty" and be swapped with it)
            self.target = Path(os.path.abspath(self.target))
        self.overwrite = bool(overwrite)
        self.resume = bool(resume)
        self.keep = tuple(keep)
        self.inputs = [Path(p) for p in inputs if p is not None]
        self.flag = flag
        self.staging: Path | None = None
        self._staged = False  # the staging directory exists and holds this run's files
        self._lock = None

    def __truediv__(self, name) -> Path:
        return self.staging / name

    def final(self, p) -> Path:
        """Where a staged path ``p`` ends up after :meth:`commit`."""
        p = Path(p)
        if self.staging is None:
            return p
        try:
            return self.target / p.relative_to(self.staging)
        except ValueError:
            return p

    def check(self) -> None:
        """Refuse a target that cannot hold the results (no side effects)."""
        t, f = self.target, self.flag
        if t.exists() and not t.is_dir():
            raise UserError(f"{f}: {t} exists and is not a directory")
        if not t.exists():
            a = _nearest_existing(t.parent)
            if not a.is_dir():
                raise UserError(f"{f}: {t}: {a} is a file, not a directory")
        else:
            names = {e.name for e in t.iterdir()}
            if not names:
                return
            resuming = self.resume and names & set(self.keep)
            if not self.overwrite and not resuming:
                raise UserError(f"{f}: {t} is not empty; pass --overwrite to replace its contents "
                                "(or choose another directory)")
            inside = [p for p in self.inputs if p.exists() and t.resolve() in p.resolve().parents]
            if inside:
                raise UserError(f"{f}: {t} contains the input {inside[0]}, which replacing the results would "
                                "delete; choose another directory")
            self._refuse_foreign()

    def _refuse_foreign(self) -> None:
        # The set's own list is the only list of what may go; anything else stops the run here,
        # before any computation (and again just before the swap, for a file added meanwhile).
        t, f = self.target, self.flag
        _, other = _ours(t, self.keep)
        if not other:
            return
        more = f" and {len(other) - 1} more" if len(other) > 1 else ""
        if not is_output_set(t):
            raise UserError(f"{f}: {t} holds files that accel-bayes did not write ({other[0]}{more}; no "
                            f"{SET_MARKER}); --overwrite replaces only an earlier output set: choose another "
                            "directory")
        raise UserError(f"{f}: {t} holds {other[0]}{more}, which its output set does not list; accel-bayes "
                        "removes only the files of its own set: move it out or choose another directory")

    def open(self) -> "OutputDir":
        """Check the target, lock it and create the staging directory, before any computation."""
        self.check()
        t = self.target
        try:
            t.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserError(f"{self.flag}: cannot create {t.parent} ({exc.strerror or exc})") from None
        self._lock = acquire_lock(t, self.flag)
        OPEN_TARGETS.append(self)
        try:
            self.check()  # again, under the lock: a run that finished meanwhile may have filled DIR
            self._remove_leftovers()
            self.staging = t.parent / f".{t.name}.partial-{os.getpid()}-{secrets.token_hex(4)}"
            self.staging.mkdir()
            self._staged = True
        except OSError as exc:
            self.abort()
            raise UserError(f"{self.flag}: cannot write in {t.parent} ({exc.strerror or exc})") from None
        except BaseException:
            self.abort()
            raise
        return self

    def ensure_target(self) -> Path:
        """Create DIR itself (for files that must outlive a killed run, such as checkpoints)."""
        self.target.mkdir(exist_ok=True)
        return self.target

    def _remove_leftovers(self) -> None:
        # Hidden siblings of killed runs into this target (exact names with the writer's pid); we
        # hold the lock, so their writers are gone unless the pid is alive (then left alone).  A
        # staging folder holds only what its run wrote; an old set loses only the files its marker
        # lists, so a file someone put there survives.
        for p, pid in hidden_siblings(self.target, ("partial-", "old-")):
            if pid == os.getpid() or pid_alive(pid):
                continue
            if p.name.startswith(f".{self.target.name}.partial-") and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                _remove_set(p, self.keep)

    def commit(self) -> None:
        """Move the staged set into place (old set or nothing at every instant) and unlock."""
        if not self._staged:
            return
        t, s = self.target, self.staging
        for name in self.keep:
            src, dst = t / name, s / name
            if src.is_file() and not dst.exists():
                try:
                    os.link(src, dst)
                except OSError:
                    shutil.copy2(src, dst)
        from .. import __version__

        files = sorted(str(p.relative_to(s)) for p in s.rglob("*") if p.is_file())
        write_json(s / SET_MARKER, {"schema": SET_SCHEMA, "written_by": f"accel-bayes {__version__}",
                                    "pid": os.getpid(), "time": time.time(), "files": files})
        fsync_dir(s)
        if t.is_dir():
            self._refuse_foreign()
        interrupts.check()  # the last moment a SIGINT/SIGTERM can still keep the old set
        old = None
        with _signals_held():
            if t.exists():
                old = t.parent / f".{t.name}.old-{os.getpid()}-{secrets.token_hex(4)}"
                os.rename(t, old)
            try:
                os.rename(s, t)
            except BaseException:
                if old is not None:
                    os.rename(old, t)  # put the previous set back
                raise
            self._staged = False
        fsync_dir(t.parent)
        if old is not None:
            _remove_set(old, self.keep)  # what is left (added during the swap) stays in .NAME.old-*
        self._release()

    def abort(self) -> None:
        """Delete the staged files and unlock; DIR keeps what it held."""
        if self._staged:
            shutil.rmtree(self.staging, ignore_errors=True)
            self._staged = False
        self._release()
