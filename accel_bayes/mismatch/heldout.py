"""Held-out scoring of the physics model against strong generic models (DESIGN §7.2.1; issue #27
item 4).

A recording's *residuals* are the nominal model's (``baseline_fit``: positions and per-sample
motion states fitted), leverage-corrected and rotated into the array frame, per sensor
(:func:`residuals_of`); every model scores the same residuals, on the samples where all triads of
the sensor are observed.  Models (:mod:`accel_bayes.mismatch.generic`), all per |ω| band with the
source's band edges:

- generic: ``white`` (banded white noise per IMU), ``triad_t``, ``sample_t``, ``full_cov``;
- physics: the clock's data age d_kt (centred over the IMUs, s) gives a mean −c·d_kt ẏ_kt (ẏ the
  fitted output's rate: the resolved motion seen late) and loads the unresolved motion
  (:mod:`accel_bayes.mismatch.unresolved`) — ``physics`` has a white remainder, ``physics+sample_t``
  and ``physics+full_cov`` put the term on those models' covariance, ``physics+triad_t`` has the
  mean only (a per-triad scale mixture does not marginalise with a term shared across triads).

The clock's beat and phase per IMU are acquired from each IMU's gyro instant errors
(:func:`accel_bayes.mismatch.vibration.instant_errors`) by :func:`acquire_clock` — on the
target's first ``acquire_s`` seconds of kept samples only; the source's on its whole recording.
Every scale (white variances, degrees of freedom, covariances, unresolved scales, the mean's c)
comes from the source.  Uncertainty: a moving-block bootstrap over the scored samples
(:func:`block_bootstrap_se`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..physics.effects import clock_age as sawtooth_age
from .budget import band_edges
from .generic import BandedWhite, FullCov, SampleT, TriadT, describe
from .vibration import array_residuals, instant_errors

__all__ = ["Residuals", "residuals_of", "acquire_clock", "clock_age", "centred", "fit_source", "score",
           "block_bootstrap_se", "GENERIC", "PHYSICS"]

GENERIC = ("white", "triad_t", "sample_t", "full_cov")
PHYSICS = ("physics", "physics+triad_t", "physics+sample_t", "physics+full_cov")
F_INT_NOMINAL = 1000.0  # Hz: the MPU-6050/9150 internal sample rate (DLPF on), the data age's span 1/f_int


@dataclass
class Residuals:
    """One recording's held-out inputs (torch float64): ``time`` (T,) s; ``omega`` (T,) |ω| of the
    fitted motion rad/s; per sensor ``y[s]`` (T, K, 3) array-frame residuals, ``rate[s]`` (T, K, 3)
    the fitted outputs' rates in the array frame (units/s), ``ok[s]`` (T,) all triads observed;
    ``delta`` (T, K) s the gyro instant errors and ``delta_ok`` (T, K)."""

    time: torch.Tensor
    omega: torch.Tensor
    y: dict
    rate: dict
    ok: dict
    delta: torch.Tensor
    delta_ok: torch.Tensor
    f_read: float


def residuals_of(prep, fit) -> Residuals:
    """The :class:`Residuals` of a prepared recording and its nominal fit (``baseline_fit``, which
    also set ``prep.acc_rate`` / ``prep.gyro_rate``)."""
    from ..physics.geometry import quat_to_matrix

    R = quat_to_matrix(torch.as_tensor(prep.q, dtype=torch.float64))
    y, rate, ok = {}, {}, {}
    for s, r in (("acc", prep.acc_rate), ("gyro", prep.gyro_rate)):
        y[s], okk = array_residuals(prep, fit, s)
        ok[s] = okk.all(1)
        rate[s] = torch.einsum("kji,tkj->tki", R, r.to(torch.float64))
    delta, dok = instant_errors(prep, fit)
    t = prep.time.to(torch.float64)
    f_read = float(1.0 / np.median(np.diff(t.numpy())))
    return Residuals(t, torch.linalg.norm(fit.x[:, 0:3].detach(), dim=1).to(torch.float64), y, rate, ok,
                     delta, dok, f_read)


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


def _saw_fit(t, x, f):
    """Least-squares fit of x ≈ c − A·frac(f t + φ) over a phase grid (A ≥ 0): (sse, φ, A)."""
    best = (math.inf, 0.0, 0.0)
    for phi in np.linspace(0, 1, 64, endpoint=False):
        s = np.remainder(f * t + phi, 1.0)
        s = s - s.mean()
        den = float(s @ s)
        if den <= 0:
            continue
        A = -float(s @ x) / den
        if A < 0:
            continue
        sse = float(((x + A * s) ** 2).sum())
        if sse < best[0]:
            best = (sse, float(phi), A)
    return best


def acquire_clock(res: Residuals, window=None, *, pad: int = 4):
    """Beat frequency (K,) Hz in (−f_read/2, f_read/2] and phase (K,) cycles of each IMU's data
    age from its gyro instant errors δ ≈ c − age (the reading is the sample of age s before).
    The peak of δ's periodogram over (0, f_read/2) — an FFT on the read grid (samples not kept
    are zeros), zero-padded ``pad``× — refined by a direct transform on a 20× finer grid around
    it; then the sign (which way the sawtooth ramps) and the phase from a sawtooth least-squares
    fit.  ``window`` (T,) bool: the samples used (default all).  A stand-in for the
    ``sampling_clock`` effect's own acquisition (issue #27 item 2)."""
    t_all = res.time.numpy()
    window = np.ones(len(t_all), bool) if window is None else np.asarray(window, bool)
    K = res.delta.shape[1]
    beat, phase = np.zeros(K), np.zeros(K)
    for k in range(K):
        sel = window & res.delta_ok[:, k].numpy()
        t = t_all[sel] - t_all[0]
        x = res.delta[sel, k].numpy()
        x = x - x.mean()
        if len(t) < 20:
            continue
        n = np.round((t - t[0]) * res.f_read).astype(int)
        N = 1 << int(np.ceil(np.log2(pad * (n[-1] + 1))))
        grid = np.zeros(N)
        np.add.at(grid, n, x)
        P = np.abs(np.fft.rfft(grid))
        f_axis = np.fft.rfftfreq(N, 1.0 / res.f_read)
        P[(f_axis <= 0) | (f_axis >= res.f_read / 2)] = 0
        f0 = f_axis[np.argmax(P)]
        h = f_axis[1]
        fine = f0 + np.linspace(-h, h, 41)
        f0 = fine[np.argmax(np.abs(np.exp(-2j * np.pi * np.outer(fine, t)) @ x))]
        fits = [(_saw_fit(t, x, sgn * f0), sgn * f0) for sgn in (1.0, -1.0)]
        (sse, phi, _), f = min(fits, key=lambda z: z[0][0])
        beat[k] = f
        # the phase refers to time 0 of the recording's clock, not to the window's start
        phase[k] = (phi - f * t_all[0]) % 1.0
    return beat, phase


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


def score(source: dict, res: Residuals, age: torch.Tensor, keep) -> dict:
    """Per sensor, each model's per-sample log density (nats, numpy (n,)) of the target's
    residuals on the samples ``keep`` (T,) bool that have all triads observed, with the source's
    parameters and the target's centred ages."""
    edges = source["edges"]
    lab_all = torch.as_tensor(np.digitize(res.omega.numpy(), edges), dtype=torch.long)
    d_all = centred(age)
    keep = torch.as_tensor(np.asarray(keep, bool))
    out = {}
    for s in ("acc", "gyro"):
        sel = keep & res.ok[s]
        y, lab, d, rate = res.y[s][sel], lab_all[sel], d_all[sel], res.rate[s][sel]
        m = source[s]
        e = y + m["c"] * d[:, :, None] * rate
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
