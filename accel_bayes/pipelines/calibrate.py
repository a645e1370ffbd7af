"""Posterior calibration of the accelerometer-triad positions with PmMH ([C21]; DESIGN §2, §5, §7.3).

:func:`calibrate` strings the stages together for one recording:

0. real-data preprocessing (:mod:`accel_bayes.prep.preprocess`): intrinsic calibration from the
   recording's own rests, then dropping static, clipped and non-rotating samples; and, for such
   recordings, the accelerometer noise model estimated from the data (:mod:`accel_bayes.model.noise`:
   a level per triad × a factor per gyro-rate bin, type-II ML at the MAP, and the sandwich
   inflation for what the model still misses).  On a recording without rests (e.g. simulated
   twisting) the intrinsics are skipped with a note and the stated noise is used;
1. the Rao-Blackwellized likelihood (:class:`~accel_bayes.model.likelihood.RaoBlackwellLikelihood`,
   [C21] eq. 26 with the −½ power of DESIGN §4) with the chosen gyro posterior and sample
   selection;
2. the prior on θ (Gaussian, σ_r = 3 mm by default, [C21] §IV-A; or a box of the same std);
3. optionally the MAP and its Laplace covariance (:mod:`accel_bayes.inference.map`): a central
   θ for choosing N, over-dispersed chain starts, the random-walk shape and an independence
   proposal;
4. N, the number of Monte Carlo draws per likelihood estimate, chosen so that Var[log p̂] ≈ 1
   at the central θ ([C21] §III-C, accepted range 0.1–3); where that needs N > 1, instead the
   correlated pseudo-marginal kernel with N = 1 and a correlation ρ of successive estimates
   measured at the central θ (Deligiannidis, Doucet & Pitt 2018);
5. C chains of :class:`~accel_bayes.inference.mcmc.PMMHKernel` (warm-up adaptation, then a
   fixed exact kernel), crash-safe when a checkpoint file is given; by default continued until
   every coordinate has R̂ < 1.01 and bulk and tail ESS ≥ 400, checked every 500 draws per chain,
   up to 20 000 draws per chain (:func:`~accel_bayes.inference.mcmc.run_pmmh_until`), or a fixed
   number of draws when ``draws`` is given;
6. ArviZ diagnostics and the DESIGN §7.3 ``positions.json``.

:func:`write_outputs` writes ``posterior.nc``, ``summary.csv``, ``positions.json`` and the plots.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from .. import __version__
from .. import diagnostics as dg
from ..data import positions as _positions_mod
from ..errors import UserError
from ..inference.mcmc import PMMHKernel, PMMHRun, check_checkpoint_request, read_checkpoint, run_pmmh, \
    run_pmmh_until
from ..inference.mcmc.priors import BoxPrior, GaussianPrior
from ..inference.noise_fit import fit_map_tempered, fit_map_with_noise, sandwich_inflation
from ..model.draw_tuning import choose_correlation, choose_num_draws
from ..model.gyro_posterior import GyroPosterior
from ..model.likelihood import RaoBlackwellLikelihood, positions_from_theta
from ..model.noise import NOISE_MODES, scale_samples
from ..model.phi_prior import PHI_PRIOR_CHOICES, PhiPrior, empirical_phi_prior
from ..model.tempering import TemperedLikelihood
from ..threads import torch_threads
from .calibrate_defaults import DEFAULTS
from ..data.outputs import to_jsonable, write_text
from ..prep.preprocess import preprocess
from ..data.io import load_recording

__all__ = ["calibrate", "CalibrationResult", "write_outputs", "positions_document", "DEFAULTS"]

# Defaults: pipelines/calibrate_defaults.py (torch-free: the command line's --help shows them).

# Upper bound on N·T when N is chosen automatically: one estimate then costs at most ~0.1 s here.
# Far from the posterior (e.g. at the prior mean of a long recording) Var[log p̂] can need a huge
# N; the chains do not stay there, so the cap only costs some stickiness early in warm-up.
NUM_DRAWS_BUDGET = 300_000

# Correlated pseudo-marginal defaults (correlation="auto", Deligiannidis, Doucet & Pitt 2018): when
# the automatic N of fresh-draw PmMH exceeds 1, the chains instead carry the estimator's normals z
# and move them by z' = ρz + √(1−ρ²)ε with N = CPM_NUM_DRAWS; ρ is set from seeded draws at the
# central θ so that Var[log p̂(θ, z') − log p̂(θ, z)] ≈ CPM_TARGET_VAR (likelihood.choose_correlation).
CPM_NUM_DRAWS = 1
CPM_TARGET_VAR = 1.0

_PRIORS = ("gaussian", "box")
_GYRO_METHODS = ("auto", "sample_cov", "sample_cov_mean", "calibrated")
_PROPOSALS = ("auto", "rw", "mixture")


@dataclass
class CalibrationResult:
    """What :func:`calibrate` returns.

    idata : ``az.InferenceData`` (posterior ``r`` (chain, draw, imu, axis), m, relative to the
        reference triad; sample stats; log-likelihood estimates).
    summary : pandas DataFrame from :func:`accel_bayes.diagnostics.summarize` (R̂, ESS, MCSE).
    positions : the DESIGN §7.3 ``positions.json`` document (a dict).
    settings : every setting used (including the N chosen and its variance table).
    seconds : wall time of the whole calibration.
    run : the :class:`~accel_bayes.inference.mcmc.PMMHRun` (draws and per-draw statistics).
    map_result : the MAP result when one was used, else None.
    array : the :class:`~accel_bayes.physics.arrays.SensorArray` of the recording (for plots).
    """

    idata: object
    summary: object
    positions: dict
    settings: dict
    seconds: float
    run: PMMHRun
    map_result: object = None
    array: object = None
    input_sha256: str | None = None
    extra: dict = field(default_factory=dict)


# ---------------------------------------------------------------------------- validation

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


def _validate(chains, draws, warmup, num_draws, seed, prior, prior_std, gyro_method, checkpoint,
              checkpoint_every, resume, proposal, independence_prob, init, noise, noise_bins, select,
              max_draws, check_every, rhat_max, ess_min, max_seconds, phi_prior, correlation="auto"):
    """Every option of :func:`calibrate`, checked once before the recording is read; returns the
    integer options as ints (``num_draws`` only when given; ``draws`` None: run until converged)."""
    out = {
        "chains": _int_option("chains", chains, 1),
        "draws": None if draws is None else _int_option("draws", draws, 1),
        "warmup": _int_option("warmup", warmup, 0),
        "seed": _int_option("seed", seed, 0),
        "checkpoint_every": _int_option("checkpoint_every", checkpoint_every, 0),
        "max_draws": _int_option("max_draws", max_draws, 1),
        "check_every": _int_option("check_every", check_every, 1),
        "rhat_max": _real_option("rhat_max", rhat_max, 1.0, "R-hat threshold"),
        # None: 100 per chain (``chains`` is checked above: the literal is evaluated in order)
        "ess_min": float(dg.ESS_PER_CHAIN * int(chains)) if ess_min is None
        else _real_option("ess_min", ess_min, 0.0, "effective draws, all chains together"),
        "max_seconds": _real_option("max_seconds", max_seconds, 0.0, "seconds", allow_none=True),
    }
    if num_draws is not None:
        out["num_draws"] = _int_option("num_draws", num_draws, 1)
    if prior not in _PRIORS:
        raise UserError(f"prior: expected one of {_PRIORS}, got {prior!r}")
    try:
        ps = float(prior_std)
    except (TypeError, ValueError):
        raise UserError(f"prior_std: expected a positive number (metres), got {prior_std!r}") from None
    if not (ps > 0 and math.isfinite(ps)):
        raise UserError(f"prior_std: expected a positive number (metres), got {prior_std!r}")
    if gyro_method not in _GYRO_METHODS:
        raise UserError(f"gyro_method: expected one of {_GYRO_METHODS}, got {gyro_method!r}")
    if proposal not in _PROPOSALS:
        raise UserError(f"proposal: expected one of {_PROPOSALS}, got {proposal!r}")
    if init not in ("auto", "map", "prior"):
        raise UserError(f"init: expected 'auto', 'map' or 'prior', got {init!r}")
    if not (isinstance(correlation, str) and correlation == "auto"):
        if isinstance(correlation, bool) or not isinstance(correlation, (int, float, np.floating)) \
                or not 0.0 <= float(correlation) < 1.0:
            raise UserError(f"correlation: expected 'auto' or a number in [0, 1), got {correlation!r}")
    out["correlation"] = correlation if isinstance(correlation, str) else float(correlation)
    if independence_prob is not None and not 0.0 <= float(independence_prob) < 1.0:
        raise UserError(f"independence_prob: expected a number in [0, 1), got {independence_prob!r}")
    if (out["checkpoint_every"] or resume) and checkpoint is None:
        raise UserError("checkpoint: --checkpoint-every/--resume need a checkpoint file")
    if noise not in NOISE_MODES:
        raise UserError(f"noise: expected one of {NOISE_MODES}, got {noise!r}")
    out["noise_bins"] = _int_option("noise_bins", noise_bins, 1)
    if isinstance(select, str) and select != "rotation":
        raise UserError(f"select: expected None, a mask, indices or 'rotation', got {select!r}")
    if isinstance(phi_prior, str):
        if phi_prior not in PHI_PRIOR_CHOICES:
            raise UserError(f"phi_prior: expected one of {PHI_PRIOR_CHOICES} or a prior covariance, got {phi_prior!r}")
    else:
        PhiPrior.coerce(phi_prior)  # refuses a malformed prior here, before the recording is read
    if not (isinstance(phi_prior, str) and phi_prior == "flat") and out["noise_bins"] > 1:
        raise UserError("phi_prior: a proper prior on φ needs noise_bins=1 (the rate-bin rescaling of the samples "
                        "assumes φ free); pass phi_prior='flat' (CLI --phi-prior flat) with --noise-bins > 1")
    return out


def _device_option(device, checkpoint):
    """The chains' device: None (the default path, on the CPU), else a usable ``torch.device``;
    refused with a one-line error when torch cannot allocate there."""
    if device is None:
        return None
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise UserError(f"device: expected a torch device such as 'cpu' or 'cuda', got {device!r}") from None
    try:
        torch.empty(1, device=dev)
    except Exception as exc:  # noqa: BLE001 — whatever torch raises, the device is not usable here
        raise UserError(f"device: {str(dev)!r} is not usable here ({str(exc).splitlines()[0]})") from None
    # an explicit "cpu" takes the device path too (its draws equal the default path's, bit for bit:
    # tests/mcmc/test_device.py), and keeps checkpoints
    if checkpoint is not None and dev.type != "cpu":
        raise UserError(f"checkpoint: not supported with device={str(dev)!r} (checkpoints hold CPU chain states)")
    return dev


def _data_fingerprint(lik) -> str:
    h = hashlib.sha256()
    for t in (lik.acc, lik.omega.mean, lik.omega.cov, lik.acc_noise_std):
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def _recording_hash(rec) -> str:
    """SHA-256 of an in-memory recording's data (a file's is :func:`accel_bayes.data.io.recording_sha256`)."""
    h = hashlib.sha256()
    for x in (rec.time, rec.acc, rec.gyro, rec.nominal_position, rec.nominal_orientation, rec.acc_noise_std,
              rec.gyro_noise_std, rec.acc_clipped, rec.gyro_clipped, rec.acc_flagged, rec.gyro_flagged):
        if x is not None:
            h.update(np.ascontiguousarray(np.asarray(x)).tobytes())
    return h.hexdigest()


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


def prop_planned(proposal: str, lap) -> str:
    """The proposal "auto" resolves to: the mixture when a Laplace covariance exists, else rw."""
    return ("mixture" if lap is not None else "rw") if proposal == "auto" else proposal


# Per-θ work of one estimate that does not depend on N (projection, O(T·A)), in units of the
# per-draw work (O(T)): measured ≈ 0.8·A on the 2-core machine (32 IMUs: ~24 draws' worth).
OVERHEAD_PER_TRIAD = 0.8


def cost_aware_num_draws(N0: int, var0: float, A: int, max_draws: int = 100_000) -> int:
    """N for a sampler dominated by independence moves ([C21] §III-C range kept: Var 0.1–3).

    With Var[log p̂] = v0·N0/N (the 1/N law [C21] Fig. 2), an independence move with a good
    proposal is accepted with probability ≈ 2Φ(−σ/√2), σ² = Var[log p̂] (log-normal noise on
    both sides).  Cost per move ∝ N + 0.8·A (the N-independent projection work).  Returns the N
    minimising cost/acceptance over Var ∈ [0.1, 3] — deterministic (no timing), so the same seed
    still gives the same run."""
    from math import erf, sqrt

    def accept(var):
        return 1.0 + erf(-sqrt(var) / 2.0)  # 2Φ(−σ/√2) = 1 + erf(−σ/2)

    k = var0 * N0
    lo = max(1, int(math.ceil(k / 3.0)))
    hi = max(lo, min(int(max_draws), int(math.ceil(k / 0.1))))
    best, best_cost = N0, float("inf")
    for N in range(lo, hi + 1):
        c = (N + OVERHEAD_PER_TRIAD * A) / accept(k / N)
        if c < best_cost - 1e-12:
            best, best_cost = N, c
    return best


def _fit_map(lik, nominal_acc, prior_std, settings):
    """MAP and Laplace covariance (:mod:`accel_bayes.inference.map`), or None (with the reason in
    ``settings["map_failed"]``) when it is unavailable, diverged or has no usable covariance."""
    try:
        from ..inference.map import fit_map
    except ImportError as exc:  # pragma: no cover - depends on the installed package
        warnings.warn(f"use_map: accel_bayes.inference.map unavailable ({exc}); chains start from the prior")
        settings["map_failed"] = f"unavailable: {exc}"
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        res = fit_map(lik.acc, lik.omega.mean, lik.omega.cov, lik.acc_noise_std, reference=lik.reference,
                      prior_mean=nominal_acc, prior_std=prior_std, on_divergence="ignore", phi_prior=lik.phi_prior)
    return _usable_map(res, settings)


def _usable_map(res, settings):
    """``res`` if its θ is finite and its Laplace covariance positive definite, else None (with a
    warning and the reason in ``settings["map_failed"]``; chains then start from prior draws)."""
    cov = torch.as_tensor(res.laplace_cov, dtype=torch.float64)
    ok = bool(torch.isfinite(cov).all()) and int(torch.linalg.cholesky_ex(0.5 * (cov + cov.T))[1]) == 0
    if not ok or not bool(torch.isfinite(torch.as_tensor(res.theta)).all()):
        msg = f"MAP not usable ({res.reason}); chains start from prior draws"
        warnings.warn(msg, RuntimeWarning)
        settings["map_failed"] = msg
        return None
    settings["map"] = {"converged": bool(res.converged), "reason": str(res.reason), "iterations": int(res.n_iter)}
    return res


def _estimate_noise(lik, nominal_acc, prior_std, bins, inflate, settings, phi_prior="flat"):
    """Fit the MAP with the data-estimated noise model (:mod:`accel_bayes.model.noise`); with
    ``inflate`` temper the likelihood by the sandwich factor κ.  Returns the likelihood the
    chains use (:class:`~accel_bayes.model.tempering.TemperedLikelihood` of the scaled samples), the MAP
    of exactly that target (or None if unusable) and the :class:`~accel_bayes.model.noise.NoiseModel`.

    ``phi_prior``: "flat", "empirical" or a given prior.  The noise levels are fitted with φ free
    (the REML update of :mod:`accel_bayes.model.noise`); an empirical prior is then estimated with
    those levels (its M⁻¹ correction depends on them), the MAP refitted under it (warm start),
    and the sandwich, the tempered MAP and the chains' likelihood all carry it."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        res, nm = fit_map_with_noise(lik.acc, lik.omega.mean, lik.omega.cov, lik.acc_noise_std,
                                     reference=lik.reference, prior_mean=nominal_acc, prior_std=prior_std, bins=bins)
    s_t = nm.sample_scale(lik.omega.mean.norm(dim=-1).cpu().numpy())
    acc_s, w_s, P_s = scale_samples(lik.acc, lik.omega.mean, lik.omega.cov, s_t)
    std = np.asarray(nm.std, dtype=np.float64)
    info = nm.to_dict()
    prior = _phi_prior_step(acc_s, w_s, std, nominal_acc, phi_prior, settings)
    if prior is not None and bool(torch.isfinite(torch.as_tensor(res.theta)).all()):
        from ..inference.map import fit_map

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            res = fit_map(acc_s, w_s, P_s, std, reference=lik.reference, prior_mean=nominal_acc, prior_std=prior_std,
                          init_positions=res.positions, init_omega=res.omega, on_divergence="ignore", phi_prior=prior)
    kappa = 1.0
    lap_ok = bool(torch.isfinite(torch.as_tensor(res.laplace_cov)).all())
    if inflate and lap_ok:
        sw = sandwich_inflation(acc_s, w_s, P_s, std, res, reference=lik.reference, prior_mean=nominal_acc,
                                prior_std=prior_std, phi_prior=prior)
        kappa = max(1.0, sw["kappa"])  # never narrower than the fitted model says
        info["sandwich"] = {"kappa": sw["kappa"], "applied": kappa, "lags": sw["lags"],
                            "std_ratio_median": float(np.median(sw["std_ratio"])),
                            "std_ratio_max": float(np.max(sw["std_ratio"]))}
        if kappa > 1.0:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                res = fit_map_tempered(acc_s, w_s, P_s, std * math.sqrt(kappa), kappa, reference=lik.reference,
                                       prior_mean=nominal_acc, prior_std=prior_std, init_positions=res.positions,
                                       init_omega=res.omega, phi_prior=prior)
    elif inflate:
        info["sandwich"] = {"kappa": None, "applied": 1.0, "why": "no Laplace covariance at the MAP"}
    info["tempering"] = (("likelihood^(1/kappa): Gaussian exponent via std x sqrt(kappa)"
                          + (" and the phi prior's F x kappa" if prior is not None else "")
                          + ", Occam term (T/2) log|M| weighted 1/kappa") if kappa > 1.0 else None)
    info["std_used"] = [float(v) for v in std * math.sqrt(kappa)]
    settings["noise_model"] = info
    new = TemperedLikelihood(acc_s, GyroPosterior(w_s, P_s, lik.omega.method), std * math.sqrt(kappa), 1, kappa,
                             reference=lik.reference, dtype=lik.dtype, device=lik.device, phi_prior=prior)
    new.imu_labels, new.gyro_labels = lik.imu_labels, lik.gyro_labels
    new.sample_index, new.nominal_positions = lik.sample_index, lik.nominal_positions
    return new, _usable_map(res, settings), nm


# ---------------------------------------------------------------------------- main entry

def calibrate(
    recording,
    *,
    chains: int = DEFAULTS["chains"],
    draws: int | None = DEFAULTS["draws"],
    warmup: int = DEFAULTS["warmup"],
    max_draws: int = DEFAULTS["max_draws"],
    check_every: int = DEFAULTS["check_every"],
    rhat_max: float = DEFAULTS["rhat_max"],
    ess_min: float | None = DEFAULTS["ess_min"],
    max_seconds: float | None = DEFAULTS["max_seconds"],
    num_draws: int | None = None,
    seed: int = 0,
    prior: str = DEFAULTS["prior"],
    prior_std: float = DEFAULTS["prior_std"],
    use_map: bool = True,
    init: str = "auto",
    gyro_method: str = DEFAULTS["gyro_method"],
    select=None,
    drop_clipped: bool = DEFAULTS["drop_clipped"],
    proposal: str = "auto",
    independence_prob: float | None = None,
    target_accept_prob: float = DEFAULTS["target_accept_prob"],
    progress: bool = True,
    checkpoint=None,
    checkpoint_every: int = 0,
    resume: bool = False,
    callback=None,
    intrinsics="auto",
    drop_static: bool = DEFAULTS["drop_static"],
    min_rotation: float | None = DEFAULTS["min_rotation"],
    noise: str = DEFAULTS["noise"],
    noise_bins: int = DEFAULTS["noise_bins"],
    noise_inflation: bool | None = DEFAULTS["noise_inflation"],
    phi_prior=DEFAULTS["phi_prior"],
    threads: int | None = DEFAULTS["threads"],
    correlation=DEFAULTS["correlation"],
    model=None,
    device=None,
) -> CalibrationResult:
    """Sample the posterior of the accelerometer-triad positions of one recording with PmMH.

    recording : a :class:`~accel_bayes.data.recording.Recording` or a path to a format-v1 file.
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
        model error during motion), "stated" otherwise (simulations whose stated σ is the
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
    progress : tqdm bars (stderr) with the acceptance rate.
    checkpoint, checkpoint_every, resume : see :func:`accel_bayes.inference.mcmc.run_pmmh` and
        :func:`~accel_bayes.inference.mcmc.run_pmmh_until` (a resume continues bit-exactly, also
        in the middle of a block; a run stopped by ``max_draws``/``max_seconds`` can be resumed with
        larger ones, which are not part of the settings a resume must match).
    callback : ``callback(chain, iteration, kernel)`` after every iteration.
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

    Returns a :class:`CalibrationResult`.
    """
    with torch_threads(threads):  # small tensors: one thread is faster on a shared machine (accel_bayes.threads)
        t0 = time.perf_counter()
        # Steps: options (checked once, here, before the file is read: DESIGN §7.5 refuses early),
        # 1 load, 2 prepare, 3 noise, 4 MAP, 5 central θ and N, 6 posterior, 7 summary; writing the
        # files is :func:`write_outputs`.
        opts = _validate(chains, draws, warmup, num_draws, seed, prior, prior_std, gyro_method, checkpoint,
                         checkpoint_every, resume, proposal, independence_prob, init, noise, noise_bins, select,
                         max_draws, check_every, rhat_max, ess_min, max_seconds, phi_prior, correlation)
        noise_bins = opts["noise_bins"]
        opts["device"] = _device_option(device, checkpoint)
        cmodel = _model_option(model, gyro_method)
        if noise_inflation is None:
            noise_inflation = cmodel is None  # with a model: measured, not applied
        raw, sha, src = _load_step(recording)
        if cmodel is not None:
            cmodel.check_recording(raw)
        _check_resume(raw, sha, opts, checkpoint=checkpoint, resume=resume, prior=prior, prior_std=prior_std,
                      use_map=use_map, init=init, gyro_method=gyro_method, select=select, drop_clipped=drop_clipped,
                      proposal=proposal, independence_prob=independence_prob, target_accept_prob=target_accept_prob,
                      intrinsics=intrinsics, drop_static=drop_static, min_rotation=min_rotation, noise=noise,
                      noise_bins=noise_bins, noise_inflation=noise_inflation, phi_prior=phi_prior,
                      model=None if cmodel is None else cmodel.sha256)
        # step 2, prepare: intrinsics and sample selection; then the likelihood, the prior and the settings
        pre, rec = _prepare_step(raw, intrinsics=intrinsics, drop_static=drop_static, drop_clipped=drop_clipped,
                                   min_rotation=min_rotation, select=select)
        noise_mode = ("estimate" if pre.has_rests else "stated") if noise == "auto" else noise
        gm = ("calibrated" if noise_mode == "estimate" else "sample_cov") if gyro_method == "auto" else gyro_method
        if cmodel is not None:
            gm = "calibrated"  # the model's fused posterior generalises it (model.report_terms)
        lik = RaoBlackwellLikelihood.from_recording(rec, num_draws=1, gyro_method=gm, selection=pre.selection)
        gyro_info = None
        if cmodel is not None:
            lik, gyro_info = _model_gyro_step(lik, rec, cmodel)
            gm = "model"
        array = raw.sensor_array()
        labels = list(lik.imu_labels)
        ref_label = labels[lik.reference]
        free_labels = [k for i, k in enumerate(labels) if i != lik.reference]
        nominal_acc = torch.as_tensor(np.asarray(rec.nominal_position)[labels], dtype=torch.float64)
        ps = float(prior_std)
        if prior == "gaussian":
            pri = GaussianPrior(nominal_acc, std=ps, reference=lik.reference)
        else:
            pri = BoxPrior.with_std(nominal_acc, std=ps, reference=lik.reference)

        settings = {
            "chains": opts["chains"], "draws": opts["draws"], "warmup": opts["warmup"], "seed": opts["seed"],
            "prior": prior, "prior_std": ps, "gyro_method": gm,
            "select": select if (select is None or isinstance(select, str)) else "mask",
            "drop_clipped": bool(drop_clipped), "drop_static": bool(drop_static),
            "min_rotation": pre.summary["samples"]["min_rotation"],
            "intrinsics": intrinsics if isinstance(intrinsics, (str, bool)) or intrinsics is None else "given",
            "noise": noise_mode, "noise_bins": noise_bins if noise_mode == "estimate" else None,
            "noise_inflation": bool(noise_inflation) if noise_mode == "estimate" else None,
            "T": lik.T, "A": lik.A, "imu_labels": labels, "reference_imu": ref_label,
            "samples": {"recording": int(rec.T), "used": int(lik.T)},
            "target_accept_prob": float(target_accept_prob),
            "preprocess": pre.summary,
        }
        if src is not None:
            settings["input"] = src
        extra = {"preprocess": pre}

        lik, map_res = _noise_step(lik, nominal_acc, ps, noise_mode, noise_bins, noise_inflation, settings, extra,
                                   phi_prior)
        map_res = _map_step(lik, nominal_acc, ps, noise_mode, use_map, map_res, settings)
        if cmodel is not None:
            settings["model"] = cmodel.describe()
            settings["model"]["gyro_posterior"] = gyro_info
            settings["model"]["sandwich"] = _sandwich_record(lik, map_res, nominal_acc, ps, free_labels)
        lik, theta_c, lap, N = _central_step(lik, pri, map_res, opts, proposal, settings)
        run = _posterior_step(lik, pri, theta_c, lap, opts, proposal=proposal, independence_prob=independence_prob,
                              init=init, target_accept_prob=target_accept_prob, settings=settings, request=opts["request"],
                              progress=progress, checkpoint=checkpoint, resume=resume, callback=callback)

        # step 7, summary: ArviZ diagnostics and the positions document
        idata = dg.to_inference_data(
            run.theta, free_labels, run.log_phat, log_prior=run.log_prior, accepted=run.accepted,
            accept_prob=run.accept_prob, step_size=run.step_size, reference_imu=ref_label,
            attrs={"method": "pmmh", "num_draws": int(N), "seed": opts["seed"], "accel_bayes_version": __version__},
        )
        summary = dg.summarize(idata)
        seconds = time.perf_counter() - t0
        _convergence_settings(run, opts, settings)
        settings["acceptance_rate"] = [float(a) for a in run.acceptance_rate]
        settings["step_size"] = [float(s) for s in run.step_size]
        settings["divergences"] = int(sum(len(d.get("divergences", [])) for d in run.diagnostics))
        positions = positions_document(idata, K=rec.K, reference_imu=ref_label, seconds=seconds, settings=settings,
                                       input_sha256=sha, seed=opts["seed"])
        return CalibrationResult(idata=idata, summary=summary, positions=positions, settings=settings, seconds=seconds,
                                 run=run, map_result=map_res, array=array, input_sha256=sha, extra=extra)


# ---------------------------------------------------------------------------- the steps of calibrate

def _load_step(recording):
    """Step 1, load: the recording (:func:`accel_bayes.data.io.load_recording`, gyroscopes
    required), its file's SHA-256 (None in memory) and its path as given (None in memory)."""
    loaded = load_recording(recording, require_gyro=True)
    raw = loaded.recording
    if raw.gyro is None or not raw.has_gyro.any():
        raise UserError("recording: has no gyroscope data; the [C21] likelihood needs gyroscopes")
    return raw, loaded.sha256(), None if loaded.path is None else str(loaded.path)


def _check_resume(raw, sha, opts, *, checkpoint, resume, prior, prior_std, use_map, init, gyro_method, select,
                  drop_clipped, proposal, independence_prob, target_accept_prob, intrinsics, drop_static,
                  min_rotation, noise, noise_bins, noise_inflation, phi_prior, model=None):
    """What the run depends on, known before any computation (stored in ``opts["request"]``): a
    resumed checkpoint is checked against it here, not after minutes of preprocessing and MAP."""
    # the budgets of the run-until-converged mode may change on resume (continue a run that hit
    # them); in the fixed mode the convergence criteria do not change the draws either
    skip = {"checkpoint_every", "noise_bins", "request", "max_draws", "max_seconds"}
    if opts["draws"] is not None:
        skip |= {"check_every", "rhat_max", "ess_min"}
    options = {k: v for k, v in opts.items() if k not in skip}
    options.update(
        prior=prior, prior_std=float(prior_std), use_map=bool(use_map), init=init, gyro_method=gyro_method,
        select=_select_key(select), drop_clipped=bool(drop_clipped), proposal=proposal,
        independence_prob=independence_prob, target_accept_prob=float(target_accept_prob),
        intrinsics=intrinsics if isinstance(intrinsics, (str, bool, os.PathLike)) or intrinsics is None
        else _intrinsics_key(intrinsics),
        drop_static=bool(drop_static), min_rotation=min_rotation, noise=noise, noise_bins=noise_bins,
        noise_inflation=bool(noise_inflation),
        phi_prior=phi_prior if isinstance(phi_prior, str) else PhiPrior.coerce(phi_prior).cov.flatten().tolist())
    if model is not None:  # only with a model: the request of a run without one is unchanged
        options["model"] = model
    request = json.loads(json.dumps({"version": __version__, "recording": sha or _recording_hash(raw),
                                     "options": options}, default=str))
    if resume and checkpoint is not None and Path(checkpoint).exists():
        check_checkpoint_request(read_checkpoint(checkpoint), request, checkpoint)
    opts["request"] = request


def _model_option(model, gyro_method):
    """The mismatch report of ``model`` read and checked (:func:`accel_bayes.model.report_terms.load_model`),
    or None.  Its fused gyro posterior replaces the "calibrated" one, so ``gyro_method`` must be
    "auto" or "calibrated"."""
    if model is None:
        return None
    if gyro_method not in ("auto", "calibrated"):
        raise UserError(f"gyro_method: a model's gyro posterior replaces 'calibrated'; expected 'auto' or "
                        f"'calibrated' with model, got {gyro_method!r}")
    from ..model.report_terms import load_model

    return load_model(model)


def _model_gyro_step(lik, rec, cmodel):
    """The likelihood with the model's gyro posterior (:func:`accel_bayes.model.report_terms.fused_gyro_posterior`)
    on the same samples, and a summary of what it changed: the median posterior std of ω per
    axis before and after, and the median share of the precision the gyros with a finding keep."""
    from ..model.report_terms import corrected_gyro_array, fused_gyro_posterior

    idx = np.asarray(lik.sample_index)
    glabels = list(lik.gyro_labels)
    gyro = rec.gyro_tensor("array", dtype=torch.float64)[torch.as_tensor(idx)][:, torch.as_tensor(glabels)]
    if cmodel.gyro_linear:  # the report's gyro linear blocks, inverted first
        q = np.asarray(rec.nominal_orientation, dtype=np.float64)[glabels]
        gyro = corrected_gyro_array(gyro, q, glabels, [(k, e) for _, k, e in cmodel.gyro_linear])
    gstd = np.asarray(rec.gyro_noise_std, dtype=np.float64)[glabels]
    time_s = np.asarray(rec.time, dtype=np.float64)[idx]
    effects = [(k, e) for _, k, e in cmodel.gyro_effects]
    omega, wdot = fused_gyro_posterior(gyro, gstd, glabels, time_s, effects)
    new = RaoBlackwellLikelihood(lik.acc, omega, lik.acc_noise_std, lik.num_draws, reference=lik.reference,
                                 dtype=lik.dtype, device=lik.device, phi_prior=lik.phi_prior)
    for name in ("imu_labels", "gyro_labels", "sample_index", "selection", "nominal_positions"):
        setattr(new, name, getattr(lik, name))
    sd = lambda P: float(torch.diagonal(P, dim1=-2, dim2=-1).sqrt().median())  # noqa: E731
    info = {"method": "model (precision-weighted fusion with per-sample gyro covariances)",
            "omega_std_median_rad_s": {"calibrated": sd(lik.omega.cov), "model": sd(omega.cov)},
            "omega_dot_norm_median_rad_s2": float(wdot.norm(dim=-1).median()),
            "omega_shift_rms_rad_s": float((omega.mean - lik.omega.mean).norm(dim=-1).pow(2).mean().sqrt())}
    return new, info


def _sandwich_record(lik, map_res, nominal_acc, prior_std, free_labels) -> dict:
    """The sandwich covariance at the MAP of the chains' likelihood against its Laplace covariance
    (:func:`accel_bayes.inference.noise_fit.sandwich_inflation`): per free coordinate the Laplace std, the
    sandwich std and their ratio (m, m, 1), κ and the lags — what the model still misses."""
    if map_res is None:
        return {"kappa": None, "why": "no usable MAP"}
    kappa = float(getattr(lik, "kappa", 1.0))
    std = lik.acc_noise_std
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        sw = sandwich_inflation(lik.acc, lik.omega.mean, lik.omega.cov, std, map_res, reference=lik.reference,
                                prior_mean=nominal_acc, prior_std=prior_std, phi_prior=lik.phi_prior)
    lap = np.sqrt(np.clip(np.diagonal(np.asarray(map_res.laplace_cov, dtype=np.float64)), 0, None))
    ratio = np.asarray(sw["std_ratio"], dtype=np.float64)
    names = [f"r[{k}, {a}]" for k in free_labels for a in dg.AXES]
    return {"kappa": float(sw["kappa"]), "lags": int(sw["lags"]), "tempering_applied": kappa,
            "std_ratio_max": float(ratio.max()), "std_ratio_median": float(np.median(ratio)),
            "coordinates": names, "laplace_std_m": [float(v) for v in lap],
            "sandwich_std_m": [float(v) for v in lap * ratio], "std_ratio": [float(v) for v in ratio]}


def _prepare_step(raw, *, intrinsics, drop_static, drop_clipped, min_rotation, select):
    """Step 2, prepare: intrinsics and THE sample selection (:func:`accel_bayes.prep.preprocess.preprocess`,
    the user's ``select`` ANDed in).  Returns (Preprocessed, recording); ``pre.selection`` is what
    the likelihood takes."""
    pre = preprocess(raw, intrinsics=intrinsics, drop_static=bool(drop_static), drop_clipped=bool(drop_clipped),
                     min_rotation=min_rotation, select=select)
    rec = pre.recording
    return pre, rec


def _noise_step(lik, nominal_acc, ps, noise_mode, noise_bins, noise_inflation, settings, extra, phi_prior):
    """Step 3, noise and the prior on φ: with ``noise_mode`` "estimate" the noise model fitted with
    the MAP (and the tempered likelihood of that target, :func:`_estimate_noise`); "stated" keeps
    the recording's.  Either way the prior on φ (:func:`_phi_prior_step`) is set with the noise
    the chains use.  Returns (likelihood the chains use, the MAP of the estimated-noise target or
    None)."""
    if noise_mode != "estimate":
        prior = _phi_prior_step(lik.acc, lik.omega.mean, lik.acc_noise_std, nominal_acc, phi_prior, settings)
        return lik.with_phi_prior(prior), None
    lik, map_res, nm = _estimate_noise(lik, nominal_acc, ps, noise_bins, bool(noise_inflation), settings,
                                       phi_prior=phi_prior)
    extra["noise"] = nm
    return lik, map_res


def _phi_prior_step(acc, omega_mean, acc_noise_std, nominal_acc, phi_prior, settings):
    """The prior on φ_t = [ω̇_t; s_t] the chains use (:mod:`accel_bayes.model.phi_prior`): None for
    "flat" ([C21]), the type-II ML estimate at the nominal design for "empirical" (default), or
    the given one.  Recorded in ``settings["phi_prior"]`` (positions.json provenance)."""
    if isinstance(phi_prior, str) and phi_prior == "flat":
        settings["phi_prior"] = {"source": "flat"}
        return None
    if isinstance(phi_prior, str):
        prior = empirical_phi_prior(acc, omega_mean, acc_noise_std, nominal_acc)
    else:
        prior = PhiPrior.coerce(phi_prior)
    settings["phi_prior"] = prior.describe()
    return prior


def _map_step(lik, nominal_acc, ps, noise_mode, use_map, noise_map, settings):
    """Step 4, MAP: with estimated noise the noise step's MAP is already the MAP of the chains'
    target (kept when ``use_map``); with the stated noise it is fitted here.  None: no MAP."""
    if noise_mode == "estimate":
        map_res = noise_map if use_map else None
    else:
        map_res = _fit_map(lik, nominal_acc, ps, settings) if use_map else None
    settings["use_map"] = map_res is not None
    return map_res


def _central_step(lik, pri, map_res, opts, proposal, settings):
    """Step 5, central θ and N: the MAP (or prior mean) and its Laplace covariance, and the
    number of draws per likelihood estimate ([C21] §III-C).  Sets ``lik.num_draws``."""
    if map_res is not None:
        theta_c = torch.as_tensor(map_res.theta, dtype=torch.float64).reshape(lik.A - 1, 3)
        lap = torch.as_tensor(map_res.laplace_cov, dtype=torch.float64)
        lap = 0.5 * (lap + lap.T)
    else:
        theta_c = pri.mean.clone()
        lap = None
    if "num_draws" in opts:
        N, table = opts["num_draws"], []
    else:
        N, table = choose_num_draws(lik, positions_from_theta(theta_c, lik.reference, lik.A), target=1.0,
                                    seed=opts["seed"], max_draws=max(64, NUM_DRAWS_BUDGET // lik.T))
        # (a variance below 0.1 at N = 1 only means the estimate is nearly exact: nothing to fix)
        if table and not 0.1 <= table[-1]["var"] <= 3.0 and not (N == 1 and table[-1]["var"] < 0.1):
            msg = (f"num_draws: Var[log p̂] = {table[-1]['var']:.3g} at N = {N} (wanted 0.1–3; "
                   f"{'MAP' if map_res is not None else 'prior mean'} as central θ)")
            warnings.warn(msg, RuntimeWarning)
            settings["num_draws_warning"] = msg
    if table and prop_planned(proposal, lap) == "mixture" and "num_draws" not in opts:
        N2 = cost_aware_num_draws(int(table[-1]["num_draws"]), float(table[-1]["var"]), lik.A,
                                  max_draws=max(64, NUM_DRAWS_BUDGET // lik.T))
        if N2 != N:
            settings["num_draws_rule"] = (f"Var[log p̂]·N ≈ {table[-1]['var'] * table[-1]['num_draws']:.3g}: "
                                          f"N = {N2} (predicted Var {table[-1]['var'] * table[-1]['num_draws'] / N2:.2g}) "
                                          "minimises cost/acceptance of independence moves")
            N = N2
    rho, rho_table = _correlation_step(lik, theta_c, opts, table, N, settings)
    if rho > 0 and opts["correlation"] == "auto":
        N = CPM_NUM_DRAWS
    settings["correlation"] = float(rho)
    settings["correlation_table"] = rho_table
    lik.num_draws = int(N)
    settings["num_draws"] = int(N)
    settings["num_draws_auto"] = "num_draws" not in opts
    settings["var_log_phat"] = [{"num_draws": int(r["num_draws"]), "var": float(r["var"])} for r in table]
    return lik, theta_c, lap, N


def _correlation_step(lik, theta_c, opts, table, N, settings):
    """ρ of the correlated pseudo-marginal kernel and its measurement table.  "auto": when N was
    chosen automatically and came out above 1 (a noisy estimator), ρ from
    :func:`~accel_bayes.model.draw_tuning.choose_correlation` at the central θ with N = CPM_NUM_DRAWS
    (the caller then uses that N); otherwise 0 — fresh draws, the chains of earlier versions.
    A number: that ρ with the N chosen as before."""
    c = opts["correlation"]
    if c != "auto":
        return float(c), []
    if "num_draws" in opts or not table or int(N) <= 1 or not hasattr(lik, "sample_z"):
        return 0.0, []
    pos = positions_from_theta(theta_c, lik.reference, lik.A)
    rho, rows = choose_correlation(lik, pos, CPM_NUM_DRAWS, target=CPM_TARGET_VAR, seed=opts["seed"])
    if rho > 0:
        settings["correlation_rule"] = (
            f"fresh draws would need N = {int(N)}; correlated pseudo-marginal with N = {CPM_NUM_DRAWS} and "
            f"rho = {rho:.6g} (Var[log p-hat(theta, z') - log p-hat(theta, z)] = {rows[-1]['var']:.3g} at the "
            f"central theta, target {CPM_TARGET_VAR:g})")
    return rho, [{k: float(v) for k, v in r.items()} for r in rows]


def _posterior_step(lik, pri, theta_c, lap, opts, *, proposal, independence_prob, init, target_accept_prob,
                    settings, request, progress, checkpoint, resume, callback):
    """Step 6, posterior: the proposal, the chain starts, the PmMH kernel and its C chains
    (:func:`accel_bayes.inference.mcmc.run_pmmh`, crash-safe with a checkpoint)."""
    prop = proposal
    if prop == "auto":
        prop = "mixture" if lap is not None else "rw"
    p_ind = (DEFAULTS["independence_prob"] if independence_prob is None else float(independence_prob)) \
        if prop == "mixture" else 0.0
    settings["proposal"] = prop
    settings["independence_prob"] = p_ind
    g = torch.Generator().manual_seed(int(opts["seed"]) * 7919 + 17)
    C = opts["chains"]
    start = init if init != "auto" else ("map" if lap is not None else "prior")
    settings["init"] = start
    if start == "map" and lap is None:
        raise UserError("init: 'map' needs the MAP (use_map=True and accel_bayes.inference.map available)")
    if start == "map":
        L = torch.linalg.cholesky(lap)
        eps = torch.randn(C, lik.A - 1, 3, generator=g, dtype=torch.float64)
        init_theta = theta_c + DEFAULTS["start_overdispersion"] * (eps.reshape(C, -1) @ L.T).reshape(C, lik.A - 1, 3)
        # keep starts inside a box prior's support
        lp = pri.log_prob(init_theta)
        init_theta = torch.where(torch.isfinite(lp)[:, None, None], init_theta, theta_c.expand_as(init_theta))
        settings["start"] = f"Laplace draws around the MAP, ×{DEFAULTS['start_overdispersion']}"
    else:
        init_theta = pri.sample((C,), generator=g)
        settings["start"] = "prior draws"
    dev = opts.get("device")
    lik_cpu = lik
    if dev is not None:  # only the chains run on the device (tests/mcmc/test_device.py: no stray CPU tensors)
        lik, pri = lik.to(dev), pri.to(dev)
        theta_c, init_theta = theta_c.to(dev), init_theta.to(dev)
        lap = None if lap is None else lap.to(dev)
    if lap is not None:
        kernel = PMMHKernel(lik, pri, seed=opts["seed"], proposal_cov=lap, target_accept_prob=float(target_accept_prob),
                            independence_prob=p_ind, correlation=float(settings.get("correlation", 0.0)),
                            independence_mean=theta_c if p_ind > 0 else None,
                            independence_cov=lap if p_ind > 0 else None)
    else:
        kernel = PMMHKernel(lik, pri, seed=opts["seed"], target_accept_prob=float(target_accept_prob),
                            independence_prob=p_ind, correlation=float(settings.get("correlation", 0.0)))

    fingerprint = {k: v for k, v in settings.items() if k not in ("var_log_phat", "input")}
    fingerprint["data_sha256"] = _data_fingerprint(lik_cpu)
    fingerprint["version"] = __version__
    fingerprint["request"] = request
    fingerprint = json.loads(json.dumps(fingerprint))
    # after the fingerprint: CPU checkpoints of earlier versions stay resumable (a device run has none)
    settings["device"] = "cpu" if dev is None else str(dev)
    if opts["draws"] is not None:
        run = run_pmmh(kernel, opts["draws"], opts["warmup"], C, init_theta, progress=progress,
                       checkpoint=checkpoint, checkpoint_every=opts["checkpoint_every"], resume=resume,
                       fingerprint=fingerprint, callback=callback)
        return run if dev is None else _run_on_cpu(run)
    names = _coordinate_names(settings["imu_labels"], lik.reference)

    def check(theta):
        return dg.convergence_check(theta.cpu(), rhat_max=opts["rhat_max"], ess_min=opts["ess_min"], names=names)

    run = run_pmmh_until(kernel, check, opts["warmup"], C, init_theta, check_every=opts["check_every"],
                         max_samples=opts["max_draws"], max_seconds=opts["max_seconds"], progress=progress,
                         checkpoint=checkpoint, checkpoint_every=opts["checkpoint_every"], resume=resume,
                         fingerprint=fingerprint, callback=callback)
    return run if dev is None else _run_on_cpu(run)


def _run_on_cpu(run):
    """The chains' draws and statistics back on the CPU (the summary and ArviZ work there)."""
    import dataclasses

    return dataclasses.replace(run, **{f.name: getattr(run, f.name).cpu() for f in dataclasses.fields(run)
                                       if isinstance(getattr(run, f.name), torch.Tensor)})


def _coordinate_names(imu_labels, reference: int) -> list[str]:
    """``r[imu, axis]`` of the free coordinates, in θ's order (the rows of ``summary.csv``)."""
    return [f"r[{k}, {a}]" for i, k in enumerate(imu_labels) if i != reference for a in dg.AXES]


# why a run ended, in words (settings["convergence"]["stopped"] holds the key)
_STOPPED = {"converged": "converged", "max_samples": "the draw budget (max_draws) was spent",
            "max_seconds": "the wall-clock budget (max_seconds) was spent; the number of draws depends on the "
                           "machine's speed", "fixed": "fixed number of draws"}


def _convergence_settings(run, opts, settings) -> None:
    """``settings["draws"]`` (the draws per chain it took) and ``settings["convergence"]``: the
    criteria, the mode and budgets, the number of checks, why the run stopped and every check."""
    auto = opts["draws"] is None
    stopped = "max_draws" if run.stopped == "max_samples" else (run.stopped or "fixed")
    settings["draws"] = run.num_samples
    settings["convergence"] = {
        "mode": "until converged" if auto else "fixed draws",
        "criteria": {"rhat_max": opts["rhat_max"], "ess_bulk_min": opts["ess_min"], "ess_tail_min": opts["ess_min"],
                     "rule": "every coordinate: R-hat < rhat_max, bulk ESS >= ess_min and tail ESS >= ess_min "
                             "(ESS over all chains)"},
        "check_every": opts["check_every"] if auto else None,
        "max_draws": opts["max_draws"] if auto else None,
        "max_seconds": opts["max_seconds"] if auto else None,
        "draws": run.num_samples,
        "checks": len(run.checks),
        "stopped": stopped,
        "why": _STOPPED["max_samples" if stopped == "max_draws" else stopped],
        "history": [dict(c) for c in run.checks],
    }


def positions_document(idata, *, K: int, reference_imu: int, seconds: float, settings: dict,
                       input_sha256: str | None, seed: int) -> dict:
    """The DESIGN §7.3 document for a PmMH posterior (built by :mod:`accel_bayes.data.positions`, the
    one writer of the format): every IMU sorted by label, posterior mean/std/cov of its triad
    position relative to the reference IMU (array frame, m; zeros for the reference), R̂/ESS
    diagnostics (``converged`` and ``warnings`` by :func:`accel_bayes.diagnostics.convergence_check`
    with the criteria of ``settings["convergence"]`` (default R̂ < 1.01, bulk and tail ESS ≥ 400);
    R̂/ESS are null where they cannot be computed; the draws per chain, the number of checks and
    why the run stopped) and provenance.  IMUs without an accelerometer triad get null moments."""
    mom = dg.posterior_moments(idata)
    means = np.zeros((int(K), 3))
    covs = np.zeros((int(K), 3, 3))
    estimated = set(mom["imu"]) | {int(reference_imu)}
    for i, lab in enumerate(mom["imu"]):
        means[lab] = mom["mean"][i]
        covs[lab] = mom["cov"][i]
    for k in range(int(K)):
        if k not in estimated:  # no accelerometer triad: nothing to report (null in JSON)
            means[k] = np.nan
            covs[k] = np.nan
    conv = settings.get("convergence") or {}
    crit = conv.get("criteria") or {}
    x = idata.posterior[dg.VAR]
    names = [f"r[{int(i)}, {a}]" for i in x.coords["imu"].values for a in x.coords["axis"].values]
    chk = dg.convergence_check(x.values, rhat_max=crit.get("rhat_max", dg.RHAT_MAX),
                               ess_min=crit.get("ess_bulk_min", dg.ESS_MIN), names=names)
    reasons = list(chk.failed)
    if reasons and conv.get("stopped") in ("max_draws", "max_seconds"):
        reasons.append(f"stopped unconverged after {conv.get('draws')} draws per chain and {conv.get('checks')} "
                       f"checks: {conv.get('why')}")
    diagnostics = {
        "rhat_max": to_jsonable(float(chk.rhat_max), nonfinite="null"),
        "ess_bulk_min": to_jsonable(float(chk.ess_bulk_min), nonfinite="null"),
        # added keys (§7.3 allows them): False with the reasons when R̂/ESS fail the rule, DESIGN §7.5 status 4
        "ess_tail_min": to_jsonable(float(chk.ess_tail_min), nonfinite="null"),
        "converged": not reasons,
        "warnings": reasons,
        "criteria": {"rhat_max": chk.rhat_limit, "ess_min": chk.ess_min},
        "draws_per_chain": int(x.sizes["draw"]),
        "checks": conv.get("checks"),
        "stopped": conv.get("stopped"),
        "seconds": float(seconds),
        "acceptance_rate": settings.get("acceptance_rate"),
        "num_draws": settings.get("num_draws"),
    }
    provenance = {"version": __version__, "input_sha256": input_sha256, "seed": int(seed),
                  "settings": json.loads(json.dumps(settings, default=str))}
    return _positions_mod.positions_document(method="pmmh", reference_imu=int(reference_imu), means=means,
                                             covs=covs, diagnostics=diagnostics, provenance=provenance)


def write_outputs(result: CalibrationResult, out_dir, *, plots: bool = True, truth=None) -> dict:
    """Write ``posterior.nc``, ``summary.csv``, ``positions.json`` and (``plots``) trace.png,
    rank.png, autocorr.png, ellipses.png into ``out_dir``, each file atomically; returns
    {name: path}.  ``truth``: (K, 3) true positions relative to the reference, m, drawn in
    ellipses.png where known (a simulation's).  The CLI passes the staging directory of an
    :class:`accel_bayes.data.outputs.OutputDir`, so that the files appear in ``--out`` as one set."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out: {out} exists and is not a directory")
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    paths["posterior"] = dg.save(result.idata, out / "posterior.nc")
    paths["summary"] = write_text(out / "summary.csv", result.summary.to_csv())
    paths["positions"] = _positions_mod.write_positions(result.positions, out / "positions.json")
    if plots and result.array is not None:
        for q in dg.save_plots(result.idata, result.array, out, prior_std=result.settings.get("prior_std"),
                               truth=truth):
            paths[q.stem] = q
    return paths
