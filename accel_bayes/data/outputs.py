"""Output files and output directories: the one atomic writer and the output-set rules (DESIGN §7.5).

Files
    Every file the package writes goes through :func:`atomic_path` (or its wrappers
    :func:`write_bytes`, :func:`write_text`, :func:`write_json`, :func:`write_netcdf`): the data
    go to a hidden temporary file in the target's directory, are flushed to disk (``fsync``) and
    renamed over the target (:func:`os.replace`), so a reader sees the old file or the complete
    new one, never a partial one.  NetCDF (recordings, motion, ``posterior.nc``) is serialised
    in memory first and written with plain file I/O: no HDF5 handle is ever open on the target
    file system, so a full disk is an ordinary :class:`OSError` (HDF5 failing to close a file
    on a full disk used to crash the interpreter).

``-o FILE`` targets (:class:`OutputFile`)
    Checked before any computation: FILE is not a directory, its parent is an existing,
    writable directory, and an existing FILE is refused without ``--overwrite``.  An output that
    is one of the command's inputs (same path or same inode: a hard or symbolic link) is refused,
    also with ``--overwrite`` (:func:`check_not_inputs`, called by the CLI for every command).
    Once one file of an open target (FILE or a sidecar) has been replaced, the others are written
    even after a SIGINT/SIGTERM, so a recording and its truth file never come from two runs.

``--out DIR`` targets (:class:`OutputDir`): one consistent set
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

Leftovers
    The next run into a target removes the hidden siblings of dead runs into *that* target only:
    the parent folder is listed and each name parsed against the exact schemes above
    (``.NAME.partial-<pid>-<hex8>``, ``.NAME.old-<pid>-<hex8>``, ``.NAME.<pid>-<hex8>.tmp``, NAME
    escaped) — never a glob built from NAME — and only when that pid no longer runs.  A hidden
    folder without a pid is never ours.  A staging folder is removed whole (only its run wrote
    into it); an old set loses only what its marker lists, so a file put there survives.

Signals
    SIGINT/SIGTERM only set a flag (:mod:`accel_bayes.interrupts`); every writer checks it just
    before making a file (:func:`atomic_path`) or a set (:meth:`OutputDir.commit`) visible and
    then discards what it staged, leaving the earlier output as it was.

Locks
    A target being written is locked by a sibling file ``.NAME.lock`` created with ``O_EXCL``
    and holding ``<pid> <host>``; a second run into the same target is refused with one line.
    Stale-lock rule: a lock whose process no longer exists on this host (or an unreadable lock
    older than :data:`STALE_UNREADABLE_S` seconds) is removed and taken over.

All refusals are :class:`~accel_bayes.errors.UserError` with one line naming the option
(``--out`` / ``-o``) and what was expected; the CLI turns them into exit status 2.
"""
from __future__ import annotations

import contextlib
import json
import os
import re
import secrets
import shutil
import signal
import socket
import time
from contextlib import contextmanager
from pathlib import Path

from .. import interrupts
from ..errors import UserError

__all__ = [
    "to_jsonable",
    "check_file_target",
    "check_not_inputs",
    "atomic_path",
    "write_bytes",
    "write_text",
    "write_json",
    "write_netcdf",
    "write_csv",
    "save_figure",
    "OutputFile",
    "OutputDir",
    "abort_open",
    "display_path",
    "lock_path",
    "hold_lock",
    "STALE_UNREADABLE_S",
    "SET_MARKER",
    "SET_SCHEMA",
    "is_output_set",
    "OVERWRITE_DIR_HELP",
]


# ---------------------------------------------------------------- JSON values

_NONFINITE = ("keep", "null")
_UNKNOWN = ("error", "repr", "keep")


def to_jsonable(obj, *, nonfinite: str = "keep", unknown: str = "error", where: str = "value"):
    """Plain-JSON copy of ``obj``: numpy/torch arrays and scalars, tuples, paths and dataclasses
    become nested lists, floats, ints, str, bool and None, recursively (the one JSON cleaner of
    the package: recording attributes, truth sidecars, positions.json, mismatch reports, noise
    and import summaries).

    nonfinite : "keep" — NaN/±inf floats stay (``json.dumps`` writes them as NaN/Infinity, which
        the package's own readers accept); "null" — they become None (strict JSON, DESIGN §7.3).
    unknown : what to do with any other object — "error" (a one-line :class:`UserError` naming
        ``where``; dictionary keys must then be strings or integers), "repr" (its ``repr``),
        "keep" (left as it is, for callers that serialise it themselves).
    where : the name of ``obj`` in error messages (e.g. ``attrs['x']``); nested entries append
        ``.key`` / ``[i]``.
    """
    if nonfinite not in _NONFINITE:
        raise ValueError(f"nonfinite: expected one of {_NONFINITE}, got {nonfinite!r}")
    if unknown not in _UNKNOWN:
        raise ValueError(f"unknown: expected one of {_UNKNOWN}, got {unknown!r}")
    return _plain(obj, nonfinite == "null", unknown, where)


def _plain(obj, null: bool, unknown: str, where: str):
    import dataclasses
    import math

    import numpy as np

    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):
        return None if null and not math.isfinite(obj) else float(obj)
    if isinstance(obj, np.generic):
        return _plain(obj.item(), null, unknown, where)
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist(), null, unknown, where) if null else obj.tolist()
    # torch is imported only where it is already loaded: a tensor implies it is
    if type(obj).__module__.startswith("torch") and hasattr(obj, "detach"):
        return _plain(obj.detach().cpu().numpy(), null, unknown, where)
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, dict):
        out = {}
        for k, v in obj.items():
            if unknown == "error" and not isinstance(k, (str, int, np.integer)):
                raise UserError(f"{where}: dictionary keys must be strings, got {k!r}")
            out[str(k)] = _plain(v, null, unknown, f"{where}.{k}")
        return out
    if isinstance(obj, (list, tuple)):
        return [_plain(v, null, unknown, f"{where}[{i}]") for i, v in enumerate(obj)]
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _plain(getattr(obj, f.name), null, unknown, f"{where}.{f.name}")
                for f in dataclasses.fields(obj)}
    if unknown == "repr":
        return repr(obj)
    if unknown == "keep":
        return obj
    raise UserError(f"{where}: cannot store a {type(obj).__name__} as JSON; convert it to numbers, strings or arrays")

# Written last into every committed --out DIR: what --overwrite is allowed to replace.
SET_MARKER = ".accel-bayes-set.json"
SET_SCHEMA = "accel_bayes.output_set/1"

# The --overwrite help of every --out DIR command (one wording everywhere).
OVERWRITE_DIR_HELP = ("replace the earlier results in a non-empty --out DIR (only a set written by accel-bayes; "
                      "refused otherwise)")

# A lock file is written in one small write right after its O_EXCL creation; one that still
# cannot be parsed after this long belongs to a process that died in between.
STALE_UNREADABLE_S = 60.0


# ---------------------------------------------------------------- the one atomic writer

def _fsync_dir(d: Path) -> None:
    # The rename itself is durable only once the directory entry is on disk.
    try:
        fd = os.open(d, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def check_file_target(path, *, overwrite: bool, flag: str | None = None) -> Path:
    """Refuse a file target that cannot be written: a directory, a missing parent directory, or
    (without ``overwrite``) an existing file.  ``flag`` (e.g. ``"-o"``) prefixes the message."""
    path = Path(path)
    pre = f"{flag}: " if flag else ""
    if path.is_dir():
        raise UserError(f"{pre}{path} is a directory; expected a file name")
    parent = path.parent
    if not parent.is_dir():
        if parent.exists() or any(a.exists() and not a.is_dir() for a in parent.parents):
            bad = next(a for a in (parent, *parent.parents) if a.exists())
            raise UserError(f"{pre}{path}: {bad} is a file, not a directory")
        raise UserError(f"{pre}{path}: directory {parent} does not exist")
    if path.exists() and not overwrite:
        how = "--overwrite" if flag else "overwrite=True (--overwrite on the command line)"
        raise UserError(f"{pre}{path} exists; pass {how} to replace it")
    return path


def _temp_sibling(path: Path) -> Path:
    # Same directory (so os.replace is a rename on one file system), hidden, unique per writer,
    # and ending in .tmp so that a leftover of a killed writer never passes for a result.
    return path.parent / f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp"


def _commit_file(tmp: Path, path: Path) -> None:
    with open(tmp, "rb+") as f:  # data on disk before the rename makes it visible
        os.fsync(f.fileno())
    started = [t for t in _OPEN if isinstance(t, OutputFile) and t.started]
    if not started:  # once one file of a command is replaced, its others follow (no mix of two runs)
        interrupts.check()  # the last moment a SIGINT/SIGTERM can still keep the old file
    os.replace(tmp, path)
    for t in _OPEN:
        if isinstance(t, OutputFile) and t.owns(path):
            t.started = True
    _fsync_dir(path.parent)


@contextmanager
def atomic_path(path, *, overwrite: bool = True):
    """Context manager for writing ``path`` atomically: yields a temporary path in the same
    directory for the caller to write; on a clean exit the file is fsynced and renamed over
    ``path``, on any exception (a full disk, an interrupt) it is deleted and ``path`` is left
    as it was.  An existing ``path`` raises :class:`UserError` unless ``overwrite``."""
    path = check_file_target(path, overwrite=overwrite)
    tmp = _temp_sibling(path)
    try:
        yield tmp
        _commit_file(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        if exc.errno is not None and (exc.filename is None or str(exc.filename) == str(tmp)):
            # name the file being written, not its temporary name
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
        raise
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_bytes(path, data, *, overwrite: bool = True) -> Path:
    """Write ``data`` (bytes-like) to ``path`` atomically; returns the path."""
    path = Path(path)
    with atomic_path(path, overwrite=overwrite) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
    return path


def write_text(path, text: str, *, overwrite: bool = True) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; returns the path."""
    return write_bytes(path, text.encode("utf-8"), overwrite=overwrite)


def write_json(path, obj, *, indent: int = 2, overwrite: bool = True, allow_nan: bool = True) -> Path:
    """Write ``obj`` as JSON (plus a final newline) to ``path`` atomically; returns the path."""
    return write_text(path, json.dumps(obj, indent=indent, allow_nan=allow_nan) + "\n", overwrite=overwrite)


def write_csv(path, table, header: str, *, overwrite: bool = True) -> Path:
    """Write a 2-D numeric array as CSV (one header line of column names, numbers as
    ``numpy.savetxt`` prints them) to ``path`` atomically; returns the path."""
    import io

    import numpy as np

    buf = io.StringIO()
    np.savetxt(buf, np.asarray(table), delimiter=",", header=header, comments="")
    return write_text(path, buf.getvalue(), overwrite=overwrite)


def save_figure(fig, path, **savefig_kw) -> Path:
    """Save a matplotlib figure to ``path`` atomically, in the format of its suffix; returns the
    path.  Keyword arguments go to ``fig.savefig``; the caller closes the figure."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=path.suffix.lstrip(".") or "png", **savefig_kw)
    return path


def write_netcdf(path, obj, *, engine: str = "h5netcdf", encoding: dict | None = None,
                 overwrite: bool = True) -> Path:
    """Write an ``xarray.Dataset`` or ``xarray.DataTree`` as NetCDF-4 to ``path`` atomically.

    The file is built in memory (HDF5 never holds a handle on the target file system, so a full
    disk cannot leave HDF5 unable to close it) and written with :func:`write_bytes`."""
    with _local_write_lock():
        data = obj.to_netcdf(None, engine=engine, encoding=encoding)
    return write_bytes(path, data, overwrite=overwrite)


def _local_write_lock():
    """Inside a dask.distributed task xarray guards NetCDF writes with a cluster-wide lock named
    after the target, which for an in-memory target is a BytesIO the scheduler cannot name
    ("Semaphore or Lock … not known"); the synchronous scheduler gives it a process-local lock,
    which is all an in-memory write needs."""
    try:
        import dask
    except ImportError:
        return contextlib.nullcontext()
    return dask.config.set(scheduler="synchronous")


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)  # one inode: hard links, symbolic links, ./x and x
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def check_not_inputs(targets: dict, inputs: dict) -> None:
    """Refuse (:class:`UserError`, one line) an output file that is one of the command's inputs,
    or two outputs that are one file: ``--overwrite`` would otherwise replace the input (a raw
    stream lost) before or while it is read.  ``targets`` and ``inputs`` map the option that
    names each file (``-o``, ``REC``) to its path; None values are skipped."""
    outs = [(f, Path(p)) for f, p in targets.items() if p is not None]
    for i, (flag, out) in enumerate(outs):
        for what, path in [*((k, v) for k, v in inputs.items() if v is not None), *outs[:i]]:
            if _same_file(out, Path(path)):
                raise UserError(f"{flag}: {out} is also the input {what} ({path}); an output never replaces an "
                                "input: choose another file")


# ---------------------------------------------------------------- locks

def lock_path(target) -> Path:
    """The lock file of an output target: ``.NAME.lock`` beside it."""
    target = Path(target)
    return target.parent / f".{target.name}.lock"


def _pid_alive(pid: int) -> bool:
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
    return host == socket.gethostname() and not _pid_alive(pid)


def _acquire(target: Path, flag: str) -> Path:
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
    lock = _acquire(Path(target), flag)
    try:
        yield lock
    finally:
        lock.unlink(missing_ok=True)


# ---------------------------------------------------------------- output targets

_OPEN: list = []  # targets opened and neither committed nor aborted (aborted by the CLI on error)


def display_path(p) -> str:
    """``p`` as the user knows it: a path inside the staging directory of an open
    :class:`OutputDir` is shown at its place in DIR."""
    for t in _OPEN:
        if isinstance(t, OutputDir) and t._staged:
            q = t.final(p)
            if q != Path(p):
                return str(q)
    return str(p)


def abort_open() -> None:
    """Abort every output target still open: staged files deleted, locks released.  The CLI
    calls this after each command, so that an error or interrupt leaves nothing behind."""
    while _OPEN:
        _OPEN[-1].abort()


class _Target:
    flag = "--out"

    def __enter__(self):
        return self.open()

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.commit()
        else:
            if isinstance(exc, OSError) and exc.filename is not None:
                exc.filename = display_path(exc.filename)  # before the staging directory goes
            self.abort()
        return False

    def _release(self) -> None:
        if self._lock is not None:
            self._lock.unlink(missing_ok=True)
            self._lock = None
        if self in _OPEN:
            _OPEN.remove(self)


class OutputFile(_Target):
    """An ``-o FILE`` target (plus sidecar files written beside it, e.g. ``rec.truth.json``).

    :meth:`open` checks every path (:func:`check_file_target`) and locks FILE; the writers then
    write each file atomically; :meth:`commit` (or :meth:`abort`) releases the lock."""

    def __init__(self, path, *, overwrite: bool = False, also=(), flag: str = "-o"):
        self.path = Path(path)
        self.also = [Path(p) for p in also]
        self.overwrite = bool(overwrite)
        self.flag = flag
        self._lock = None
        self.started = False  # one of its files has been replaced

    def owns(self, p) -> bool:
        """Whether ``p`` is FILE or one of its sidecars."""
        p = os.path.abspath(p)
        return any(p == os.path.abspath(q) for q in (self.path, *self.also))

    def open(self) -> "OutputFile":
        for p in (self.path, *self.also):
            check_file_target(p, overwrite=self.overwrite, flag=self.flag)
        self._lock = _acquire(self.path, self.flag)
        _OPEN.append(self)
        try:
            for p in (self.path, *self.also):  # again, under the lock: another run may have written it
                check_file_target(p, overwrite=self.overwrite, flag=self.flag)
        except BaseException:
            self.abort()
            raise
        for p in (self.path, *self.also):  # temporary files of killed writers of these targets
            for tmp, pid in _siblings(p, ("",), ".tmp"):
                if pid != os.getpid() and not _pid_alive(pid) and not tmp.is_dir():
                    tmp.unlink(missing_ok=True)
        return self

    def commit(self) -> None:
        self._release()

    def abort(self) -> None:
        self._release()


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


def _siblings(target: Path, kinds, suffix: str = ""):
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


class OutputDir(_Target):
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
        self._lock = _acquire(t, self.flag)
        _OPEN.append(self)
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
        for p, pid in _siblings(self.target, ("partial-", "old-")):
            if pid == os.getpid() or _pid_alive(pid):
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
        _fsync_dir(s)
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
        _fsync_dir(t.parent)
        if old is not None:
            _remove_set(old, self.keep)  # what is left (added during the swap) stays in .NAME.old-*
        self._release()

    def abort(self) -> None:
        """Delete the staged files and unlock; DIR keeps what it held."""
        if self._staged:
            shutil.rmtree(self.staging, ignore_errors=True)
            self._staged = False
        self._release()
