"""``accel-bayes`` command line.

Each sub-command lives in its own module of this package and exposes ``register(subparsers)``,
which adds its parser and sets ``func`` (called with the parsed namespace, returns an exit code).
User errors (:class:`accel_bayes.errors.UserError`, missing files) exit with status 2 and one
line on stderr, never a traceback.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from ..errors import UserError

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


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (UserError, FileNotFoundError, IsADirectoryError, PermissionError) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        print(f"accel-bayes {args.command}: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"accel-bayes {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
