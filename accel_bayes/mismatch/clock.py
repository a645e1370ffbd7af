"""The detector's clock stage: a ``sampling_clock`` (:class:`~accel_bayes.physics.effects.SamplingClock`)
estimated on every IMU with a gyroscope, compared with the random timing explanations, and held
fixed in the rounds (:mod:`accel_bayes.mismatch.detector`, step 3b).

Data.  Per IMU k and sample t the gyro triad's restricted timing statistics of
:func:`accel_bayes.mismatch.jitter.jitter_ab` (the machinery ``timing_wander`` is fitted on):
a_t = ṽᵀPṽ (s⁻²) and b_t = ṽᵀP r̃ (s⁻¹), P the projection off the per-sample motion states, r̃
the whitened residual, and ṽ the whitened rate of the gyro output, ġ_kt = R_k ω̇_t.  A timing error
δ_t (s, positive = the output is the motion δ later) adds a_t δ_t to b_t, so the clock's data age,
δ_t = −age_t, gives

    b_t ≈ −a_t·age_t + n_t,   n_t ~ N(0, a_t)   (Var b = a under the null, exactly).

The regressor (issue #27, recall).  IMU k's output read at t is its filtered signal at
t − age_kt, so its residual is −age_kt·ġ_kt with ġ the true rate *at the sample instant*.  The
board's per-sample motion states hold that rate, ω̇_t, measured by the accelerometer array through
the tangential term ω̇ × r (:func:`accel_bayes.physics.effects.board_gyro_rate`); the finite
difference of the sampled gyro outputs (``prep.gyro_rate``, the regressor until 2026-11-27) is not
it once the board vibrates above the read's Nyquist rate: a line at f folds to f' = f_read − f,
where the sampled signal's derivative is −(f'/f) times the true one — flipped and shrunk.  On
clockgen's 125 Hz cube6 case (seed 14) the age effect regressed on the finite difference had
R² 0.02–0.10 with the sign flipped, on R_k ω̇ R² 0.88–0.93 with slope ≈ 1; on the real MIMU's
six experiments the evidence of the same beats rose 1.3–3.2× (``experiments/clock_mimu.md``).  The
unresolved part of the board's motion (what the states get wrong: ``unresolved_motion``,
:mod:`accel_bayes.mismatch.unresolved`) is then noise on the regressor, common to the board; it
scales W by |ω̇|²/(|ω̇|² + noise), it does not move the beat or the phase.

Width (issue #27, clock_proof at 97e5674: mimu4444 at 250 Hz 0/8).  The per-sample ω̇ states
carry the fitted lever arms' scale error (ω̇ ∝ 1/r) and noise: on clockgen's mimu4444 board with
real-size gyro errors they are ~3.6× the true angular acceleration below 20 Hz, and the sawtooth
fitted on R_k ω̇ is λ·W wide, λ = 0.28 (0.3 ms of a 1 ms tick), under :data:`WIDTH_RANGE_S` with the
beat right.  The scale is not the clock's: λ, the true gyro rate per unit of the regressor, is
measured where the gyro itself is exact — its increments over 0.1 s blocks, the integral of its
true rate (:func:`rate_scale`) — and the data age's width is the fitted one over λ (reported as
``width_s``, the fit's as ``width_fit_s``; the :class:`SamplingClock` carries λ as ``rate_scale``,
so its correction is the fitted one).  λ stands for the full-band scale of the regressor: where its
noise lies above 10 Hz the width is over-corrected by the share of that noise.

Search.  age_t = W·frac(φ + βt + ½dt²) + const.  The sawtooth's fundamental carries the phase:
−W·frac(x) = const + (W/π)·Σ_m sin(2πmx)/m, so Σ_t b_t e^(−2πim(βt + ½dt²)) peaks at the beat for
every harmonic m; the search ranks β by Σ_{m≤3} |F_m|²/m (a residual at the motion's own frequencies
has no such harmonics, and on boards with linear gyro errors it outranks the fundamental alone).
The constant is taken off b first (b − a·Σb/Σa): a constant time offset (read skew) gives
b = −a·const, the spectrum of the motion's envelope, which outranked beats.
The kept samples go onto the uniform grid of the read rate (zeros where the selection dropped
one), are de-chirped for each drift on a grid (step 1/(2D²), D the span), zero-padded ×4 and
FFT'd: every β in (−f_read/2, f_read/2].  The best peaks of that ranking are nominated, and the best
of the same ranking with each harmonic divided by the periodogram's local continuum (median over
0.5 Hz): slow motion-frequency lines in b (a wander explains them) have a red continuum and
outrank a beat that stands out where it is.  A broad line (vibration folded near a beat) is many local
maxima of the ranking and can fill those places while a beat on its shoulder ranks 80th (clockgen
clock-029 IMU 1: a ±13 Hz line, the true −16.45 Hz at 0.85 of its height, ``clock_nomination_probe.md``);
so the next 100 local maxima, on lines apart from the nominated peaks', are screened in the exact model
on its phase grid (the profile below at the peak's β and d, cheap: no refinement;
:mod:`~accel_bayes.mismatch.clock_screen`) and the best 4 by that gain are nominated too — on clock-029
the true beat is the screen's first.  The screen adds candidates (one could only displace a nominated
candidate by refining onto its beat with a larger gain), so where its peaks lose to the nominated ones
nothing changes (every IMU of the six real experiments has the same six best candidates with and without
it).  The real input makes (β, d) and (−β, −d) peak alike; the sawtooth's shape (slow ramp, fast jump)
tells them apart, so each peak is tried with both in the exact sawtooth model (W and the constant
profiled by weighted least squares, weights a_t), then (φ, β, d) refined by Nelder–Mead on that profile.
The refined fits with W > 0 are candidates, best gain first; the stage keeps the first that passes its
acceptance (below).

Evidence (nats ×2; the triad's white-noise factor c profiled throughout, so a clock never earns
what a larger noise would):

* ``evidence`` = 2·(log L(clock) − log L(no clock));
* ``evidence_vs_wander`` = 2·(log L(clock + best AR(1) instant error) − log L(best AR(1) instant
  error)): what the deterministic sawtooth explains that the random timing effects cannot
  (``timing_wander`` is the AR(1) instant error; its ρ = 0 end is white jitter, the Gaussian form
  of ``sampling_jitter``).  :func:`accel_bayes.mismatch.wander.fit_wander` gives both fits.

An IMU's clock is accepted when its sawtooth width W is physical (:data:`WIDTH_RANGE_S`: a 1 kHz
tick is 1 ms), its beat is one of an internal rate within :data:`INTERNAL_RATE_TOLERANCE` of
1 kHz (:func:`physical_beats`: at a 200 Hz read |β| ≤ 30 Hz; at 62.5 Hz every beat — only those are
searched, and the look-elsewhere count is theirs), and both evidences exceed the stage threshold:
the detector's threshold, or, if larger, the χ²₄ quantile at 1 − α/(K·cells), cells = the
independent (β, d) cells searched — the search looks at every frequency, and the largest of many
noise peaks is not χ²-distributed.  Among accepted candidates related as β and 2β (a slow motion
line at β/2 carries the beat as its 2nd harmonic) the larger evidence over the wander decides
(:func:`_choose`).

Leaks.  Each IMU is searched on the residual of the fit with every other IMU's timing error still in
the outputs, and the fitted rate follows the gyros: about 1/n of IMU j's data-age error appears, with
the opposite sign, in every other IMU's residual — a sawtooth at −β_j.  Where an IMU's own clock is
weak that copy can win its search and pass (clockgen clock-020: IMU 2, true beat −1.785 Hz, picked
+2.446 Hz, IMU 3's −2.447 Hz mirrored, evidence over the wander 111; clock-028: IMUs 2 and 3 both at
IMU 1's mirror).  So an IMU whose pick sits within the search's resolution (1/span Hz) of ±β_j, j an
IMU with an accepted clock and a larger evidence over the wander, is searched again on the recording
corrected for the other IMUs' accepted clocks (those not themselves so flagged) and refitted; its
second pick replaces the first (clock-020's IMU 2 then finds −1.787 Hz, evidence over the wander 567).
Two true beats that close are searched again too, and keep their clock (what the second look removes
is the other IMU's copy, not the IMU's own signal).  The report's ``details.clock_stage.second_look``
lists the IMUs; each one's fit carries its first pick and the IMU it was taken for a copy of.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from ..physics.effects import SamplingClock, board_gyro_rate
from .clock_screen import N_PHASE as _N_PHASE
from .clock_screen import _distinct, _frac
from .clock_screen import screen as _screen
from .jitter import jitter_ab
from .model import ModelFit
from .prepared import Prepared
from .wander import fit_wander, sample_steps

__all__ = ["ClockStage", "estimate_clock", "clock_ab", "clock_stage", "clock_ages", "data_age", "clock_corrected", "physical_beats",
           "rate_scale", "physical_width", "NOMINAL_INTERNAL_RATE_HZ", "INTERNAL_RATE_TOLERANCE"]

#: the internal sampling rate of an MPU-6050/9150 with its low-pass on (Hz): reports f_k from the beat
NOMINAL_INTERNAL_RATE_HZ = 1000.0
#: the largest |beat drift| searched (Hz/s): a temperature drift of ±1e-4 of 1 kHz over ≥ 100 s periods
MAX_DRIFT_HZ_PER_S = 0.008
_PAD = 4           # zero padding of the FFT (frequency step f_read/(4N))
_N_PEAKS = 8       # peaks of the periodogram tried in the exact model
_HARMONICS = 3     # sawtooth harmonics summed in the search
_FLOOR_HZ = 0.5    # width (Hz) of the blocks whose median is the periodogram's local continuum
_N_CONTINUUM = 6   # further peaks nominated by their height over the local continuum
#: fewest sawtooth cycles over the recording's span for a clock (fewer: indistinguishable from a wander).
#: Tried at 2 (2026-11-29, ``clock_proof.md``'s reading of 20:15): clockgen's slow beats of 2.3–3.7 cycles
#: (clock-003, -006, -013) were then found to 0.005 Hz, but calibrating clock-003 with that report got worse
#: (max |z| 2.19 → 4.50, ``percov_conceal``) — and so did it with IMU 0's true clock (``clock_use_probe.md``:
#: a clocked triad has no term for its timing beyond the sawtooth unless ``--instant-error``), so the bound stays
MIN_CYCLES = 5.0
#: the sawtooth width W (s) a clock may have: 1/f_k ≈ 1 ms, larger where the fitted output rates
#: under-state the true ones (fast content near the read rate's Nyquist frequency), never ≪ 1 ms
WIDTH_RANGE_S = (0.4e-3, 4e-3)
#: the largest relative offset of an IMU's internal rate from :data:`NOMINAL_INTERNAL_RATE_HZ` a beat may
#: imply: the gyro oscillator's ±1 % over temperature, with room for a part out of its datasheet
INTERNAL_RATE_TOLERANCE = 0.03
#: the block (s) over which the gyro's own increments measure the regressor's scale (:func:`rate_scale`)
SCALE_BLOCK_S = 0.1


@dataclasses.dataclass
class ClockStage:
    """What :func:`clock_stage` found: ``clocks`` (accepted :class:`SamplingClock` effects, with
    ``stats``), ``fits`` (every IMU's estimate dict, accepted or not), ``prep``/``fit`` (the
    recording corrected for the accepted clocks and the model refitted on it; the inputs when none
    was accepted), ``threshold``, ``info`` (the report's ``details.clock_stage``)."""

    clocks: list
    fits: list
    prep: Prepared
    fit: ModelFit
    threshold: float
    info: dict


def _profile(b, a, age_shape):
    """Weighted LS of b/a on [1, −s] with weights a: returns (gain Σbm − ½Σam², W, const, m)."""
    s = age_shape
    Saa, Sas, Sass = a.sum(), (a * s).sum(), (a * s * s).sum()
    Sb, Sbs = b.sum(), (b * s).sum()
    G = np.array([[Saa, -Sas], [-Sas, Sass]])
    g = np.array([Sb, -Sbs])
    try:
        c, W = np.linalg.solve(G, g)
    except np.linalg.LinAlgError:
        return 0.0, 0.0, 0.0, np.zeros_like(b)
    m = c - W * s
    return float(g @ np.array([c, W])) / 2.0, float(W), float(c), m


def _continuum(power, nb: int) -> np.ndarray:
    """The periodogram's local continuum: the median of ``power`` over blocks of ``nb`` bins, per
    bin (a line is a few bins, so it barely moves its block's median)."""
    L = len(power)
    nblk = -(-L // nb)
    padded = np.concatenate([power, np.full(nblk * nb - L, np.nan)])
    med = np.nanmedian(padded.reshape(nblk, nb), axis=1)
    return np.maximum(np.repeat(med, nb)[:L], 1e-300 + 1e-12 * float(np.nanmax(med)))


def _white_loglik(rr: float, n: int) -> float:
    """log N(r̃; 0, c²I) at the best c (c² = rr/n), constants dropped (nats): −n/2·log(rr/n) − n/2.
    ``wander.fit_wander``'s gains are over this model on the same residuals."""
    return -0.5 * n * math.log(max(rr / n, 1e-300)) - 0.5 * n


def physical_beats(beat, f_read: float, *, f_nominal: float = NOMINAL_INTERNAL_RATE_HZ,
                   tolerance: float = INTERNAL_RATE_TOLERANCE):
    """True where a beat (Hz, array) is n·f_read away from an internal rate within ``tolerance``
    (relative) of ``f_nominal`` (Hz) for some integer n: the beats a real clock can have."""
    beat = np.asarray(beat, float)
    n = np.rint((f_nominal - beat) / f_read)
    return np.abs(n * f_read + beat - f_nominal) <= tolerance * f_nominal


def _spectra(t, a, b, f_read: float, *, max_drift: float = MAX_DRIFT_HZ_PER_S,
             rate_tolerance: float | None = INTERNAL_RATE_TOLERANCE) -> dict:
    """The search's two rankings of (β, d) (module docstring, "Search") on one IMU's (a, b) at times t (s):
    {"freqs" (L,) Hz, "drifts" (nd,) Hz/s, "P" (nd, L) Σ_m |F_m(mβ)|²/m, "Pn" (nd, L) the same with each
    harmonic over the local continuum — both 0 where β is not searched (under :data:`MIN_CYCLES`, not
    physical) —, "L", "step" (the drift grid's step), "cells" (independent (β, d) cells searched), "f_read"}."""
    t0 = t[0]
    n = np.rint((t - t0) * f_read).astype(np.int64)
    N = int(n[-1]) + 1
    D = max(float(t[-1] - t0), 1.0 / f_read)
    step = 0.5 / D ** 2
    nd = int(min(max_drift / step, 100))
    drifts = step * np.arange(-nd, nd + 1)
    L = int(2 ** math.ceil(math.log2(_PAD * N)))
    freqs = np.fft.fftfreq(L, 1.0 / f_read)
    tt = t - t0
    idx = np.arange(L)
    # beats no real clock has (at 200 Hz reads, |β| > 30 Hz is a rate 3 % off 1 kHz) are not searched:
    # there a vibration line's product with its own fold, or a beat's 2nd harmonic, outranked the beat
    allowed = np.ones(L, bool) if rate_tolerance is None else physical_beats(freqs, f_read, tolerance=rate_tolerance)
    n_cells = int(N * len(drifts) * allowed.mean())
    # a constant time offset (read skew, filter delay) gives b = −a·const, whose spectrum is that
    # of a_t — the slow envelope of the motion — and outranks the beat: searched without it
    b_search = b - a * (b.sum() / max(a.sum(), 1e-300))
    z = np.zeros(L)
    z[n] = b_search
    floor = _continuum(np.abs(np.fft.fft(z)) ** 2, max(int(round(_FLOOR_HZ * L / f_read)), 8))
    Ps, Pns = np.zeros((len(drifts), L)), np.zeros((len(drifts), L))
    for i, d in enumerate(drifts):
        # harmonic m of the sawtooth sits at m·β with chirp m·d, amplitude 1/m: ranking by
        # Σ_m |F_m(mβ)|²/m, a slow motion-frequency residual (one line, no harmonics) ranks lower.
        # Where that residual is strong, its red continuum (what a wander explains) still outranks
        # a beat that stands out where it is: the peaks of Σ_m |F_m(mβ)|²/(m·continuum(mβ)) are
        # nominated too (alone they favour a beat's harmonics, whose continuum is lower)
        P, Pn = Ps[i], Pns[i]
        for mh in range(1, _HARMONICS + 1):
            z = np.zeros(L, complex)
            z[n] = b_search * np.exp(-1j * math.pi * mh * d * tt ** 2)
            j = (mh * idx) % L
            pw = np.abs(np.fft.fft(z))[j] ** 2 / mh
            P += pw
            Pn += pw / floor[j]
        for Q in (P, Pn):
            # under MIN_CYCLES over the span a sawtooth is a slow wander, not a clock
            Q[np.abs(freqs) < MIN_CYCLES / D] = 0.0
            Q[~allowed] = 0.0
    return {"freqs": freqs, "drifts": drifts, "P": Ps, "Pn": Pns, "L": L, "step": step, "cells": n_cells,
            "f_read": float(f_read)}


def _nominate(sp: dict) -> list:
    """The peaks of :func:`_spectra`'s rankings tried in the exact model, [(height, β Hz, d Hz/s)]: the
    best :data:`_N_PEAKS` distinct peaks of the raw ranking, then distinct peaks of the ranking over the
    local continuum up to :data:`_N_PEAKS` + :data:`_N_CONTINUUM` in all."""
    freqs, L, step, f_read = sp["freqs"], sp["L"], sp["step"], sp["f_read"]
    peaks = ([], [])  # (raw ranking, ranking against the local continuum)
    for d, P, Pn in zip(sp["drifts"], sp["P"], sp["Pn"]):
        for Q, out in ((P, peaks[0]), (Pn, peaks[1])):
            top = np.argpartition(Q, -_N_PEAKS)[-_N_PEAKS:]
            out += [(float(Q[i]), float(freqs[i]), float(d)) for i in top]
    # a peak and its neighbours are one peak: keep distinct |β| (beyond 2 bins) or drifts only
    chosen = []
    for ranked, n_keep in ((peaks[0], _N_PEAKS), (peaks[1], _N_PEAKS + _N_CONTINUUM)):
        ranked.sort(key=lambda p: -p[0])
        for p in ranked:
            if len(chosen) >= n_keep:
                break
            if _distinct(p, chosen, 2 * f_read / L, 2 * step):
                chosen.append(p)
    return chosen


def estimate_clock(t, a, b, f_read: float, *, max_drift: float = MAX_DRIFT_HZ_PER_S, candidates: bool = False,
                   rate_tolerance: float | None = INTERNAL_RATE_TOLERANCE):
    """The beat search of the module docstring on one IMU's (a, b) (:func:`clock_ab`) at times t (s): returns
    {"beat_hz", "phase", "drift_hz_per_s", "width_s" (W, s), "const_s", "gain" (Σbm − ½Σam², nats
    at the stated noise), "mean" (T,) the fitted δ_t = const − age_t (s), "cells" (independent
    (β, d) cells searched)}.  ``candidates``: the list of such dicts instead, one per distinct refined
    peak with W > 0, best gain first (the stage ranks them by what the random timing cannot explain)."""
    from scipy.optimize import minimize

    t = np.asarray(t, float)
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    sp = _spectra(t, a, b, f_read, max_drift=max_drift, rate_tolerance=rate_tolerance)
    chosen = _nominate(sp)
    chosen += _screen(sp, t, a, b, chosen)
    t0, L, step, n_cells = t[0], sp["L"], sp["step"], sp["cells"]

    def neg(x):
        phase, beat, drift = x
        s = _frac(phase + beat * t + 0.5 * drift * t * t)
        gain, W, _, _ = _profile(b, a, s)
        return -gain if W > 0 else 0.0

    fits = []
    for _, f0, d0 in chosen:
        for beat, drift in ((f0, d0), (-f0, -d0)):  # the real input's mirror peak is (−β, −d)
            # the phase on a grid first (the profile is piecewise smooth in it); the search's
            # chirp is about t0, the model's about t = 0: the beat at t = 0 is β − d·t0
            cands = []
            for ph in np.linspace(0, 1, _N_PHASE, endpoint=False):
                x0 = np.array([ph, beat - drift * t0, drift])
                cands.append((neg(x0), x0))
            cands.sort(key=lambda c: c[0])
            x0 = cands[0][1]
            res = minimize(neg, x0, method="Nelder-Mead",
                           options={"xatol": 1e-7, "fatol": 1e-6, "maxiter": 600,
                                    "initial_simplex": [x0, x0 + [0.02, 0, 0], x0 + [0, 0.1 * f_read / L, 0],
                                                        x0 + [0, 0, 0.5 * step]]})
            x = res.x if res.fun <= cands[0][0] else x0
            fits.append((min(res.fun, cands[0][0]), x))
    fits.sort(key=lambda f: f[0])
    out = []
    for _, (phase, beat, drift) in fits:
        # β and β + f_read give the same reads: report it in (−f_read/2, f_read/2]
        beat = beat - f_read * math.ceil(beat / f_read - 0.5)
        s = _frac(phase + beat * t + 0.5 * drift * t * t)
        gain, W, c, m = _profile(b, a, s)
        if W <= 0 or any(abs(beat - o["beat_hz"]) < 2 * f_read / L for o in out):
            continue
        if rate_tolerance is not None and not physical_beats(beat, f_read, tolerance=rate_tolerance):
            continue  # the refinement walked out of the physical beats
        out.append({"beat_hz": float(beat), "phase": float(_frac(phase)), "drift_hz_per_s": float(drift), "width_s": W,
                    "const_s": c, "gain": gain, "mean": m, "cells": n_cells})
    if not out:  # no sawtooth with W > 0 anywhere: the best fit, for the record (rejected by its width)
        phase, beat, drift = fits[0][1]
        s = _frac(phase + beat * t + 0.5 * drift * t * t)
        gain, W, c, m = _profile(b, a, s)
        out.append({"beat_hz": float(beat - f_read * math.ceil(beat / f_read - 0.5)), "phase": float(_frac(phase)),
                    "drift_hz_per_s": float(drift), "width_s": W, "const_s": c, "gain": gain, "mean": m,
                    "cells": n_cells})
    return out if candidates else out[0]


#: refined peaks the stage weighs against the random timing (the rest rank lower on the white gain)
_N_STAGE = 6


def _rank(est) -> tuple:
    """The order of rejected candidates (the one kept for the record): physical width first, then the
    evidence over the best AR(1) instant error."""
    return (WIDTH_RANGE_S[0] <= est["width_s"] <= WIDTH_RANGE_S[1], est["evidence_vs_wander"])


def _versus_wander(est, a, b, t, steps, dt, rr, n_obs, w0, g_none) -> dict:
    """``est`` (one :func:`estimate_clock` candidate) with its width and offset by GLS under the
    no-clock wander ``w0`` and its two evidences (module docstring) added; ``mean`` removed."""
    mean = est.pop("mean")
    if w0["sigma"] > 0:
        # the sawtooth's width and offset again by GLS under the wander's covariance: fitted
        # under white noise they would claim what the wander explains and lose against it
        s_t = _frac(est["phase"] + est["beat_hz"] * t + 0.5 * est["drift_hz_per_s"] * t * t)
        mean, est["width_s"], est["const_s"] = _gls_mean(a, b, steps, s_t, w0)
    # the clock's mean timing taken off: b' = b − a m, Σ r̃'² = Σ r̃² − 2Σbm + Σam²
    b2 = b - a * mean
    rr2 = max(rr - 2 * float(b @ mean) + float(a @ (mean * mean)), 1e-12)
    g_clock = _white_loglik(rr2, n_obs)
    w1 = fit_wander(a, b2, steps, sigma_max=dt, rr=rr2, n=n_obs)
    est.update({"evidence": 2 * (g_clock - g_none),
                "evidence_vs_wander": 2 * ((g_clock + w1["gain"]) - (g_none + w0["gain"])),
                "wander_before": {"sigma_s": w0["sigma"], "rho": w0["rho"], "evidence": w0["evidence"]},
                "wander_after": {"sigma_s": w1["sigma"], "rho": w1["rho"], "evidence": w1["evidence"]}})
    return est


def _gls_mean(a, b, steps, s_t, wander: dict) -> tuple[np.ndarray, float, float]:
    """δ_t = const − W·s_t with (const, W) by GLS under the AR(1) instant error + white noise of
    ``wander`` (σ, ρ, c; :func:`accel_bayes.mismatch.wander.fit_wander`): with M = diag(a)/c² and
    P = Σ⁻¹ + M (tridiagonal), the weight matrix is M − M P⁻¹ M (Woodbury), and its product with
    δ_LS = b/a is b/c² − M P⁻¹ b/c² (no division by a).  Returns (δ (T,) s, W s, const s)."""
    from scipy.linalg import cho_solve_banded, cholesky_banded

    from .wander import ar1_precision_bands

    c2 = wander["c"] ** 2
    P, _ = ar1_precision_bands(len(a), steps, wander["sigma"], wander["rho"])
    P[1] += a / c2
    cP = cholesky_banded(P, lower=False)
    X = np.stack([np.ones_like(s_t), -s_t], 1)
    MX = X * (a / c2)[:, None]
    KX = MX - (a / c2)[:, None] * cho_solve_banded((cP, False), MX)
    Kd = b / c2 - (a / c2) * cho_solve_banded((cP, False), b / c2)
    theta = np.linalg.solve(X.T @ KX, X.T @ Kd)
    return X @ theta, float(theta[1]), float(theta[0])


def data_age(clocks, time, K: int) -> torch.Tensor:
    """(T, K) the data age (s) of every IMU at the read times ``time`` (s) from its
    :class:`SamplingClock` (0 on IMUs without one).  ``clocks``: SamplingClock effects (a
    :class:`ClockStage`'s ``clocks``, or a report's refitted ``fixed_effects`` filtered to them)."""
    t = torch.as_tensor(time, dtype=torch.float64)
    out = torch.zeros(len(t), K, dtype=torch.float64)
    for c in clocks:
        out[:, c.imu] = c.age(t)
    return out


def clock_corrected(prep: Prepared, fit: ModelFit, clocks) -> Prepared:
    """``prep`` with every accepted clock's linearised output effect taken off its outputs
    (y − d, d the :class:`SamplingClock` perturbation at ``fit``'s context: the fit's output rates)."""
    if not clocks:
        return prep
    ya, yg = prep.y_acc.clone(), prep.y_gyro.clone()
    for c in clocks:
        da, dg = c.perturbation(None, fit.ctx)
        ya, yg = ya - da, yg - dg
    return dataclasses.replace(prep, y_acc=ya * prep.m_acc, y_gyro=yg * prep.m_gyro)


def clock_ab(prep: Prepared, fit: ModelFit, k: int):
    """IMU k's gyro timing statistics at ``fit`` with the data age's regressor of the module
    docstring, ġ = R_k ω̇ (:func:`accel_bayes.physics.effects.board_gyro_rate`), not the finite
    difference ``prep.gyro_rate``: (a (T,) s⁻², b (T,) s⁻¹, Σ r̃ᵀr̃, observed channels) as
    :func:`accel_bayes.mismatch.jitter.jitter_ab` (``"gyro"``, ``with_residual_power``).  What
    :func:`estimate_clock` takes, wherever a clock is acquired."""
    prep_rate = dataclasses.replace(prep, gyro_rate=board_gyro_rate(fit.ctx))
    return jitter_ab(prep_rate, fit, k, "gyro", with_residual_power=True)


def rate_scale(prep: Prepared, fit: ModelFit, k: int, *, block_s: float = SCALE_BLOCK_S) -> float:
    """λ: the true gyro rate of IMU k per unit of the data age's regressor R_k ω̇ (:func:`clock_ab`),
    measured where the gyro itself is exact — over blocks of ``block_s`` s (contiguous kept samples):
    the finite difference ``prep.gyro_rate`` summed over a block telescopes to the gyro's own
    increment, the integral of its true rate (no folding), so λ = Σ G·V / Σ V·V, G and V the block
    sums of the finite difference and of the regressor (observed channels).  The fitted width is
    λ·W (W the data age's, s): the per-sample ω̇ states carry the fitted lever arms' scale error
    (ω̇ ∝ 1/r) and noise (clockgen's mimu4444 at 250 Hz: λ ≈ 0.28, fitted W 0.3 ms of a 1 ms tick)."""
    t = prep.time.detach().cpu().double().numpy()
    f_read = 1.0 / float(np.median(np.diff(t)))
    n = np.rint((t - t[0]) * f_read).astype(np.int64)
    run = np.concatenate([[0], np.cumsum(np.diff(n) != 1)])
    # a block: one time bin of one contiguous run (a gap breaks the telescoping)
    _, blk = np.unique(np.stack([n // max(int(round(block_s * f_read)), 2), run]), axis=1, return_inverse=True)
    blk = blk.ravel()
    m = prep.m_gyro[:, k].detach().cpu().double().numpy()
    v = board_gyro_rate(fit.ctx)[:, k].detach().cpu().double().numpy() * m
    g = prep.gyro_rate[:, k].detach().cpu().double().numpy() * m
    V, G = np.zeros((blk.max() + 1, 3)), np.zeros((blk.max() + 1, 3))
    np.add.at(V, blk, v)
    np.add.at(G, blk, g)
    vv = float((V * V).sum())
    return float((V * G).sum()) / vv if vv > 0 else 1.0


def physical_width(width_fit_s: float, lam: float) -> float:
    """The data age's sawtooth width (s) from the width fitted on the regressor R_k ω̇ and the
    regressor's scale λ (:func:`rate_scale`): width_fit/λ (module docstring, "Width"); λ ≤ 0 (a
    regressor against the gyro's own rate) gives an unphysical width, rejected by :data:`WIDTH_RANGE_S`.
    The reported ``age_rms_s`` is this width over √12."""
    return float(width_fit_s) / max(float(lam), 1e-12)


def _choose(cands: list, tol_hz: float) -> dict:
    """One IMU's clock from its candidates (in the search's order, with ``accepted``): the first
    accepted one — the next peak only where it is not: on reads slower than twice the vibration, slow
    motion-frequency lines in b (a wander explains them) outrank the beat on the white gain, and
    ranking every peak by its evidence over the wander instead would trade a slow true beat (partly a
    wander) for a faster line — else the best rejected one for the record (:func:`_rank`).

    A sawtooth at β/2 carries β as its 2nd harmonic, so where a slow motion line sits at β/2 (or the
    beat's 2nd harmonic meets one at 2β) the exact fit there can gain more on the white noise than the
    beat itself (clockgen clock-020: a 6.19 Hz hand-motion line, IMU 4 beating at −12.37 Hz).  The
    motion line is what the random timing explains, so between an accepted pick and its accepted
    ½× / 2× relatives (|β| within ``tol_hz``, Hz, at the recording's middle) the one with the larger
    evidence over the wander is kept."""
    acc = [c for c in cands if c["accepted"]]
    if not acc:
        return max(cands, key=_rank)
    best = acc[0]
    rel = [c for c in acc[1:] if any(abs(abs(c["beat_mid_hz"]) - r * abs(best["beat_mid_hz"])) < tol_hz
                                     for r in (0.5, 2.0))]
    return max([best] + rel, key=lambda c: c["evidence_vs_wander"])


def _clock_effect(est: dict) -> SamplingClock:
    """The :class:`SamplingClock` of one IMU's accepted estimate (:func:`clock_stage`'s fits)."""
    f_read = est["f_read_hz"]
    f_int = f_read * round(NOMINAL_INTERNAL_RATE_HZ / f_read) + est["beat_hz"]
    c = SamplingClock(imu=est["imu"], params={"internal_rate_hz": f_int, "beat_hz": est["beat_hz"], "phase": est["phase"],
                                              "drift_hz_per_s": est["drift_hz_per_s"],
                                              "age_rms_s": est["width_s"] / math.sqrt(12.0),
                                              "filter_delay_acc_minus_gyro_s": 0.0, "rate_scale": est["rate_scale"]})
    c.stats = {kk: v for kk, v in est.items() if kk not in ("wander_before", "wander_after")}
    return c


def _leaks(fits: list, tol_hz: float) -> dict:
    """{IMU k: IMU j} for every IMU whose pick (accepted or not) sits within ``tol_hz`` (Hz, at the
    recording's middle) of +β_j or −β_j, j another IMU with an accepted clock and a larger evidence over
    the wander: what :func:`clock_stage` looks at again (module docstring, "Leaks")."""
    out = {}
    for f in fits:
        src = [g for g in fits if g["accepted"] and g["imu"] != f["imu"]
               and g["evidence_vs_wander"] > f["evidence_vs_wander"]
               and min(abs(f["beat_mid_hz"] - g["beat_mid_hz"]), abs(f["beat_mid_hz"] + g["beat_mid_hz"])) <= tol_hz]
        if src:
            out[f["imu"]] = max(src, key=lambda g: g["evidence_vs_wander"])["imu"]
    return out


def clock_stage(prep: Prepared, fit: ModelFit, *, m: int, alpha: float, threshold: float) -> ClockStage:
    """Estimate a clock on every IMU with a gyroscope at ``fit`` (module docstring), accept those
    whose two evidences pass the stage threshold, correct ``prep`` for them and refit the model
    (effects of ``fit`` kept).  ``m``, ``alpha``, ``threshold``: the detector's Bonferroni count,
    family-wise error rate and threshold."""
    from scipy.stats import chi2

    from .fit import fit_model

    t = prep.time.detach().cpu().double().numpy()
    dt = float(np.median(np.diff(t)))
    f_read = 1.0 / dt
    steps = sample_steps(t)
    tol = 1.0 / max(float(t[-1] - t[0]), dt)
    n_imu = int(np.asarray(prep.has_gyro).sum())
    thr = None

    def one_imu(prep_k, fit_k, k):
        # IMU k's candidates at fit_k, refined, judged, and its pick (_choose)
        nonlocal thr
        a_t, b_t, rr, n_obs = clock_ab(prep_k, fit_k, k)
        a, b = a_t.numpy(), b_t.numpy()
        w0 = fit_wander(a, b, steps, sigma_max=dt, rr=rr, n=n_obs)
        g_none = _white_loglik(rr, n_obs)
        cands = estimate_clock(t, a, b, f_read, candidates=True)[:_N_STAGE]
        if thr is None:
            thr = max(threshold, float(chi2.isf(alpha / max(n_imu * cands[0]["cells"], 1), 4)))
        lam = rate_scale(prep_k, fit_k, k)
        done = []
        for cand in cands:
            cand = _versus_wander(cand, a, b, t, steps, dt, rr, n_obs, w0, g_none)
            # the data age's width: what the fit found over the regressor's scale (rate_scale)
            cand.update({"imu": k, "f_read_hz": f_read, "rate_scale": lam, "width_fit_s": cand["width_s"],
                         "beat_mid_hz": cand["beat_hz"] + cand["drift_hz_per_s"] * 0.5 * (t[0] + t[-1]),
                         "width_s": physical_width(cand["width_s"], lam)})
            cand["accepted"] = bool(cand["evidence"] > thr and cand["evidence_vs_wander"] > thr
                                    and WIDTH_RANGE_S[0] <= cand["width_s"] <= WIDTH_RANGE_S[1]
                                    and physical_beats(cand["beat_hz"], f_read))
            done.append(cand)
        return _choose(done, tol)

    fits = [one_imu(prep, fit, int(k)) for k in np.flatnonzero(prep.has_gyro)
            if prep.gyro_rate is not None and bool(prep.m_gyro[:, int(k)].any())]
    # second look (module docstring, "Leaks"): an IMU whose pick is ±β of a stronger accepted clock on
    # another IMU is searched again with the other IMUs' clocks taken out
    leaks = _leaks(fits, tol)
    if leaks:
        # the flagged IMUs' own picks are left out, so one corrected recording serves them all
        sources = [_clock_effect(f) for f in fits if f["accepted"] and f["imu"] not in leaks]
        prep_s = clock_corrected(prep, fit, sources)
        fit_s = fit_model(prep_s, [e.copy() for e in fit.effects], init=fit, laplace=False)
        for i, f in enumerate(fits):
            k = f["imu"]
            if k not in leaks:
                continue
            again = one_imu(prep_s, fit_s, k)
            again.update({"second_look": True, "first_look_beat_mid_hz": f["beat_mid_hz"],
                          "first_look_accepted": f["accepted"], "leak_of_imu": leaks[k]})
            fits[i] = again
    clocks = [_clock_effect(est) for est in fits if est["accepted"]]
    thr = threshold if thr is None else thr
    info = {"threshold": thr, "imus": [{kk: v for kk, v in f.items()} for f in fits],
            "accepted": [c.imu for c in clocks], "second_look": sorted(leaks)}
    if not clocks:
        return ClockStage([], fits, prep, fit, thr, info)
    prep_c = clock_corrected(prep, fit, clocks)
    fit_c = fit_model(prep_c, [e.copy() for e in fit.effects], init=fit, laplace=False)
    info["evidence_refit"] = 2.0 * (fit_c.loglik - fit.loglik)
    return ClockStage(clocks, fits, prep_c, fit_c, thr, info)


def clock_ages(prep: Prepared, fit: ModelFit, *, alpha: float = 0.01, threshold: float = 0.0) -> tuple[torch.Tensor, ClockStage]:
    """(ages (T, K) s, the :class:`ClockStage`): every IMU's data age at ``prep``'s sample times from
    the clocks :func:`clock_stage` accepts at ``fit`` (0 on IMUs without one).  ``threshold`` adds a
    floor to the stage's own look-elsewhere threshold (the detector passes its Bonferroni one)."""
    st = clock_stage(prep, fit, m=1, alpha=alpha, threshold=threshold)
    return data_age(st.clocks, prep.time, prep.K), st
