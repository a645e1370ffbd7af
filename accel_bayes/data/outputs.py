"""Output files: the one atomic writer, ``-o FILE`` targets and JSON values (DESIGN §7.5).

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

``--out DIR`` targets
    One consistent set of results: :class:`accel_bayes.data.output_sets.OutputDir`.

Signals
    SIGINT/SIGTERM only set a flag (:mod:`accel_bayes.interrupts`); every writer checks it just
    before making a file (:func:`atomic_path`) or a set
    (:meth:`~accel_bayes.data.output_sets.OutputDir.commit`) visible and then discards what it
    staged, leaving the earlier output as it was.

Locks
    A target being written is locked by a sibling ``.NAME.lock``; a second run into it is refused
    with one line (:mod:`accel_bayes.data.output_siblings`).

All refusals are :class:`~accel_bayes.errors.UserError` with one line naming the option
(``--out`` / ``-o``) and what was expected; the CLI turns them into exit status 2.
"""
from __future__ import annotations

import contextlib
import json
import os
import secrets
from contextlib import contextmanager
from pathlib import Path

from .. import interrupts
from ..errors import UserError
from .output_siblings import acquire_lock, hidden_siblings, pid_alive

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
    "abort_open",
    "display_path",
    "Target",
    "OPEN_TARGETS",
    "fsync_dir",
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


# ---------------------------------------------------------------- the one atomic writer

def fsync_dir(d: Path) -> None:
    """Flush directory ``d``'s entries to disk (best effort)."""
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
    started = [t for t in OPEN_TARGETS if isinstance(t, OutputFile) and t.started]
    if not started:  # once one file of a command is replaced, its others follow (no mix of two runs)
        interrupts.check()  # the last moment a SIGINT/SIGTERM can still keep the old file
    os.replace(tmp, path)
    for t in OPEN_TARGETS:
        if isinstance(t, OutputFile) and t.owns(path):
            t.started = True
    fsync_dir(path.parent)


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


# ---------------------------------------------------------------- output targets

OPEN_TARGETS: list = []  # targets opened and neither committed nor aborted (aborted by the CLI on error)


def display_path(p) -> str:
    """``p`` as the user knows it: a path inside the staging directory of an open
    :class:`OutputDir` is shown at its place in DIR."""
    for t in OPEN_TARGETS:
        if t._staged:
            q = t.final(p)
            if q != Path(p):
                return str(q)
    return str(p)


def abort_open() -> None:
    """Abort every output target still open: staged files deleted, locks released.  The CLI
    calls this after each command, so that an error or interrupt leaves nothing behind."""
    while OPEN_TARGETS:
        OPEN_TARGETS[-1].abort()


class Target:
    """An output target being written (:class:`OutputFile`, :class:`~accel_bayes.data.output_sets.OutputDir`):
    a context manager that commits on a clean exit and aborts on an exception."""

    flag = "--out"
    _staged = False  # an OutputDir's staging directory holds this run's files

    def final(self, p) -> Path:
        """Where a path written for this target ends up once committed (itself, but for an
        OutputDir's staged files)."""
        return Path(p)

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
        if self in OPEN_TARGETS:
            OPEN_TARGETS.remove(self)


class OutputFile(Target):
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
        self._lock = acquire_lock(self.path, self.flag)
        OPEN_TARGETS.append(self)
        try:
            for p in (self.path, *self.also):  # again, under the lock: another run may have written it
                check_file_target(p, overwrite=self.overwrite, flag=self.flag)
        except BaseException:
            self.abort()
            raise
        for p in (self.path, *self.also):  # temporary files of killed writers of these targets
            for tmp, pid in hidden_siblings(p, ("",), ".tmp"):
                if pid != os.getpid() and not pid_alive(pid) and not tmp.is_dir():
                    tmp.unlink(missing_ok=True)
        return self

    def commit(self) -> None:
        self._release()

    def abort(self) -> None:
        self._release()
