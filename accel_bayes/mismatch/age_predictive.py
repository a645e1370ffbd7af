"""The predictive distribution of each IMU's data age after a clock acquisition, and the held-out
physics model with the age marginalised over it (issue #27 item 4; DESIGN §7.2.1).

Why.  A clock acquired on the target's first 30 s of motion is extrapolated over the following
~75 s; the beats drift with temperature, so the phase error grows with the time since the
acquisition.  Scoring the physics with the acquired (deterministic) age treats that extrapolation
as certain.  The predictive here is what the physics model knows about its own clock.

Phase.  IMU k's sawtooth phase is ψ_k(t) = φ_k + β_k τ (cycles), τ = t − t_c, t_c the acquisition
window's centre.  (φ_k, β_k) has the acquisition's posterior (:func:`phase_posterior`: the beat
search's exact sawtooth likelihood on a grid, flat prior, drift 0 inside the window).  After it the
beat moves: a random walk of rate q (Hz²/s) — a Brownian beat W(τ) adds ∫₀^τ W, of variance q|τ|³/3,
to the phase — and a linear drift at a random rate of variance σ²_d (Hz²/s², temperature: phase ½dτ²,
variance σ²_dτ⁴/4); :class:`ForecastNoise`.  Both rates are fitted on the *source* recording by maximum
likelihood of its own phase forecast errors (its window's posterior against its local phases later,
:func:`forecast_errors`, :func:`fit_forecast_noise`): on the real MIMU recordings the errors grow faster
than τ^1.5 (a drifting, not a wandering, beat), and a rate of beat increments alone
(:func:`beat_walk_rate`, the previous forecast) left the predictive too narrow at 60–85 s.  To first
order (Gaussian posterior, :func:`phase_predictive`)

    ψ_k(t) ~ N(φ̂ + β̂τ,  σ²_φ + 2τσ_φβ + τ²σ²_β + q|τ|³/3 + σ²_dτ⁴/4).

Age.  The data age is W·frac(ψ) (W = 1/f_int, s).  Its first two moments under a Gaussian phase
N(μ, σ²) are exact (:func:`sawtooth_moments`): per integer cycle n the truncated-normal moments of
ψ − n on [n, n + 1) summed, or — the same numbers — the sawtooth's Fourier series damped by the
Gaussian characteristic function ρ_m = exp(−2π²m²σ²):

    E frac ψ  = ½ − Σ_m ρ_m sin(2πmμ)/(πm),
    E frac² ψ = ⅓ + Σ_m ρ_m [cos(2πmμ)/(π²m²) − sin(2πmμ)/(πm)].

As σ grows ρ_m → 0: mean W/2, variance W²/12 — the uniform age of a clock whose phase is lost.

Model.  The held-out physics (:mod:`accel_bayes.mismatch.heldout`) is, per sample and sensor,
y_kt = −c d_kt ẏ_kt + d_kt m_t + e_kt: the clock's mean (rate regressor ẏ, coefficient c), the
unresolved motion m_t ~ N(0, s² I₃) loaded on the centred age d = C·age (C = I − 11ᵀ/K), and the
remainder e_t (covariance A).  With the ages random — independent between IMUs (independent clocks
and acquisitions) and of m_t and e_t — the marginal's first two moments are

    E y_kt = −c μ_kt ẏ_kt,
    Cov(y_kt, y_jt) = A_kj + s² (μ_kt μ_jt + Σ_kj,t) I₃ + c² Σ_kj,t ẏ_kt ẏ_jtᵀ,

μ = C E[age], Σ = C diag(Var age) C.  The marginal itself is a continuous mixture over the ages;
the density scored is its Gaussian projection (the Gaussian with these exact moments, the one
closest to it in KL(p‖q)), or for a t remainder the t with that scale matrix.  Σ = 0 gives the
deterministic model back; a lost phase leaves no mean and the unresolved motion loaded by the age
variance W²/12·C — the covariance part of the same physics.  :class:`AgeMoments` holds μ and a
factor F (Σ = F Fᵀ); :func:`moment_loadings` writes the covariance as a low-rank term for
:func:`accel_bayes.model.unresolved_cov.lowrank_terms`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
from scipy.special import ndtr

from ..model.unresolved_cov import loadings

__all__ = ["sawtooth_moments", "phase_posterior", "beat_walk_rate", "ForecastNoise",
           "forecast_errors", "fit_forecast_noise", "phase_predictive", "age_moments", "AgeMoments", "moment_loadings"]

_SQRT2PI = math.sqrt(2.0 * math.pi)
_SERIES_SIGMA = 0.5   # cycles: above it the Fourier series (ρ_2 < 3e-9) is used, under it the cycle sums
_CYCLES = 6           # cycles either side of μ summed under _SERIES_SIGMA (≥ 10 σ)


def sawtooth_moments(mu, sigma) -> tuple[np.ndarray, np.ndarray]:
    """(E frac ψ, E frac² ψ) for ψ ~ N(mu, sigma²) (cycles; arrays, broadcast): the module
    docstring's exact moments — cycle sums of truncated-normal moments for sigma ≤ 0.5, the damped
    Fourier series above (both exact to rounding there).  sigma = 0 gives frac(mu), frac(mu)²."""
    mu, sigma = np.broadcast_arrays(np.asarray(mu, float), np.asarray(sigma, float))
    m1, m2 = np.empty(mu.shape), np.empty(mu.shape)
    big = sigma > _SERIES_SIGMA
    if big.any():
        u, s = mu[big], sigma[big]
        a1, a2 = np.full(u.shape, 0.5), np.full(u.shape, 1.0 / 3.0)
        for m in range(1, 6):
            rho = np.exp(-2 * math.pi ** 2 * m * m * s * s)
            sn, cs = np.sin(2 * math.pi * m * u), np.cos(2 * math.pi * m * u)
            a1 -= rho * sn / (math.pi * m)
            a2 += rho * (cs / (math.pi * m) ** 2 - sn / (math.pi * m))
        m1[big], m2[big] = a1, a2
    sm = ~big
    if sm.any():
        u, s = mu[sm][..., None], np.maximum(sigma[sm], 1e-12)[..., None]
        n = np.floor(u) + np.arange(-_CYCLES, _CYCLES + 1)
        al, be = (n - u) / s, (n + 1 - u) / s
        pa, pb = np.exp(-0.5 * al * al) / _SQRT2PI, np.exp(-0.5 * be * be) / _SQRT2PI
        P = ndtr(be) - ndtr(al)
        off = u - n  # ψ − n = off + sZ on the cycle
        m1[sm] = (off * P + s * (pa - pb)).sum(-1)
        m2[sm] = ((off * off + s * s) * P + 2 * off * s * (pa - pb) + s * s * (al * pa - be * pb)).sum(-1)
    return m1, m2


def _profile_gain(tau, a, b, phi, beta) -> np.ndarray:
    """The beat search's exact-sawtooth gain (clock.py ``_profile``: W and the constant by weighted LS,
    weights a; 0 where W ≤ 0) at each (phi, beta) (G,) for ψ = phi + beta·tau; nats at unit noise."""
    Saa, Sb = a.sum(), b.sum()
    out = np.empty(len(phi))
    for i in range(0, len(phi), 256):  # chunks keep the (G, n) arrays small
        x = phi[i:i + 256, None] + beta[i:i + 256, None] * tau[None, :]
        s = x - np.floor(x)
        Sas, Sass, Sbs = s @ a, (s * s) @ a, s @ b
        det = Saa * Sass - Sas * Sas
        ok = det > 1e-300 * max(Saa, 1e-300)
        c = np.where(ok, (Sass * Sb - Sas * Sbs) / np.where(ok, det, 1.0), 0.0)
        W = np.where(ok, (Sas * Sb - Saa * Sbs) / np.where(ok, det, 1.0), 0.0)
        out[i:i + 256] = np.where(W > 0, 0.5 * (Sb * c - Sbs * W), 0.0)
    return out


def phase_posterior(t, a, b, *, beat_hz: float, phase: float, drift_hz_per_s: float = 0.0, t_c: float | None = None,
                    n_grid: int = 33, n_zoom: int = 4) -> dict:
    """The posterior of one IMU's sawtooth phase and beat at the window's centre from its timing
    statistics a (n,) s⁻², b (n,) s⁻¹ at times t (n,) s (:func:`~accel_bayes.mismatch.clock.clock_ab`),
    around a clock of the beat search (``beat_hz``, ``phase`` cycles at t = 0, ``drift_hz_per_s``).

    Likelihood: the search's exact sawtooth model with the noise factor profiled,
    exp(gain/ĉ²), ĉ² = Σb²/Σa (the evidence of :func:`accel_bayes.mismatch.heldout.clocks_from` is
    2·gain/ĉ²); drift 0 inside the window (what the beat does after it is the :class:`ForecastNoise`'s);
    flat prior.  Evaluated on an n_grid² grid, first ±½ cycle × ±2/D Hz
    (D the span) about the search's local (φ, β) at t_c, then ``n_zoom`` − 1 times re-centred on the
    posterior mean and narrowed to ±4 posterior standard deviations (never under 2 grid steps).
    Returns {"t_c" s, "phase" cycles at t_c, "beat_hz", "cov" 2×2 (cycles², cycles·Hz, Hz²)}."""
    t, a, b = (np.asarray(x, float) for x in (t, a, b))
    t_c = 0.5 * (t[0] + t[-1]) if t_c is None else float(t_c)
    tau = t - t_c
    beat_c = beat_hz + drift_hz_per_s * t_c
    phi_c = phase + beat_hz * t_c + 0.5 * drift_hz_per_s * t_c * t_c
    phi_c -= math.floor(phi_c)
    c2 = max(float((b * b).sum()) / max(float(a.sum()), 1e-300), 1e-300)
    D = max(float(t[-1] - t[0]), 1e-3)
    centre, half = np.array([phi_c, beat_c]), np.array([0.5, 2.0 / D])
    for _ in range(max(n_zoom, 1)):
        g = np.linspace(-1.0, 1.0, n_grid)
        P, B = np.meshgrid(centre[0] + half[0] * g, centre[1] + half[1] * g, indexing="ij")
        ll = _profile_gain(tau, a, b, P.ravel(), B.ravel()) / c2
        w = np.exp(ll - ll.max())
        w /= w.sum()
        x = np.stack([P.ravel(), B.ravel()], 1)
        mean = w @ x
        cov = (x - mean).T @ ((x - mean) * w[:, None])
        step = 2 * half / (n_grid - 1)
        centre = mean
        half = np.maximum(4 * np.sqrt(np.maximum(np.diag(cov), 0)), 2 * step)
        half = np.minimum(half, [0.5, 2.0 / D])
    return {"t_c": t_c, "phase": float(centre[0]), "beat_hz": float(centre[1]), "cov": cov}


def beat_walk_rate(t, a, b, clocks: dict, *, start: float, block_s: float = 30.0, min_info: int = 20) -> dict:
    """The beat's random-walk rate q (Hz²/s) of a recording, from its beats tracked over consecutive
    blocks of ``block_s`` s from ``start`` (s): each block's beat is the posterior mean of
    :func:`phase_posterior` on the block about the recording's clock (``clocks``: per IMU (K,)
    "beat_hz", "phase", "drift_hz_per_s", "width_s", as :func:`accel_bayes.mismatch.heldout.clocks_from`
    gives; an IMU with width 0 is skipped).  For a walk, the increment between consecutive blocks Δt
    apart is Δβ ~ N(0, q Δt + v₁ + v₂), v the blocks' posterior variances; q is the maximum-likelihood
    value over every IMU's increments (pooled: one temperature), q ≥ 0 — a block the data barely
    constrain (large v, e.g. a short last block) weighs little instead of swamping the sum.
    a, b (n, K), t (n,) s.  Returns {"q_hz2_per_s", "blocks": per IMU [(t_c, β, var β)], "n_increments"}."""
    from scipy.optimize import minimize_scalar

    t = np.asarray(t, float)
    a, b = np.asarray(a, float), np.asarray(b, float)
    K = a.shape[1]
    blocks, inc = [], []
    edges = np.arange(start, t[-1] + block_s, block_s)
    for k in range(K):
        rows = []
        if clocks["width_s"][k] > 0:
            for lo in edges[:-1]:
                sel = (t >= lo) & (t < lo + block_s) & (a[:, k] > 0)
                if int(sel.sum()) < min_info:
                    continue
                p = phase_posterior(t[sel], a[sel, k], b[sel, k], beat_hz=clocks["beat_hz"][k], phase=clocks["phase"][k],
                                    drift_hz_per_s=clocks["drift_hz_per_s"][k], t_c=lo + 0.5 * block_s)
                rows.append((p["t_c"], p["beat_hz"], float(p["cov"][1, 1])))
        inc += [((b2 - b1) ** 2, t2 - t1, v1 + v2) for (t1, b1, v1), (t2, b2, v2) in zip(rows[:-1], rows[1:])]
        blocks.append(rows)
    if not inc:
        return {"q_hz2_per_s": 0.0, "blocks": blocks, "n_increments": 0}
    d2, dt, v = (np.array(x) for x in zip(*inc))
    v = np.maximum(v, 1e-18)

    def nll(q):
        var = q * dt + v
        return float((np.log(var) + d2 / var).sum())

    r = minimize_scalar(lambda lq: nll(math.exp(lq)), bounds=(math.log(1e-14), math.log(1e-1)), method="bounded",
                        options={"xatol": 1e-4})
    q = math.exp(r.x) if nll(math.exp(r.x)) < nll(0.0) else 0.0
    return {"q_hz2_per_s": q, "blocks": blocks, "n_increments": len(inc)}


@dataclass(frozen=True)
class ForecastNoise:
    """What the phase does after the acquisition that the acquisition cannot see: a Brownian beat of rate
    ``q`` (Hz²/s; phase variance qτ³/3) and a beat drifting linearly at a random rate of variance
    ``drift_var`` (Hz²/s²; phase ½dτ², variance drift_var·τ⁴/4), τ s from the acquisition's centre."""

    q: float = 0.0
    drift_var: float = 0.0

    def cov(self, ti, tj) -> np.ndarray:
        """Phase covariance (cycles²) between τ = ti (n,) and tj (m,) s (both ≥ 0): the integrated
        Brownian beat's q(m²M/2 − m³/6), m = min, M = max, plus drift_var·ti²tj²/4."""
        ti, tj = np.abs(np.asarray(ti, float))[:, None], np.abs(np.asarray(tj, float))[None, :]
        lo, hi = np.minimum(ti, tj), np.maximum(ti, tj)
        return self.q * (lo * lo * hi / 2.0 - lo ** 3 / 6.0) + self.drift_var * (ti * tj) ** 2 / 4.0

    def var(self, tau) -> np.ndarray:
        """Phase variance (cycles²) at τ (any shape) s: qτ³/3 + drift_var·τ⁴/4."""
        tau = np.abs(np.asarray(tau, float))
        return self.q * tau ** 3 / 3.0 + self.drift_var * tau ** 4 / 4.0


def forecast_errors(t, a, b, post: dict, *, taus, block_s: float = 10.0, max_sd: float = 0.05,
                    min_info: int = 100) -> dict:
    """One IMU's phase forecast errors: at each τ of ``taus`` (s after ``post``'s centre, ascending) the
    phase of :func:`phase_posterior` (white noise) on the timing statistics a (n,) s⁻², b (n,) s⁻¹ at
    times t (n,) s within ±block_s/2 of t_c + τ, about the forecast φ̂ + β̂τ, less that forecast
    (cycles; wrapped, then unwrapped along τ — consecutive errors closer than ½ cycle).  A block with
    under ``min_info`` informative samples, or whose phase sd exceeds ``max_sd`` cycles (no sawtooth
    seen), is skipped.  Returns {"tau" (m,) s, "e" (m,) cycles, "var" (m,) the local phases' variances}."""
    t, a, b = (np.asarray(x, float) for x in (t, a, b))
    out, prev = {"tau": [], "e": [], "var": []}, 0.0
    for tau in taus:
        tc = post["t_c"] + tau
        sel = (np.abs(t - tc) <= 0.5 * block_s) & (a > 0)
        if int(sel.sum()) < min_info:
            continue
        loc = phase_posterior(t[sel], a[sel], b[sel], beat_hz=post["beat_hz"],
                              phase=post["phase"] - post["beat_hz"] * post["t_c"], t_c=tc)  # ±½ cycle: any seed
        if loc["cov"][0, 0] > max_sd ** 2:
            continue
        e = (loc["phase"] - post["phase"] - post["beat_hz"] * tau + 0.5) % 1.0 - 0.5
        e += round(prev - e)
        prev = e
        out["tau"].append(float(tau))
        out["e"].append(e)
        out["var"].append(float(loc["cov"][0, 0]))
    return {k: np.array(v) for k, v in out.items()}


def _forecast_cov(err: dict, post: dict, noise: ForecastNoise) -> np.ndarray:
    """Covariance (cycles²) of one IMU's forecast errors ``err`` (:func:`forecast_errors`) under the
    acquisition's posterior, the local phases' variances and ``noise``."""
    J = np.stack([np.ones_like(err["tau"]), err["tau"]], 1)
    return J @ post["cov"] @ J.T + np.diag(err["var"]) + noise.cov(err["tau"], err["tau"])


def fit_forecast_noise(errors: list, posts: list) -> ForecastNoise:
    """The :class:`ForecastNoise` that maximises the likelihood of a recording's own phase forecast
    errors (``errors`` per IMU a :func:`forecast_errors` or None, ``posts`` the acquisition posteriors
    they came from): per IMU the errors are jointly Gaussian with :func:`_forecast_cov`, independent
    between IMUs (own oscillators).  Both rates ≥ 0 (searched on a log scale down to 1e-16; a rate
    that does not raise the likelihood above its value at zero is set to zero)."""
    from scipy.optimize import minimize

    use = [(e, p) for e, p in zip(errors, posts) if e is not None and p is not None and len(e["tau"])]
    if not use:
        return ForecastNoise()
    groups = {}  # IMUs checked at the same τ share the noise's covariance shapes: one batched solve each
    for e, p in use:
        groups.setdefault(tuple(e["tau"]), []).append((_forecast_cov(e, p, ForecastNoise()), e["e"]))
    stacks = [(ForecastNoise(1.0, 0.0).cov(tau, tau), ForecastNoise(0.0, 1.0).cov(tau, tau),
               np.stack([c for c, _ in g]), np.stack([x for _, x in g])) for tau, g in groups.items()]

    def nll(noise):
        tot = 0.0
        for Kq, Kd, base, x in stacks:
            C = base + noise.q * Kq + noise.drift_var * Kd
            sign, logdet = np.linalg.slogdet(C)
            if np.any(sign <= 0):
                return np.inf
            tot += 0.5 * float(logdet.sum() + np.einsum("ni,ni->", x, np.linalg.solve(C, x[..., None])[..., 0]))
        return tot

    best = min((minimize(lambda x: nll(ForecastNoise(*np.exp(x))), x0, method="Nelder-Mead",
                         options={"xatol": 1e-3, "fatol": 1e-6, "maxiter": 2000}) for x0 in
                ([-15.0, -18.0], [-12.0, -22.0], [-18.0, -15.0])), key=lambda r: r.fun)
    q, d = np.exp(best.x)
    q = 0.0 if q < 1e-16 or nll(ForecastNoise(0.0, d)) <= best.fun else float(q)
    d = 0.0 if d < 1e-16 or nll(ForecastNoise(q, 0.0)) <= nll(ForecastNoise(q, d)) else float(d)
    return ForecastNoise(q, d)


def phase_predictive(t, post: dict, noise) -> tuple[np.ndarray, np.ndarray]:
    """(mean, std) of the phase (cycles) at times t (T,) s from :func:`phase_posterior`'s ``post``
    and what happens after it: ``noise`` a :class:`ForecastNoise`, or a float, the beat walk's rate q
    (Hz²/s) alone: N(φ̂ + β̂τ, σ²_φ + 2τσ_φβ + τ²σ²_β + qτ³/3 + drift_var·τ⁴/4)."""
    noise = noise if isinstance(noise, ForecastNoise) else ForecastNoise(q=float(noise))
    tau = np.asarray(t, float) - post["t_c"]
    C = post["cov"]
    var = C[0, 0] + 2 * tau * C[0, 1] + tau * tau * C[1, 1] + noise.var(tau)
    return post["phase"] + post["beat_hz"] * tau, np.sqrt(np.maximum(var, 0.0))


def age_moments(t, posts: list, q, width_s: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(mean (T, K) s, variance (T, K) s²) of each IMU's data age W·frac(ψ) at times t (T,) s
    (W = ``width_s``): ``posts`` per IMU a :func:`phase_posterior` or None (no clock: the phase is
    lost, the age uniform on [0, W)), q the beat walk's rate (Hz²/s) or a :class:`ForecastNoise`."""
    t = np.asarray(t, float)
    mean = np.full((len(t), len(posts)), 0.5 * width_s)
    var = np.full_like(mean, width_s * width_s / 12.0)
    for k, p in enumerate(posts):
        if p is None:
            continue
        m1, m2 = sawtooth_moments(*phase_predictive(t, p, q))
        mean[:, k], var[:, k] = width_s * m1, width_s * width_s * np.maximum(m2 - m1 * m1, 0.0)
    return torch.as_tensor(mean), torch.as_tensor(var)


@dataclass
class AgeMoments:
    """The centred data age's predictive moments: ``mean`` (T, K) s, μ = C E[age]; ``factor``
    (T, K, K) s with Σ = F Fᵀ = C diag(Var age) C; ``rate_c`` (T, K, 3) c·ẏ (units/s) of the
    clock's mean term, set per sensor by the scoring (None: that term's age variance left out)."""

    mean: torch.Tensor
    factor: torch.Tensor
    rate_c: torch.Tensor | None = None

    @classmethod
    def of(cls, mean: torch.Tensor, var: torch.Tensor) -> "AgeMoments":
        """From :func:`age_moments`' per-IMU mean and variance (independent IMUs), centred."""
        K = mean.shape[1]
        C = torch.eye(K, dtype=mean.dtype) - 1.0 / K
        return cls(mean - mean.mean(1, keepdim=True), C[None, :, :] * torch.sqrt(var.clamp_min(0))[:, None, :])

    def select(self, sel) -> "AgeMoments":
        """The samples ``sel`` (bool (T,))."""
        return replace(self, mean=self.mean[sel], factor=self.factor[sel],
                       rate_c=None if self.rate_c is None else self.rate_c[sel])


def moment_loadings(m: AgeMoments, s2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(U (T, 3K, r), s2 (T, r)) for :func:`~accel_bayes.model.unresolved_cov.lowrank_terms` of the
    module docstring's added covariance s²(μμᵀ + Σ) ⊗ I₃ + c² Σ ∘ ẏẏᵀ: columns μ ⊗ I₃ and F_·l ⊗ I₃
    (variance s², ``s2`` (T,) the unresolved motion's per sample, (units/s)²), and F_kl c·ẏ_k
    (variance 1) for each l.  r = 3 + 3K (+ K with ``rate_c``)."""
    T, K = m.mean.shape
    U = [loadings(m.mean)] + [loadings(m.factor[:, :, l]) for l in range(K)]
    v = [s2[:, None].expand(T, 3 + 3 * K)]
    if m.rate_c is not None:
        U.append((m.factor[:, :, None, :] * m.rate_c[:, :, :, None]).reshape(T, 3 * K, K))
        v.append(torch.ones(T, K, dtype=m.mean.dtype))
    return torch.cat(U, -1), torch.cat(v, -1)
