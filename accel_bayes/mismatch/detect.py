"""Name a mismatch: which physical effect (and where) explains the excess of the residuals.

:func:`detect` is the public entry point (DESIGN §2 "mismatch", §7.2 report v1)::

    report = detect(recording)           # a Recording or a path to a format-v1 file
    report.mismatch_detected, report.findings[0].effect.name, report.to_dict(), report.write("out")

Procedure
---------
1. **Baseline**: the nominal model fitted jointly in geometry and motion
   (:func:`accel_bayes.mismatch.fit.baseline_fit`, started from the package's MAP), on the
   recording prepared as the calibration prepares it (:func:`accel_bayes.mismatch.prepared.prepare`
   through :func:`accel_bayes.prep.preprocess.preprocess`: intrinsics from the rests when it has
   them, rests, flagged-clipped and slowly rotating samples dropped by THE sample selection; a
   reading at the range is censored, not a measurement; unflagged clipping stays in and is the
   ``saturation`` effect's business).
2. **Locate** (:func:`accel_bayes.mismatch.locate.locate`): standardized residuals, excess per
   IMU/axis/regime, posterior predictive check.
3. **Candidates**: every location of every requested effect class
   (:meth:`Effect.candidates`; the identifiability rules are in
   :mod:`accel_bayes.physics.effects`).  m = their number.
3a. **Gyro linear stage** (:mod:`accel_bayes.mismatch.gyro_linear`): every gyroscope's whole
   linear error (3 × 3 scale/misalignment + offset, :class:`~accel_bayes.physics.effects.GyroLinear`,
   12 parameters per IMU) is tested as a group and per IMU, fitted in closed form alternating
   with the motion (its part common to all gyros through the accelerometer lever arms), and the
   recording is corrected for the blocks that pass; the rounds below run on the corrected
   recording with the blocks held fixed, and never try a gyro scale/misalignment/bias term on
   an IMU that has a block.  Each block is a finding (vocabulary ``gyro_scale``, axis null,
   parameters {"scale": 3 × 3, "bias": 3}); ``max_findings`` counts the rounds' findings only.
   Why: raw MEMS gyros carry all twelve terms on every IMU, and one term per round leaves the
   rest in the residual, where a random timing effect explains them better (1/21 concealed
   multi-effect cases named right before this stage, experiments/mismatch_multi.md).  Skipped
   when ``effects`` does not name ``gyro_linear`` (the default names every effect).
3b. **Clock stage** (:mod:`accel_bayes.mismatch.clock`): on every IMU with a gyroscope, a
   ``sampling_clock`` (:class:`~accel_bayes.physics.effects.SamplingClock`: the data age a sawtooth
   beating against the read rate, shared by the IMU's acc and gyro) found by a beat-frequency search
   on the gyro's restricted timing statistics (those ``timing_wander`` is fitted on), accepted where
   its evidence against no clock *and* against the best AR(1) instant error (``timing_wander``; its
   ρ = 0 end is white jitter) both exceed the stage threshold (the threshold below, or the χ²₄
   look-elsewhere quantile over the (beat, drift) cells searched if larger) and its width is
   physical.  The recording is corrected for the accepted clocks, which are held fixed from here
   on like the gyro blocks; one finding per IMU, not counted by ``max_findings``.  Skipped when
   ``effects`` does not name ``sampling_clock``.
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
5. **Refit** the best screened candidate of each effect class and the overall top three
   (at most ``n_refit``, only those with a screen statistic ≥ ½ of the threshold): the
   augmented model is re-optimised jointly with the geometry and the motion by the LM solver,
   and the **evidence** is the likelihood ratio 2·(log L with − log L without) at the two optima
   (for ``noise_level`` the restricted likelihood ratio of step 4 at the refitted model, because
   the plain one is biased by the leverage of the per-sample motion states).
6. **Accept** one candidate per round, repeat from step 4 with it in the model, at most
   ``max_findings`` times:

   * a mean (or clip) effect is acceptable when its *noise-robust* evidence — the evidence
     divided by max(1, P), P the mean leverage-corrected z² left in its IMU/sensor group after
     the refit — exceeds the threshold.  This F-test-like guard keeps noise larger than stated
     (which inflates every mean candidate's likelihood ratio on that IMU by the same factor)
     from being named as a bias or scale error; for a correctly named effect P ≈ 1.  It must
     also be *constant*: its score test across :data:`STATIONARITY_SEGMENTS` time segments
     (:func:`stationarity`, also over max(1, P)) must stay below the χ²_{(S−1)d} quantile at
     1 − α/m; a drifting bias that least squares projects onto a constant bias or a
     misalignment is refused there and left to the ``unexplained`` characterisation;
   * ``noise_level`` and the random effects (``sampling_jitter``) are considered only in a round
     where no mean/clip effect is acceptable: any unmodelled mean structure also raises the
     residual power, so the variance explanations come last.  They compete on equal terms
     (both a likelihood ratio of leverage-corrected residuals): ``noise_level`` predicts a
     constant variance factor on one sensor, ``sampling_jitter`` variance growing with the
     squared output rate on both sensors of the IMU.  ``noise_level`` is refused
     (:func:`_heteroscedastic`) where its group's excess power varies more than 1.25× across the
     quintiles of a motion covariate (significant by the characteriser's F test): a constant
     factor does not describe such an excess, which is then left to a better variance model or
     to the characterised ``unexplained`` finding of step 7.  Exception to "mean first": a random
     effect whose evidence exceeds :data:`RANDOM_DOMINANCE` (10) × the best acceptable mean
     candidate's is taken first (a wandering timing error looks like structure to every mean
     candidate, each explaining a small part of it).  At most one random effect per IMU and
     sensor is in the model (each is profiled as if alone), and a ``timing_wander`` only where its
     timing term alone (against the triad's best noise-only fit) passes the threshold.  ``noise_level`` refits of step 5
     are only done in a round where no mean/clip candidate is acceptable (elsewhere the
     round's ``refits`` list them as skipped);
   * among the acceptable ones the smallest p-value (χ²_df of the robust evidence) wins.

   With several findings, each one's evidence is recomputed with all the others in the model
   (drop-one refits).  Each finding lists as ``alternatives`` the other candidates refitted in
   its round whose Akaike relative likelihood against it, exp(−ΔAIC/2), is ≥ 5 %: effects this
   recording cannot tell apart from the named one (e.g. a quadratic response and a scale error
   on an axis whose specific force never changes sign).
7. **Unexplained**: at the final model, the located-excess tests of
   :func:`accel_bayes.mismatch.locate.excess_cells` (free mean and variance per regime bin, χ²_2B),
   Bonferroni-corrected over the cells × schemes tested; a significant one that also exceeds the
   threshold is reported as an ``unexplained`` finding with its location.  The cells are ranked
   by a p-value that stays finite for any statistic (:func:`accel_bayes.mismatch.locate.log10_chi2_sf`;
   with SciPy's underflowing ``logsf`` every cell beyond χ² ≈ 1400 tied at −inf and the first
   cell enumerated — IMU 0, accelerometer x — was reported whatever the data).
8. **Budget** (:func:`accel_bayes.mismatch.budget.residual_budget`, vocabulary 1.1): per sensor and
   per |ω| and |ω̇| quantile band of the baseline motion, the excess variance the baseline leaves
   (a, leverage-corrected squared residual minus the stated variance) and the part the final
   model accounts for (b, the squared residual its mean effects remove plus the variance its
   variance effects predict); b = 0 when nothing was found.  Reported also with ``refine=False``.

Threshold rule (reported as ``threshold``): Bonferroni over the m tests made (the round
candidates, plus the gyro linear stage's group test and one test per gyro),

    threshold = χ²_{d_max} quantile at 1 − α/m,

with d_max the largest number of parameters of any candidate (3).  One number for every finding,
conservative for candidates with fewer parameters (and for ``sampling_jitter``, whose boundary
null ½χ²₀ + ½χ²₁ is not used to lower it).  The gyro linear stage holds its group to χ²_{12n}, each
block to χ²_12 and each block's terms to χ²_1, all at 1 − α/m.  Findings are ranked by the p-value of their
evidence under χ²_df (most supported first; equal to ranking by evidence for equal df).

Budget: one baseline fit, one screen per round (vectorised algebra, a few ms per candidate) and
at most ``n_refit`` LM refits per round (``noise_level`` ones only in a round that needs them);
every sample the prepared selection keeps is used.  ``experiments/bench_detect.py`` (one thread):
the whole real MIMU exp_1 (5885 samples kept, 8 IMUs; gyro linear stage, blocks on all eight gyros,
three rounds, each random effect refitted by GLS) in 64 s and a 32-IMU, T = 3000 recording in 27 s,
at load ≈ 1 on the shared 2-core machine (``experiments/bench_detect.md``; 7adf109: 123 s and 27 s).
The GLS refits of the random effects (a few more LM solves each) doubled the time on exp_1 (37 s
before them).
"""
from __future__ import annotations

import copy as _copy
import functools
import inspect
import math
import time as _time
from dataclasses import dataclass

import numpy as np
import torch

from ..data.io import load_recording
from ..errors import UserError
from ..physics.effects import EFFECTS, Effect, Unexplained, get_effect
from .characterise import characterise, describe
from ..threads import DEFAULT_THREADS, torch_threads
from .locate import locate, log10_chi2_sf, regime_concentration, regimes, time_window
from .budget import group_power, residual_budget
from .compare import compare_fits, posterior_comparison
from .fit import _effect_std, baseline_fit, fit_model
from .gyro_linear import block_corrected_recording, gyro_linear_stage, refresh_blocks
from .clock import clock_corrected, clock_stage
from .jitter import jitter_evidence
from .model import ModelFit, project_off_states
from .prepared import Prepared, prepare
from .report import Finding, MismatchReport

__all__ = ["Screen", "detect", "candidate_effects", "screen", "threshold_rule", "noise_evidence"]


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


def _log10_sf(stat: float, df: int) -> float:
    """log10 P(χ²_df > stat), finite for any finite stat (:func:`~accel_bayes.mismatch.locate.log10_chi2_sf`)."""
    return log10_chi2_sf(stat, df)


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


# ------------------------------------------------------------------------------ screens

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
                results[id(c)] = Screen(c, stat, p, _log10_sf(stat, p), True, c.unflatten(est))
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
        out.append(Screen(c, stat, 1, _log10_sf(stat, 1), True, {"factor": torch.tensor(fac)}))
    return out


def _log10_p(stat: float, effect) -> float:
    """log10 p-value of an evidence: χ²_df, or for a random effect (a variance on the boundary
    w = 0) the 50:50 mixture ½χ²₀ + ½χ²₁."""
    lp = _log10_sf(stat, effect.df)
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
        out.append(Screen(c, stat, 1, _log10_p(stat, c), True, {"width": torch.tensor(prof["width"])}))
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
        out.append(Screen(c, stat, 1, _log10_sf(stat, 1), True, {"limit": torch.tensor(lim)}))
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


def _choose(screens: list[Screen], threshold: float, n_refit: int) -> list[Screen]:
    ok = [s for s in screens if s.identifiable and s.statistic >= 0.5 * threshold]
    chosen, seen = [], set()
    for s in ok:
        if s.effect.name not in seen:
            chosen.append(s)
            seen.add(s.effect.name)
    chosen = chosen[:n_refit]
    for s in ok[:3]:
        if all(s is not c for c in chosen):
            chosen.append(s)
    return chosen


# An alternative explanation is reported beside a finding when its Akaike relative likelihood
# exp(−ΔAIC/2) against the finding is at least this: the recording cannot rule it out.
ALTERNATIVE_MIN_RELATIVE_LIKELIHOOD = 0.05


def alternatives(best: dict, results: list[dict]) -> list[dict]:
    """The other candidates refitted in the round that accepted ``best`` whose fit is nearly as
    good: relative likelihood exp(((e_alt − 2 df_alt) − (e_best − 2 df_best)) / 2) ≥
    :data:`ALTERNATIVE_MIN_RELATIVE_LIKELIHOOD` (e = noise-robust evidence, both against the same
    model without them; AIC's penalty of 2 per parameter).  Example: on an axis whose specific
    force stays on one side of zero, a² is nearly a linear function of a, and a quadratic
    response is hard to tell from a scale error plus a bias."""
    e_b = best["evidence_robust"] - 2 * best["effect"].df
    out = []
    for r in results:
        if r is best or r["effect"].kind in ("noise", "random"):
            continue
        rel = math.exp(min(0.0, (r["evidence_robust"] - 2 * r["effect"].df - e_b) / 2))
        if rel >= ALTERNATIVE_MIN_RELATIVE_LIKELIHOOD:
            eff = r["effect"]
            out.append({"effect": eff.vocabulary_name or eff.name, "imu": eff.imu, "axis": eff.axis,
                        "evidence": float(r["evidence"]), "df": int(eff.df), "relative_likelihood": rel})
    return sorted(out, key=lambda a: -a["relative_likelihood"])


def _evidence(prep, with_fit: ModelFit, without_fit: ModelFit, effect) -> float:
    if effect.kind == "noise":
        return noise_evidence(prep, with_fit, effect)[0]
    if effect.kind == "random":
        return jitter_evidence(prep, with_fit, effect)[0]
    return 2.0 * (with_fit.loglik - without_fit.loglik)


# ------------------------------------------------------------------------------ detect

def _check_recording(rec) -> None:
    """Refuse (one line) a recording the detector cannot judge, before any fit."""
    from ..prep.selection import DEFAULT_MIN_ROTATION, rotation_rate

    if rec.T < 3:
        raise UserError(f"time: mismatch detection needs at least 3 samples, the recording has {rec.T}")
    w = rotation_rate(rec)
    # Without rotation ω = ω̇ = 0 and every effect that acts through the rotation (axis_displacement,
    # the lever arms, time_offset, gyro_scale, gyro_nonlinearity, sampling_jitter) leaves no trace:
    # "no mismatch detected" would be a verdict on effects that were never testable.
    if not np.nanmax(w) >= DEFAULT_MIN_ROTATION:
        raise UserError(f"gyro: the recording does not rotate (largest mean gyro rate |w| {np.nanmax(w):.3g} rad/s < "
                        f"{DEFAULT_MIN_ROTATION} rad/s); the rotation-dependent effects cannot be tested; "
                        "record the array in motion")


def _check_options(effects, alpha, max_findings, seed):
    try:
        a = float(alpha)
    except (TypeError, ValueError):
        raise UserError(f"alpha: expected a number in (0, 1), got {alpha!r}") from None
    if not 0 < a < 1:
        raise UserError(f"alpha: expected a number in (0, 1), got {alpha!r}")
    if isinstance(max_findings, bool) or not isinstance(max_findings, (int, np.integer)) or max_findings < 0:
        raise UserError(f"max_findings: expected an integer >= 0, got {max_findings!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise UserError(f"seed: expected a non-negative integer, got {seed!r}")
    names = None
    if effects is not None:
        if isinstance(effects, str):
            effects = [e for e in effects.split(",") if e.strip()]
        names = []
        for e in effects:
            nm = e.strip() if isinstance(e, str) else getattr(e, "name", e)
            get_effect(nm)  # raises UserError for unknown names
            if nm != "unexplained" and nm not in names:
                names.append(nm)
        if not names and "unexplained" not in [str(e).strip() for e in effects]:
            raise UserError("effects: expected at least one effect name")
    return a, names


#: the excess power of a noise_level candidate's group may vary by at most this factor between the
#: lowest and the highest quintile of any motion covariate before the constant-factor explanation
#: is refused (a concealed noise_level gives 1 ± 0.1 at T ≥ 1500 — sampling error only; the real MIMU data 10–40)
HETEROSCEDASTIC_RATIO = 1.25


#: a random effect is accepted in a round where mean effects are acceptable too when its evidence
#: exceeds this many times the best mean candidate's noise-robust evidence
RANDOM_DOMINANCE = 10.0


#: the vocabulary terms a gyro_linear block contains (never round candidates on an IMU that has one)
_GYRO_LINEAR_TERMS = ("gyro_bias", "gyro_scale", "gyro_misalignment")

#: alternations of (gyro linear blocks | the rounds' findings) after each accepted finding: a block and
#: a finding on the same gyro share part of their signature (an offset and a second-order response), so
#: one re-estimate of the blocks leaves the finding's parameter biased; three settle it
REFRESH_PASSES = 3


def _random_channels(effect) -> tuple:
    """The sensors a random effect's variance acts on ("acc", "gyro")."""
    which = getattr(effect, "which", None)
    if which in ("acc", "gyro"):
        return (which,)
    return ("acc", "gyro") if effect.sensor == "both" else (effect.sensor,)


def _heteroscedastic(char: dict, effect, alpha: float) -> str | None:
    """Why a ``noise_level`` candidate contradicts the residuals' structure, or None.

    ``noise_level`` predicts the same excess power at every sample.  Refused when, in its group
    (one IMU's sensor; for imu=None the pooled sensor and each IMU, Bonferroni over the IMUs),
    the characteriser's top covariate
    (:func:`accel_bayes.mismatch.characterise.characterise`) both varies the mean z² by more than
    :data:`HETEROSCEDASTIC_RATIO` between its lowest and highest quintile and is significant at
    α / (number of covariates) by its F test."""
    c = char.get(effect.which)
    if not c:
        return None
    # imu=None claims the same factor for every IMU: any one IMU's structured excess refutes it
    groups = ([(None, c["covariates"], 1)] + [(x["imu"], x["covariates"], len(c["imus"])) for x in c["imus"]]
              if effect.imu is None else
              [(x["imu"], x["covariates"], 1) for x in c["imus"] if x["imu"] == effect.imu])
    for imu, rows, n_groups in groups:
        if not rows:
            continue
        top = rows[0]
        q = top["quintile_mean_z2"]
        lo, hi = min(q), max(q)
        ratio = hi / lo if lo > 0 else math.inf
        if not (ratio > HETEROSCEDASTIC_RATIO and top["log10_p"] < math.log10(alpha / (len(rows) * n_groups))):
            continue
        where = "" if imu is None else f" on IMU {imu}"
        return (f"the excess power{where} varies {ratio:.3g}× across the quintiles of {top['name']} "
                f"(F-test log10 p = {top['log10_p']:.3g}); a constant noise factor does not describe it")
    return None


def _pinned_threads(fn):
    """Give ``fn`` a keyword ``threads`` (default :data:`~accel_bayes.threads.DEFAULT_THREADS` = 1) and
    run it under :func:`~accel_bayes.threads.torch_threads`, as ``calibrate`` runs: the detector's
    tensors are (T, 6K, ·) blocks and tiny per-sample systems, where a second torch thread only adds
    synchronisation on a shared machine.  ``None`` leaves torch's setting alone.  Results do not
    depend on it beyond floating-point reduction order."""
    sig = inspect.signature(fn)

    @functools.wraps(fn)
    def wrapper(*args, threads: int | None = DEFAULT_THREADS, **kwargs):
        with torch_threads(threads):
            return fn(*args, **kwargs)

    extra = inspect.Parameter("threads", inspect.Parameter.KEYWORD_ONLY, default=DEFAULT_THREADS)
    wrapper.__signature__ = sig.replace(parameters=[*sig.parameters.values(), extra])
    return wrapper


@_pinned_threads
def detect(recording, *, effects=None, alpha: float = 0.01, max_findings: int = 3, refine: bool = True,
           posterior=False, seed: int = 0, progress: bool = False, n_twins: int = 100,
           n_refit: int = 6, use_map: bool = True, loo_draws: int = 200) -> MismatchReport:
    """Find, name and fix model mismatch in one recording (module docstring).

    Parameters
    ----------
    recording : :class:`~accel_bayes.data.recording.Recording` or path to a format-v1 file (needs
        gyroscope data).
    effects : effect names to try (list or comma-separated string; default every registered effect,
        i.e. vocabulary v1.1 and the extensions; ``gyro_linear`` switches the gyro linear stage, step 3a);
        ``unexplained`` is always considered.
    alpha : family-wise error rate of the Bonferroni threshold (default 0.01).
    max_findings : most effects added to the model (default 3).
    refine : fill ``report.refined`` (the model with the findings, χ²/dof, log-likelihood, ELPD
        by PSIS-LOO, geometry before/after); False leaves it null.
    posterior : False, or the calibration function (:func:`accel_bayes.pipelines.calibrate.calibrate`,
        which ``mismatch`` cannot import: the pipelines stand above it) to run with short PmMH
        chains before and after correcting the recording for the findings (slow).
    seed : seeds the PPC twins, the Laplace draws and the posterior runs.
    progress : print stage messages (and LM progress bars).
    threads : torch CPU threads for the call (default 1, restored afterwards; None leaves torch's
        setting; :func:`_pinned_threads`).
    n_twins : PPC twins; n_refit : LM refits per round; use_map : start the baseline from the
        package's MAP; loo_draws : Laplace draws for PSIS-LOO.

    Returns a :class:`~accel_bayes.mismatch.report.MismatchReport`.
    """
    t_start = _time.perf_counter()
    alpha, names = _check_options(effects, alpha, max_findings, seed)
    if posterior is not False and posterior is not None and not callable(posterior):
        raise UserError(f"posterior: expected False or the calibration function "
                        f"(accel_bayes.pipelines.calibrate.calibrate), got {posterior!r}")
    loaded = load_recording(recording, require_gyro=True)
    rec, source = loaded.recording, None if loaded.path is None else str(loaded.path)
    _check_recording(rec)
    say = (lambda msg: print(f"[mismatch {(_time.perf_counter() - t_start):6.1f} s] {msg}", flush=True)) if progress \
        else (lambda msg: None)
    timings = {}
    prep = prepare(rec)
    t0 = _time.perf_counter()
    base, base_info = baseline_fit(prep, use_map=use_map, progress=False)
    timings["baseline_fit_s"] = _time.perf_counter() - t0
    say(f"baseline fit: χ²/dof = {base.chi2_per_dof:.4g} ({base_info['start']} start)")
    t0 = _time.perf_counter()
    loc0 = locate(prep, base, n_twins=n_twins, seed=seed)
    timings["locate_s"] = _time.perf_counter() - t0
    say(f"locate: {loc0.summary}")

    cands_all = candidate_effects(prep, names)
    n_gyro = int(np.asarray(prep.has_gyro).sum())
    gyro_stage = (names is None or "gyro_linear" in names) and n_gyro >= 2
    # Bonferroni over every test: the round candidates, and the stage's group and per-block tests
    m = len(cands_all) + (n_gyro + 1 if gyro_stage else 0)
    df_max = max([c.df for c in cands_all] + [1])
    threshold = threshold_rule(m, df_max, alpha)
    say(f"{m} candidates, threshold {threshold:.4g} (χ²_{df_max}, 1 − {alpha}/{m})")

    current = base
    accepted: list[dict] = []
    rounds = []
    t0 = _time.perf_counter()
    stage = None
    if gyro_stage:
        # step 3a: every gyro's linear error, held fixed from here on (the rounds run on the recording
        # corrected for it: accel_bayes.mismatch.gyro_linear)
        stage = gyro_linear_stage(prep, base, m=m, alpha=alpha)
        prep0, prep, current = prep, stage.prep, stage.fit
        say(f"gyro linear stage: {stage.info['result']}")
    timings["gyro_linear_s"] = _time.perf_counter() - t0
    t0 = _time.perf_counter()
    clock = None
    if (names is None or "sampling_clock" in names) and prep.gyro_rate is not None:
        # step 3b: every IMU's sampling clock, held fixed from here on like the gyro blocks (not a
        # round candidate, so not capped by max_findings: accel_bayes.mismatch.clock)
        clock = clock_stage(prep, current, m=m, alpha=alpha, threshold=threshold)
        if clock.clocks:
            if stage is not None:  # the blocks' refresh re-corrects prep0: it must carry the clocks too
                prep0 = clock_corrected(prep0, current, clock.clocks)
                stage.prep, stage.fit = clock.prep, clock.fit
            prep, current = clock.prep, clock.fit
        say(f"clock stage: sampling_clock on IMUs {clock.info['accepted']}")
    timings["clock_s"] = _time.perf_counter() - t0
    blocked = {e.imu for e in stage.blocks} if stage is not None else set()
    last_screens: list[Screen] = []
    for rnd in range(int(max_findings)):
        in_model = {e.label() for e in current.effects}
        taken = {(e.imu, ch) for e in current.effects if e.kind == "random" for ch in _random_channels(e)}
        # one random effect per IMU and sensor: two would each be profiled as if alone and
        # count the same variance twice; no gyro scale/misalignment/bias term where a gyro_linear
        # block already holds all twelve
        pool = [c.copy() for c in cands_all if c.label() not in in_model
                and not (c.kind == "random" and any((c.imu, ch) in taken for ch in _random_channels(c)))
                and not (c.name in _GYRO_LINEAR_TERMS and c.imu in blocked)]
        ts = _time.perf_counter()
        screens = screen(prep, current, pool)
        last_screens = screens
        chosen = _choose(screens, threshold, n_refit)
        info = {"round": rnd + 1, "screen_s": _time.perf_counter() - ts,
                "screen_top": [s.to_dict() for s in screens[:10]], "refits": []}
        say(f"round {rnd + 1}: screened {len(screens)}; refitting {[s.effect.label() for s in chosen]}")
        h_cur = current.linear().h
        results = []

        def refit(sc):
            cand = sc.effect
            try:
                model_eff = [e.copy() for e in current.effects] + [cand]
                f = fit_model(prep, model_eff, init=current, laplace=False)
            except Exception as exc:  # a candidate that cannot be fitted is reported, not fatal
                info["refits"].append({"candidate": cand.label(), "error": f"{type(exc).__name__}: {exc}"})
                return
            ev = _evidence(prep, f, current, cand)
            # noise-robust evidence of mean effects: the LR over the residual power left in the
            # effect's IMU/sensor group (an F-test-like guard: noise larger than stated inflates
            # every mean candidate's LR by the same factor)
            power = 1.0 if cand.kind in ("noise", "random") else group_power(prep, f, cand, h_cur)
            ev_r = ev / max(power, 1.0)
            lp = _log10_p(ev_r, cand)
            row = {"candidate": cand.label(), "evidence": ev, "evidence_robust": ev_r,
                   "group_power_after": power, "df": cand.df, "log10_p": lp,
                   "screen_statistic": sc.statistic, "seconds": f.seconds}
            unsteady = None
            if cand.kind == "mean" and ev_r > threshold:
                # a constant parameter must be constant: the score test across time segments
                # (noise-robust like the evidence), at the same family-wise level
                q, q_df = stationarity(prep, f, f.effects[-1])
                q_r = q / max(power, 1.0)
                q_thr = threshold_rule(m, q_df, alpha)
                row.update({"stationarity": q_r, "stationarity_df": q_df, "stationarity_threshold": q_thr})
                if q_r > q_thr:
                    unsteady = (f"its parameter is not constant through the recording: stationarity score "
                                f"{q_r:.4g} > {q_thr:.4g} (χ²_{q_df}, {STATIONARITY_SEGMENTS} time segments)")
            info["refits"].append(row)
            f.drop_linear()
            results.append({"effect": f.effects[-1], "fit": f, "evidence": ev, "evidence_robust": ev_r,
                            "log10_p": lp, "screen": sc, "without": current, "unsteady": unsteady})

        for sc in chosen:
            if sc.effect.kind != "noise":
                refit(sc)
        # noise_level is only considered in a round where no mean/clip candidate is acceptable
        # (below), so its refits are only done then: each one is up to ``noise_rounds`` + 1
        # LM solves, and on a badly fitting recording (real MIMU data, χ²/dof ~ 3000) they were
        # 3/4 of the detector's time while their result could not change the verdict.
        for r in [r for r in results if r.get("unsteady")]:
            info.setdefault("refused", []).append({"candidate": r["effect"].label(), "why": r["unsteady"]})
        results = [r for r in results if not r.get("unsteady")]
        mean_ok = any(r["effect"].kind not in ("noise", "random") and r["evidence_robust"] > threshold for r in results)
        for sc in chosen:
            if sc.effect.kind == "noise":
                if mean_ok:
                    info["refits"].append({"candidate": sc.effect.label(), "screen_statistic": sc.statistic,
                                           "skipped": "a mean/clip candidate is acceptable in this round"})
                else:
                    refit(sc)
        rounds.append(info)
        # mean (and clip) effects first; noise_level only when no structured effect passes,
        # because any unmodelled mean structure also raises the residual power
        variance_kinds = ("noise", "random")
        ok = [r for r in results if r["effect"].kind not in variance_kinds and r["evidence_robust"] > threshold]
        dominant = [r for r in results if r["effect"].kind == "random" and ok
                    and r["evidence"] > RANDOM_DOMINANCE * max(x["evidence_robust"] for x in ok)]
        # a timing_wander carries its triad's white-noise excess too: accept it only where the
        # timing term alone passes the threshold, otherwise it is noise_level under another name
        refused_w = [r for r in results if r["effect"].name == "timing_wander"
                     and r["effect"].stats.get("timing_evidence", math.inf) <= threshold]
        for r in refused_w:
            info.setdefault("refused", []).append({"candidate": r["effect"].label(),
                                                   "why": f"its timing term alone has evidence "
                                                          f"{r['effect'].stats['timing_evidence']:.4g} <= threshold"})
        results_ok = [r for r in results if r not in refused_w]
        dominant = [r for r in dominant if r not in refused_w]
        if dominant:
            # a correlated timing error looks like structure to every mean candidate, yet each
            # explains a small part of it: a random effect far ahead of all of them goes first
            ok = dominant
        elif not ok:
            ok = [r for r in results_ok if r["effect"].kind in variance_kinds and r["evidence"] > threshold]
            if any(r["effect"].kind == "noise" for r in ok):
                # noise_level says "a constant factor": refuse it where the excess power varies
                # strongly with the motion (the characteriser's covariates), and leave that excess
                # to a better variance model or to the characterised ``unexplained`` finding
                char_now = characterise(prep, current)
                keep = []
                for r in ok:
                    why = _heteroscedastic(char_now, r["effect"], alpha) if r["effect"].kind == "noise" else None
                    if why is None:
                        keep.append(r)
                    else:
                        info.setdefault("refused", []).append({"candidate": r["effect"].label(), "why": why})
                ok = keep
        best = min(ok, key=lambda r: r["log10_p"]) if ok else None
        if best is None:
            say("no further candidate above the threshold")
            break
        say(f"accepted {best['effect'].label()} (evidence {best['evidence']:.4g})")
        best["alternatives"] = alternatives(best, results)
        accepted.append(best)
        current = best["fit"]
        if stage is not None and stage.blocks:
            # the blocks were fitted without this finding: re-estimate them given it (gyro_linear.refresh_blocks)
            for _ in range(REFRESH_PASSES):
                current = refresh_blocks(prep0, stage, current)
            prep = stage.prep
    timings["detection_s"] = _time.perf_counter() - t0

    # ---- evidence with all other findings in the model (drop-one); a finding whose evidence falls
    # to the threshold or below once the others are in the model is withdrawn and the model refitted
    t0 = _time.perf_counter()
    withdrawn = []
    while True:
        drops = []
        for i, acc_ in enumerate(accepted):
            eff = current.effects[i]
            if len(accepted) > 1:
                others = [e.copy() for j, e in enumerate(current.effects) if j != i]
                without = fit_model(prep, others, init=current, laplace=False)
                ev = _evidence(prep, current, without, eff)
            else:
                without, ev = acc_["without"], acc_["evidence"]
            drops.append((ev, without))
        weakest = min(range(len(drops)), key=lambda i: drops[i][0]) if drops else None
        if weakest is None or drops[weakest][0] > threshold:
            break
        withdrawn.append({"effect": current.effects[weakest].label(), "evidence": drops[weakest][0]})
        say(f"withdrew {current.effects[weakest].label()} (evidence {drops[weakest][0]:.4g} with the others in the model)")
        current = drops[weakest][1]
        accepted.pop(weakest)
    if accepted:
        _effect_std(current, [e for e in current.effects if e.kind in ("mean", "clip")])
    reg = regimes(prep, current)
    findings: list[Finding] = []
    for i, acc_ in enumerate(accepted):
        eff = current.effects[i]
        ev, without = drops[i]
        gain = (current.loglik_t - without.loglik_t).numpy()
        if eff.kind == "noise":
            where = {"regime": "all regimes", "time_s": None}
        else:
            where = regime_concentration(prep, reg, gain)
        findings.append(Finding(effect=eff, evidence=float(ev), df=eff.df, log10_p=_log10_p(ev, eff),
                                where=where, explanation=eff.explain(), screen_statistic=acc_["screen"].statistic,
                                orientations=prep.q,
                                extra={"evidence_when_added": acc_["evidence"],
                                       "evidence_noise_robust": acc_["evidence_robust"],
                                       "alternatives": acc_.get("alternatives", []),
                                       # a wander's estimated instants (jitter.random_offsets): mean, rms, s
                                       **({"instants_s": {"mean": eff.stats["instant_mean_s"],
                                                          "rms": eff.stats["instant_rms_s"]}}
                                          if "instant_mean_s" in eff.stats else {})}))
    for c in (clock.clocks if clock is not None else []):  # the clock stage's (held fixed like the blocks)
        ev = float(c.stats["evidence"])
        findings.append(Finding(effect=c, evidence=ev, df=c.df, log10_p=_log10_sf(ev, 4),
                                where={"regime": "all regimes", "time_s": None}, explanation=c.explain(),
                                screen_statistic=None, orientations=prep.q,
                                extra={"evidence_kind": "2·Δlog L of the gyro's restricted timing statistics, "
                                                        "white-noise factor profiled (mismatch.clock)",
                                       "evidence_vs_wander": float(c.stats["evidence_vs_wander"]),
                                       "units": {p.name: p.unit for p in c.parameters}}))
    fixed = list(stage.blocks) if stage is not None else []
    for e in fixed:  # the gyro linear stage's blocks (held fixed in every fit above)
        ev = float(e.stats["statistic_robust"])
        findings.append(Finding(effect=e, evidence=ev, df=e.df, log10_p=_log10_sf(ev, e.df),
                                where=regime_concentration(prep, reg, stage.gain_t), explanation=e.explain(),
                                screen_statistic=None, orientations=prep.q,
                                extra={"evidence_kind": "the block's conditional likelihood ratio at the final rates "
                                                        "over max(1, P) (gyro linear stage)",
                                       "evidence_raw": float(e.stats["statistic"])}))
    timings["evidence_s"] = _time.perf_counter() - t0

    # ---- unexplained located excess at the final model
    t0 = _time.perf_counter()
    loc_final = loc0 if current is base else locate(prep, current, n_twins=n_twins, seed=seed + 1)
    tests = loc_final.excess_tests
    # what the final model leaves, described (item 2 of issue #11): what it scales with, white or
    # correlated in time, along the output's rate (timing-like) or isotropic
    t_c = _time.perf_counter()
    characterisation = characterise(prep, current, coupling=True)
    timings["characterise_s"] = _time.perf_counter() - t_c
    unexplained = None
    if tests:
        from scipy.stats import chi2

        m_u = len(tests)
        top = tests[0]
        thr_u = float(chi2.isf(alpha / m_u, top["df"]))
        if top["statistic"] > thr_u and top["statistic"] > threshold:
            # the same cell's strongest regime bin and time window, where each is significant
            same = [t for t in tests if (t["imu"], t["sensor"], t["axis"]) == (top["imu"], top["sensor"], top["axis"])]
            sig = [t for t in same if t["statistic"] > float(chi2.isf(alpha / m_u, t["df"]))]
            reg_t = next((t for t in sig if t["scheme"] != "time"), None)
            time_t = next((t for t in sig if t["scheme"] == "time"), None)
            tw = time_window(prep, loc_final.reg, time_t["contributions"]) if time_t is not None else None
            where = {"regime": reg_t["bin"] if reg_t is not None else None, "time_s": tw,
                     "scheme": top["scheme"], "bin": top["bin"]}
            char_u = characterisation.get(top["sensor"]) if top["sensor"] in ("acc", "gyro") else None
            imu_c = None if char_u is None else next((r for r in char_u["imus"] if r["imu"] == top["imu"]), None)
            u = Unexplained(imu=top["imu"], axis=top["axis"], sensor=top["sensor"], where=where,
                            excess={"chi2_ratio": top["chi2_ratio"], "mean_z": top["mean_z"],
                                    "scheme": top["scheme"], "bin": top["bin"], "df": top["df"],
                                    "threshold": thr_u,
                                    "scales_with": None if imu_c is None else imu_c["top_covariate"],
                                    "lag1_autocorrelation": None if imu_c is None else imu_c["autocorrelation"].get("lag1"),
                                    "anisotropy": None if imu_c is None else imu_c["anisotropy"]},
                            characterisation=None if imu_c is None else describe(char_u, top["sensor"], top["imu"]))
            unexplained = Finding(effect=u, evidence=float(top["statistic"]), df=int(top["df"]),
                                  log10_p=float(top["log10_p"]), where=dict(u.where), explanation=u.explain(),
                                  screen_statistic=None)
            findings.append(unexplained)
    timings["unexplained_s"] = _time.perf_counter() - t0
    findings.sort(key=lambda f: f.log10_p)

    # ---- refined model and comparison
    refined = None
    comparison = None
    post = None
    t0 = _time.perf_counter()
    if refine and (accepted or fixed or (clock is not None and clock.clocks)):
        refined = current
        comparison = compare_fits(base, refined, draws=loo_draws, seed=seed)
        say(f"refined: χ²/dof {base.chi2_per_dof:.4g} → {refined.chi2_per_dof:.4g}")
        if posterior:
            fixed_src = None if stage is None else block_corrected_recording(prep.source, stage.blocks)
            post = posterior_comparison(prep.source, refined, posterior, seed=seed, progress=progress, corrected_base=fixed_src,
                                        index=prep.selection.index)
    timings["refine_s"] = _time.perf_counter() - t0
    # residual budget (vocabulary 1.1): against the model with the findings, also with
    # refine=False (it is fitted already); b = 0 where nothing was found
    budget = residual_budget(prep, base, None if current is base else current)
    timings["total_s"] = _time.perf_counter() - t_start
    settings = {"effects": names if names is not None else list(EFFECTS), "alpha": alpha,
                "max_findings": int(max_findings), "refine": bool(refine), "posterior": bool(posterior),
                "seed": int(seed), "n_twins": int(n_twins), "n_refit": int(n_refit), "use_map": bool(use_map),
                "loo_draws": int(loo_draws)}
    return MismatchReport(
        findings=findings, baseline_fit=base, refined_fit=refined, threshold=threshold, alpha=alpha, n_candidates=m,
        df_max=df_max, location=loc0, location_after=None if current is base else loc_final,
        comparison=comparison, posterior=post, settings=settings, timings=timings, rounds=rounds,
        withdrawn=withdrawn, budget=budget,
        screens=[s.to_dict() for s in last_screens[:20]], baseline_info=base_info, source=source,
        recording_info={"T": prep.T, "K": prep.K, "reference_imu": prep.ref, "description": rec.description,
                        "T_given": int(len(rec.time)), "dropped_clipped": int(prep.n_dropped_clipped),
                        "preparation": prep.preparation,
                        "sample_rate_hz": rec.sample_rate},
        prep=prep, characterisation=characterisation,
        gyro_linear=None if stage is None else stage.info,
        fixed_effects=fixed + (list(clock.clocks) if clock is not None else []),
        clock=None if clock is None else clock.info,
    )
