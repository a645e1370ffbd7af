"""When and where an experiment document was generated, measured rather than assumed: the
document headers used to say "2-core CPU shared with other jobs" whether or not the run was alone,
and timings are only comparable with the load they ran under."""
from __future__ import annotations

import datetime
import os
import platform

__all__ = ["machine_note", "run_stamp"]


def machine_note() -> str:
    """"x86_64 Linux, 2 cores, load average 0.4": the machine and its 1-minute load average now."""
    return (f"{platform.machine()} {platform.system()}, {os.cpu_count()} cores, "
            f"load average {os.getloadavg()[0]:.1f}")


def run_stamp() -> str:
    """"2026-11-27 21:12 UTC, x86_64 Linux, 2 cores, load average 0.4" (UTC now and :func:`machine_note`)."""
    return f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, {machine_note()}"
