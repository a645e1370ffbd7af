"""The options of [S16] self-calibration (:func:`accel_bayes.pipelines.selfcal.selfcal`) as one
frozen record (issue #26 item 3), built once by the command line (:meth:`SelfcalOptions.from_args`)
or by a library user and checked at construction (one-line :class:`~accel_bayes.errors.UserError`
naming the field).  What needs the recording (the fixed IMU's label against its IMUs, a selection
against its samples) is checked by :func:`accel_bayes.pipelines.selfcal.prepare`.

Torch-free at import: the command line builds the record before it decides to compute.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import UserError

__all__ = ["SelfcalOptions", "PROCESS_NOISE_MODES", "MARGINAL_SCALE_MODES"]

# inference.selfcal.PROCESS_NOISE_MODES, written out so that checking the record imports no torch
# (tests/test_options.py keeps them equal)
PROCESS_NOISE_MODES = ("s16", "estimate", "estimate-snap")
MARGINAL_SCALE_MODES = (True, False, "score")

# seeds are only recorded, but as everywhere in the package: an integer in [0, 2³² − 1] (cli/_options.seed)
_SEED_MAX = 2 ** 32 - 1


def _optional_int(name, v, lo, hi=None):
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or int(v) < lo or (hi is not None and int(v) > hi):
        rng = f">= {lo}" + (f" and <= {hi}" if hi is not None else "")
        raise UserError(f"{name}: expected an integer {rng}, got {v!r}")
    return int(v)


@dataclass(frozen=True)
class SelfcalOptions:
    """Every option of one [S16] self-calibration (the model and its stages are described in
    :func:`accel_bayes.inference.selfcal.self_calibrate`).

    fixed : label of the IMU held at its nominal pose (None: the recording's reference IMU).
    selection : the samples to fit, a :class:`~accel_bayes.prep.selection.Selection` of the
        recording (None: every sample, the [S16] setting).
    drop_clipped : without a ``selection``, leave out the samples where an accelerometer triad is
        flagged at its range (default False: fitted as they are).
    max_iter : Levenberg-Marquardt iteration limit per stage (≥ 1, default 200).
    rerun : the [S16] §VI-A re-run from the estimated poses (default True).
    seed : recorded in the provenance only (the self-calibration draws no random numbers).
    process_noise : the motion model, "estimate-snap" (default), "estimate", "s16", or a dict of
        intensities (:func:`~accel_bayes.inference.selfcal.self_calibrate`).
    marginal_scale : with an estimated process noise, move the estimate along the scale orbit to
        the maximum of the Laplace marginal likelihood (True, default), to the root of its
        approximate derivative ("score"), or keep the joint MAP (False).

    Frozen: a changed option is a new record (``dataclasses.replace``, checked again).
    """

    fixed: int | None = None
    selection: Any = None
    drop_clipped: bool = False
    max_iter: int = 200
    rerun: bool = True
    seed: int | None = None
    process_noise: Any = "estimate-snap"
    marginal_scale: bool | str = True

    def __post_init__(self):
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 — normalising a frozen record's own fields
        set_("fixed", _optional_int("fixed", self.fixed, 0))
        max_iter = _optional_int("max_iter", self.max_iter, 1)
        if max_iter is None:
            raise UserError("max_iter: expected an integer >= 1, got None")
        set_("max_iter", max_iter)
        set_("seed", _optional_int("seed", self.seed, 0, _SEED_MAX))
        if self.selection is not None and self.drop_clipped:
            raise UserError("drop_clipped: give either a selection or drop_clipped, not both")
        pn = self.process_noise
        if not isinstance(pn, dict) and pn not in PROCESS_NOISE_MODES:
            raise UserError(f"process_noise: expected one of {PROCESS_NOISE_MODES} or a dict of intensities, "
                            f"got {pn!r}")
        if not any(self.marginal_scale is m or (isinstance(m, str) and self.marginal_scale == m)
                   for m in MARGINAL_SCALE_MODES):
            raise UserError(f"marginal_scale: expected True, False or 'score', got {self.marginal_scale!r}")
        for name in ("drop_clipped", "rerun"):
            set_(name, bool(getattr(self, name)))

    @classmethod
    def from_args(cls, args) -> "SelfcalOptions":
        """The record of ``accel-bayes selfcal``'s parsed arguments (argparse namespace)."""
        return cls(fixed=args.fixed, drop_clipped=args.drop_clipped, max_iter=args.max_iter, rerun=not args.no_rerun,
                   seed=args.seed, process_noise=args.process_noise)

    def to_settings(self, *, fixed_label: int) -> dict:
        """The options' entries of the provenance settings (``positions.json``
        ``provenance.settings``), in their order there; ``fixed_label`` is the IMU the
        preparation held fixed (``fixed`` resolved against the recording)."""
        return {"fixed": int(fixed_label), "max_iter": self.max_iter, "rerun_from_estimate": self.rerun}
