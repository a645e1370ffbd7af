"""The steps of :func:`accel_bayes.pipelines.calibrate.calibrate` and the records they return
(issue #26: steps return small frozen records instead of writing into one settings dict).

Step 1 load (:func:`_load_step`), the resume check (:func:`_check_resume`), 2 prepare
(:func:`_prepare_step`: intrinsics and THE sample selection), 3 noise (:func:`_noise_step`: the
noise model, the sandwich tempering, the prior on φ), 4 MAP (:func:`_map_step`), 5 central θ, N
and ρ (:func:`_central_step`), 6 chain starts and chains (:func:`_start_step`,
:func:`_chains_step`); ``calibrate`` strings them together and assembles the provenance settings
from each record's ``settings()``.  Split from ``calibrate.py`` to keep both under 600 lines.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .. import __version__
from ..diagnostics import arviz_calls as dg_az, stats as dg_stats
from ..data.io import load_recording
from ..errors import UserError
from ..inference.mcmc import PMMHKernel, check_checkpoint_request, read_checkpoint, run_pmmh, run_pmmh_until
from ..inference.noise_fit import fit_map_tempered, fit_map_with_noise, sandwich_inflation
from ..model.draw_tuning import choose_correlation, choose_num_draws
from ..model.gyro_posterior import GyroPosterior
from ..model.likelihood import RaoBlackwellLikelihood, positions_from_theta
from ..model.noise import scale_samples
from ..model.phi_prior import PhiPrior, empirical_phi_prior
from ..model.tempering import TemperedLikelihood
from ..prep.preprocess import preprocess
from .calibrate_defaults import DEFAULTS
from .calibrate_options import CalibrateOptions

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


# ---------------------------------------------------------------------------- hashes and N

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


# ---------------------------------------------------------------------------- what the steps return
# Each step returns one of these; :func:`calibrate` alone assembles the provenance settings from
# their ``settings()``, in the order the keys have always had in positions.json.

@dataclass(frozen=True)
class MapFit:
    """A MAP fit as the chains may use it: ``result`` (the :class:`~accel_bayes.inference.map`
    result, or None when unavailable, diverged or without a usable Laplace covariance) and its
    provenance entry ``{"map": {converged, reason, iterations}}`` or ``{"map_failed": why}``."""

    result: object
    record: dict


@dataclass(frozen=True)
class TemperStep:
    """The sandwich tempering of the estimated noise: ``kappa`` (≥ 1, the likelihood's power is
    1/κ; 1: none), ``result`` the MAP of the tempered target (the untempered one when κ = 1) and
    ``record`` the entries it adds to ``noise_model`` (``sandwich``, ``tempering``, ``std_used``,
    m/s²)."""

    kappa: float
    result: object
    record: dict


@dataclass(frozen=True)
class NoiseStep:
    """Step 3: the likelihood the chains use (``lik``), the prior on φ's provenance
    (``phi_prior``), and with estimated noise the :class:`~accel_bayes.model.noise.NoiseModel`
    (``noise``), its provenance (``noise_model``) and the MAP of exactly that target (``map``)."""

    lik: object
    phi_prior: dict
    noise: object = None
    noise_model: dict | None = None
    map: MapFit | None = None

    def settings(self) -> dict:
        out = {"phi_prior": self.phi_prior}
        if self.noise_model is not None:
            out["noise_model"] = self.noise_model
        if self.map is not None:
            out.update(self.map.record)
        return out


@dataclass(frozen=True)
class MapStep:
    """Step 4: the MAP the later steps use (``result``, None: none) and its provenance."""

    result: object
    record: dict

    def settings(self) -> dict:
        return {**self.record, "use_map": self.result is not None}


@dataclass(frozen=True)
class DrawsStep:
    """Step 5: the central θ (``theta``, (A−1, 3), m) and its Laplace covariance (``laplace``, or
    None), N draws per likelihood estimate and how it was chosen (``table``: Var[log p̂] per N
    tried; ``warning``, ``rule``), and ρ of the correlated kernel with its table and rule."""

    theta: object
    laplace: object
    num_draws: int
    auto: bool
    table: list
    correlation: float
    correlation_table: list
    warning: str | None = None
    rule: str | None = None
    correlation_rule: str | None = None

    def settings(self) -> dict:
        out = {}
        if self.warning is not None:
            out["num_draws_warning"] = self.warning
        if self.rule is not None:
            out["num_draws_rule"] = self.rule
        if self.correlation_rule is not None:
            out["correlation_rule"] = self.correlation_rule
        out.update(correlation=float(self.correlation), correlation_table=self.correlation_table,
                   num_draws=int(self.num_draws), num_draws_auto=self.auto,
                   var_log_phat=[{"num_draws": int(r["num_draws"]), "var": float(r["var"])} for r in self.table])
        return out


@dataclass(frozen=True)
class StartStep:
    """Step 6a: the proposal the chains use, the probability of an independence move, the chain
    starts (``init``: "map" or "prior"; ``theta``: (C, A−1, 3), m) and how they were drawn."""

    proposal: str
    independence_prob: float
    init: str
    start: str
    theta: object

    def settings(self) -> dict:
        return {"proposal": self.proposal, "independence_prob": self.independence_prob, "init": self.init,
                "start": self.start}


# ---------------------------------------------------------------------------- MAP and noise

def _fit_map(lik, nominal_acc, prior_std) -> MapFit:
    """MAP and Laplace covariance (:mod:`accel_bayes.inference.map`), or a :class:`MapFit` without
    a result (the reason in its record) when it is unavailable, diverged or has no usable covariance."""
    try:
        from ..inference.map import fit_map
    except ImportError as exc:  # pragma: no cover - depends on the installed package
        warnings.warn(f"use_map: accel_bayes.inference.map unavailable ({exc}); chains start from the prior")
        return MapFit(None, {"map_failed": f"unavailable: {exc}"})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        res = fit_map(lik.acc, lik.omega.mean, lik.omega.cov, lik.acc_noise_std, reference=lik.reference,
                      prior_mean=nominal_acc, prior_std=prior_std, on_divergence="ignore", phi_prior=lik.phi_prior)
    return _usable_map(res)


def _usable_map(res) -> MapFit:
    """``res`` if its θ is finite and its Laplace covariance positive definite, else no result
    (with a warning and the reason as ``map_failed``; chains then start from prior draws)."""
    cov = torch.as_tensor(res.laplace_cov, dtype=torch.float64)
    ok = bool(torch.isfinite(cov).all()) and int(torch.linalg.cholesky_ex(0.5 * (cov + cov.T))[1]) == 0
    if not ok or not bool(torch.isfinite(torch.as_tensor(res.theta)).all()):
        msg = f"MAP not usable ({res.reason}); chains start from prior draws"
        warnings.warn(msg, RuntimeWarning)
        return MapFit(None, {"map_failed": msg})
    return MapFit(res, {"map": {"converged": bool(res.converged), "reason": str(res.reason),
                                "iterations": int(res.n_iter)}})


def _estimate_noise(lik, nominal_acc, prior_std, bins, inflate, phi_prior="flat") -> NoiseStep:
    """Fit the MAP with the data-estimated noise model (:mod:`accel_bayes.model.noise`); with
    ``inflate`` temper the likelihood by the sandwich factor κ (:func:`_temper_step`).  Returns
    the likelihood the chains use (:class:`~accel_bayes.model.tempering.TemperedLikelihood` of the
    scaled samples), the MAP of exactly that target and the
    :class:`~accel_bayes.model.noise.NoiseModel`, as a :class:`NoiseStep`.

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
    prior, phi_record = _phi_prior_step(acc_s, w_s, std, nominal_acc, phi_prior)
    if prior is not None and bool(torch.isfinite(torch.as_tensor(res.theta)).all()):
        res, start = _prior_map(acc_s, w_s, P_s, std, res, lik.reference, nominal_acc, prior_std, prior)
        if start["start"] == "nominal":  # recorded where it changes the result: elsewhere the settings stay as they were
            phi_record["map_start"] = start
    temper = _temper_step(acc_s, w_s, P_s, std, res, lik.reference, nominal_acc, prior_std, prior, inflate)
    kappa = temper.kappa
    new = TemperedLikelihood(acc_s, GyroPosterior(w_s, P_s, lik.omega.method), std * math.sqrt(kappa), 1, kappa,
                             reference=lik.reference, dtype=lik.dtype, device=lik.device, phi_prior=prior,
                             prepared=lik.prepared)
    return NoiseStep(lik=new, phi_prior=phi_record, noise=nm, noise_model={**nm.to_dict(), **temper.record},
                     map=_usable_map(temper.result))


#: nats by which the refit from the nominal design must beat the warm start to replace it: LM
#: round-off between two fits of one mode is far below this, a different mode far above
MODE_MARGIN_NATS = 1.0


def _prior_map(acc_s, w_s, P_s, std, flat, reference, nominal_acc, prior_std, prior):
    """The MAP under the proper φ prior, fitted from the flat-φ MAP ``flat`` (warm start) and from
    the nominal design; the one with the higher log posterior (the nominal start only where it wins
    by more than :data:`MODE_MARGIN_NATS`).  Returns (result, record): the record names the start kept
    ("flat_map" or "nominal") and both log posteriors (nats, θ-free constants dropped).

    Why two starts: under the flat prior the Occam term −(T/2)·log|M(θ)| falls by 3 nats per sample
    for each e-fold the array shrinks (M's ω̇ block scales with |θ|²); where the fitted noise is as
    large as the centripetal signal (vibration and impacts, concealed clock recordings clock-001,
    -002, -009, -010, -018, -019) it outweighs the data and the flat MAP collapses to θ ≈ 0, and the
    proper-prior refit warm-started there stops in a reflected (scale −0.6…−0.85) or mis-sized
    (×0.5, ×1.6, ×2.1) mode thousands of nats below the one reached from the design
    (``experiments/vibgeom_probe.md``)."""
    from ..inference.map import fit_map

    fits = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for name, init, init_w in (("flat_map", flat.positions, flat.omega), ("nominal", nominal_acc, None)):
            fits.append((name, fit_map(acc_s, w_s, P_s, std, reference=reference, prior_mean=nominal_acc,
                                       prior_std=prior_std, init_positions=init, init_omega=init_w,
                                       on_divergence="ignore", phi_prior=prior)))
    (_, warm), (_, nom) = fits
    record = {"log_posterior": {name: float(f.log_posterior) for name, f in fits}}
    ok = math.isfinite(nom.log_posterior) and bool(torch.isfinite(torch.as_tensor(nom.theta)).all())
    if ok and (not math.isfinite(warm.log_posterior) or nom.log_posterior > warm.log_posterior + MODE_MARGIN_NATS):
        return nom, {"start": "nominal", **record}
    return warm, {"start": "flat_map", **record}


def _temper_step(acc_s, w_s, P_s, std, res, reference, nominal_acc, prior_std, prior, inflate) -> TemperStep:
    """With ``inflate``: κ, the average variance inflation of the sandwich covariance at the MAP
    ``res`` (never below 1: never narrower than the fitted model says), and the MAP refitted
    under the likelihood tempered by 1/κ; without, κ = 1 and ``res`` as it is."""
    kappa, record = 1.0, {}
    lap_ok = bool(torch.isfinite(torch.as_tensor(res.laplace_cov)).all())
    if inflate and lap_ok:
        sw = sandwich_inflation(acc_s, w_s, P_s, std, res, reference=reference, prior_mean=nominal_acc,
                                prior_std=prior_std, phi_prior=prior)
        kappa = max(1.0, sw["kappa"])
        record["sandwich"] = {"kappa": sw["kappa"], "applied": kappa, "lags": sw["lags"],
                              "std_ratio_median": float(np.median(sw["std_ratio"])),
                              "std_ratio_max": float(np.max(sw["std_ratio"]))}
        if kappa > 1.0:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                res = fit_map_tempered(acc_s, w_s, P_s, std * math.sqrt(kappa), kappa, reference=reference,
                                       prior_mean=nominal_acc, prior_std=prior_std, init_positions=res.positions,
                                       init_omega=res.omega, phi_prior=prior)
    elif inflate:
        record["sandwich"] = {"kappa": None, "applied": 1.0, "why": "no Laplace covariance at the MAP"}
    record["tempering"] = (("likelihood^(1/kappa): Gaussian exponent via std x sqrt(kappa)"
                            + (" and the phi prior's F x kappa" if prior is not None else "")
                            + ", Occam term (T/2) log|M| weighted 1/kappa") if kappa > 1.0 else None)
    record["std_used"] = [float(v) for v in std * math.sqrt(kappa)]
    return TemperStep(kappa=kappa, result=res, record=record)


# ---------------------------------------------------------------------------- the steps of calibrate

def _load_step(recording):
    """Step 1, load: the recording (:func:`accel_bayes.data.io.load_recording`, gyroscopes
    required), its file's SHA-256 (None in memory) and its path as given (None in memory)."""
    loaded = load_recording(recording, require_gyro=True)
    raw = loaded.recording
    if raw.gyro is None or not raw.has_gyro.any():
        raise UserError("recording: has no gyroscope data; the [C21] likelihood needs gyroscopes")
    return raw, loaded.sha256(), None if loaded.path is None else str(loaded.path)


def _check_resume(raw, sha, opts: CalibrateOptions, model_sha) -> dict:
    """What the run depends on, known before any computation (:meth:`CalibrateOptions.fingerprint`):
    a resumed checkpoint is checked against it here, not after minutes of preprocessing and MAP.
    Returns it (the chains' fingerprint holds it as ``request``)."""
    request = opts.fingerprint(sha or _recording_hash(raw), model_sha256=model_sha)
    if opts.resume and opts.checkpoint is not None and Path(opts.checkpoint).exists():
        check_checkpoint_request(read_checkpoint(opts.checkpoint), request, opts.checkpoint)
    return request


def _model_option(model):
    """The mismatch report of ``model`` read and checked (:func:`accel_bayes.model.report_terms.load_model`),
    or None (its ``gyro_method`` is checked with the options)."""
    if model is None:
        return None
    from ..model.report_terms import load_model

    return load_model(model)


def _prepare_step(raw, opts: CalibrateOptions):
    """Step 2, prepare: intrinsics and THE sample selection (:func:`accel_bayes.prep.preprocess.preprocess`,
    the user's ``select`` ANDed in).  Returns the Preprocessed (its ``recording``, and its
    ``selection``, which the likelihood takes)."""
    return preprocess(raw, intrinsics=opts.intrinsics, drop_static=opts.drop_static, drop_clipped=opts.drop_clipped,
                      min_rotation=opts.min_rotation, select=opts.select)


def _noise_step(lik, nominal_acc, ps, noise_mode, opts: CalibrateOptions) -> NoiseStep:
    """Step 3, noise and the prior on φ: with ``noise_mode`` "estimate" the noise model fitted with
    the MAP (and the tempered likelihood of that target, :func:`_estimate_noise`); "stated" keeps
    the recording's.  Either way the prior on φ (:func:`_phi_prior_step`) is set with the noise
    the chains use."""
    if noise_mode != "estimate":
        prior, record = _phi_prior_step(lik.acc, lik.omega.mean, lik.acc_noise_std, nominal_acc, opts.phi_prior)
        return NoiseStep(lik=lik.with_phi_prior(prior), phi_prior=record)
    return _estimate_noise(lik, nominal_acc, ps, opts.noise_bins, opts.inflate_noise, phi_prior=opts.phi_prior)


def _phi_prior_step(acc, omega_mean, acc_noise_std, nominal_acc, phi_prior):
    """The prior on φ_t = [ω̇_t; s_t] the chains use (:mod:`accel_bayes.model.phi_prior`): None for
    "flat" ([C21]), the type-II ML estimate at the nominal design for "empirical" (default), or
    the given one; and its provenance entry (``settings["phi_prior"]``)."""
    if isinstance(phi_prior, str) and phi_prior == "flat":
        return None, {"source": "flat"}
    if isinstance(phi_prior, str):
        prior = empirical_phi_prior(acc, omega_mean, acc_noise_std, nominal_acc)
    else:
        prior = PhiPrior.coerce(phi_prior)
    return prior, prior.describe()


def _map_step(lik, nominal_acc, ps, noise_mode, use_map, noise_map: MapFit | None) -> MapStep:
    """Step 4, MAP: with estimated noise the noise step's MAP is already the MAP of the chains'
    target (kept when ``use_map``; its record is the noise step's); with the stated noise it is
    fitted here."""
    if noise_mode == "estimate":
        return MapStep(noise_map.result if use_map else None, {})
    if not use_map:
        return MapStep(None, {})
    fit = _fit_map(lik, nominal_acc, ps)
    return MapStep(fit.result, fit.record)


def _central_step(lik, pri, map_res, opts: CalibrateOptions) -> DrawsStep:
    """Step 5, central θ and N: the MAP (or prior mean) and its Laplace covariance, and the
    number of draws per likelihood estimate ([C21] §III-C)."""
    if map_res is not None:
        theta_c = torch.as_tensor(map_res.theta, dtype=torch.float64).reshape(lik.A - 1, 3)
        lap = torch.as_tensor(map_res.laplace_cov, dtype=torch.float64)
        lap = 0.5 * (lap + lap.T)
    else:
        theta_c = pri.mean.clone()
        lap = None
    given = opts.num_draws is not None
    warning = rule = None
    if given:
        N, table = opts.num_draws, []
    else:
        N, table = choose_num_draws(lik, positions_from_theta(theta_c, lik.reference, lik.A), target=1.0,
                                    seed=opts.seed, max_draws=max(64, NUM_DRAWS_BUDGET // lik.T))
        # (a variance below 0.1 at N = 1 only means the estimate is nearly exact: nothing to fix)
        if table and not 0.1 <= table[-1]["var"] <= 3.0 and not (N == 1 and table[-1]["var"] < 0.1):
            warning = (f"num_draws: Var[log p̂] = {table[-1]['var']:.3g} at N = {N} (wanted 0.1–3; "
                       f"{'MAP' if map_res is not None else 'prior mean'} as central θ)")
            warnings.warn(warning, RuntimeWarning)
    if table and prop_planned(opts.proposal, lap) == "mixture" and not given:
        N2 = cost_aware_num_draws(int(table[-1]["num_draws"]), float(table[-1]["var"]), lik.A,
                                  max_draws=max(64, NUM_DRAWS_BUDGET // lik.T))
        if N2 != N:
            rule = (f"Var[log p̂]·N ≈ {table[-1]['var'] * table[-1]['num_draws']:.3g}: "
                    f"N = {N2} (predicted Var {table[-1]['var'] * table[-1]['num_draws'] / N2:.2g}) "
                    "minimises cost/acceptance of independence moves")
            N = N2
    rho, rho_table, rho_rule = _correlation_step(lik, theta_c, opts, table, N)
    if rho > 0 and opts.correlation == "auto":
        N = CPM_NUM_DRAWS
    return DrawsStep(theta=theta_c, laplace=lap, num_draws=int(N), auto=not given, table=table, correlation=float(rho),
                     correlation_table=rho_table, warning=warning, rule=rule, correlation_rule=rho_rule)


def _correlation_step(lik, theta_c, opts: CalibrateOptions, table, N):
    """ρ of the correlated pseudo-marginal kernel, its measurement table and the rule that chose
    it (or None).  "auto": when N was chosen automatically and came out above 1 (a noisy
    estimator), ρ from :func:`~accel_bayes.model.draw_tuning.choose_correlation` at the central θ with
    N = CPM_NUM_DRAWS (the caller then uses that N); otherwise 0 — fresh draws, the chains of
    earlier versions.  A number: that ρ with the N chosen as before."""
    c = opts.correlation
    if c != "auto":
        return float(c), [], None
    if opts.num_draws is not None or not table or int(N) <= 1 or not hasattr(lik, "sample_z"):
        return 0.0, [], None
    pos = positions_from_theta(theta_c, lik.reference, lik.A)
    rho, rows = choose_correlation(lik, pos, CPM_NUM_DRAWS, target=CPM_TARGET_VAR, seed=opts.seed)
    rule = None
    if rho > 0:
        rule = (f"fresh draws would need N = {int(N)}; correlated pseudo-marginal with N = {CPM_NUM_DRAWS} and "
                f"rho = {rho:.6g} (Var[log p-hat(theta, z') - log p-hat(theta, z)] = {rows[-1]['var']:.3g} at the "
                f"central theta, target {CPM_TARGET_VAR:g})")
    return rho, [{k: float(v) for k, v in r.items()} for r in rows], rule


def _start_step(lik, pri, draws: DrawsStep, opts: CalibrateOptions) -> StartStep:
    """Step 6a: the proposal ("auto": the mixture when there is a Laplace covariance), the
    probability of an independence move and the C chain starts — Laplace draws around the MAP
    over-dispersed ×1.5 (kept inside a box prior's support), or prior draws (seeded)."""
    theta_c, lap = draws.theta, draws.laplace
    prop = prop_planned(opts.proposal, lap)
    p_ind = (DEFAULTS["independence_prob"] if opts.independence_prob is None else float(opts.independence_prob)) \
        if prop == "mixture" else 0.0
    g = torch.Generator().manual_seed(int(opts.seed) * 7919 + 17)
    C = opts.chains
    init = opts.init if opts.init != "auto" else ("map" if lap is not None else "prior")
    if init == "map" and lap is None:
        raise UserError("init: 'map' needs the MAP (use_map=True and accel_bayes.inference.map available)")
    if init == "map":
        L = torch.linalg.cholesky(lap)
        eps = torch.randn(C, lik.A - 1, 3, generator=g, dtype=torch.float64)
        theta = theta_c + DEFAULTS["start_overdispersion"] * (eps.reshape(C, -1) @ L.T).reshape(C, lik.A - 1, 3)
        lp = pri.log_prob(theta)
        theta = torch.where(torch.isfinite(lp)[:, None, None], theta, theta_c.expand_as(theta))
        how = f"Laplace draws around the MAP, ×{DEFAULTS['start_overdispersion']}"
    else:
        theta = pri.sample((C,), generator=g)
        how = "prior draws"
    return StartStep(proposal=prop, independence_prob=p_ind, init=init, start=how, theta=theta)


def _chains_fingerprint(settings: dict, lik, request: dict) -> dict:
    """What a checkpoint of these chains must match on resume: the settings so far (less the
    Var[log p̂] table and the input path), the hash of the data the chains see, the version and
    the request (:func:`_check_resume`)."""
    fingerprint = {k: v for k, v in settings.items() if k not in ("var_log_phat", "input")}
    fingerprint["data_sha256"] = _data_fingerprint(lik)
    fingerprint["version"] = __version__
    fingerprint["request"] = request
    return json.loads(json.dumps(fingerprint))


def _chains_step(lik, pri, draws: DrawsStep, start: StartStep, opts: CalibrateOptions, *, device, fingerprint,
                 names, progress, callback):
    """Step 6b, posterior: the PmMH kernel and its C chains (:func:`accel_bayes.inference.mcmc.run_pmmh`,
    or :func:`~accel_bayes.inference.mcmc.run_pmmh_until` until converged; crash-safe with a
    checkpoint).  On a ``device`` only the chains run there; the run comes back on the CPU."""
    theta_c, lap, init_theta = draws.theta, draws.laplace, start.theta
    p_ind = start.independence_prob
    if device is not None:  # only the chains run on the device (tests/test_device.py: no stray CPU tensors)
        lik, pri = lik.to(device), pri.to(device)
        theta_c, init_theta = theta_c.to(device), init_theta.to(device)
        lap = None if lap is None else lap.to(device)
    if lap is not None:
        kernel = PMMHKernel(lik, pri, seed=opts.seed, proposal_cov=lap, target_accept_prob=opts.target_accept_prob,
                            independence_prob=p_ind, correlation=draws.correlation,
                            independence_mean=theta_c if p_ind > 0 else None,
                            independence_cov=lap if p_ind > 0 else None)
    else:
        kernel = PMMHKernel(lik, pri, seed=opts.seed, target_accept_prob=opts.target_accept_prob,
                            independence_prob=p_ind, correlation=draws.correlation)
    common = dict(progress=progress, checkpoint=opts.checkpoint, checkpoint_every=opts.checkpoint_every,
                  resume=opts.resume, fingerprint=fingerprint, callback=callback)
    if opts.draws is not None:
        run = run_pmmh(kernel, opts.draws, opts.warmup, opts.chains, init_theta, **common)
    else:
        def check(theta):
            return dg_stats.convergence_check(theta.cpu(), rhat_max=opts.rhat_max, ess_min=opts.ess_target, names=names)

        run = run_pmmh_until(kernel, check, opts.warmup, opts.chains, init_theta, check_every=opts.check_every,
                             max_samples=opts.max_draws, max_seconds=opts.max_seconds, **common)
    return run if device is None else _run_on_cpu(run)


def _run_on_cpu(run):
    """The chains' draws and statistics back on the CPU (the summary and ArviZ work there)."""
    return dataclasses.replace(run, **{f.name: getattr(run, f.name).cpu() for f in dataclasses.fields(run)
                                       if isinstance(getattr(run, f.name), torch.Tensor)})


def _coordinate_names(imu_labels, reference: int) -> list[str]:
    """``r[imu, axis]`` of the free coordinates, in θ's order (the rows of ``summary.csv``)."""
    return [f"r[{k}, {a}]" for i, k in enumerate(imu_labels) if i != reference for a in dg_az.AXES]


# why a run ended, in words (settings["convergence"]["stopped"] holds the key)
_STOPPED = {"converged": "converged", "max_samples": "the draw budget (max_draws) was spent",
            "max_seconds": "the wall-clock budget (max_seconds) was spent; the number of draws depends on the "
                           "machine's speed", "fixed": "fixed number of draws"}


def _convergence_settings(run, opts: CalibrateOptions) -> dict:
    """``draws`` (the draws per chain it took) and ``convergence``: the criteria, the mode and
    budgets, the number of checks, why the run stopped and every check."""
    auto = opts.draws is None
    stopped = "max_draws" if run.stopped == "max_samples" else (run.stopped or "fixed")
    return {"draws": run.num_samples, "convergence": {
        "mode": "until converged" if auto else "fixed draws",
        "criteria": {"rhat_max": opts.rhat_max, "ess_bulk_min": opts.ess_target, "ess_tail_min": opts.ess_target,
                     "rule": "every coordinate: R-hat < rhat_max, bulk ESS >= ess_min and tail ESS >= ess_min "
                             "(ESS over all chains)"},
        "check_every": opts.check_every if auto else None,
        "max_draws": opts.max_draws if auto else None,
        "max_seconds": opts.max_seconds if auto else None,
        "draws": run.num_samples,
        "checks": len(run.checks),
        "stopped": stopped,
        "why": _STOPPED["max_samples" if stopped == "max_draws" else stopped],
        "history": [dict(c) for c in run.checks],
    }}
