"""``accel-bayes`` command line.

Each sub-command lives in its own module of this package and exposes ``register(subparsers)``,
which adds its parser and sets ``func`` (called with the parsed namespace, returns an exit code).
User errors (:class:`accel_bayes.errors.UserError`, missing files) and I/O errors (an
``OSError`` from a read or write: a full disk, a read-only or vanished directory) exit with
status 2 and one line on stderr naming the path, never a traceback.  SIGINT and SIGTERM exit
with status 130 (a checkpoint already written stays usable for ``--resume``).  Whatever way a
command ends short of success, the output targets it opened (:mod:`accel_bayes.data.outputs`) are
aborted: staged files deleted, locks released, earlier results left as they were.
"""
from __future__ import annotations

import argparse
import importlib
import signal
import sys

from ..errors import UserError
from ..data.outputs import abort_open, display_path

# Sub-command modules listed first, in this order, by `accel-bayes --help`; any other module of
# this package that defines ``register`` is added after them (so a new command is one new file).
COMMANDS = ["demo", "simulate", "import_mimu", "info", "map", "calibrate", "selfcal"]


def _command_modules() -> list[str]:
    import pkgutil

    found = {m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_")}
    return [c for c in COMMANDS if c in found] + sorted(found - set(COMMANDS))


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse's own usage errors: one line, status 2
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="accel-bayes", description="Bayesian self-calibration of inertial sensor arrays.")
    from .. import __version__

    parser.add_argument("--version", action="version", version=f"accel-bayes {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name in _command_modules():
        importlib.import_module(f".{name}", __name__).register(sub)
    return parser


def _one_line(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.filename is not None and not isinstance(exc, (FileNotFoundError,
                                                                                       IsADirectoryError)):
        # "[Errno 27] File too large: '/x/.posterior.nc.123-ab.tmp.nc'" → the path and the reason
        return f"{display_path(exc.filename)}: {exc.strerror or type(exc).__name__}"
    msg = str(exc).splitlines()[0].strip() if str(exc).strip() else ""
    return msg or type(exc).__name__


def _sigterm(signum, frame):
    raise KeyboardInterrupt  # handled like Ctrl-C: exit 130, outputs aborted, checkpoint kept


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        previous = signal.signal(signal.SIGTERM, _sigterm)
    except ValueError:  # not the main thread: leave signals alone
        previous = None
    try:
        return int(args.func(args) or 0)
    except (UserError, OSError) as exc:
        print(f"accel-bayes {args.command}: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"accel-bayes {args.command}: interrupted", file=sys.stderr)
        return 130
    finally:
        abort_open()  # anything not committed by the command: staged files removed, locks released
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
