"""The steps of ``calibrate --model report.json`` (:mod:`accel_bayes.model.report_terms`): the gyro
posterior with the report's random gyro effects and, when the report has an ``unresolved_motion``
finding, its angular acceleration loaded by the clocks' data ages (:func:`_model_gyro_step`); the
per-sample unresolved-jerk covariance in the accelerometer likelihood (:func:`_model_percov_step`,
issue #30); the accelerometers' linear errors integrated out (:func:`_model_block_step`); and the
sandwich of the chains' target at its mode (:func:`_sandwich_record`, :func:`_percov_sandwich_record`,
:func:`_block_sandwich_record`).  Split from ``calibrate_steps.py`` to keep both under 600 lines.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch

from ..diagnostics import arviz_calls as dg_az
from ..errors import UserError
from ..inference.noise_fit import sandwich_inflation, score_sandwich
from ..model.likelihood import RaoBlackwellLikelihood
from ..model.unresolved_fit import per_sample_scores


def _model_gyro_step(lik, rec, cmodel):
    """The likelihood with the model's gyro posterior (:func:`accel_bayes.model.report_terms.fused_gyro_posterior`)
    on the same samples, and a summary of what it changed: the median posterior std of ω per
    axis before and after, and the median share of the precision the gyros with a finding keep.
    Returns (likelihood, summary, :class:`~accel_bayes.model.report_terms.UnresolvedTerms` or None):
    with an ``unresolved_motion`` finding the report's clocks and scales at the samples, read at
    the bands of the "calibrated" |ω̄| (before the model changes ω̄); the clocks' mean effect is then
    taken off the accelerometer and gyro outputs (:func:`~accel_bayes.model.report_terms.clock_corrected`)
    and the angular acceleration enters the fused posterior."""
    from ..model.report_terms import clock_corrected, corrected_array, fused_gyro_posterior, unresolved_terms

    idx = np.asarray(lik.sample_index)
    glabels = list(lik.gyro_labels)
    gyro = rec.gyro_tensor("array", dtype=torch.float64)[torch.as_tensor(idx)][:, torch.as_tensor(glabels)]
    if cmodel.gyro_linear:  # the report's gyro linear blocks, inverted first
        q = np.asarray(rec.nominal_orientation, dtype=np.float64)[glabels]
        gyro = corrected_array(gyro, q, glabels, [(k, e) for _, k, e in cmodel.gyro_linear])
    gstd = np.asarray(rec.gyro_noise_std, dtype=np.float64)[glabels]
    time_s = np.asarray(rec.time, dtype=np.float64)[idx]
    effects = [(k, e) for _, k, e in cmodel.gyro_effects]
    rms = lambda d: float(d.square().sum(-1).mean().sqrt())  # noqa: E731
    acc0, shift = lik.acc, {}
    if cmodel.acc_linear:  # the report's accelerometer blocks, inverted first like the gyro blocks
        labels = list(lik.imu_labels)
        qa = np.asarray(rec.nominal_orientation, dtype=np.float64)[labels]
        acc0 = corrected_array(lik.acc, qa, labels, [(k, e) for _, k, e in cmodel.acc_linear if k in labels])
        shift["acc_linear_correction_rms_m_s2"] = rms(acc0 - lik.acc)
    terms, acc = None, acc0
    if cmodel.unresolved:
        terms = unresolved_terms(cmodel.report, time_s, list(lik.imu_labels), glabels, lik.omega.mean.norm(dim=-1))
        acc, gyro_c = clock_corrected(acc0, gyro, time_s, terms.age_acc, terms.age_gyro)
        shift["clock_mean_correction_rms"] = {"acc_m_s2": rms(acc - acc0), "gyro_rad_s": rms(gyro_c - gyro)}
        gyro = gyro_c
    omega, wdot = fused_gyro_posterior(gyro, gstd, glabels, time_s, effects,
                                       age=None if terms is None else terms.age_gyro,
                                       angular_acc_std=None if terms is None else terms.angular_acc_std,
                                       age_var=None if terms is None else terms.age_var_gyro)
    new = RaoBlackwellLikelihood(acc, omega, lik.acc_noise_std, lik.num_draws, reference=lik.reference,
                                 dtype=lik.dtype, device=lik.device, phi_prior=lik.phi_prior, prepared=lik.prepared)
    sd = lambda P: float(torch.diagonal(P, dim1=-2, dim2=-1).sqrt().median())  # noqa: E731
    info = {"method": "model (precision-weighted fusion with per-sample gyro covariances"
                      + ("; unresolved angular acceleration loaded by the centred data ages)" if terms else ")"),
            "omega_std_median_rad_s": {"calibrated": sd(lik.omega.cov), "model": sd(omega.cov)},
            "omega_dot_norm_median_rad_s2": float(wdot.norm(dim=-1).median()),
            "omega_shift_rms_rad_s": float((omega.mean - lik.omega.mean).norm(dim=-1).pow(2).mean().sqrt()), **shift}
    return new, info, terms


@dataclass
class PercovStep:
    """The chains' likelihood with the per-sample covariance (``lik``), its mode at ω̄ with the
    Laplace covariance (``positions`` (A, 3) m, ``laplace_cov`` m²) and the provenance ``record``."""

    lik: object
    positions: torch.Tensor
    laplace_cov: torch.Tensor
    record: dict


def _model_percov_step(lik, terms, omega_norm, sample_scale, map_res, nominal_acc, prior_std, *,
                       instant_error: bool = False, angular_jerk: bool = False) -> PercovStep:
    """The untempered likelihood of the noise step (``lik``: the samples already divided by the noise
    model's per-sample scale ``sample_scale`` (T,), 1 with the stated noise) with the report's
    unresolved jerk projected out per sample (:func:`accel_bayes.model.likelihood_percov.with_unresolved_motion`).

    The loading is each row's centred data age (``terms.age_acc``, s); the jerk's scale per |ω|
    band of the report (``omega_edges``, bands of the "calibrated" |ω̄| ``omega_norm`` rad/s) is
    fitted by type-II ML on this likelihood at the MAP's positions and ω̄
    (:func:`accel_bayes.model.unresolved_fit.fit_unresolved_scales`), with the noise levels kept:
    the detector's scales were fitted against its own white levels, and refitting the levels
    with the scales made the real board's std less honest (``experiments/percov_honesty_probe.md``,
    'σ refit').  In the scaled samples a band's scale s_b is the physical jerk s_b·s_t.

    ``instant_error`` (the ``instant_error`` option): also each triad's own instant error times its
    output rate, e by type-II ML; off, the record says why it was left out.

    ``angular_jerk`` (the ``angular_jerk`` option, on by default): also the board's unresolved
    angular jerk ω̈_t, loaded on triad k by its centred age times its lever arm about the triads'
    centroid (the nominal positions ``nominal_acc``, a fixed covariate), its own scale per band by
    type-II ML with the jerk's: rigid-body kinematics moves triad k's specific force at
    j_t + ω̈_t × r_k, and ω̈ × r × the age differences is the larger part of the clock misfit on
    vibrating boards (``experiments/angjerk_probe.md``, ``experiments/percov_conceal.md``); off,
    the record says why it was left out."""
    from ..model.likelihood_percov import triad_rates, with_unresolved_motion
    from ..model.unresolved_fit import fit_unresolved_scales, fixed_omega_mode

    if float(getattr(lik, "kappa", 1.0)) != 1.0:  # pragma: no cover - refused with the options
        raise UserError("noise_inflation: the per-sample covariance replaces the tempering; expected none")
    base = lik.untempered_copy()
    p = terms.parameters
    band = torch.bucketize(torch.as_tensor(omega_norm, dtype=torch.float64),
                           torch.as_tensor(p["omega_edges"], dtype=torch.float64), right=True)
    pos0 = nominal_acc if map_res is None else torch.as_tensor(map_res.positions, dtype=torch.float64)
    s_t = torch.as_tensor(np.asarray(sample_scale, dtype=np.float64))
    rate = triad_rates(base.acc, terms.time, s_t) if instant_error and terms.time is not None else None
    # triads without a clock: their random age also reads the resolved rate late (model.unresolved_cov.age_prior_blocks)
    unclocked = terms.age_var_acc is not None and bool((terms.age_var_acc > 0).any())
    age_prior = None if not unclocked else {
        "age_var": terms.age_var_acc,
        "age_rate": rate if rate is not None or terms.time is None else triad_rates(base.acc, terms.time, s_t)}
    e0 = (p.get("age_error_rms_s") or {}).get("acc") if isinstance(p.get("age_error_rms_s"), dict) else None
    e0 = float(e0) if e0 is not None and float(e0) > 0 else 1e-4
    lever = nominal_acc if angular_jerk else None
    fit = fit_unresolved_scales(base, terms.age_acc, band, pos0, rate=rate, fit_instant=rate is not None,
                                instant_start=e0, lever=lever, age_prior=age_prior)
    rot = {} if lever is None else {"angjerk_std": fit.angjerk_rms[band], "lever": lever}
    new = with_unresolved_motion(base, terms.age_acc, fit.jerk_rms[band], rate=rate,
                                 instant_std=None if rate is None else fit.instant_std, **(age_prior or {}), **rot)
    P, cov = fixed_omega_mode(new, pos0, prior_mean=nominal_acc, prior_std=prior_std)
    phys = [float((fit.jerk_rms[b] * s_t[band == b]).median()) if bool((band == b).any()) else None
            for b in range(len(fit.jerk_rms))]
    record = {"omega_edges_rad_s": [float(e) for e in p["omega_edges"]],
              "band_samples": [int((band == b).sum()) for b in range(len(fit.jerk_rms))],
              "jerk_rms_report_m_s3": [float(v) for v in p["jerk_rms"]],
              "jerk_rms_fitted_m_s3": phys,
              "jerk_rms_fitted_scaled": [float(v) for v in fit.jerk_rms],
              "angular_acc_rms_report_rad_s2": [float(v) for v in p["angular_acc_rms"]],
              "type2_gain_nats": float(fit.gain),
              "angular_jerk": "used" if lever is not None else
              "skipped: switched off (option angular_jerk, --no-angular-jerk)",
              "angular_jerk_rms_fitted_rad_s3": None if lever is None else
              [float((fit.angjerk_rms[b] * s_t[band == b]).median()) if bool((band == b).any()) else None
               for b in range(len(fit.jerk_rms))],
              "angular_jerk_gain_nats": fit.gain_angjerk,
              "instant_error_rms_report_s": e0 if rate is not None else None,
              "instant_error_rms_fitted_s": fit.instant_std,
              "instant_error_gain_nats": fit.gain_instant,
              "instant_error": ("used" if rate is not None else
                                "skipped: not asked (option instant_error; ~20x the likelihood's cost)" if not instant_error
                                else "skipped: the recording has no sample times"),
              "triad_rate_rms_m_s3": None if rate is None else float((rate * s_t[:, None, None]).square().sum(-1)
                                                                     .mean().sqrt()),
              "unclocked": list(terms.unclocked),
              "age_rms_s": float(terms.age_acc.sub(terms.age_acc.mean(-1, keepdim=True)).square().mean().sqrt()),
              "how": "jerk m_t ~ N(0, s_b^2 I3) per |omega| band of the report, loaded on triad k by its centred "
                     "data age" + (", the angular jerk w'' ~ N(0, a_b^2 I3) per band loaded on triad k by its "
                                   "centred data age times [r_k - r_mean]x (nominal positions)" if lever is not None
                                   else "")
                     + (", and each triad's own instant error eps_kt ~ N(0, e^2) times the rate of its "
                                   "output (per-triad covariance e^2 rho rho^T)" if rate is not None else "")
                     + ", projected out with phi_t; s_b" + (", a_b" if lever is not None else "")
                     + (" and e" if rate is not None else "")
                     + " by type-II ML at the MAP positions and omega-bar, noise levels kept; untempered"}
    return PercovStep(new, P, cov, record)


@dataclass
class BlockStep:
    """The chains' likelihood with the accelerometers' linear errors integrated out (``lik``), its
    mode at ω̄ with the Laplace covariance (``positions`` (A, 3) m, ``laplace_cov`` m²) and the
    provenance ``record``."""

    lik: object
    positions: torch.Tensor
    laplace_cov: torch.Tensor
    record: dict
    term: object = None


def _common_cut_step(run, blk: BlockStep, lik, seed: int, record: dict):
    """The chains' draws of θ moved by the accelerometers' common error drawn from its prior
    (:func:`accel_bayes.model.acc_block_marginal.common_shifts`, the cut of the module docstring), one
    draw per kept draw, seeded by ``seed``; ``record`` (the settings' ``acc_blocks``) gains what was added.
    The chains' stored log p̂ and log prior stay those of the unshifted draws (the cut is not part of the
    target the chains sample)."""
    import dataclasses

    from ..model.acc_block_marginal import common_shifts

    theta = run.theta  # (C, D, A − 1, 3)
    C, D = theta.shape[:2]
    free = [c for c in range(3 * lik.A) if c // 3 != lik.reference]
    gen = torch.Generator().manual_seed(int(seed) + 104729)  # its own stream: the chains' draws are unchanged
    shift = common_shifts(blk.term, blk.laplace_cov, free, C * D, gen).to(theta.dtype)
    record["common_shift_mean_m"] = [float(v) for v in shift.mean(0)]
    record["common_shift_std_median_m"] = float(shift.std(0).median())
    return dataclasses.replace(run, theta=theta + shift.view(C, D, *theta.shape[2:]))


def _model_block_step(lik, rec, cmodel, pos0, nominal_acc, prior_std, sample_scale, acc_blocks,
                      prev_cov=None) -> BlockStep:
    """The triads' linear accelerometer errors integrated out of ``lik``, the part they share left to
    :func:`_common_cut_step` (option ``acc_blocks``:
    "fit" or (τ_M, τ_b); :mod:`accel_bayes.model.acc_block_marginal`), the prior centred by the
    report's blocks (which ``lik``'s outputs already have inverted), expanded to second order about
    ``pos0`` (A, 3) m (the mode so far); ``sample_scale`` (T,) the noise model's per-sample scale the
    outputs were divided by.  Then the new mode and its Laplace covariance, where the chains start;
    ``prev_cov`` the Laplace covariance without the term (m², computed here when None) for the record."""
    from ..model.acc_block_marginal import block_prior_mean, build_block_marginal, with_block_marginal
    from ..model.unresolved_fit import fixed_omega_mode

    labels = list(lik.imu_labels)
    q = np.asarray(rec.nominal_orientation, dtype=np.float64)[labels]
    mu = block_prior_mean([(k, e) for _, k, e in cmodel.acc_linear], q, labels)
    pos0 = torch.as_tensor(pos0, dtype=torch.float64)
    term = build_block_marginal(lik, pos0, mu, tau=acc_blocks, sample_scale=sample_scale)
    new = with_block_marginal(lik, term)
    # Newton from the previous mode: the term's gradient there is ~10⁴ nats/m (acc_block_marginal, "Positions")
    P, cov = fixed_omega_mode(new, pos0, prior_mean=nominal_acc, prior_std=prior_std, newton=True)
    record = {**term.record, "report_blocks": sorted(int(k) for _, k, _ in cmodel.acc_linear),
              "mode_shift_m": float((P - pos0).sub(P[lik.reference] - pos0[lik.reference]).norm(dim=-1).max()),
              "laplace_std_ratio_median": float((cov.diagonal().sqrt() / (
                  _laplace_std(lik, pos0, nominal_acc, prior_std) if prev_cov is None
                  else torch.as_tensor(prev_cov, dtype=torch.float64).diagonal().sqrt())).median())}
    return BlockStep(new, P, cov, record, term)


def _laplace_std(lik, pos, nominal_acc, prior_std) -> torch.Tensor:
    """The Laplace std (m) of the free coordinates of ``lik`` alone at ω̄, at its own mode near ``pos``."""
    from ..model.unresolved_fit import fixed_omega_mode

    return fixed_omega_mode(lik, pos, prior_mean=nominal_acc, prior_std=prior_std)[1].diagonal().sqrt()


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
    return _ratio_record(sw, lap, tempering=kappa, free_labels=free_labels)


def _percov_sandwich_record(step: PercovStep, free_labels) -> dict:
    """The sandwich of the per-sample-covariance likelihood at its mode ``step.positions`` (ω = ω̄):
    per-sample scores ψ_t = ∂ℓ_t/∂θ of its own terms ℓ_t = log p(y_t | ω̄_t, θ) less their common
    share of ∂(−½ log|M|)/∂θ (:func:`sandwich_inflation`'s convention, which these scores reproduce
    to 1e-12 on the flat model: ``experiments/percov_honesty_probe.md``), Newey–West meat, against
    the Laplace covariance at that mode; the same record as :func:`_sandwich_record`."""
    lik = step.lik
    P = step.positions
    th, full = _free_theta(lik, P)
    S = per_sample_scores(lambda t: lik.log_lik_per_sample(full(t), lik.omega.mean), th)
    return _scores_record(S - _logdet_share(lik, th, full), step.laplace_cov, free_labels)


def _block_sandwich_record(step: BlockStep, free_labels) -> dict:
    """The sandwich of the chains' target with the accelerometers' linear errors integrated out
    (``step``: :func:`_model_block_step`) at its mode: per-sample efficient scores by Fisher's identity
    (:func:`accel_bayes.model.acc_block_marginal.marginal_scores`: the likelihood's own terms on the
    outputs corrected by the errors' posterior mean, plus the posterior covariance's trace term, less
    their projection on the errors' own per-sample scores), less
    the common determinant's share as in :func:`_percov_sandwich_record`, Newey–West meat, against the
    Laplace covariance of ℓ + Δ there; the same record as :func:`_sandwich_record`."""
    from ..model.acc_block_marginal import marginal_scores

    lik = step.lik
    if float(getattr(lik, "kappa", 1.0)) != 1.0:  # pragma: no cover - a model run does not temper
        return {"kappa": None, "why": f"tempered target (kappa {lik.kappa:g}): no per-sample scores of its own"}
    th, full = _free_theta(lik, step.positions)
    free = [c for c in range(3 * lik.A) if c // 3 != lik.reference]
    S = marginal_scores(lik, step.term, full(th), free)
    rec = _scores_record(S - _logdet_share(lik, th, full), step.laplace_cov, free_labels)
    # the cut's spread (:func:`_common_cut_step`) is added to the draws after the chains, outside this target:
    # its std per coordinate, for comparing the sandwich with the draws' std
    M = -torch.as_tensor(step.laplace_cov, dtype=torch.float64) @ step.term.common_J[:, free].T  # (F, 12)
    rec["cut_std_m"] = [float(v) for v in (M.square() @ step.term.common_std.square()).sqrt()]
    return rec


def _free_theta(lik, positions):
    """(θ (F,) the free coordinates of ``positions`` (A, 3) m relative to the reference, θ ↦ (A, 3))."""
    A, ref = lik.A, lik.reference
    free = [k for k in range(A) if k != ref]
    P = torch.as_tensor(positions, dtype=torch.float64)

    def full(th):
        out = torch.zeros(A, 3, dtype=th.dtype)
        out[free] = th.reshape(A - 1, 3)
        return out

    return (P - P[ref])[free].reshape(-1), full


def _logdet_share(lik, th, full):
    """(F,) nats/m: ∂(−½ log|M(θ)|)/∂θ, the common determinant's share in every sample's term."""
    return per_sample_scores(lambda t: -0.5 * lik._projection_hot(lik._positions(full(t))[None])["logdetM"], th)[0]


def _scores_record(S, laplace_cov, free_labels) -> dict:
    """The record of :func:`_ratio_record` for per-sample scores ``S`` (T, F) against ``laplace_cov`` (m²), untempered."""
    sw = score_sandwich(S, laplace_cov)
    lap = torch.as_tensor(laplace_cov).diagonal().clamp_min(0).sqrt().numpy()
    return _ratio_record(sw, lap, tempering=1.0, free_labels=free_labels)


def _ratio_record(sw, lap, *, tempering, free_labels) -> dict:
    ratio = np.asarray(sw["std_ratio"], dtype=np.float64)
    names = [f"r[{k}, {a}]" for k in free_labels for a in dg_az.AXES]
    return {"kappa": float(sw["kappa"]), "lags": int(sw["lags"]), "tempering_applied": float(tempering),
            "std_ratio_max": float(ratio.max()), "std_ratio_median": float(np.median(ratio)),
            "coordinates": names, "laplace_std_m": [float(v) for v in lap],
            "sandwich_std_m": [float(v) for v in lap * ratio], "std_ratio": [float(v) for v in ratio]}
