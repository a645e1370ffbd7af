"""The options of :func:`accel_bayes.mismatch.detect` as one frozen record (issue #26 "Options as
frozen records", issue #27).

:class:`DetectOptions` is built once — by ``accel-bayes mismatch`` from its arguments
(:meth:`DetectOptions.from_args`) or by a library user — and checked as a whole at construction (a
one-line :class:`~accel_bayes.errors.UserError` naming the field, before any recording is read).
It gives the report's ``settings`` (:meth:`~DetectOptions.to_settings`) and what a cached result
must match (:meth:`~DetectOptions.fingerprint`).

Torch-free at import (like :mod:`accel_bayes.pipelines.calibrate_options`; the package's
``__init__`` loads its torch names on first use): the command line checks the record before it
decides to compute.
"""
from __future__ import annotations

import json
import math
import numbers
import sys
from dataclasses import dataclass
from typing import Any

from ..constants import DEFAULT_THREADS
from ..errors import UserError

__all__ = ["DetectOptions", "EFFECT_NAMES"]

# Written out so that checking the record imports no torch; tests/mismatch/test_detect_options.py keeps
# it equal to the effects library's registry (accel_bayes.physics.effects.EFFECTS).
EFFECT_NAMES = ("acc_bias", "acc_scale", "acc_misalignment", "acc_nonlinearity", "acc_linear", "axis_displacement",
                "triad_orientation", "gyro_bias", "gyro_scale", "gyro_misalignment", "gyro_g_sensitivity",
                "gyro_nonlinearity", "gyro_linear", "time_offset", "gyro_delay", "saturation", "noise_level",
                "unexplained", "sampling_jitter", "timing_wander", "sampling_clock")


def _known_effects() -> list:
    """The effect names a record may ask for: the registry's when the effects library is loaded
    (a user's :func:`~accel_bayes.physics.effects.register_effect` adds names), else the built-in ones."""
    lib = sys.modules.get("accel_bayes.physics.effects")
    return list(lib.EFFECTS) if lib is not None else list(EFFECT_NAMES)


def _int_option(name, v, lo):
    # numbers.Integral: numpy's integers too, without importing numpy
    if isinstance(v, bool) or not isinstance(v, numbers.Integral) or int(v) < lo:
        raise UserError(f"{name}: expected an integer >= {lo}, got {v!r}")
    return int(v)


def _effect_names(effects) -> tuple | None:
    """``effects`` (None, a comma-separated string, or names / effect classes) as a tuple of known names
    without ``unexplained`` (always considered) and without repeats; None = every effect."""
    if effects is None:
        return None
    items = effects.split(",") if isinstance(effects, str) else list(effects)
    given = [(e.strip() if isinstance(e, str) else getattr(e, "name", e)) for e in items]
    given = [e for e in given if e != ""]
    if not given:
        raise UserError("effects: expected at least one effect name")
    known = _known_effects()
    names = []
    for nm in given:
        if nm not in known:
            raise UserError(f"effects: unknown name {nm!r}; expected one of {sorted(known)}")
        if nm != "unexplained" and nm not in names:
            names.append(nm)
    return tuple(names)


@dataclass(frozen=True)
class DetectOptions:
    """Every option of one mismatch detection (:func:`accel_bayes.mismatch.detect`).  Frozen: a
    changed option is a new record (``dataclasses.replace``, checked again).

    effects : effect names to try (tuple, list or comma-separated string; None = every registered
        effect; ``gyro_linear`` switches the gyro linear stage, ``sampling_clock`` the clock stage and
        with it ``unresolved_motion``); ``unexplained`` is always considered.  Stored as a tuple.
    alpha : family-wise error rate of the Bonferroni threshold, in (0, 1) (default 0.01).
    max_findings : most round findings added to the model (default 3; the stages' findings — gyro
        linear blocks, clocks, unresolved motion — are not counted).
    refine : fill ``report.refined`` (default True).
    posterior : False, or the calibration function to run before/after the findings (slow).
    seed : seeds every random step (PPC twins, permutations, Laplace draws, posterior runs).
    progress : print stage messages (not part of the settings).
    n_twins : posterior predictive twins (default 100); n_refit : LM refits per round (default 6);
    use_map : start the baseline from the package's MAP (default True); loo_draws : Laplace draws
        for PSIS-LOO (default 200).
    unresolved_permutations : permutations of the data ages among the samples of each |ω| band in
        the ``unresolved_motion`` test (default 19; 0 skips the term).
    threads : torch CPU threads for the call (default 1, restored afterwards; None leaves torch's).
    unresolved_angular_jerk : the ``unresolved_motion`` term on the accelerometers also carries the
        board's unresolved angular jerk through each triad's lever arm (default False; opt-in while it
        is measured: ``experiments/budget_gap_probe.md``).  In ``settings`` only when True, so that
        reports and fingerprints of the default are unchanged.
    acc_linear : run the accelerometer linear stage (every triad's 3 × 3 scale/misalignment + offset
        block, :mod:`accel_bayes.mismatch.acc_linear`) after the gyro linear stage (default False;
        opt-in while it is measured: ``experiments/acc_linear_budget.md``; where ``prep`` calibrated the
        triads from rests it runs on those outputs and estimates what the rests leave,
        ``experiments/mimu_blind_acc.md``).  In ``settings`` only when True.
    """

    effects: Any = None
    alpha: float = 0.01
    max_findings: int = 3
    refine: bool = True
    posterior: Any = False
    seed: int = 0
    progress: bool = False
    n_twins: int = 100
    n_refit: int = 6
    use_map: bool = True
    loo_draws: int = 200
    unresolved_permutations: int = 19
    threads: int | None = DEFAULT_THREADS
    unresolved_angular_jerk: bool = False
    acc_linear: bool = False

    def __post_init__(self):
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 — normalising a frozen record's own fields
        set_("effects", _effect_names(self.effects))
        a = self.alpha
        if isinstance(a, bool):
            raise UserError(f"alpha: expected a number in (0, 1), got {a!r}")
        try:
            a = float(a)
        except (TypeError, ValueError):
            raise UserError(f"alpha: expected a number in (0, 1), got {self.alpha!r}") from None
        if not (math.isfinite(a) and 0 < a < 1):
            raise UserError(f"alpha: expected a number in (0, 1), got {self.alpha!r}")
        set_("alpha", a)
        set_("max_findings", _int_option("max_findings", self.max_findings, 0))
        if isinstance(self.seed, bool) or not isinstance(self.seed, numbers.Integral) or int(self.seed) < 0:
            raise UserError(f"seed: expected a non-negative integer, got {self.seed!r}")
        set_("seed", int(self.seed))
        set_("n_twins", _int_option("n_twins", self.n_twins, 1))
        set_("n_refit", _int_option("n_refit", self.n_refit, 1))
        set_("loo_draws", _int_option("loo_draws", self.loo_draws, 1))
        set_("unresolved_permutations", _int_option("unresolved_permutations", self.unresolved_permutations, 0))
        if self.posterior is not False and self.posterior is not None and not callable(self.posterior):
            raise UserError(f"posterior: expected False or the calibration function "
                            f"(accel_bayes.pipelines.calibrate.calibrate), got {self.posterior!r}")
        if self.posterior is None:
            set_("posterior", False)
        if self.threads is not None:
            set_("threads", _int_option("threads", self.threads, 1))
        for name in ("refine", "progress", "use_map", "unresolved_angular_jerk", "acc_linear"):
            set_(name, bool(getattr(self, name)))

    @classmethod
    def from_args(cls, args, **given) -> "DetectOptions":
        """The record of ``accel-bayes mismatch``'s parsed arguments (argparse namespace); ``given``
        adds what the command decides itself (``posterior``: the calibration function)."""
        return cls(effects=args.effects, alpha=args.alpha, max_findings=args.max_findings,
                   refine=not args.no_refine, seed=args.seed, progress=args.progress, n_twins=args.twins,
                   unresolved_angular_jerk=getattr(args, "unresolved_angular_jerk", False),
                   acc_linear=getattr(args, "acc_linear", False), **given)

    def to_settings(self) -> dict:
        """The report's ``settings`` (the keys 0.1 wrote, in their order, then the ones added):
        ``effects`` lists every effect tried when the record says None."""
        return {"effects": list(self.effects) if self.effects is not None else _known_effects(),
                "alpha": self.alpha, "max_findings": self.max_findings, "refine": self.refine,
                "posterior": bool(self.posterior), "seed": self.seed, "n_twins": self.n_twins,
                "n_refit": self.n_refit, "use_map": self.use_map, "loo_draws": self.loo_draws,
                "unresolved_permutations": self.unresolved_permutations,
                **({"unresolved_angular_jerk": True} if self.unresolved_angular_jerk else {}),
                **({"acc_linear": True} if self.acc_linear else {})}

    def fingerprint(self, recording_sha256: str) -> dict:
        """What a detection's result depends on, known before any computation: the package version, the
        recording's SHA-256 and the options that change the numbers (not ``progress`` nor
        ``threads``, which change only floating-point reduction order).  Plain JSON values."""
        from .. import __version__

        options = {k: v for k, v in self.to_settings().items()}
        options["effects"] = None if self.effects is None else list(self.effects)
        return json.loads(json.dumps({"version": __version__, "recording": recording_sha256, "options": options}))
