"""Exit statuses of the command line (DESIGN §7.5) and the one way to report status 4.

0 finished; 2 refused (bad input, option or output path; set by the dispatcher for
:class:`~accel_bayes.errors.UserError` and by argparse); 3 optimisation diverged; 4 finished but
not trustworthy (results written and marked so); 130 interrupted.
"""
from __future__ import annotations

import sys

EXIT_OK = 0
EXIT_REFUSED = 2
EXIT_DIVERGED = 3
EXIT_UNTRUSTED = 4
EXIT_INTERRUPTED = 130


def untrusted(command: str, reasons: list[str], files: str = "") -> int:
    """Print one line on stderr saying why the written results of ``command`` are not trustworthy
    and return :data:`EXIT_UNTRUSTED` (the command's files say so too)."""
    where = f" (marked in {files})" if files else ""
    print(f"accel-bayes {command}: warning: results not trustworthy{where}: {'; '.join(reasons)}", file=sys.stderr)
    return EXIT_UNTRUSTED
