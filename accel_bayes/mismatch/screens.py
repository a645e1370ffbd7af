"""The detector's screens (:func:`accel_bayes.mismatch.detect`, step 4): every candidate tested cheaply
at the current fit, and the threshold rule.

4. **Screen** (cheap, all candidates, at the current fit):

* mean effects — the score (Lagrange-multiplier) test: u = ∂logL/∂η at η = 0 and the
  *efficient* information I_ηη·g = I_ηη − I_ηg S_g⁻¹ I_gη, where the per-sample motion states
  are eliminated sample by sample and the geometry (and effects already in the model)
  through the Schur-reduced information S_g; statistic uᵀ I_ηη·g⁻¹ u ~ χ²_df under the null,
  the local approximation of the likelihood-ratio statistic.  Candidates whose efficient
  information is singular (relative eigenvalue < 1e-8) are not identifiable in this
  recording and are dropped;
* ``noise_level`` — the restricted (leverage-corrected) likelihood ratio for a variance
  factor, n(m − 1 − log m), m the mean z² of the group (exact, no refit needed);
* ``sampling_jitter`` (a random effect) — the exact marginal likelihood of the uniform
  sampling-instant error at the current mean fit, profiled over the width w in 1-D
  (:mod:`accel_bayes.mismatch.jitter`: the restricted likelihood, exact per sample); statistic
  2·(max_w log L − log L(w = 0)), a boundary hypothesis whose null distribution is the
  50:50 mixture ½χ²₀ + ½χ²₁, so its p-value is half the χ²₁ one;
* ``saturation`` — the gain in Σr² from clamping the fitted outputs at a limit L, profiled
  over L on a grid from the channel's largest |output| down to 80 % of it.

Threshold rule (:func:`threshold_rule`, reported as ``threshold``): Bonferroni over the m tests made,
χ²_{d_max} quantile at 1 − α/m, d_max the largest number of parameters of any candidate.
"""
from __future__ import annotations

import copy as _copy
import math
from dataclasses import dataclass

import torch

from ..physics.effects import EFFECTS, Effect, get_effect
from .jitter import jitter_evidence
from .locate import log10_chi2_sf
from .model import ModelFit, project_off_states
from .prepared import Prepared

__all__ = ["Screen", "screen", "candidate_effects", "threshold_rule", "noise_evidence", "stationarity",
           "STATIONARITY_SEGMENTS", "log10_p"]


@dataclass
class Screen:
    """One screened candidate: effect (instance, params = screening estimate), statistic, df,
    log10_p (of the statistic under χ²_df), identifiable."""

    effect: Effect
    statistic: float
    df: int
    log10_p: float
    identifiable: bool = True
    estimate: dict | None = None

    def to_dict(self) -> dict:
        return {"candidate": self.effect.label(), "statistic": self.statistic, "df": self.df,
                "log10_p": self.log10_p, "identifiable": self.identifiable}


def threshold_rule(m: int, df_max: int, alpha: float) -> float:
    """χ²_{df_max} quantile at 1 − α/m (Bonferroni over m candidates)."""
    from scipy.stats import chi2

    return float(chi2.isf(alpha / max(int(m), 1), max(int(df_max), 1)))


def candidate_effects(prep: Prepared, effects=None) -> list[Effect]:
    """Every candidate location of the requested effect classes (names; None = all)."""
    names = list(EFFECTS) if effects is None else list(effects)
    out = []
    for nm in names:
        cls = get_effect(nm)
        if getattr(cls, "screened", True):  # gyro_linear: tested in its own stage (step 3a)
            out += cls.candidates(prep.layout)
    return out


def _rows(K: int, k: int) -> torch.Tensor:
    return torch.tensor([3 * k, 3 * k + 1, 3 * k + 2, 3 * K + 3 * k, 3 * K + 3 * k + 1, 3 * K + 3 * k + 2])


def _regressor(c: Effect, ctx, k: int) -> torch.Tensor:
    """∂(outputs of IMU k)/∂η at η = 0 for a mean candidate, (T, 6, p) [acc xyz, gyro xyz].

    Central differences with a step of 1e-3 × the parameter's prior scale: exact for the
    effects linear in their parameters (all but triad_orientation) and accurate to ~1e-7
    relative for the rotation — ample for a test statistic, and far cheaper than forward-mode
    autodiff per candidate."""
    null = c.null_params()
    v0 = c.flatten(null)
    scales = c.prior_scales()
    # Effects are IMU-separable (an effect on IMU k changes IMU k's outputs only, from IMU k's
    # own context), so the perturbation is evaluated on IMU k's one-IMU sub-context: the same
    # numbers at 1/K of the cost.
    c1 = _copy.copy(c)
    c1.imu = 0
    sub = _imu_context(ctx, k)
    cols = []
    for j in range(c.df):
        h = 1e-3 * (float(scales[j]) if math.isfinite(float(scales[j])) else 1.0)
        outs = []
        for sgn in (1.0, -1.0):
            v = v0.clone()
            v[j] += sgn * h
            da, dg = c1.perturbation(c.unflatten(v), sub)
            outs.append(torch.cat((da[:, 0], dg[:, 0]), -1))
        cols.append((outs[0] - outs[1]) / (2 * h))
    return torch.stack(cols, -1)


def _imu_context(ctx, k: int):
    """The signal context of IMU k alone (one-IMU slices of every per-IMU field)."""
    from ..physics.effects import SignalContext

    sl = slice(k, k + 1)
    pick = lambda v: None if v is None else v[:, sl]  # noqa: E731
    return SignalContext(ctx.time, ctx.omega, ctx.omega_dot, ctx.s, ctx.positions[sl], ctx.orientations[sl],
                         pick(ctx.acc), pick(ctx.gyro), pick(ctx.acc_rate), pick(ctx.gyro_rate))


def _score_tests(prep: Prepared, fit: ModelFit, cands) -> list[Screen]:
    """Score tests of the mean candidates (module docstring, step 4), batched per IMU: the
    regressors of every candidate on one IMU are stacked so the efficient information of all of
    them is one (P × P) matrix whose diagonal blocks are the candidates'."""
    lin = fit.linear()
    ctx = fit.ctx
    K = prep.K
    wa = prep.m_acc / (prep.sigma_acc * fit.acc_factor)[None, :, None]
    wg = prep.m_gyro / (prep.sigma_gyro * fit.gyro_factor)[None, :, None]
    SinvT = lin.Sinv
    by_imu: dict[int, list] = {}
    for c in cands:
        by_imu.setdefault(int(c.imu), []).append(c)
    results = {}
    with torch.no_grad():
        for k, group in by_imu.items():
            Ds = [_regressor(c, ctx, k) for c in group]
            D = torch.cat(Ds, -1)  # (T, 6, P)
            w = torch.cat((wa[:, k], wg[:, k]), -1)
            Dr = -D * w.unsqueeze(-1)
            rows = _rows(K, k)
            Jx, Jg, rk = lin.Jx[:, rows], lin.jg_rows(k), lin.r[:, rows]
            a = Jx.transpose(-1, -2) @ Dr  # (T, 9, P)
            Va = lin.Vinv @ a
            T_, _, P = Dr.shape
            DtD = Dr.reshape(-1, P).T @ Dr.reshape(-1, P)
            I_ee = DtD - a.reshape(-1, P).T @ Va.reshape(-1, P)
            n = Jg.shape[-1]
            I_eg = Dr.reshape(-1, P).T @ Jg.reshape(-1, n) - a.reshape(-1, P).T @ lin.Z.reshape(-1, n)
            eff_all = I_ee - I_eg @ SinvT @ I_eg.T
            u_all = -(Dr.reshape(-1, P).T @ rk.reshape(-1))
            i = 0
            for c, Dc in zip(group, Ds):
                p = c.df
                sl = slice(i, i + p)
                i += p
                scale = torch.diagonal(DtD)[sl]
                if not bool((scale > 0).all()):
                    results[id(c)] = Screen(c, 0.0, p, 0.0, identifiable=False)
                    continue
                eff = eff_all[sl, sl]
                eff = 0.5 * (eff + eff.T)
                dn = torch.sqrt(scale)
                ev = torch.linalg.eigvalsh(eff / (dn[:, None] * dn[None, :]))
                if float(ev.min()) < 1e-8:
                    results[id(c)] = Screen(c, 0.0, p, 0.0, identifiable=False)
                    continue
                u = u_all[sl]
                est = torch.linalg.solve(eff, u)
                stat = float(u @ est)
                c.set_params(c.unflatten(est))
                results[id(c)] = Screen(c, stat, p, log10_chi2_sf(stat, p), True, c.unflatten(est))
    return [results[id(c)] for c in cands]


def noise_evidence(prep: Prepared, fit: ModelFit, effect) -> tuple[float, float, int]:
    """Restricted likelihood ratio of a noise_level effect at a fit: (n(m − 1 − log m), factor √m, n),
    m the mean leverage-corrected z² of the effect's group in the fit's noise units with the
    effect's own factor (if it is in the fit) taken out — i.e. relative to every *other* noise
    factor of the model (module docstring, step 4)."""
    lin = fit.linear()
    T, K = prep.T, prep.K
    z2 = (lin.r ** 2 / (1 - lin.h).clamp_min(1e-3)).reshape(T, 2, K, 3)
    z2 = z2[:, 0] if effect.which == "acc" else z2[:, 1]
    mask = prep.m_acc if effect.which == "acc" else prep.m_gyro
    # (lin.r is whitened by the fit's weights, which include random effects' predicted variance)
    own = any(e is effect or (e.label() == effect.label() and e.kind == "noise") for e in fit.effects)
    if own:
        z2 = z2 * float(effect.params["factor"]) ** 2
    if effect.imu is not None:
        z2, mask = z2[:, effect.imu], mask[:, effect.imu]
    n = float(mask.sum())
    if n == 0:
        return 0.0, 1.0, 0
    m = float((z2 * mask).sum() / n)
    return n * (m - 1 - math.log(m)), math.sqrt(m), int(n)


def _noise_screen(prep, fit, cands) -> list[Screen]:
    out = []
    for c in cands:
        stat, fac, n = noise_evidence(prep, fit, c)
        if n == 0:
            out.append(Screen(c, 0.0, 1, 0.0, identifiable=False))
            continue
        c.set_params({"factor": fac})
        out.append(Screen(c, stat, 1, log10_chi2_sf(stat, 1), True, {"factor": torch.tensor(fac)}))
    return out


def log10_p(stat: float, effect) -> float:
    """log10 p-value of an evidence: χ²_df, or for a random effect (a variance on the boundary
    w = 0) the 50:50 mixture ½χ²₀ + ½χ²₁."""
    lp = log10_chi2_sf(stat, effect.df)
    return lp + math.log10(0.5) if effect.kind == "random" and stat > 0 else lp


#: time segments of the stationarity test of a mean effect (consecutive, equal sample counts)
STATIONARITY_SEGMENTS = 5


def stationarity(prep, fit: ModelFit, effect, n_seg: int = STATIONARITY_SEGMENTS) -> tuple[float, int]:
    """(Q, df): does a fitted mean effect's parameter stay the same through the recording?

    ``effect`` is the last effect of ``fit`` (a refit).  Per sample t, its Jacobian columns E_t
    (whitened) are projected off the motion states, Ẽ_t = E_t − Jx_t (Jx_tᵀJx_t)⁻¹ Jx_tᵀ E_t, and
    the score g_s = Σ_{t∈s} Ẽ_tᵀ r_t and information I_s = Σ_{t∈s} Ẽ_tᵀẼ_t summed over ``n_seg``
    consecutive time segments s.  At the fit Σ_s g_s ≈ 0, and

        Q = Σ_s g_sᵀ I_s⁻¹ g_s  ~  χ²_{(n_seg − 1)·d}

    if the parameter is constant (the score test of one parameter vector per segment against a
    common one; d = ``effect.df``).  A constant-parameter effect (bias, scale, misalignment,
    displacement, rotation, offset) that the data want different in different parts of the
    recording is not that physics: e.g. a drifting bias, partly projected onto a misalignment
    or a constant bias by least squares (``experiments/characterise_proof.md``)."""
    lin = fit.linear()
    T, m = lin.r.shape
    d = int(effect.df)
    E = lin.Je.reshape(T, m, -1)[..., -d:]  # (T, m, d), rows in lin.r's order
    Et = project_off_states(lin.Jx, lin.Vinv, E)
    g_t = (Et * lin.r.unsqueeze(-1)).sum(1)  # (T, d)
    I_t = Et.transpose(-1, -2) @ Et  # (T, d, d)
    q = 0.0
    for idx in torch.arange(T).chunk(n_seg):
        g, info = g_t[idx].sum(0), I_t[idx].sum(0)
        try:
            q += float(g @ torch.linalg.solve(info, g))
        except RuntimeError:  # a segment that does not see the effect: nothing to compare
            continue
    return q, (n_seg - 1) * d


def _jitter_screen(prep, fit, cands) -> list[Screen]:
    """Random-effect candidates (``sampling_jitter``): the profiled exact marginal likelihood
    ratio at the current fit (module docstring, step 4)."""
    out = []
    for c in cands:
        if prep.acc_rate is None:
            out.append(Screen(c, 0.0, 1, 0.0, identifiable=False))
            continue
        stat, prof = jitter_evidence(prep, fit, c)
        c.set_params({p.name: prof[p.name] for p in c.parameters if p.name in prof})
        c.stats["width_interval_s"] = prof["interval"]
        out.append(Screen(c, stat, 1, log10_p(stat, c), True, {"width": torch.tensor(prof["width"])}))
    return out


def _saturation_screen(prep, fit, cands, n_grid: int = 41, lowest: float = 0.8) -> list[Screen]:
    out = []
    frac = torch.linspace(1.0, lowest, n_grid, dtype=torch.float64)
    cache = {}
    for sensor in ("acc", "gyro"):
        y = prep.y_acc if sensor == "acc" else prep.y_gyro
        pred = fit.pred_acc if sensor == "acc" else fit.pred_gyro
        mask = prep.m_acc if sensor == "acc" else prep.m_gyro
        sig = (prep.sigma_acc * fit.acc_factor if sensor == "acc" else prep.sigma_gyro * fit.gyro_factor)[None, :, None]
        cache[sensor] = (y, pred, mask, sig)
    for c in cands:
        y, pred, mask, sig = cache[c.which]
        if c.imu is not None:
            sl = (slice(None), slice(c.imu, c.imu + 1), slice(c.axis_index, c.axis_index + 1))
            y_, p_, m_, s_ = y[sl], pred[sl], mask[sl], sig[:, c.imu:c.imu + 1]
        else:
            y_, p_, m_, s_ = y, pred, mask, sig
        if float(m_.sum()) == 0:
            out.append(Screen(c, 0.0, 1, 0.0, identifiable=False))
            continue
        M = float((y_.abs() * m_).max())
        L = (M * frac)[:, None, None, None]
        r0 = ((y_ - p_) / s_ * m_) ** 2
        r1 = ((y_ - torch.minimum(torch.maximum(p_, -L), L)) / s_ * m_) ** 2
        gain = (r0 - r1).sum((1, 2, 3))
        j = int(torch.argmax(gain))
        stat = float(gain[j])
        if stat <= 0:
            out.append(Screen(c, 0.0, 1, 0.0))
            continue
        lim = float(M * frac[j])
        c.set_params({"limit": lim})
        out.append(Screen(c, stat, 1, log10_chi2_sf(stat, 1), True, {"limit": torch.tensor(lim)}))
    return out


def screen(prep: Prepared, fit: ModelFit, candidates) -> list[Screen]:
    """Screen candidates at a fit (module docstring, step 4); each candidate's params are set to
    its screening estimate.  Returns the screens sorted by log10 p (most significant first)."""
    mean = [c for c in candidates if c.kind == "mean"]
    clip = [c for c in candidates if c.kind == "clip"]
    noise = [c for c in candidates if c.kind == "noise"]
    rand = [c for c in candidates if c.kind == "random"]
    out = (_score_tests(prep, fit, mean) + _saturation_screen(prep, fit, clip) + _noise_screen(prep, fit, noise)
           + _jitter_screen(prep, fit, rand))
    out.sort(key=lambda s: s.log10_p)
    return out
