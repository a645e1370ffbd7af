"""The options of :func:`accel_bayes.pipelines.calibrate.calibrate` as one frozen record (issue #26 item 3).

:class:`CalibrateOptions` is built once — by the command line from its arguments
(:meth:`CalibrateOptions.from_args`) or by a library user — and checked as a whole at construction
(a one-line :class:`~accel_bayes.errors.UserError` naming the field, before any recording is read).
It gives the options' part of the provenance settings (:meth:`~CalibrateOptions.to_settings`) and
the request a resumed checkpoint must match (:meth:`~CalibrateOptions.fingerprint`).

Torch-free at import, like :mod:`.calibrate_defaults`: the command line builds and checks the
record before it decides to compute.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..constants import ESS_PER_CHAIN
from ..errors import UserError
from .calibrate_defaults import DEFAULTS

__all__ = ["CalibrateOptions", "NOISE_MODES", "PHI_PRIOR_CHOICES", "PRIORS", "GYRO_METHODS", "PROPOSALS", "INITS"]

# Written out so that checking an options record imports no torch; tests/test_options.py keeps them
# equal to model.noise.NOISE_MODES and model.phi_prior.PHI_PRIOR_CHOICES.
NOISE_MODES = ("auto", "stated", "estimate")
PHI_PRIOR_CHOICES = ("empirical", "flat")
PRIORS = ("gaussian", "box")
GYRO_METHODS = ("auto", "sample_cov", "sample_cov_mean", "calibrated")
PROPOSALS = ("auto", "rw", "mixture")
INITS = ("auto", "map", "prior")


def _int_option(name, v, lo):
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or int(v) < lo:
        raise UserError(f"{name}: expected an integer >= {lo}, got {v!r}")
    return int(v)


def _real_option(name, v, lo, unit, allow_none=False):
    """A finite number > ``lo`` (or None when ``allow_none``), else one-line UserError naming ``name``."""
    if v is None and allow_none:
        return None
    want = f"expected a finite number > {lo:g} ({unit})" + (" or None" if allow_none else "")
    if isinstance(v, bool):
        raise UserError(f"{name}: {want}, got {v!r}")
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise UserError(f"{name}: {want}, got {v!r}") from None
    if not (math.isfinite(x) and x > lo):
        raise UserError(f"{name}: {want}, got {v!r}")
    return x


def _select_key(select):
    """``select`` as a plain value for the checkpoint fingerprint (a mask or indices by their hash)."""
    if select is None or isinstance(select, str):
        return select
    return hashlib.sha256(np.ascontiguousarray(np.asarray(select)).tobytes()).hexdigest()


def _intrinsics_key(intrinsics) -> str:
    """A given :class:`~accel_bayes.prep.intrinsics.Intrinsics` object by the hash of its arrays."""
    h = hashlib.sha256()
    for v in vars(intrinsics).values():
        if isinstance(v, np.ndarray):
            h.update(np.ascontiguousarray(v).tobytes())
    return h.hexdigest()


def _acc_blocks_option(v):
    """``acc_blocks`` normalised: "fit", "fixed" or a pair of finite tolerances > 0 (τ_M, τ_b)."""
    if isinstance(v, str) and v in ("fit", "fixed"):
        return v
    want = "expected 'fit', 'fixed' or two tolerances > 0 (matrix entries, 1; offsets, m/s²)"
    if isinstance(v, str):
        parts = v.split(",")
        if len(parts) != 2:
            raise UserError(f"acc_blocks: {want}, got {v!r}")
        v = parts
    try:
        tm, tb = (float(x) for x in v)
    except (TypeError, ValueError):
        raise UserError(f"acc_blocks: {want}, got {v!r}") from None
    if not (math.isfinite(tm) and math.isfinite(tb) and tm > 0 and tb > 0):
        raise UserError(f"acc_blocks: {want}, got {v!r}")
    return (tm, tb)


def _angular_jerk_arg(args) -> bool:
    """``--angular-jerk`` / ``--no-angular-jerk`` (absent: the default, on with a model).  Asked for
    explicitly without ``--model`` it is refused: the term exists only in a model's likelihood."""
    if args.angular_jerk is None:
        return DEFAULTS["angular_jerk"]
    if args.angular_jerk and args.model is None:
        raise UserError("angular_jerk: the angular-jerk term needs a model (--model REPORT.json)")
    return bool(args.angular_jerk)


@dataclass(frozen=True)
class CalibrateOptions:
    """Every option of one PmMH calibration (:func:`accel_bayes.pipelines.calibrate.calibrate`);
    defaults in :data:`~accel_bayes.pipelines.calibrate_defaults.DEFAULTS`.  Frozen: a changed
    option is a new record (``dataclasses.replace``, checked again).

    chains, warmup : C chains, W warm-up (adaptation) iterations each (default 4 and 1000); the
        adaptation happens in warm-up only, the kept draws come from a fixed exact kernel.
    draws : kept draws per chain.  None (default): run until converged — the chains are continued
        (each from its current state, so the same seed gives the draws of one long run) until
        every coordinate has R̂ < ``rhat_max`` and bulk and tail ESS ≥ ``ess_min``, checked every
        ``check_every`` draws per chain, up to ``max_draws`` draws per chain or ``max_seconds``
        of sampling.  An int: exactly that many draws (the chains of earlier versions, bit for
        bit where the sampler is unchanged — ``correlation`` 0 or an automatic N of 1); the same
        criteria then only decide ``diagnostics.converged``.
    max_draws : most kept draws per chain in the run-until-converged mode (default 20 000).
    check_every : kept draws per chain between two convergence checks (default 500).  The checks
        happen at fixed draw counts (500, 1000, …), never at wall-clock times, so where a run
        stops does not depend on the machine's speed.
    rhat_max : R̂ threshold, a coordinate passes when its rank-normalised split R̂ < rhat_max
        (default 1.01).
    ess_min : bulk and tail ESS threshold, effective draws of all chains together; None (default):
        100 per chain, i.e. 400 for the default 4 chains (Vehtari et al. 2021).
    max_seconds : wall-clock budget of the sampling in seconds (warm-up included, the steps
        before it not), tested after each check (default 3600; None: no limit).  A safety stop:
        a run that hits it has a machine-dependent number of draws, is reported as not converged
        and says so (``settings["convergence"]["stopped"] == "max_seconds"``).
        What a run did — the criteria, the draws it took, every check and why it stopped — is in
        ``settings["convergence"]`` and the ``diagnostics`` block of ``positions.json``.
    num_draws : N, Monte Carlo draws per likelihood estimate; None chooses it so that
        Var[log p̂] ≈ 1 at the central θ (the MAP, or the prior mean) ([C21] §III-C) — or 1
        with the correlated kernel, see ``correlation``.
    correlation : "auto" (default) or ρ in [0, 1).  ρ > 0: the correlated pseudo-marginal
        kernel (Deligiannidis, Doucet & Pitt 2018; :class:`~accel_bayes.inference.mcmc.PMMHKernel`):
        the standard normals z (T, N, 3) of the estimate are part of each chain's state and are
        moved with each proposal by z' = ρ z + √(1 − ρ²) ε, exact for the same posterior.  "auto":
        when ``num_draws`` is None and fresh draws would need N > 1, N = 1 and ρ such that
        Var[log p̂(θ, z') − log p̂(θ, z)] ≈ 1 at the central θ
        (:func:`~accel_bayes.model.draw_tuning.choose_correlation`, seeded); otherwise 0.  0: fresh draws
        every iteration ([C21] Alg. 1, the chains of earlier versions).  A number: that ρ with N
        as given or chosen by the fresh-draw rule.  Recorded in ``settings["correlation"]``,
        ``settings["correlation_table"]`` and ``settings["correlation_rule"]``.
    seed : one seed for everything random (N choice, chain starts, chains); same seed → same
        draws, bit for bit.
    prior, prior_std : "gaussian" — N(design position, σ²) per coordinate ([C21] §IV-A, σ = 3 mm);
        "box" — uniform with the same std (half-width √3·σ).  Metres.
    use_map : fit the MAP first (if :mod:`accel_bayes.inference.map` is installed) and use it for
        the central θ, the chain starts (Laplace draws over-dispersed ×1.5), the random-walk shape
        and the independence proposal.  False: chains start from prior draws, the random walk is
        shaped by the prior and re-shaped from warm-up draws.
    init : chain starts — "map" (Laplace draws around the MAP, over-dispersed ×1.5), "prior"
        (prior draws, e.g. to check convergence from far away while the proposals still use the
        MAP), "auto" ("map" when a MAP is used, else "prior").
    gyro_method : gyro posterior, see :func:`accel_bayes.model.gyro_posterior.gyro_posterior`.  "auto"
        (default): "calibrated" when the noise is estimated (the estimated accelerometer noise
        then absorbs the gyro errors that [C21] eq. 30's sample covariance is meant to cover;
        on the MIMU data both give the same MAP and Laplace std to a few %, but eq. 30 needs
        Var[log p̂] ≈ 300 at N = 64 on ~6000 samples, out of reach), else "sample_cov" ([C21]
        eq. 30 as printed).
    intrinsics : "auto" (default), "estimate", "none", an
        :class:`~accel_bayes.prep.intrinsics.Intrinsics` or an intrinsics JSON path — the intrinsic
        calibration step of :func:`accel_bayes.prep.preprocess.preprocess` ("auto": from the
        recording's own rests, skipped with a note when it has none).
    drop_static : drop the samples of the rests (default True).
    drop_clipped : drop samples where any accelerometer or gyroscope is flagged as clipped (at
        its range): the model cannot explain them, and a handful of them makes Var[log p̂]
        explode.  Default True.
    min_rotation : drop samples with |ω̄_t| below this, rad/s (default 0.5; None/0 keeps all).
    select : further selection ANDed with the above: a (T,) bool mask or sample indices
        ("rotation" is accepted for compatibility: the ``min_rotation`` threshold, default 0.5
        rad/s even if ``min_rotation`` is 0).  Every count is in ``settings["preprocess"]``.
    noise : "stated" — the recording's ``acc_noise_std``; "estimate" — a level per triad fitted
        with the MAP (type-II ML, :mod:`accel_bayes.model.noise`), then, with ``noise_inflation``,
        the likelihood tempered by κ, the average variance inflation of the sandwich covariance
        at the MAP (what the fitted white-noise model still misses: heteroscedasticity, errors
        shared by the triads of a sample); "auto" (default) — "estimate" for a recording with
        rests (the real-data protocol: its stated σ is the rest noise, which does not cover
        model error during motion) or calibrated with a ``model`` that has an ``unexplained``
        finding (:meth:`noise_mode`), "stated" otherwise (simulations whose stated σ is the
        truth).  What was estimated is in ``settings["noise_model"]``.
    noise_bins : quantile bins of |ω̄| for a rate-dependent noise factor (default 1 = one level
        per triad; see :mod:`accel_bayes.model.noise` for why more bins are not the default).
    noise_inflation : temper by the sandwich factor κ ≥ 1 (estimated noise only).  None (default):
        True without ``model``, False with one (the model's variances at their type-II ML values,
        untempered; the sandwich is then measured and recorded, not applied).
    model : None (default: the likelihood as before, bit for bit) or a mismatch report (DESIGN §7.2
        ``report.json`` path, dict or :class:`~accel_bayes.mismatch.report.MismatchReport`) of this
        recording: its random gyroscope effects (``timing_wander``, ``sampling_jitter``) become
        per-sample gyro covariances and the gyro posterior of ω_t their precision-weighted fusion
        (:mod:`accel_bayes.model.report_terms`; ``gyro_method`` must be "auto" or "calibrated");
        what it cannot carry is skipped with the reason.  The report is checked against the
        recording (IMU count, number of samples: refused otherwise).  The sandwich-to-Laplace std
        ratio per coordinate at the MAP is recorded in ``settings["model"]["sandwich"]``, with the
        report's SHA-256 and the findings used and skipped.
    instant_error : with ``model``, also project out each triad's own sampling-instant error times
        the rate of its output (per-triad covariance e²ρρᵀ, e by type-II ML from the report's
        ``age_error_rms_s``; :mod:`accel_bayes.model.likelihood_percov`, "Instant error").  Default
        False: it makes one log p̂ ~5× the flat model's (issue #30's bar is 4×) and moves the real
        board's sandwich ratio only part of the way (``experiments/mimu_model_calibrate.md``).
    angular_jerk : with ``model``, also project out the board's unresolved angular jerk ω̈_t,
        loaded on each triad by its centred data age times its lever arm (the nominal positions),
        its scale per |ω| band by type-II ML beside the jerk's
        (:mod:`accel_bayes.model.likelihood_percov`, "Angular jerk").  Default True (no effect
        without a model): one log p̂ with it meets issue #30's cost bar, ≤ 4× the flat model's on
        exp_1 (``experiments/bench_likelihood_percov.md``), the rule fixed before the figures; it
        helps on the concealed clock recordings (``experiments/percov_conceal.md``) and a little on
        the six real experiments (``experiments/mimu_model_calibrate.md``).  False (CLI
        ``--no-angular-jerk``): the jerk alone, as before.
    acc_blocks : with ``model``, when its report has accelerometer blocks (``acc_scale`` findings of a
        recording the preparation could not calibrate): "fit" (default) — the triads' linear errors
        (3×3 and offset) with a Gaussian tolerance centred by the report's blocks: their deviations from
        their mean integrated out of the likelihood, the part they share cut (drawn from the prior onto
        the chains' draws), the tolerance by type-II ML (:mod:`accel_bayes.model.acc_block_marginal`);
        a pair (τ_M, τ_b) — that tolerance (matrix entries, 1; offsets, m/s²; e.g. a datasheet's);
        "fixed" — the blocks inverted as exact (before this option: the posterior then ignores
        their estimation error, ``experiments/percov_blind_acc.md``).  Recorded in
        ``settings["model"]["acc_blocks"]``.  CLI ``--acc-blocks {fit,fixed,TAU_M,TAU_B}``.
    phi_prior : the prior on φ_t = [ω̇_t; s_t] (angular acceleration, specific force) that the
        likelihood integrates out (:mod:`accel_bayes.model.phi_prior`).  "empirical" (default) — a
        zero-mean Gaussian whose 6×6 covariance is the type-II ML estimate from the recording
        (with the noise the chains use); it removes the inward pull of the flat prior's
        −(T/2)·log|M(θ)| (demo configuration: array scale 0.99812 ± 0.00034 flat, 0.99978 ±
        0.00032 empirical, 0.99990 ± 0.00031 for the log|M|-free reference;
        experiments/phi_prior_probe.md).  "flat" — [C21] as published (DESIGN §4; what the paper
        reproductions use).  A :class:`~accel_bayes.model.phi_prior.PhiPrior`, (σ_ω̇ rad/s²,
        σ_s m/s²), six stds or a (6, 6) covariance — that prior.  What was used is in
        ``settings["phi_prior"]``.
    proposal : "rw" (Gaussian random walk only, [C21] eq. 27 with a shaped covariance),
        "mixture" (random walk mixed with independence moves from the Laplace approximation or
        the warm-up moments), "auto" (mixture when a MAP is used, else rw).
    independence_prob : probability of an independence move in "mixture" (default 0.8; warm-up
        uses at most 0.5 so the random walk's step size adapts).
    target_accept_prob : random-walk acceptance targeted in warm-up (default 0.15).
    checkpoint, checkpoint_every, resume : see :func:`accel_bayes.inference.mcmc.run_pmmh` and
        :func:`~accel_bayes.inference.mcmc.run_pmmh_until` (a resume continues bit-exactly, also
        in the middle of a block; a run stopped by ``max_draws``/``max_seconds`` can be resumed with
        larger ones, which are not part of the settings a resume must match).
    device : where the chains run — None or "cpu" (default), or a torch device such as "cuda".
        Only step 6 (the PmMH chains: likelihood estimates, prior, proposals, the chains'
        generators) moves there; loading, preparation, noise, MAP and summary stay on the CPU, and
        the draws come back to the CPU.  On another device the generators differ, so the same
        seed gives other (equally valid) draws than on the CPU.  Not with ``checkpoint``.
        Recorded in ``settings["device"]``.
    threads : torch CPU threads for the whole call (default 1, restored afterwards; None leaves
        torch's setting): the tensors are small, and on a shared 2-core machine two threads made
        one likelihood estimate 100× slower (:mod:`accel_bayes.threads`).  Results do not depend
        on it beyond floating-point reduction order.
    """

    chains: int = DEFAULTS["chains"]
    draws: int | None = DEFAULTS["draws"]
    warmup: int = DEFAULTS["warmup"]
    max_draws: int = DEFAULTS["max_draws"]
    check_every: int = DEFAULTS["check_every"]
    rhat_max: float = DEFAULTS["rhat_max"]
    ess_min: float | None = DEFAULTS["ess_min"]
    max_seconds: float | None = DEFAULTS["max_seconds"]
    num_draws: int | None = None
    seed: int = 0
    prior: str = DEFAULTS["prior"]
    prior_std: float = DEFAULTS["prior_std"]
    use_map: bool = True
    init: str = "auto"
    gyro_method: str = DEFAULTS["gyro_method"]
    select: Any = None
    drop_clipped: bool = DEFAULTS["drop_clipped"]
    proposal: str = "auto"
    independence_prob: float | None = None
    target_accept_prob: float = DEFAULTS["target_accept_prob"]
    checkpoint: Any = None
    checkpoint_every: int = 0
    resume: bool = False
    intrinsics: Any = DEFAULTS["intrinsics"]
    drop_static: bool = DEFAULTS["drop_static"]
    min_rotation: float | None = DEFAULTS["min_rotation"]
    noise: str = DEFAULTS["noise"]
    noise_bins: int = DEFAULTS["noise_bins"]
    noise_inflation: bool | None = DEFAULTS["noise_inflation"]
    phi_prior: Any = DEFAULTS["phi_prior"]
    threads: int | None = DEFAULTS["threads"]
    correlation: Any = DEFAULTS["correlation"]
    model: Any = None
    instant_error: bool = False
    angular_jerk: bool = DEFAULTS["angular_jerk"]
    acc_blocks: Any = DEFAULTS["acc_blocks"]
    device: Any = None

    def __post_init__(self):
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 — normalising a frozen record's own fields
        set_("chains", _int_option("chains", self.chains, 1))
        set_("draws", None if self.draws is None else _int_option("draws", self.draws, 1))
        set_("warmup", _int_option("warmup", self.warmup, 0))
        set_("seed", _int_option("seed", self.seed, 0))
        set_("checkpoint_every", _int_option("checkpoint_every", self.checkpoint_every, 0))
        set_("max_draws", _int_option("max_draws", self.max_draws, 1))
        set_("check_every", _int_option("check_every", self.check_every, 1))
        set_("rhat_max", _real_option("rhat_max", self.rhat_max, 1.0, "R-hat threshold"))
        if self.ess_min is not None:
            set_("ess_min", _real_option("ess_min", self.ess_min, 0.0, "effective draws, all chains together"))
        set_("max_seconds", _real_option("max_seconds", self.max_seconds, 0.0, "seconds", allow_none=True))
        if self.num_draws is not None:
            set_("num_draws", _int_option("num_draws", self.num_draws, 1))
        if self.prior not in PRIORS:
            raise UserError(f"prior: expected one of {PRIORS}, got {self.prior!r}")
        try:
            ps = float(self.prior_std)
        except (TypeError, ValueError):
            raise UserError(f"prior_std: expected a positive number (metres), got {self.prior_std!r}") from None
        if not (ps > 0 and math.isfinite(ps)):
            raise UserError(f"prior_std: expected a positive number (metres), got {self.prior_std!r}")
        set_("prior_std", ps)
        if self.gyro_method not in GYRO_METHODS:
            raise UserError(f"gyro_method: expected one of {GYRO_METHODS}, got {self.gyro_method!r}")
        if self.proposal not in PROPOSALS:
            raise UserError(f"proposal: expected one of {PROPOSALS}, got {self.proposal!r}")
        if self.init not in INITS:
            raise UserError(f"init: expected 'auto', 'map' or 'prior', got {self.init!r}")
        c = self.correlation
        if not (isinstance(c, str) and c == "auto"):
            if isinstance(c, bool) or not isinstance(c, (int, float, np.floating)) or not 0.0 <= float(c) < 1.0:
                raise UserError(f"correlation: expected 'auto' or a number in [0, 1), got {c!r}")
            set_("correlation", float(c))
        if self.independence_prob is not None and not 0.0 <= float(self.independence_prob) < 1.0:
            raise UserError(f"independence_prob: expected a number in [0, 1), got {self.independence_prob!r}")
        set_("target_accept_prob", float(self.target_accept_prob))
        if (self.checkpoint_every or self.resume) and self.checkpoint is None:
            raise UserError("checkpoint: --checkpoint-every/--resume need a checkpoint file")
        if self.noise not in NOISE_MODES:
            raise UserError(f"noise: expected one of {NOISE_MODES}, got {self.noise!r}")
        set_("noise_bins", _int_option("noise_bins", self.noise_bins, 1))
        if isinstance(self.select, str) and self.select != "rotation":
            raise UserError(f"select: expected None, a mask, indices or 'rotation', got {self.select!r}")
        if isinstance(self.phi_prior, str):
            if self.phi_prior not in PHI_PRIOR_CHOICES:
                raise UserError(f"phi_prior: expected one of {PHI_PRIOR_CHOICES} or a prior covariance, "
                                f"got {self.phi_prior!r}")
        else:
            self._given_phi_prior()  # refuses a malformed prior here, before the recording is read
        if not (isinstance(self.phi_prior, str) and self.phi_prior == "flat") and self.noise_bins > 1:
            raise UserError("phi_prior: a proper prior on φ needs noise_bins=1 (the rate-bin rescaling of the samples "
                            "assumes φ free); pass phi_prior='flat' (CLI --phi-prior flat) with --noise-bins > 1")
        if self.threads is not None and (isinstance(self.threads, bool) or not isinstance(self.threads, int)
                                         or self.threads < 1):
            raise UserError(f"threads: expected an integer >= 1 or None, got {self.threads!r}")
        if self.model is not None and self.gyro_method not in ("auto", "calibrated"):
            # the model's fused gyro posterior replaces the "calibrated" one
            raise UserError(f"gyro_method: a model's gyro posterior replaces 'calibrated'; expected 'auto' or "
                            f"'calibrated' with model, got {self.gyro_method!r}")
        if self.instant_error and self.model is None:
            raise UserError("instant_error: the triads' instant-error term needs a model (--model REPORT.json)")
        set_("acc_blocks", _acc_blocks_option(self.acc_blocks))
        for name in ("use_map", "drop_clipped", "drop_static", "resume", "instant_error", "angular_jerk"):
            set_(name, bool(getattr(self, name)))

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_args(cls, args, **given) -> "CalibrateOptions":
        """The record of ``accel-bayes calibrate``'s parsed arguments (argparse namespace);
        ``given`` adds what the command decides itself (``checkpoint``: the file in ``--out``)."""
        return cls(
            chains=args.chains, draws=args.draws, warmup=args.warmup, num_draws=args.num_draws,
            max_draws=args.max_draws, check_every=args.check_every, max_seconds=args.max_seconds,
            rhat_max=args.rhat_max, ess_min=args.ess_min, seed=args.seed, prior=args.prior, prior_std=args.prior_std,
            use_map=not args.no_map, gyro_method=args.gyro_method, select=args.select, proposal=args.proposal,
            checkpoint_every=args.checkpoint_every, resume=args.resume, intrinsics=args.intrinsics,
            drop_static=not args.keep_static, drop_clipped=not args.keep_clipped, min_rotation=args.min_rotation,
            noise=args.noise, noise_bins=args.noise_bins, noise_inflation=False if args.no_noise_inflation else None,
            phi_prior=args.phi_prior, threads=args.threads, correlation=args.correlation, model=args.model,
            instant_error=args.instant_error, angular_jerk=_angular_jerk_arg(args),
            acc_blocks=getattr(args, "acc_blocks", DEFAULTS["acc_blocks"]),
            device=args.device, **given)

    # ------------------------------------------------------------------ derived values

    @property
    def ess_target(self) -> float:
        """The ESS threshold in effect: ``ess_min``, or 100 per chain when it is None."""
        return float(ESS_PER_CHAIN * self.chains) if self.ess_min is None else self.ess_min

    @property
    def inflate_noise(self) -> bool:
        """Whether the estimated noise is tempered by the sandwich factor: ``noise_inflation``, or
        when None, True without a model and False with one (then measured, not applied)."""
        return (self.model is None) if self.noise_inflation is None else bool(self.noise_inflation)

    def noise_mode(self, has_rests: bool, unexplained: bool) -> str:
        """The noise mode the run uses: ``noise`` itself unless "auto", then "estimate" when the
        recording has rests or the model's report has an ``unexplained`` finding, "stated" otherwise.

        Why the finding and not any report: ``unexplained`` is the detector saying that the stated σ
        with its effects does not explain the misfit, and ``calibrate --model`` skips it because the
        fitted noise level covers it — without rests the stated σ did not, and there is no κ with a
        model (the 7 concealed clock recordings without rests: sandwich/Laplace std ratio 6–10 per
        channel, error/std RMS 9.1, ``experiments/noise_auto.md``).  A report without it keeps the
        stated σ: on a simulation whose stated σ is the truth the model's terms explain the misfit,
        and an estimated level would absorb what the terms leave out (``experiments/noise_auto.md``:
        a report without findings on the wander simulation, κ 12.6 → 2.6)."""
        if self.noise != "auto":
            return self.noise
        return "estimate" if has_rests or unexplained else "stated"

    def _given_phi_prior(self):
        from ..model.phi_prior import PhiPrior  # torch: only for a prior given as numbers

        return PhiPrior.coerce(self.phi_prior)

    # ------------------------------------------------------------------ provenance and resume

    def to_settings(self, *, gyro_method: str, noise: str, min_rotation) -> dict:
        """The options' entries of the provenance settings (``positions.json``
        ``provenance.settings``), in their order there, with what the recording resolved:
        ``gyro_method`` and ``noise`` the modes "auto" became, ``min_rotation`` the threshold the
        preparation applied (rad/s)."""
        return {
            "chains": self.chains, "draws": self.draws, "warmup": self.warmup, "seed": self.seed,
            "prior": self.prior, "prior_std": self.prior_std, "gyro_method": gyro_method,
            "select": self.select if (self.select is None or isinstance(self.select, str)) else "mask",
            "drop_clipped": self.drop_clipped, "drop_static": self.drop_static, "min_rotation": min_rotation,
            "intrinsics": self.intrinsics if isinstance(self.intrinsics, (str, bool)) or self.intrinsics is None
            else "given",
            "noise": noise, "noise_bins": self.noise_bins if noise == "estimate" else None,
            "noise_inflation": self.inflate_noise if noise == "estimate" else None,
        }

    def fingerprint(self, recording_sha256: str, *, model_sha256: str | None = None) -> dict:
        """What a run depends on, known before any computation: the package version, the
        recording's SHA-256 and the options that change the draws (not the budgets
        ``max_draws``/``max_seconds``, which a resume may raise, nor, with fixed ``draws``, the
        convergence criteria).  A resumed checkpoint must hold the same (plain JSON values; the
        layout of 0.2.0's checkpoints)."""
        from .. import __version__

        options = {"chains": self.chains, "draws": self.draws, "warmup": self.warmup, "seed": self.seed}
        if self.draws is None:
            options.update(check_every=self.check_every, rhat_max=self.rhat_max, ess_min=self.ess_target)
        if self.num_draws is not None:
            options["num_draws"] = self.num_draws
        options.update(
            correlation=self.correlation, device=None if self.device is None else str(self.device),
            prior=self.prior, prior_std=self.prior_std, use_map=self.use_map, init=self.init,
            gyro_method=self.gyro_method, select=_select_key(self.select), drop_clipped=self.drop_clipped,
            proposal=self.proposal, independence_prob=self.independence_prob,
            target_accept_prob=self.target_accept_prob,
            intrinsics=self.intrinsics if isinstance(self.intrinsics, (str, bool, os.PathLike))
            or self.intrinsics is None else _intrinsics_key(self.intrinsics),
            drop_static=self.drop_static, min_rotation=self.min_rotation, noise=self.noise,
            noise_bins=self.noise_bins, noise_inflation=self.inflate_noise,
            phi_prior=self.phi_prior if isinstance(self.phi_prior, str)
            else self._given_phi_prior().cov.flatten().tolist())
        if model_sha256 is not None:  # only with a model: the request of a run without one is unchanged
            options["model"] = model_sha256
            if self.instant_error:  # only when asked: the request of a model run without it is unchanged
                options["instant_error"] = True
            if self.angular_jerk:  # only when on: a checkpoint of a model run without it stays resumable
                options["angular_jerk"] = True
        return json.loads(json.dumps({"version": __version__, "recording": recording_sha256, "options": options},
                                     default=str))
