"""When and where an experiment document was generated, measured rather than assumed: the
document headers used to say "2-core CPU shared with other jobs" whether or not the run was alone,
and timings are only comparable with the load they ran under."""
from __future__ import annotations

import datetime
import os
import platform

__all__ = ["invocation", "machine_note", "run_stamp"]


def machine_note() -> str:
    """"x86_64 Linux, 2 cores, load average 0.4": the machine and its 1-minute load average now."""
    return (f"{platform.machine()} {platform.system()}, {os.cpu_count()} cores, "
            f"load average {os.getloadavg()[0]:.1f}")


def run_stamp() -> str:
    """"2026-11-27 21:12 UTC, x86_64 Linux, 2 cores, load average 0.4" (UTC now and :func:`machine_note`)."""
    return f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, {machine_note()}"


def invocation(script: str, argv=None) -> str:
    """The command a document names to regenerate it: "PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3
    experiments/SCRIPT ARGS" (``script`` the file name, ``argv`` the script's arguments; None: ``sys.argv[1:]``)."""
    import sys

    args = sys.argv[1:] if argv is None else argv
    return f"PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/{script} {' '.join(args)}".strip()
