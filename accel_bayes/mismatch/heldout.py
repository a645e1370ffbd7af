"""Held-out scoring of the physics model against strong generic models (DESIGN §7.2.1; issue #27
item 4).

A recording's *residuals* are the nominal model's (``baseline_fit``: positions and per-sample
motion states fitted), leverage-corrected and rotated into the array frame, per sensor
(:func:`residuals_of`); every model scores the same residuals, on the samples where all triads of
the sensor are observed.  Models (:mod:`accel_bayes.mismatch.generic`), all per |ω| band with the
source's band edges:

- generic: ``white`` (banded white noise per IMU), ``triad_t``, ``sample_t``, ``full_cov``;
- physics: the clock's data age d_kt (centred over the IMUs, s) gives a mean −c·d_kt ẏ_kt (ẏ the
  ``sampling_clock`` effect's rate regressor: the resolved motion seen late) and loads the unresolved motion
  (:mod:`accel_bayes.mismatch.unresolved`) — ``physics`` has a white remainder, ``physics+sample_t``
  and ``physics+full_cov`` put the term on those models' covariance, ``physics+triad_t`` has the
  mean only (a per-triad scale mixture does not marginalise with a term shared across triads).

The clock's beat, phase and drift per IMU are acquired by the detector's own beat search
(:func:`accel_bayes.mismatch.clock.estimate_clock`) on each IMU's gyro timing statistics — the
clock stage's (:func:`accel_bayes.mismatch.clock.clock_ab`, on the regressor R_k ω̇; kept in
:class:`Residuals`): the source's on its whole recording (:func:`clocks_of`); the target's on its
first 30 s of contiguous motion (:func:`motion_window`), every sample of it, from the window's own
fit (:func:`window_statistics`), every model then scored on the kept samples after the window.  The
causal tracker (:func:`tracked_age`) scores prequentially: each later block's clock is acquired on
the target samples before that block only (a protocol extension).

The age marginalised (the protocol's physics): the acquisition is a posterior, not a certainty, and
the beats drift.  :func:`clock_posteriors` gives each IMU's phase/beat posterior on the window,
:func:`marginal_age` carries it forward with the *source's* beat random walk
(:func:`~accel_bayes.mismatch.age_predictive.beat_walk_rate`) into the centred ages' predictive moments,
and :func:`score` then scores the physics with the age marginalised (the mean term on E d, the
covariance gaining the age variance: :mod:`accel_bayes.mismatch.age_predictive`).  The evidence rule
(:func:`clock_accepted`) reads the data age's width, the fitted one over the regressor's scale λ
(:func:`with_rate_scale`, the clock stage's definition).
Every scale (white variances, degrees of freedom, covariances, unresolved scales, the mean's c)
comes from the source.  Uncertainty: a moving-block bootstrap over the scored samples
(:func:`block_bootstrap_se`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..physics.effects import board_gyro_rate, clock_age as sawtooth_age
from .age_predictive import AgeMoments, age_moments, phase_posterior
from .budget import band_edges
from .clock import WIDTH_RANGE_S, clock_ab, estimate_clock, physical_width, rate_scale
from .generic import BandedWhite, FullCov, SampleT, TriadT, describe
from .vibration import array_residuals, instant_errors

__all__ = ["Residuals", "residuals_of", "clocks_of", "clock_age", "centred", "fit_source", "score",
           "block_bootstrap_se", "acquired_age", "motion_window", "window_statistics", "clocks_from", "tracked_clocks", "tracked_age",
           "with_rate_scale", "clock_accepted", "clock_posteriors", "marginal_age", "GENERIC", "PHYSICS"]

GENERIC = ("white", "triad_t", "sample_t", "full_cov")
PHYSICS = ("physics", "physics+triad_t", "physics+sample_t", "physics+full_cov")
F_INT_NOMINAL = 1000.0  # Hz: the MPU-6050/9150 internal sample rate (DLPF on), the data age's span 1/f_int


@dataclass
class Residuals:
    """One recording's held-out inputs (torch float64): ``time`` (T,) s; ``omega`` (T,) |ω| of the
    fitted motion rad/s; per sensor ``y[s]`` (T, K, 3) array-frame residuals, ``rate[s]`` (T, K, 3)
    the clock effect's rate regressor in the array frame (units/s: R_k ω̇ for the gyro, the fitted
    outputs' finite difference for the accelerometer), ``ok[s]`` (T,) all triads observed;
    ``delta`` (T, K) s the gyro instant errors and ``delta_ok`` (T, K); ``timing_a`` (T, K) s⁻² and
    ``timing_b`` (T, K) s⁻¹ each IMU's gyro timing statistics (:func:`~accel_bayes.mismatch.clock.clock_ab`,
    0 where it has no gyro), which the clock acquisition reads."""

    time: torch.Tensor
    omega: torch.Tensor
    y: dict
    rate: dict
    ok: dict
    delta: torch.Tensor
    delta_ok: torch.Tensor
    f_read: float
    timing_a: torch.Tensor | None = None
    timing_b: torch.Tensor | None = None


def residuals_of(prep, fit) -> Residuals:
    """The :class:`Residuals` of a prepared recording and its nominal fit (``baseline_fit``, which
    also set ``prep.acc_rate``).  The rate regressors are the ``sampling_clock`` effect's
    (:class:`~accel_bayes.physics.effects.SamplingClock`): the gyro's R_k ω̇ of the fitted motion
    (:func:`~accel_bayes.physics.effects.board_gyro_rate`; the finite difference of the sampled
    outputs folds vibration above the read's Nyquist rate, flipped and shrunk), the accelerometer's
    ``prep.acc_rate``; the timing statistics are the detector's clock stage's
    (:func:`accel_bayes.mismatch.clock.clock_ab`)."""
    from ..physics.geometry import quat_to_matrix

    R = quat_to_matrix(torch.as_tensor(prep.q, dtype=torch.float64))
    y, rate, ok = {}, {}, {}
    for s, r in (("acc", prep.acc_rate), ("gyro", board_gyro_rate(fit.ctx).detach())):
        y[s], okk = array_residuals(prep, fit, s)
        ok[s] = okk.all(1)
        rate[s] = torch.einsum("kji,tkj->tki", R, r.to(torch.float64))
    delta, dok = instant_errors(prep, fit)
    t = prep.time.to(torch.float64)
    f_read = float(1.0 / np.median(np.diff(t.numpy())))
    ta = torch.zeros(prep.T, prep.K, dtype=torch.float64)
    tb = torch.zeros_like(ta)
    for k in [int(j) for j in np.flatnonzero(prep.has_gyro)]:
        a, b, *_ = clock_ab(prep, fit, k)
        ta[:, k], tb[:, k] = a.detach(), b.detach()
    return Residuals(t, torch.linalg.norm(fit.x[:, 0:3].detach(), dim=1).to(torch.float64), y, rate, ok,
                     delta, dok, f_read, ta, tb)


def clock_age(t, beat, phase, f_int=F_INT_NOMINAL) -> torch.Tensor:
    """(T, K) data age (s) of IMUs with beat frequencies ``beat`` (K,) Hz and phases ``phase``
    (K,) cycles at times t (T,) s: frac(beat·t + phase)/f_int, a sawtooth on [0, 1/f_int) —
    the effect's own :func:`accel_bayes.physics.effects.clock_age` without drift, over the IMUs."""
    t = torch.as_tensor(t, dtype=torch.float64)[:, None]
    beat = torch.as_tensor(beat, dtype=torch.float64)[None, :]
    phase = torch.as_tensor(phase, dtype=torch.float64)[None, :]
    return sawtooth_age(t, beat, phase, 0.0, 1.0 / f_int)


def centred(age: torch.Tensor) -> torch.Tensor:
    """Ages less their mean over the IMUs (s): a common age is absorbed by the motion states."""
    return age - age.mean(1, keepdim=True)


def clocks_of(res: Residuals, window=None) -> dict:
    """Each IMU's clock from the detector's beat search (:func:`accel_bayes.mismatch.clock.estimate_clock`)
    on its gyro timing statistics over the samples ``window`` (T,) bool (default all): {"beat_hz",
    "phase" (cycles at t = 0 of the recording's clock), "drift_hz_per_s", "width_s"}, each (K,) numpy;
    zeros on an IMU without gyro statistics or with fewer than 20 samples in the window."""
    window = np.ones(len(res.time), bool) if window is None else np.asarray(window, bool)
    return clocks_from(res.time.numpy()[window], res.timing_a[window], res.timing_b[window], res.f_read)


def motion_window(prep, seconds: float) -> np.ndarray:
    """(T_source,) bool over ``prep.source`` (every sample of the recording): the first ``seconds``
    of contiguous motion — from the first sample after which the board does not rest for
    ``seconds`` (rests: :func:`accel_bayes.prep.intrinsics.rest_segments`).  Why not the
    recording's first ``seconds``: a recording that opens with rests for the intrinsics (the MIMU
    experiments: ~500 s of rests with 1.5 s turns between them) has no timing information there
    (ω̇ = 0 gives a_t = 0).  Every sample of the window counts, slow ones too (the position fit's
    rotation test is about the centripetal term, not about timing); the window's clipped and
    flagged samples are dropped by the selection.  Refuses a recording without such a stretch."""
    from ..errors import UserError
    from ..prep.intrinsics import rest_segments

    src = prep.source
    T = int(src.T)
    moving = np.ones(T, bool)
    for a, b in rest_segments(src, None):
        moving[a:b] = False
    t = np.asarray(src.time, float)
    starts = np.flatnonzero(moving & np.concatenate(([True], ~moving[:-1])))
    for i0 in starts:
        end = i0 + np.searchsorted(t[i0:], t[i0] + seconds)
        if end <= T and moving[i0:end].all() and t[min(end, T) - 1] - t[i0] >= seconds - 2 * np.median(np.diff(t)):
            w = np.zeros(T, bool)
            w[i0:end] = True
            return w
    raise UserError(f"acquire_s: expected a stretch of {seconds:g} s without rests in the recording, found none")


def window_statistics(prep, window, *, rate_scales: bool = False):
    """The gyro timing statistics of the clock stage (:func:`accel_bayes.mismatch.clock.clock_ab`) on
    the samples ``window`` of ``prep.source`` (:func:`motion_window`), from the window's own
    nominal fit (positions and motion fitted on the window alone, :func:`baseline_fit`): (times (n,)
    s, a (n, K) s⁻², b (n, K) s⁻¹, f_read Hz); with ``rate_scales``, (that, λ (K,)) — each IMU's
    regressor scale on the window's fit (:func:`accel_bayes.mismatch.clock.rate_scale`; 1 without
    gyro), which turns a fitted sawtooth width into the data age's (:func:`with_rate_scale`)."""
    from ..prep.prepared import prepare_recording
    from ..prep.selection import select_samples
    from .fit import baseline_fit
    from .prepared import from_prepared

    sel = select_samples(prep.source, min_rotation=0.0, drop_static=False, user=np.asarray(window, bool))
    prep_w = from_prepared(prepare_recording(prep.source, selection=sel))
    fit_w, _ = baseline_fit(prep_w)
    res_w = residuals_of(prep_w, fit_w)
    stats = res_w.time.numpy(), res_w.timing_a, res_w.timing_b, res_w.f_read
    if not rate_scales:
        return stats
    lam = np.ones(prep_w.K)
    for k in [int(j) for j in np.flatnonzero(prep_w.has_gyro)]:
        lam[k] = rate_scale(prep_w, fit_w, k)
    return stats, lam


def clocks_from(t, a, b, f_read: float, rate_scales=None) -> dict:
    """Each IMU's clock from the detector's beat search (:func:`accel_bayes.mismatch.clock.estimate_clock`)
    on timing statistics a, b (n, K) at times t (n,) s: {"beat_hz", "phase" (cycles at t = 0 of the
    recording's clock), "drift_hz_per_s", "width_s", "evidence", "threshold"}, each (K,) numpy;
    zeros on an IMU with fewer than 20 samples of information (a > 0).  ``evidence`` (nats ×2):
    2·gain/ĉ², the search's gain with the statistics' noise factor ĉ² = Σb²/Σa profiled (Var b = ĉ²a
    without a clock); ``threshold``: the clock stage's look-elsewhere χ²₄ quantile at 1 − 0.01/(K·cells).
    ``rate_scales`` (K,): the regressor's scale λ per IMU — ``width_s`` is then the data age's width,
    the fitted one over λ, as the clock stage reports it (:func:`with_rate_scale`)."""
    from scipy.stats import chi2

    t = np.asarray(t, float)
    K = a.shape[1]
    out = {k: np.zeros(K) for k in ("beat_hz", "phase", "drift_hz_per_s", "width_s", "evidence", "threshold")}
    for k in range(K):
        ak, bk = np.asarray(a[:, k], float), np.asarray(b[:, k], float)
        if int((ak > 0).sum()) < 20:
            continue
        est = estimate_clock(t, ak, bk, f_read)
        for key in ("beat_hz", "phase", "drift_hz_per_s", "width_s"):
            out[key][k] = est[key]
        out["evidence"][k] = 2.0 * est["gain"] * ak.sum() / max(float((bk * bk).sum()), 1e-300)
        out["threshold"][k] = float(chi2.isf(0.01 / (K * max(est["cells"], 1)), 4))
    return out if rate_scales is None else with_rate_scale(out, rate_scales)


def with_rate_scale(clock: dict, lam) -> dict:
    """A :func:`clocks_from` clock (fitted widths, as cached before λ was applied) with the clock
    stage's definition of the width: ``width_fit_s`` the fitted one, ``width_s`` =
    :func:`~accel_bayes.mismatch.clock.physical_width` (fitted / λ), ``age_rms_s`` = width_s/√12,
    ``rate_scale`` λ (K,).  Applying it twice is refused (the width would be divided twice)."""
    if "rate_scale" in clock:
        raise ValueError("with_rate_scale: the clock's width already has its rate scale")
    out = dict(clock)
    out["width_fit_s"] = np.asarray(clock["width_s"], float)
    out["rate_scale"] = np.asarray(lam, float)
    out["width_s"] = np.array([physical_width(w, l) for w, l in zip(out["width_fit_s"], out["rate_scale"])])
    out["age_rms_s"] = out["width_s"] / math.sqrt(12.0)
    return out


def clock_accepted(clock: dict) -> np.ndarray:
    """(K,) bool: the evidence rule — the clock's evidence above its look-elsewhere threshold and its
    width (``width_s``, the data age's: :func:`with_rate_scale`) within the clock stage's
    :data:`~accel_bayes.mismatch.clock.WIDTH_RANGE_S`."""
    w = np.asarray(clock["width_s"])
    return (np.asarray(clock["evidence"]) > np.asarray(clock["threshold"])) & (w >= WIDTH_RANGE_S[0]) & (w <= WIDTH_RANGE_S[1])


def tracked_clocks(res: Residuals, window_stats, *, after: float, block_s: float) -> list:
    """The causal (prequential) clock tracker: the scored stretch t ≥ ``after`` cut into blocks of
    ``block_s`` s, each with the clock the beat search (:func:`clocks_from`) acquires on every target
    sample *before the block*: the acquisition window's ``window_stats`` (:func:`window_statistics`)
    and ``res``'s own kept samples from ``after`` to the block's start.  Returns [(start s, clock)]
    (the first block's clock is the window's alone: the plain acquisition)."""
    tw, aw, bw, f_read = window_stats
    t = res.time.numpy()
    blocks, start = [], after
    while start <= t[-1]:
        past = (t >= after) & (t < start)
        blocks.append((float(start), clocks_from(np.concatenate([tw, t[past]]), torch.cat([aw, res.timing_a[past]]),
                                                 torch.cat([bw, res.timing_b[past]]), f_read)))
        start += block_s
    return blocks


def tracked_age(res: Residuals, blocks: list, *, block_s: float, accept=None, f_int=F_INT_NOMINAL) -> torch.Tensor:
    """(T, K) data age (s) at ``res``'s times from :func:`tracked_clocks`'s blocks (each block's
    samples get its clock; 0 before the first block), through :func:`acquired_age`."""
    t = res.time.numpy()
    age = torch.zeros(len(t), res.timing_a.shape[1], dtype=torch.float64)
    for start, clock in blocks:
        cur = (t >= start) & (t < start + block_s)
        if cur.any():
            age[cur] = acquired_age(res, clock, f_int, accept=accept)[cur]
    return age


def acquired_age(res: Residuals, clock: dict, f_int=F_INT_NOMINAL, accept=None) -> torch.Tensor:
    """(T, K) data age (s) at ``res``'s times of the clocks :func:`clocks_from` gave, each a
    sawtooth of span 1/f_int (the age's mean and width are taken up by the fitted coefficient c).
    ``accept``: None (every clock) or "evidence" — an IMU that fails :func:`clock_accepted` gets the
    IMUs' mean age instead (no clock: a beat the search cannot tell from noise would load the wrong
    samples)."""
    t = torch.as_tensor(res.time, dtype=torch.float64)[:, None]
    c = {k: torch.as_tensor(clock[k], dtype=torch.float64)[None, :] for k in ("beat_hz", "phase", "drift_hz_per_s")}
    age = sawtooth_age(t, c["beat_hz"], c["phase"], c["drift_hz_per_s"], 1.0 / f_int)
    if accept == "evidence":
        ok = clock_accepted(clock)
        if ok.any():
            age[:, ~ok] = age[:, ok].mean(1, keepdim=True)
        else:
            age[:] = 0.0
    return age


def clock_posteriors(window_stats, clock: dict, *, accept=None) -> list:
    """Per IMU the posterior of its phase and beat at the acquisition window's centre
    (:func:`~.age_predictive.phase_posterior`) on the window's statistics ``window_stats``
    (:func:`window_statistics`) about ``clock`` (:func:`clocks_from` on them); None — no clock, the
    age uniform — on an IMU with under 20 informative samples or no sawtooth (width 0), or failing
    :func:`clock_accepted` when ``accept`` is "evidence"."""
    tw, aw, bw, _ = window_stats
    aw, bw = np.asarray(aw, float), np.asarray(bw, float)
    ok = clock_accepted(clock) if accept == "evidence" else np.ones(aw.shape[1], bool)
    posts = []
    for k in range(aw.shape[1]):
        info = aw[:, k] > 0
        if not ok[k] or int(info.sum()) < 20 or clock["width_s"][k] <= 0:
            posts.append(None)
            continue
        posts.append(phase_posterior(tw[info], aw[info, k], bw[info, k], beat_hz=clock["beat_hz"][k], phase=clock["phase"][k],
                                     drift_hz_per_s=clock["drift_hz_per_s"][k], t_c=0.5 * (tw[0] + tw[-1])))
    return posts


def marginal_age(res: Residuals, posts: list, q, *, f_int=F_INT_NOMINAL) -> AgeMoments:
    """The centred data ages' predictive moments at ``res``'s times (:class:`~.age_predictive.AgeMoments`)
    from the acquisition's :func:`clock_posteriors` carried forward with the source's
    :class:`~.age_predictive.ForecastNoise` q (:func:`~.age_predictive.fit_forecast_noise`; a float: the beat
    walk's rate alone, Hz²/s, :func:`~.age_predictive.beat_walk_rate`), ages of span 1/f_int (s)."""
    mean, var = age_moments(res.time.numpy(), posts, q, 1.0 / f_int)
    return AgeMoments.of(mean, var)


def _mean_coeff(y, rate, d, ok) -> float:
    """c of the mean −c·d·ẏ by least squares (dimensionless; 1 when the age is the data age)."""
    m = ok.to(y.dtype)[:, None, None]
    g = -d[:, :, None] * rate * m
    return float((g * y).sum() / (g * g).sum().clamp_min(1e-300))


def fit_source(res: Residuals, age: torch.Tensor, *, models=GENERIC + PHYSICS, progress=None) -> dict:
    """Fit every model on a source's residuals (its samples with all triads observed), per sensor.
    Returns {"edges": [...], "acc": {...}, "gyro": {...}}: per sensor the fitted models by name
    and the mean's coefficient ``c``, and ``seconds`` per model.  ``progress``: called with a
    line after each fit."""
    import time
    edges = band_edges(res.omega.numpy())
    lab_all = torch.as_tensor(np.digitize(res.omega.numpy(), edges), dtype=torch.long)
    B = len(edges) + 1
    d_all = centred(age)
    out = {"edges": edges}
    for s in ("acc", "gyro"):
        ok = res.ok[s]
        y, lab, d, rate = res.y[s][ok], lab_all[ok], d_all[ok], res.rate[s][ok]
        c = _mean_coeff(y, rate, d, torch.ones(len(y), dtype=torch.bool))
        e = y + c * d[:, :, None] * rate
        m, secs = {"c": c}, {}
        fits = {"white": lambda: BandedWhite.fit(y, lab, B), "triad_t": lambda: TriadT.fit(y, lab, B),
                "sample_t": lambda: SampleT.fit(y, lab, B), "full_cov": lambda: FullCov.fit(y, lab, B),
                "physics": lambda: BandedWhite.fit(e, lab, B, d=d),
                "physics+triad_t": lambda: TriadT.fit(e, lab, B),
                "physics+sample_t": lambda: SampleT.fit(e, lab, B, d=d, start=m["physics"]),
                "physics+full_cov": lambda: FullCov.fit(e, lab, B, d=d, start=m["physics"])}
        for name in ("physics",) + tuple(k for k in fits if k in models and k != "physics"):
            t0 = time.perf_counter()
            m[name] = fits[name]()
            secs[name] = time.perf_counter() - t0
            if progress is not None:
                progress(f"  {s} {name}: {secs[name]:.1f} s")
        m["seconds"] = secs
        out[s] = m
    return out


def score(source: dict, res: Residuals, age, keep) -> dict:
    """Per sensor, each model's per-sample log density (nats, numpy (n,)) of the target's
    residuals on the samples ``keep`` (T,) bool that have all triads observed, with the source's
    parameters and the target's ages: (T, K) s (deterministic, centred here), or the centred ages'
    predictive :class:`~.age_predictive.AgeMoments` (:func:`marginal_age`, all T samples): the physics
    models then score the age marginalised (mean term on E d, covariance with the age variance)."""
    edges = source["edges"]
    lab_all = torch.as_tensor(np.digitize(res.omega.numpy(), edges), dtype=torch.long)
    marg = isinstance(age, AgeMoments)
    d_all = age.mean if marg else centred(age)
    keep = torch.as_tensor(np.asarray(keep, bool))
    out = {}
    for s in ("acc", "gyro"):
        sel = keep & res.ok[s]
        y, lab, d, rate = res.y[s][sel], lab_all[sel], d_all[sel], res.rate[s][sel]
        m = source[s]
        e = y + m["c"] * d[:, :, None] * rate
        if marg:
            d = AgeMoments(d, age.factor[sel], m["c"] * rate)
        ll = {}
        for name, model in m.items():
            if name in ("c", "seconds"):
                continue
            phys = name.startswith("physics")
            with torch.no_grad():
                ll[name] = model.logpdf(e if phys else y, lab, d if phys else None).numpy()
        out[s] = {"ll": ll, "n": int(sel.sum()), "index": np.flatnonzero(sel.numpy())}
    return out


def describe_source(source: dict) -> dict:
    """JSON-ready summary of :func:`fit_source`'s models (edges, c, ν, unresolved scales)."""
    out = {"edges": [float(e) for e in source["edges"]]}
    for s in ("acc", "gyro"):
        out[s] = {"c": float(source[s]["c"])}
        out[s].update({k: describe(v) for k, v in source[s].items() if k not in ("c", "seconds")})
        out[s]["seconds"] = dict(source[s].get("seconds", {}))
    return out


def block_bootstrap_se(x, *, block: int = 125, n_boot: int = 400, seed: int = 0) -> float:
    """Standard error of the mean of the series x (n,) by a moving-block bootstrap (blocks of
    ``block`` consecutive samples, 125 = 2 s at 62.5 Hz; ``n_boot`` resamples, seeded)."""
    x = np.asarray(x, dtype=float)
    n = len(x)
    if n < 2:
        return float("nan")
    block = max(1, min(block, n))
    nb = int(math.ceil(n / block))
    rng = np.random.default_rng(seed)
    c = np.concatenate(([0.0], np.cumsum(x)))
    starts = rng.integers(0, n - block + 1, size=(n_boot, nb))
    sums = (c[starts + block] - c[starts]).sum(1)
    return float(np.std(sums / (nb * block), ddof=1))
