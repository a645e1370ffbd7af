"""``accel-bayes`` command line.

Each sub-command lives in its own module of this package and exposes ``register(subparsers)``,
which adds its parser and sets ``func`` (called with the parsed namespace, returns an exit code).
User errors (:class:`accel_bayes.errors.UserError`, missing files) and I/O errors (an
``OSError`` from a read or write: a full disk, a read-only or vanished directory) exit with
status 2 and one line on stderr naming the path, never a traceback; the numpy/torch warnings
raised on the way are held back (shown after a success only), so that line comes alone.  An
output file that is also an input is refused the same way.  A diverged optimisation
(:class:`accel_bayes.errors.DivergenceError`) exits with status 3 and one line.  SIGINT and
SIGTERM only set a flag (:mod:`accel_bayes.interrupts`) that the long loops and the writers check:
status 130 and one line (a checkpoint already written stays usable for ``--resume``).  Whatever
way a command ends short of success, the output targets it opened
(:mod:`accel_bayes.data.outputs`) are aborted: staged files deleted, locks released, earlier
results left as they were.
"""
from __future__ import annotations

import argparse
import importlib
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


def _run_command(args) -> int:
    """The command with its numpy/torch warnings held back: a refusal is then its one line, not
    a screen of "overflow encountered" lines first; after a success they are shown, once each."""
    import warnings

    from ..interrupts import check

    check()  # a signal during the imports and the parsing: nothing has been touched yet
    with warnings.catch_warnings(record=True) as caught:
        rc = int(args.func(args) or 0)
    seen = set()
    for w in caught:
        key = (w.category, str(w.message), w.filename, w.lineno)
        if key not in seen:
            seen.add(key)
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    return rc


# The options of every command that name an output file (an --out DIR is checked by OutputDir).
_FILE_OUTPUTS = {"output": "-o", "apply_to": "--apply-to"}


def _check_not_inputs(args) -> None:
    """Refuse an output file that is also an input of the command: every other option naming an
    existing file is an input (the commands read nothing else)."""
    from pathlib import Path

    from ..data.outputs import check_not_inputs

    outs = {flag: getattr(args, k) for k, flag in _FILE_OUTPUTS.items() if getattr(args, k, None) is not None}
    if outs:
        ins = {k.replace("_", "-"): v for k, v in vars(args).items()
               if k not in _FILE_OUTPUTS and isinstance(v, (str, Path)) and Path(v).is_file()}
        check_not_inputs(outs, ins)


def _who(args) -> str:
    return f"accel-bayes {args.command}" if args is not None else "accel-bayes"


def main(argv: list[str] | None = None) -> int:
    """Run ``accel-bayes`` with ``argv`` (default: ``sys.argv[1:]``); returns the exit status
    (DESIGN §7.5).  SIGINT/SIGTERM only set a flag (:mod:`accel_bayes.interrupts`) that the long
    loops and the writers check: status 130, earlier outputs kept, never a traceback."""
    from ..interrupts import handle_signals, hold_until_exit, requested
    from ..errors import DivergenceError

    with handle_signals():
        try:
            args = parser = None
            parser = build_parser()
            args = parser.parse_args(argv)
            _check_not_inputs(args)
            rc = _run_command(args)
        except (UserError, OSError) as exc:
            print(f"{_who(args)}: error: {_one_line(exc)}", file=sys.stderr)
            rc = 2
        except DivergenceError as exc:  # DESIGN §7.5: an optimisation that diverged is status 3
            print(f"{_who(args)}: diverged: {_one_line(exc)}", file=sys.stderr)
            rc = 3
        except KeyboardInterrupt:  # Interrupted from a safe point, or Ctrl-C outside handle_signals
            rc = 130
        except SystemExit:  # argparse: --help, --version, a usage error
            if not requested():
                raise
            rc = 130
        finally:
            abort_open()  # anything not committed by the command: staged files removed, locks released
        # Called as the command (no argv), the process ends next: a signal until then still counts,
        # one after it is ignored (accel_bayes.interrupts.hold_until_exit)
        if argv is None and hold_until_exit():
            rc = 130
        if rc == 130 or requested():
            print(f"{_who(args)}: interrupted", file=sys.stderr)
            rc = 130
    return rc


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
