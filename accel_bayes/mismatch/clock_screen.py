"""The clock search's screen (:mod:`accel_bayes.mismatch.clock`, "Search"): the beat search's spectral rankings
nominate a few peaks for the exact sawtooth model; a broad line (vibration folded near a beat) is many local
maxima of the ranking and can fill those places while a beat on its shoulder ranks ~80th (clockgen clock-029
IMU 1, ``experiments/clock_nomination_probe.md``).  The screen scores the ranking's next :data:`N_SCREEN` local
maxima by the exact model's gain on its phase grid (the weighted least-squares profile of W and the constant
at each phase, batched, no refinement) and hands the best :data:`N_SCREENED` to the refinement beside the
nominated peaks.  Kept apart from ``clock.py`` as the one piece that weighs many candidates at once.
"""
from __future__ import annotations

import numpy as np

__all__ = ["screen", "N_SCREEN", "N_SCREENED", "N_PHASE"]

N_SCREEN = 100    # further local maxima of the raw ranking screened in the exact model (phase grid)
N_SCREENED = 4    # of those, the best by the screen's gain nominated besides
N_PHASE = 24      # the phase grid the exact model starts from


def _frac(x):
    return x - np.floor(x)


def _distinct(p, qs, tol_hz: float, tol_drift: float) -> bool:
    """Peak p = (height, β Hz, d Hz/s) is another peak than each of ``qs``: |β| more than ``tol_hz`` apart or
    the drift more than ``tol_drift`` — (β, d) and (−β, −d) are one peak of the real input's spectrum."""
    return all(abs(abs(p[1]) - abs(q[1])) > tol_hz or abs(p[2] * np.sign(p[1]) - q[2] * np.sign(q[1])) > tol_drift
               for q in qs)


def _grid_gains(t, a, b, beats, drifts, n_phase: int = N_PHASE) -> np.ndarray:
    """(len(beats),) the exact model's best gain over a grid of ``n_phase`` phases at each (β Hz, d Hz/s)
    (chirp about t = 0; −inf where no phase gives W > 0): :func:`accel_bayes.mismatch.clock._profile`
    batched over candidates and phases, in blocks to bound the memory."""
    beats, drifts = np.asarray(beats, float), np.asarray(drifts, float)
    ph = np.linspace(0.0, 1.0, n_phase, endpoint=False)
    Saa, Sb = a.sum(), b.sum()
    out = np.full(len(beats), -np.inf)
    per = max(1, 2 ** 22 // max(len(t) * n_phase, 1))
    for i in range(0, len(beats), per):
        x = beats[i:i + per, None] * t + 0.5 * drifts[i:i + per, None] * t * t          # (c, T)
        s = _frac(ph[None, :, None] + x[:, None, :])                                   # (c, P, T)
        Sas, Sass, Sbs = s @ a, (s * s) @ a, s @ b
        det = Saa * Sass - Sas * Sas
        ok = np.abs(det) > 1e-300
        det = np.where(ok, det, 1.0)
        c = (Sass * Sb - Sas * Sbs) / det
        W = (Sas * Sb - Saa * Sbs) / det
        gain = np.where(ok & (W > 0), 0.5 * (Sb * c - Sbs * W), -np.inf)
        out[i:i + per] = gain.max(1)
    return out


def screen(sp: dict, t, a, b, chosen: list) -> list:
    """The :data:`N_SCREENED` best of the raw ranking's next :data:`N_SCREEN` local maxima on lines apart from
    the nominated peaks' (the module docstring), by the exact model's gain on its phase grid
    (:func:`_grid_gains`, both mirrors): [(height, β Hz, d Hz/s)] to try beside ``chosen``
    (:func:`accel_bayes.mismatch.clock._nominate`'s); ``sp``: :func:`accel_bayes.mismatch.clock._spectra`'s
    rankings of the IMU's (a, b) at times t (s)."""
    freqs, L, step, f_read = sp["freqs"], sp["L"], sp["step"], sp["f_read"]
    loc = []
    for d, P in zip(sp["drifts"], sp["P"]):
        i = np.flatnonzero((P > np.roll(P, 1)) & (P >= np.roll(P, -1)) & (P > 0))
        i = i[np.argsort(-P[i])[:4 * N_SCREEN]]  # a row's tallest are enough: the pool takes N_SCREEN
        loc += [(float(P[j]), float(freqs[j]), float(d)) for j in i]
    loc.sort(key=lambda p: -p[0])

    # beats the rankings did not nominate: a peak (β, d) is the line β + d·τ over the span (τ from its
    # start); one whose line comes within the resolution 1/D of a nominated peak's somewhere in the span
    # is that chirp at another drift (the refinement's to explore).  Every drift row's maximum of a new
    # beat is screened — the tallest is not always the right drift — and the best by the exact gain
    # stands for its line
    D = float(t[-1] - t[0])

    def apart(p, qs):
        for q in qs:
            sq = 1.0 if (p[1] + 0.5 * D * p[2]) * (q[1] + 0.5 * D * q[2]) >= 0 else -1.0  # (β, d) ≡ (−β, −d)
            g0, g1 = p[1] - sq * q[1], p[1] - sq * q[1] + (p[2] - sq * q[2]) * D
            if g0 * g1 <= 0 or min(abs(g0), abs(g1)) <= max(1.0 / D, 2 * f_read / L):
                return False
        return True

    pool = []
    for p in loc:
        if len(pool) >= N_SCREEN:
            break
        if apart(p, chosen) and _distinct(p, pool, 2 * f_read / L, 2 * step):
            pool.append(p)
    if not pool:
        return []
    t0 = t[0]
    beats = np.array([s * (f - d * t0) for _, f, d in pool for s in (1.0, -1.0)])
    drifts = np.array([s * d for _, _, d in pool for s in (1.0, -1.0)])
    g = _grid_gains(t, a, b, beats, drifts).reshape(len(pool), 2).max(1)
    out = []
    for j in np.argsort(-g):
        if len(out) >= N_SCREENED or not np.isfinite(g[j]):
            break
        if apart(pool[j], out):
            out.append(pool[j])
    return out
