"""How many CPU threads torch uses inside a pipeline call.

The hot tensors of the package are small (one sample's 3A × 6 blocks, T × 6 projections, a few
draws per sample), so torch's intra-op threads buy little and cost synchronisation.  Where the
cores are shared that cost dominates: on the 2-core development machine under load (load average
7.5), one log p̂ of a 6-IMU, T = 2500 board took 0.6–3.8 ms with one thread and 240–750 ms with
two (N = 1–40), and its MAP 2.5 s against 10.5 s.  :func:`accel_bayes.pipelines.calibrate.calibrate`
therefore runs with one thread unless told otherwise (``threads=``, CLI ``--threads``).
"""
from __future__ import annotations

import contextlib

import torch

from .constants import DEFAULT_THREADS
from .errors import UserError

__all__ = ["torch_threads", "DEFAULT_THREADS"]


@contextlib.contextmanager
def torch_threads(n: int | None):
    """Run the block with ``torch.set_num_threads(n)`` and restore the previous count after it;
    ``n=None`` leaves torch's setting alone."""
    if n is None:
        yield
        return
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise UserError(f"threads: expected an integer >= 1 or None, got {n!r}")
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)
