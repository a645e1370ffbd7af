"""Exact continuous-time rigid-body motion of a board: hand motion with rests, vibration, impacts.

Everything is closed form in t (numpy/scipy only, independent of ``accel_bayes.physics``):

* a speed envelope e(t) ∈ [0, 1], C³ piecewise polynomial (scipy ``BPoly``), 0 during rests, 1
  while moving; the hand motion runs on the warped time τ(t) = ∫e, so it freezes (at a new
  orientation each time) during every rest and τ̇ = e, τ̈ = ė are exact;
* orientation R(t) = Exp(φ(t)) (array → world), φ = H(τ) + e(t)·V(t) + B(t): H a sum of sinusoids
  of 0.1–7 Hz, V board vibration of 30–95 Hz, B impacts (decaying bursts u³·exp(−u/τ)·sin, C² at
  their onset, placed while e = 1);
* position p(t) of the array origin built the same way;
* body rate ω = J_r(φ) φ̇ and its exact derivative ω̇ (closed form below), p̈ exact.

Specific force at a triad at r (array frame): f = Rᵀ(p̈ − g) + ω̇ × r + ω × (ω × r), g = (0, 0, −g₀).
"""
from __future__ import annotations

import numpy as np
from scipy.interpolate import BPoly

G0 = 9.80665  # m/s², standard gravity
GRAVITY = np.array([0.0, 0.0, -G0])


def _hat(v):
    """Skew matrices [v]× for (..., 3) vectors."""
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1),
                     np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def exp_so3(phi):
    """Rotation matrices Exp(φ) for (..., 3) rotation vectors (rad), Rodrigues' formula."""
    th = np.linalg.norm(phi, axis=-1)[..., None, None]
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    A = np.where(small, 1.0 - th**2 / 6, np.sin(ths) / ths)
    B = np.where(small, 0.5 - th**2 / 24, (1 - np.cos(ths)) / ths**2)
    K = _hat(phi)
    return np.eye(3) + A * K + B * (K @ K)


def _jr_coeffs(th):
    """a = (1−cosθ)/θ², b = (θ−sinθ)/θ³ and their θ-derivatives divided by θ (series near 0)."""
    # below 0.02 rad the closed forms lose ~eps/θ² to cancellation; the series' next terms are < 1e-11
    s = th < 0.02
    t = np.where(s, 1.0, th)
    a = np.where(s, 0.5 - th**2 / 24, (1 - np.cos(t)) / t**2)
    b = np.where(s, 1 / 6 - th**2 / 120, (t - np.sin(t)) / t**3)
    da = np.where(s, -1 / 12 + th**2 / 180, (t * np.sin(t) - 2 * (1 - np.cos(t))) / t**4)
    db = np.where(s, -1 / 60 + th**2 / 1260, ((1 - np.cos(t)) * t - 3 * (t - np.sin(t))) / t**5)
    return a, b, da, db


def body_rate(phi, dphi, ddphi):
    """Exact body rate ω = J_r(φ)φ̇ and ω̇ (rad/s, rad/s²) of R = Exp(φ), from φ, φ̇, φ̈ (..., 3).

    J_r(φ)φ̇ = φ̇ − a φ×φ̇ + b φ×(φ×φ̇); differentiating, with ȧ = (a'/θ)(φ·φ̇) and likewise ḃ,
    ω̇ = φ̈ − ȧ φ×φ̇ − a φ×φ̈ + ḃ φ×(φ×φ̇) + b [φ̇×(φ×φ̇) + φ×(φ×φ̈)].
    """
    th = np.linalg.norm(phi, axis=-1)
    a, b, da, db = (c[..., None] for c in _jr_coeffs(th))
    pd = np.sum(phi * dphi, -1)[..., None]
    c1 = np.cross(phi, dphi)
    c2 = np.cross(phi, ddphi)
    w = dphi - a * c1 + b * np.cross(phi, c1)
    wd = (ddphi - da * pd * c1 - a * c2 + db * pd * np.cross(phi, c1)
          + b * (np.cross(dphi, c1) + np.cross(phi, c2)))
    return w, wd


class Sinusoids:
    """x(u) = Σ_j A_j sin(2π f_j u + ψ_j) per axis, with exact first and second derivatives."""

    def __init__(self, amp, freq, phase):
        self.amp, self.freq, self.phase = (np.asarray(x, float) for x in (amp, freq, phase))  # (3, M)

    def __call__(self, u, order=0):
        """Value (order 0), first or second derivative at times u (N,) → (N, 3)."""
        w = 2 * np.pi * self.freq
        arg = u[:, None, None] * w + self.phase
        if order == 0:
            return np.sum(self.amp * np.sin(arg), -1)
        if order == 1:
            return np.sum(self.amp * w * np.cos(arg), -1)
        return np.sum(-self.amp * w**2 * np.sin(arg), -1)


class Bursts:
    """Impacts: Σ_i A_i u³ exp(−u/τ_i) sin(2π f_i u) with u = t − t_i ≥ 0 (zero before the onset)."""

    def __init__(self, onset, amp, tau, freq):
        self.onset, self.tau, self.freq = (np.asarray(x, float) for x in (onset, tau, freq))  # (n,)
        self.amp = np.asarray(amp, float).reshape(-1, 3)  # (n, 3), peak-normalised amplitude

    def __call__(self, t, order=0):
        """Value or derivative (order 0–2) at t (N,) → (N, 3); C² at each onset (u³ factor)."""
        out = np.zeros((len(t), 3))
        for t0, A, tau, f in zip(self.onset, self.amp, self.tau, self.freq):
            u = t - t0
            on = (u > 0) & (u < 40 * tau)
            if not on.any():
                continue
            u = u[on]
            # the envelope peaks at u = 3τ with value (3τ/e)³: normalise so A is the peak amplitude
            k = 1.0 / (3 * tau / np.e) ** 3
            E = [u**3 * np.exp(-u / tau)]
            E.append((3 * u**2 - u**3 / tau) * np.exp(-u / tau))
            E.append((6 * u - 6 * u**2 / tau + u**3 / tau**2) * np.exp(-u / tau))
            w = 2 * np.pi * f
            S = [np.sin(w * u), w * np.cos(w * u), -w**2 * np.sin(w * u)]
            if order == 0:
                v = E[0] * S[0]
            elif order == 1:
                v = E[1] * S[0] + E[0] * S[1]
            else:
                v = E[2] * S[0] + 2 * E[1] * S[1] + E[0] * S[2]
            out[on] += k * v[:, None] * A
        return out


def envelope(rest_ends, move_ends, ramp):
    """C³ speed envelope: 0 on [0, rest_ends[0]], ramps of length ``ramp`` s, 1 while moving, etc.

    ``rest_ends[i] < move_ends[i] < rest_ends[i+1]``: motion i runs from rest_ends[i] to move_ends[i].
    Returns (e, τ) as scipy BPoly objects, τ = ∫₀ᵗ e exactly.
    """
    x, y = [0.0], [[0.0, 0, 0, 0]]
    for r, m in zip(rest_ends, move_ends):
        x += [r, r + ramp, m - ramp, m]
        y += [[0.0, 0, 0, 0], [1.0, 0, 0, 0], [1.0, 0, 0, 0], [0.0, 0, 0, 0]]
    # a last knot far out so that the rest after the final move stays exactly zero (no extrapolation)
    x.append(x[-1] + 1e6)
    y.append([0.0, 0, 0, 0])
    e = BPoly.from_derivatives(np.array(x), y, extrapolate=True)
    return e, e.antiderivative()


class Motion:
    """Exact board motion (see module docstring); call :meth:`at` for the state at any instants."""

    def __init__(self, e, tau, rot_hand, pos_hand, rot0, rot_vib, pos_vib, rot_imp, pos_imp, t_end):
        self.e, self.tau = e, tau
        self.rot_hand, self.pos_hand, self.rot0 = rot_hand, pos_hand, np.asarray(rot0, float)
        self.rot_vib, self.pos_vib, self.rot_imp, self.pos_imp = rot_vib, pos_vib, rot_imp, pos_imp
        self.t_end = float(t_end)

    def _env(self, t):
        tt = np.clip(t, 0.0, self.t_end)  # constant (at rest) outside the recording
        inside = ((t >= 0) & (t <= self.t_end)).astype(float)
        return self.tau(tt), self.e(tt) * 1.0, self.e(tt, 1) * inside, self.e(tt, 2) * inside

    def _warped(self, H, t):
        """H(τ(t)) and its exact first and second t-derivatives (chain rule, τ̇ = e, τ̈ = ė)."""
        tau, e, de, _ = self._env(t)
        h0, h1, h2 = H(tau, 0), H(tau, 1), H(tau, 2)
        return h0, h1 * e[:, None], h2 * (e**2)[:, None] + h1 * de[:, None]

    def _gated(self, S, t):
        """e(t)·S(t) and its derivatives: vibration exists only while the board is handled."""
        _, e, de, dde = self._env(t)
        s0, s1, s2 = S(t, 0), S(t, 1), S(t, 2)
        e, de, dde = e[:, None], de[:, None], dde[:, None]
        return e * s0, de * s0 + e * s1, dde * s0 + 2 * de * s1 + e * s2

    def _sum(self, hand, vib, imp, t):
        parts = [self._warped(hand, t)]
        if vib is not None:
            parts.append(self._gated(vib, t))
        if imp is not None:
            parts.append(tuple(imp(t, k) for k in range(3)))
        return [sum(p[k] for p in parts) for k in range(3)]

    def at(self, t):
        """State at times t (N,) s: dict R (N,3,3) array→world, w, dw (N,3) body rad/s, rad/s²,
        p (N,3) m, acc = p̈ (N,3) m/s² world, phi (N,3)."""
        t = np.asarray(t, float)
        phi, dphi, ddphi = self._sum(self.rot_hand, self.rot_vib, self.rot_imp, t)
        phi = phi + self.rot0
        p, _, pdd = self._sum(self.pos_hand, self.pos_vib, self.pos_imp, t)
        w, dw = body_rate(phi, dphi, ddphi)
        return {"phi": phi, "R": exp_so3(phi), "w": w, "dw": dw, "p": p, "acc": pdd}

    def specific_force(self, t, r):
        """Specific force (m/s², array frame) at array-frame positions r (K,3) → (N,K,3), and ω (N,3)."""
        s = self.at(t)
        f0 = np.einsum("nji,nj->ni", s["R"], s["acc"] - GRAVITY)
        w, dw = s["w"][:, None, :], s["dw"][:, None, :]
        r = np.asarray(r, float)[None]
        f = f0[:, None, :] + np.cross(dw, r) + np.cross(w, np.cross(w, r))
        return f, s["w"]

    def rest_mask(self, t):
        """True where the board is exactly at rest (envelope zero)."""
        _, e, _, _ = self._env(np.asarray(t, float))
        return e == 0.0


def _masked(s, mask):
    s.amp = s.amp * mask[:, None]
    return s


def draw_motion(rng, duration, *, vibration=True, impacts=True, n_comp=6, rot_axes=(0, 1, 2)):
    """A random hand-held session of ``duration`` s: first rest 2–3 s, then moves of 3–6 s
    separated by rests of 1.5–3 s (0.4 s ramps), hand motion 0.1–7 Hz, vibration 30–95 Hz
    (translational 0.3–2 m/s², rotational 0.05–0.3 rad/s amplitude), 1–3 impacts per move
    (peak 3–15 m/s² and 1–5 rad/s at 40–90 Hz, decay 5–20 ms).  ``rot_axes``: the array axes the
    board rotates about (e.g. (2,) for an under-excited rig: rotation about z only, since φ then
    stays on that axis).  Returns :class:`Motion`."""
    rest_ends, move_ends, t = [], [], rng.uniform(2.0, 3.0)
    while t + 3.0 + 1.5 < duration:
        rest_ends.append(t)
        t = min(t + rng.uniform(3.0, 6.0), duration - 1.5)
        move_ends.append(t)
        t += rng.uniform(1.5, 3.0)
    e, tau = envelope(rest_ends, move_ends, 0.4)

    def hand(w_lo, w_hi, cap, accel):
        f = np.exp(rng.uniform(np.log(0.1), np.log(7.0), (3, n_comp)))
        mag = rng.uniform(w_lo, w_hi, (3, n_comp))
        A = mag / (2 * np.pi * f) ** (2 if accel else 1)
        return Sinusoids(np.minimum(A, cap), f, rng.uniform(0, 2 * np.pi, (3, n_comp)))

    def vib(lo, hi, accel):
        f = rng.uniform(30.0, 95.0, (3, 3))
        A = rng.uniform(lo, hi, (3, 3)) / (2 * np.pi * f) ** (2 if accel else 1) / np.sqrt(3)
        return Sinusoids(A, f, rng.uniform(0, 2 * np.pi, (3, 3)))

    rot_imp = pos_imp = None
    if impacts:
        on, f, tauv = [], [], []
        for r, m in zip(rest_ends, move_ends):
            for _ in range(rng.integers(1, 4)):
                # onset late enough to clear the ramp and early enough that 40 τ of decay ends before the rest
                on.append(rng.uniform(r + 0.5, max(r + 0.5, m - 1.2)))
        n = len(on)
        f = rng.uniform(40.0, 90.0, n)
        tauv = rng.uniform(0.005, 0.020, n)
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        w = 2 * np.pi * f
        pos_imp = Bursts(on, d * (rng.uniform(3, 15, n) / w**2)[:, None], tauv, f)
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        rot_imp = Bursts(on, d * (rng.uniform(1, 5, n) / w)[:, None], tauv, f)
    mask = np.isin(np.arange(3), rot_axes).astype(float)
    rot_hand = hand(0.3, 1.5, 0.6, False)
    rot_hand.amp = rot_hand.amp * mask[:, None]
    if rot_imp is not None:
        rot_imp.amp = rot_imp.amp * mask
    return Motion(e, tau, rot_hand, hand(0.3, 2.0, 0.25, True), rng.uniform(-1.2, 1.2, 3) * mask,
                  _masked(vib(0.05, 0.3, False), mask) if vibration else None,
                  vib(0.3, 2.0, True) if vibration else None,
                  rot_imp, pos_imp, duration)
