"""``python -m accel_bayes`` and the ``accel-bayes`` script: the command line of
:mod:`accel_bayes.cli`, with SIGINT/SIGTERM recorded from the first line on (the command's imports
take seconds; :func:`accel_bayes.interrupts.install`)."""
import sys

from .interrupts import install


def main() -> int:
    """Run ``accel-bayes`` with ``sys.argv``; returns the exit status (DESIGN §7.5)."""
    install()
    from .cli import main as cli_main

    return cli_main()


if __name__ == "__main__":
    sys.exit(main())
