"""An independent forward model of an IMU array on a rigid board, for blind mismatch tests.

Why a second simulator.  The mismatch detector (:mod:`accel_bayes.mismatch`) adds linearised
effect terms to the package's signal model (:mod:`accel_bayes.physics.models`).  Testing it only on data
made by those same terms proves nothing: a shared mistake (a sign, a frame, a first-order
approximation) would cancel.  This module therefore uses none of the package's numerical code
(no ``models``, no ``motion``, no ``simulate``, no ``geometry``): it is numpy from first
principles, and the effects are applied the physical way (a late IMU is *evaluated later on the
continuous trajectory*, a displaced sensing axis *sits at another point of the rigid body*, a
rotated triad *has another rotation matrix*), not as additive perturbation terms.  Only the board
designs (:mod:`accel_bayes.physics.arrays` presets), the :class:`~accel_bayes.data.recording.Recording` type
and the file writers of :mod:`accel_bayes.data.io` come from the package.

Physics
-------
World frame: z up, gravity g_w = (0, 0, −9.80665) m/s².  The board (array frame) has attitude
R_wb(t) (array → world) and its origin sits at p₀(t) (world, m).  A board point x (array frame,
m) is at p(t, x) = p₀(t) + R_wb(t) x, so its acceleration is p̈ = p̈₀ + R̈_wb x.  An
accelerometer axis e_i of IMU k (rotation R_k, array → sensor, DESIGN §7.0) sensing at board
point x reads the specific force

    y_ki^a(t) = e_iᵀ R_k R_wb(t)ᵀ (p̈₀(t) + R̈_wb(t) x − g_w),

and its gyroscope axis reads y_ki^g(t) = e_iᵀ R_k ω(t) with the body rate ω from
Ω(ω) = R_wbᵀ Ṙ_wb.  Both Ṙ_wb and R̈_wb are differentiated *analytically* from the closed form
of the attitude (below); no ω × (ω × r) formula is used anywhere.  :func:`check_point_acceleration`
compares p̈ with an 8th-order central finite difference of the world position, with an error
bound, and ``tests/experiments/test_conceal.py`` runs it.

Trajectory (:class:`RotvecTrajectory`)
--------------------------------------
R_wb(t) = R₀ · Exp(v(t)) with a rotation vector v(t) = v₀ + w t + Σ_m A_m sin(2π f_m t + φ_m)
per component (w = 0 for the random trajectories; a constant w gives rotation about a fixed axis) (a different construction from the package's product of three single-axis rotations,
on purpose).  With V = Ω(v) and s = vᵀv, Rodrigues gives Exp(v) = I + a(s) V + b(s) V²,
a = sin√s/√s, b = (1 − cos√s)/s.  Writing a, b as functions of s (smooth at s = 0, unlike θ = √s)
the time derivatives follow by the product and chain rules:

    Ṙ = ȧV + aV̇ + ḃV² + b(V̇V + VV̇)
    R̈ = äV + 2ȧV̇ + aV̈ + b̈V² + 2ḃ(V̇V + VV̇) + b(V̈V + 2V̇V̇ + VV̈),
    ȧ = a'ṡ,  ä = a''ṡ² + a's̈,  ṡ = 2vᵀv̇,  s̈ = 2(v̇ᵀv̇ + vᵀv̈),

with a' = (cos√s − a)/(2s), a'' = −(a/4 + 3a'/2)/s, b' = (a/2 − b)/s, b'' = (a'/2 − 2b')/s
(Taylor series below s = 1).  The origin moves along p₀(t) = Σ_m B_m sin(2π g_m t + ψ_m)
per world axis.

Concealed effects (:func:`make_case`)
-------------------------------------
One effect per case, on one random non-reference IMU (and one random axis where the effect has
one), with the DESIGN §7.2 names and parameters:

==================== ====================================================================
``time_offset``      the IMU's whole output (acc and gyro) is evaluated at t + δ on the
                     continuous trajectory; δ = ±(0.1–1) ms, positive = sampled late.
``axis_displacement`` accelerometer axis i of the IMU senses at x_k + R_kᵀ d with d a
                     random-direction sensor-frame 3-vector, |d| = 0.2–1 mm.
``triad_orientation`` the IMU is mounted rotated: R_k,true = Exp(ρ) R_k,nominal with ρ a
                     random-direction sensor-frame rotation vector, |ρ| = 0.05–0.5°.  Both
                     triads of the IMU turn (DESIGN §7.0: they share the sensor frame).
``acc_scale``        y_i ← (1 + s) y_i, |s| = 0.1–1 %.
``acc_misalignment`` y_i ← y_i + c·f_j with j ≠ i random, |c| = 0.2–1 % (rad).
``acc_bias``         y_i ← y_i + b, |b| = 0.02–0.2 m/s².
``acc_nonlinearity`` y_i ← y_i + k₂ f_i², |k₂| = 2·10⁻⁵–10⁻⁴ (m/s²)⁻¹.
``gyro_bias``        ω_i ← ω_i + b, |b| = 0.05–0.5 °/s.
``gyro_scale``       ω_i ← (1 + s) ω_i, |s| = 0.05–0.5 %.
``gyro_g_sensitivity`` ω_i ← ω_i + k f_i (f: the IMU's own specific force, sensor frame),
                     |k| = 0.1–0.3 (°/s)/g.
``gyro_nonlinearity`` ω_i ← ω_i + k₂ ω_i² (ω_i the true sensor-frame rate of the axis),
                     |k₂| = 4·10⁻⁵–2·10⁻⁴ (rad/s)⁻¹: on the default motion (RMS |ω| 250–600 °/s,
                     peaks of several rad/s per axis) k₂ω² reaches a few to tens of times the
                     gyro noise σ_g = 0.05–0.15 °/s at the rate peaks (DESIGN §7.2 vocabulary 1.1).
``noise_level``      the IMU's *accelerometer* noise is factor × the stated std,
                     factor = 1.2–2 (gyro noise stays as stated; axis is None).
``saturation``       the IMU's accelerometer triad clips at ±L on every axis, L = 0.90–0.97 ×
                     its largest |output| in the recording; the recording's ``acc_clipped``
                     flags are NOT set and ``acc_range`` keeps the design value (the sensor
                     saturates below its stated range, unannounced: the detector must find
                     it).  The truth's axis is the axis with the most clipped samples.
``sampling_jitter``  each sample of the IMU (acc and gyro alike) is the exact kinematics at
                     its own instant t + δ_t, δ_t ~ U(−w/2, w/2) i.i.d. per sample, w = 0.1–1 ms
                     (axis None); δ drawn from the effect stream after every other draw.
==================== ====================================================================

Multi-effect cases (:func:`make_multi_case`, issue #11 item 6) mimic the real MIMU4444
recordings instead: the mimu8 board at 62.5 Hz, vigorous motion (RMS |ω| 600–1200 °/s), a 3 × 3
linear gyro error (scale and couplings up to 1.5–2.7 %) and gyro biases on *every* IMU, and at
most one of ``sampling_jitter``, ``gyro_nonlinearity``, ``timing_wander`` (gyro) on one random
non-reference IMU; its ``effect="none"`` twin keeps the linear errors, and ``gyro_linear=False``
gives the control without them.

Signs are random.  Sensor errors act on the noise-free signal; white noise is added after them
and clipping after the noise (an ADC clips what it sees).  Every case also moves every IMU's true
position off the design by a random 0.1–0.3 mm, so the geometry has something to estimate.

Randomness: a case is a pure function of ``(board, effect, seed, overrides)``.  The seed is
split into independent streams (settings, trajectory, geometry, noise, effect), so the case with
``effect="none"`` and the same seed is the *exact clean twin* of an effect case (same motion,
same true geometry, same noise draws): the benchmark uses it to measure the clean-data position
error of the very same data set.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = [
    "G0",
    "DEG",
    "G_WORLD",
    "EFFECTS",
    "OUT_OF_VOCABULARY",
    "BOARDS",
    "EFFECT_RANGES",
    "AXIS_EFFECTS",
    "Board",
    "board",
    "irregular6",
    "quat_to_rotmat",
    "rotmat_to_quat",
    "so3_exp",
    "RotvecTrajectory",
    "sensor_outputs",
    "fd_second_derivative",
    "check_point_acceleration",
    "draw_settings",
    "ConcealedCase",
    "make_case",
    "save_case",
    "oracle_noncentrality",
    "MULTI_EFFECTS",
    "MULTI_RANGES",
    "make_multi_case",
]

G0 = 9.80665  # m/s², standard gravity (same constant as accel_bayes.physics.arrays.G0)
DEG = math.pi / 180.0
G_WORLD = np.array([0.0, 0.0, -G0])
AXES = ("x", "y", "z")

EFFECTS = (
    "acc_bias",
    "acc_scale",
    "acc_misalignment",
    "acc_nonlinearity",
    "axis_displacement",
    "triad_orientation",
    "gyro_bias",
    "gyro_scale",
    "gyro_g_sensitivity",
    "time_offset",
    "saturation",
    "noise_level",
    "gyro_nonlinearity",  # vocabulary 1.1; appended so the seeds of the other effects' cases stay put
    "sampling_jitter",
)
# Physics outside the report vocabulary (DESIGN §7.2).  ``gyro_lowpass`` is what the package's
# extension ``gyro_delay`` describes to first order, ``acc_lowpass`` what its extension
# ``timing_wander`` (accelerometer, correlation ≈ 1) does; ``acc_drift`` is outside the package's
# catalogue too and must come out as a characterised ``unexplained`` (issue #11 item 2).
OUT_OF_VOCABULARY = (
    "gyro_lowpass",  # one IMU's gyroscope behind a first-order low-pass filter, {"time_constant"} s
    "acc_lowpass",   # one IMU's accelerometer behind a first-order low-pass filter, {"time_constant"} s
    "timing_wander",  # the package's extension: one IMU's gyro sampled at AR(1)-wandering instants
    "acc_drift",     # one accelerometer axis's bias drifts linearly through the recording, {"drift"} m/s²
)
# Effects that live on one sensing axis (the truth names it); the others have axis None.
AXIS_EFFECTS = ("acc_bias", "acc_scale", "acc_misalignment", "acc_nonlinearity", "axis_displacement",
                "gyro_bias", "gyro_scale", "gyro_g_sensitivity", "gyro_nonlinearity", "saturation", "acc_drift")
# |magnitude| ranges, SI units (the brief's ranges converted).
EFFECT_RANGES = {
    "time_offset": (1e-4, 1e-3),                    # s
    "axis_displacement": (2e-4, 1e-3),              # m
    "triad_orientation": (0.05 * DEG, 0.5 * DEG),   # rad
    "acc_scale": (1e-3, 1e-2),                      # relative
    "acc_misalignment": (2e-3, 1e-2),               # rad
    "acc_bias": (0.02, 0.2),                        # m/s²
    "acc_nonlinearity": (2e-5, 1e-4),               # (m/s²)⁻¹
    "gyro_bias": (0.05 * DEG, 0.5 * DEG),           # rad/s
    "gyro_scale": (5e-4, 5e-3),                     # relative
    "gyro_g_sensitivity": (0.1 * DEG / G0, 0.3 * DEG / G0),  # rad/s per m/s²
    "noise_level": (1.2, 2.0),                      # × stated std
    "saturation": (0.90, 0.97),                     # limit / peak |output|
    "gyro_nonlinearity": (4e-5, 2e-4),              # (rad/s)⁻¹
    "gyro_lowpass": (2e-4, 1e-3),                   # s, time constant (bandwidth 160–800 Hz)
    "acc_lowpass": (2e-4, 1e-3),                    # s
    "timing_wander": (3e-4, 2e-3),                  # s, √12 × the std of the instant error
    "sampling_jitter": (1e-4, 1e-3),                # s, full width of the uniform instant error
    "acc_drift": (0.05, 0.15),                      # m/s², the bias at the recording's end (−that at its start)
}
# Signed effects (the sign is drawn at random); the others are positive by nature.
_SIGNED = ("time_offset", "acc_scale", "acc_misalignment", "acc_bias", "acc_nonlinearity", "gyro_bias",
           "gyro_scale", "gyro_g_sensitivity", "gyro_nonlinearity", "acc_drift")


# ============================================================================ rotations (numpy)

def skew(v: np.ndarray) -> np.ndarray:
    """Ω(v): (..., 3) → (..., 3, 3) with Ω(v) x = v × x."""
    v = np.asarray(v, dtype=float)
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2)


def unskew(M: np.ndarray) -> np.ndarray:
    """The vector of the antisymmetric part of (..., 3, 3) M."""
    A = 0.5 * (M - np.swapaxes(M, -1, -2))
    return np.stack([A[..., 2, 1], A[..., 0, 2], A[..., 1, 0]], -1)


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """R(q) of DESIGN §7.0 for unit quaternions (w, x, y, z): (..., 4) → (..., 3, 3)."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = (q[..., i] for i in range(4))
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`quat_to_rotmat` for one 3×3 rotation (w ≥ 0), via the largest of the
    four squared components (no cancellation for any rotation)."""
    R = np.asarray(R, dtype=float)
    tr = np.trace(R)
    cand = np.array([1 + tr, 1 + 2 * R[0, 0] - tr, 1 + 2 * R[1, 1] - tr, 1 + 2 * R[2, 2] - tr])
    i = int(np.argmax(cand))
    r = math.sqrt(max(cand[i], 0.0))
    if i == 0:
        q = [r, (R[2, 1] - R[1, 2]) / r, (R[0, 2] - R[2, 0]) / r, (R[1, 0] - R[0, 1]) / r]
    elif i == 1:
        q = [(R[2, 1] - R[1, 2]) / r, r, (R[0, 1] + R[1, 0]) / r, (R[0, 2] + R[2, 0]) / r]
    elif i == 2:
        q = [(R[0, 2] - R[2, 0]) / r, (R[0, 1] + R[1, 0]) / r, r, (R[1, 2] + R[2, 1]) / r]
    else:
        q = [(R[1, 0] - R[0, 1]) / r, (R[0, 2] + R[2, 0]) / r, (R[1, 2] + R[2, 1]) / r, r]
    q = np.array(q) * 0.5
    q = q / np.linalg.norm(q)
    return q if q[0] >= 0 else -q


# a(s) = sin√s/√s and b(s) = (1 − cos√s)/s with their first two s-derivatives.  Taylor series
# below s = 1 (|v| < 1 rad), where the closed forms of the derivatives lose digits to
# cancellation (b'' by ~1e-8 relative at s = 1e-2); 14 terms leave a truncation error below
# 1/28! ≈ 3e-30 there.
_A_SER = [(-1) ** n / math.factorial(2 * n + 1) for n in range(14)]   # a = Σ c_n s^n
_B_SER = [(-1) ** n / math.factorial(2 * n + 2) for n in range(14)]   # b = Σ c_n s^n
_SERIES_BELOW = 1.0


def _series(c, s, d):
    out = np.zeros_like(s)
    for n in range(len(c) - 1, d - 1, -1):
        coef = c[n] * math.prod(range(n - d + 1, n + 1))
        out = out * s + coef
    return out


def _rodrigues_coefficients(s: np.ndarray):
    """a, a', a'', b, b', b'' at s = |v|² (derivatives with respect to s)."""
    s = np.asarray(s, dtype=float)
    small = s < _SERIES_BELOW
    ss = np.where(small, 1.0, s)  # keeps the closed forms finite where the series is used
    th = np.sqrt(ss)
    a = np.sin(th) / th
    b = (1 - np.cos(th)) / ss
    a1 = (np.cos(th) - a) / (2 * ss)
    a2 = -(a / 4 + 1.5 * a1) / ss
    b1 = (a / 2 - b) / ss
    b2 = (a1 / 2 - 2 * b1) / ss
    out = []
    for closed, ser, d in ((a, _A_SER, 0), (a1, _A_SER, 1), (a2, _A_SER, 2),
                           (b, _B_SER, 0), (b1, _B_SER, 1), (b2, _B_SER, 2)):
        out.append(np.where(small, _series(ser, s, d), closed))
    return out


def so3_exp(v: np.ndarray) -> np.ndarray:
    """Exp(v) = I + a V + b V² (Rodrigues), rotation vector v (..., 3) in rad."""
    v = np.asarray(v, dtype=float)
    a, _, _, b, _, _ = _rodrigues_coefficients((v * v).sum(-1))
    V = skew(v)
    return np.eye(3) + a[..., None, None] * V + b[..., None, None] * (V @ V)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Haar-random rotation matrix (normalised Gaussian quaternion)."""
    q = rng.standard_normal(4)
    return quat_to_rotmat(q / np.linalg.norm(q))


def _random_unit(rng: np.random.Generator, n=None) -> np.ndarray:
    shape = (3,) if n is None else (n, 3)
    u = rng.standard_normal(shape)
    return u / np.linalg.norm(u, axis=-1, keepdims=True)


# ============================================================================ boards

@dataclass(frozen=True)
class Board:
    """A board design (numpy): nominal positions (K, 3) m array frame, orientations (K, 4)
    array → sensor quaternions (DESIGN §7.0), reference IMU, sensor ranges."""

    name: str
    positions: np.ndarray
    orientations: np.ndarray
    reference_imu: int = 0
    acc_range: float | None = 16 * G0
    gyro_range: float | None = 2000 * DEG

    @property
    def K(self) -> int:
        return int(self.positions.shape[0])

    @property
    def rotations(self) -> np.ndarray:
        """(K, 3, 3) array → sensor rotation matrices R_k."""
        return quat_to_rotmat(self.orientations)


def irregular6() -> Board:
    """A board no detector setting was tuned on: 6 IMUs spread irregularly in 3-D (up to ±23 mm,
    z spread 25 mm) with fixed pseudo-random mounting orientations; IMU 0 is the reference."""
    pos_mm = [(0.0, 0.0, 0.0), (23.0, 4.0, -3.0), (-7.0, 19.0, 6.0), (-15.0, -12.0, 2.0),
              (9.0, -21.0, 11.0), (4.0, 7.0, -14.0)]
    rng = np.random.default_rng(20240611)
    quats = []
    for _ in pos_mm:
        q = rng.standard_normal(4)
        q = q / np.linalg.norm(q)
        quats.append(q if q[0] >= 0 else -q)
    return Board("irregular6", np.asarray(pos_mm) * 1e-3, np.asarray(quats), 0, 16 * G0, 2000 * DEG)


def board(name: str) -> Board:
    """A board by name: ``mimu32``, ``mimu8`` (the package presets, converted to numpy) or
    ``irregular6`` (:func:`irregular6`)."""
    if name == "irregular6":
        return irregular6()
    if name in ("mimu32", "mimu8"):
        from accel_bayes.physics.arrays import preset

        arr = preset(name)
        return Board(name, arr.positions.numpy().astype(float).copy(), arr.orientations.numpy().astype(float).copy(),
                     int(arr.reference_imu), arr.acc_range, arr.gyro_range)
    raise ValueError(f"board: expected one of {BOARDS}, got {name!r}")


BOARDS = ("mimu32", "mimu8", "irregular6")


# ============================================================================ trajectory

def _sines(t, amp, freq, phase):
    """x, ẋ, ẍ of Σ_m amp_m sin(2π f_m t + φ_m) per row: amp etc. (3, M), t (T,) → 3 × (T, 3)."""
    w = 2 * np.pi * np.asarray(freq, float)
    arg = t[:, None, None] * w[None] + np.asarray(phase, float)[None]
    A = np.asarray(amp, float)[None]
    return ((A * np.sin(arg)).sum(-1), (A * w * np.cos(arg)).sum(-1), (-A * w * w * np.sin(arg)).sum(-1))


@dataclass
class RotvecTrajectory:
    """Continuous rigid-body motion R_wb(t) = R₀ Exp(v(t)), p₀(t) (see the module docstring).

    Parameters: R0 (3, 3); v0 (3,) rad; rot_amp, rot_freq, rot_phase (3, M) rad, Hz, rad (rotation
    vector components); pos_amp, pos_freq, pos_phase (3, P) m, Hz, rad (world position of the
    board origin); rot_rate (3,) rad/s, a linear term of v (default 0).  Everything is a closed
    form of t: evaluate at any times.
    """

    R0: np.ndarray
    v0: np.ndarray
    rot_amp: np.ndarray
    rot_freq: np.ndarray
    rot_phase: np.ndarray
    pos_amp: np.ndarray
    pos_freq: np.ndarray
    pos_phase: np.ndarray
    rot_rate: np.ndarray | None = None

    _FIELDS = ("R0", "v0", "rot_amp", "rot_freq", "rot_phase", "pos_amp", "pos_freq", "pos_phase", "rot_rate")

    def __post_init__(self):
        if self.rot_rate is None:
            self.rot_rate = np.zeros(3)
        for name in self._FIELDS:
            setattr(self, name, np.array(getattr(self, name), dtype=float))

    def _rotvec(self, t):
        v, vd, vdd = _sines(t, self.rot_amp, self.rot_freq, self.rot_phase)
        return v + self.v0 + t[:, None] * self.rot_rate, vd + self.rot_rate, vdd

    # ------------------------------------------------------------------ kinematics
    def kinematics(self, t) -> dict:
        """R, Ṙ, R̈ (T, 3, 3) of R_wb and p, ṗ, p̈ (T, 3) of the origin, at times t (T,) s."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        v, vd, vdd = self._rotvec(t)
        s = (v * v).sum(-1)
        sd = 2 * (v * vd).sum(-1)
        sdd = 2 * ((vd * vd).sum(-1) + (v * vdd).sum(-1))
        a, a1, a2, b, b1, b2 = _rodrigues_coefficients(s)
        ad, add = a1 * sd, a2 * sd * sd + a1 * sdd
        bd, bdd = b1 * sd, b2 * sd * sd + b1 * sdd
        V, Vd, Vdd = skew(v), skew(vd), skew(vdd)
        c = lambda x: x[:, None, None]  # noqa: E731
        VV = V @ V
        VdV = Vd @ V + V @ Vd
        E = np.eye(3) + c(a) * V + c(b) * VV
        Ed = c(ad) * V + c(a) * Vd + c(bd) * VV + c(b) * VdV
        Edd = (c(add) * V + 2 * c(ad) * Vd + c(a) * Vdd + c(bdd) * VV + 2 * c(bd) * VdV
               + c(b) * (Vdd @ V + 2 * Vd @ Vd + V @ Vdd))
        p, pd, pdd = _sines(t, self.pos_amp, self.pos_freq, self.pos_phase)
        return {"R": self.R0 @ E, "Rd": self.R0 @ Ed, "Rdd": self.R0 @ Edd, "p": p, "pd": pd, "pdd": pdd}

    def attitude(self, t) -> np.ndarray:
        """R_wb(t), (T, 3, 3), array → world."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        return self.R0 @ so3_exp(self._rotvec(t)[0])

    def omega_body(self, t) -> np.ndarray:
        """Body (array-frame) angular rate ω(t), rad/s (T, 3), from Ω(ω) = R_wbᵀ Ṙ_wb."""
        k = self.kinematics(t)
        return unskew(np.swapaxes(k["R"], -1, -2) @ k["Rd"])

    def omega_dot_body(self, t) -> np.ndarray:
        """Body angular acceleration ω̇(t), rad/s² (T, 3): d/dt(RᵀṘ) = ṘᵀṘ + RᵀR̈ and ṘᵀṘ is
        symmetric, so Ω(ω̇) is the antisymmetric part of RᵀR̈.  (Used only to cross-check the
        package's model in the tests; the generator itself never needs ω̇.)"""
        k = self.kinematics(t)
        return unskew(np.swapaxes(k["R"], -1, -2) @ k["Rdd"])

    def point_position(self, t, x) -> np.ndarray:
        """World position p₀ + R_wb x of board points x (..., 3) m: (T, ..., 3)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        x = np.asarray(x, dtype=float)
        R = self.R0 @ so3_exp(self._rotvec(t)[0])
        p = _sines(t, self.pos_amp, self.pos_freq, self.pos_phase)[0]
        Rx = np.einsum("tij,...j->t...i", R, x)
        return p.reshape((p.shape[0],) + (1,) * (x.ndim - 1) + (3,)) + Rx

    def point_acceleration(self, t, x) -> np.ndarray:
        """World acceleration p̈₀ + R̈_wb x of board points x (..., 3): (T, ..., 3) m/s²."""
        k = self.kinematics(t)
        x = np.asarray(x, dtype=float)
        pdd = k["pdd"].reshape((k["pdd"].shape[0],) + (1,) * (x.ndim - 1) + (3,))
        return pdd + np.einsum("tij,...j->t...i", k["Rdd"], x)

    def specific_force(self, t, x) -> np.ndarray:
        """Specific force at board points x, array frame: R_wbᵀ(p̈ − g_w), (T, ..., 3) m/s²."""
        k = self.kinematics(t)
        return _specific_force(k, np.asarray(x, dtype=float))

    # ------------------------------------------------------------------ construction
    @classmethod
    def random(cls, rng: np.random.Generator, t: np.ndarray, *, omega_rms: float, acc_rms: float = 5.0,
               freq_range=(0.2, 3.0), pos_freq_range=(0.5, 3.0), n_components: int = 4,
               omega_peak_max: float | None = None) -> "RotvecTrajectory":
        """A random smooth trajectory whose RMS |ω| over the sample times ``t`` is ``omega_rms``
        (rad/s) and whose origin acceleration has RMS |p̈₀| ≈ ``acc_rms`` (m/s²).

        Rotation-vector components: ``n_components`` sinusoids each, frequencies uniform in
        ``freq_range`` (Hz), rate amplitudes equal in expectation across frequencies.  The
        amplitudes are rescaled (a few fixed-point steps, since |ω| is not linear in them) to hit
        ``omega_rms``; if ``omega_peak_max`` is given and the largest |ω| component would exceed
        it, the scale is lowered to respect it (the RMS then comes out lower).
        """
        M = int(n_components)
        t = np.asarray(t, dtype=float)
        R0 = random_rotation(rng)
        f = rng.uniform(*freq_range, size=(3, M))
        phase = rng.uniform(0, 2 * np.pi, size=(3, M))
        rate_amp = rng.standard_normal((3, M)) * math.sqrt(2.0 / M)
        amp = rate_amp / (2 * np.pi * f)
        v0 = rng.standard_normal(3) * 0.5
        pf = rng.uniform(*pos_freq_range, size=(3, M))
        pphase = rng.uniform(0, 2 * np.pi, size=(3, M))
        pacc = rng.standard_normal((3, M)) * acc_rms * math.sqrt(2.0 / (3 * M))
        pamp = pacc / (2 * np.pi * pf) ** 2
        traj = cls(R0, v0, amp, f, phase, pamp, pf, pphase)
        scale = 1.0
        for _ in range(6):
            traj.rot_amp = amp * scale
            w = traj.omega_body(t)
            rms = math.sqrt(float((w * w).sum(-1).mean()))
            scale *= omega_rms / rms
        traj.rot_amp = amp * scale
        if omega_peak_max is not None:
            for _ in range(6):
                peak = float(np.abs(traj.omega_body(t)).max())
                if peak <= omega_peak_max:
                    break
                scale *= 0.98 * omega_peak_max / peak
                traj.rot_amp = amp * scale
        return traj

    def to_dict(self) -> dict:
        return {"class": "RotvecTrajectory", **{k: np.asarray(getattr(self, k)).tolist() for k in self._FIELDS}}

    @classmethod
    def from_dict(cls, d: dict) -> "RotvecTrajectory":
        return cls(**{k: np.asarray(v, dtype=float) for k, v in d.items() if k != "class"})


def _specific_force(k: dict, x: np.ndarray) -> np.ndarray:
    T = k["pdd"].shape[0]
    acc = k["pdd"].reshape((T,) + (1,) * (x.ndim - 1) + (3,)) + np.einsum("tij,...j->t...i", k["Rdd"], x)
    return np.einsum("tji,t...j->t...i", k["R"], acc - G_WORLD)  # R_wbᵀ (p̈ − g)


def sensor_outputs(traj: RotvecTrajectory, t, rotations: np.ndarray, points: np.ndarray,
                   time_offset=None):
    """Noise-free IMU outputs in each sensor frame.

    Parameters
    ----------
    traj : the continuous board motion.
    t : (T,) s — sample times.
    rotations : (K, 3, 3) — true array → sensor rotation R_k of each IMU (both triads).
    points : (K, 3, 3) — ``points[k, i]`` is the board point (array frame, m) where accelerometer
        axis i of IMU k senses (all three equal for a collocated triad).
    time_offset : (K,) s or None — IMU k is sampled at t + time_offset[k] (positive = late).

    Returns
    -------
    acc : (T, K, 3) m/s², y_ki = e_iᵀ R_k R_wbᵀ (p̈(points[k, i]) − g_w).
    gyro : (T, K, 3) rad/s, R_k ω.
    """
    t = np.atleast_1d(np.asarray(t, dtype=float))
    R = np.asarray(rotations, dtype=float)
    P = np.asarray(points, dtype=float)
    K = R.shape[0]
    dt = np.zeros(K) if time_offset is None else np.asarray(time_offset, dtype=float)
    acc = np.empty((t.shape[0], K, 3))
    gyro = np.empty((t.shape[0], K, 3))
    for d in np.unique(dt):  # one kinematics evaluation per distinct sampling instant
        ks = np.flatnonzero(dt == d)
        kin = traj.kinematics(t + d)
        f = _specific_force(kin, P[ks])  # (T, k', 3 axes, 3) array frame
        # axis i of IMU k reads row i of R_k applied to the force at its own point
        acc[:, ks, :] = np.einsum("kic,tkic->tki", R[ks], f)
        w = unskew(np.swapaxes(kin["R"], -1, -2) @ kin["Rd"])
        gyro[:, ks, :] = np.einsum("kij,tj->tki", R[ks], w)
    return acc, gyro


# ============================================================================ finite-difference check

# Central difference for the second derivative, 8th order, stencil −4..4.
_FD8 = np.array([-1 / 560, 8 / 315, -1 / 5, 8 / 5, -205 / 72, 8 / 5, -1 / 5, 8 / 315, -1 / 560])


def fd_second_derivative(fun, t, h: float) -> np.ndarray:
    """8th-order central finite difference of the second derivative of ``fun`` (t (T,) → (T, ...))
    with step h (s): Σ_j c_j fun(t + j h) / h², j = −4..4; truncation error O(h⁸ f⁽¹⁰⁾)."""
    t = np.asarray(t, dtype=float)
    return sum(c * fun(t + j * h) for c, j in zip(_FD8, range(-4, 5))) / (h * h)


def check_point_acceleration(traj: RotvecTrajectory, t, x, h: float = 2e-3) -> dict:
    """Compare the analytic p̈ of board points x with the finite difference of their world
    positions.

    Returns ``max_error`` (max |analytic − FD(h)|, m/s²) and ``bound``: an upper estimate of the
    FD error itself, |FD(h) − FD(2h)| (the truncation error of FD(2h) is 2⁸ times that of
    FD(h), so this difference bounds FD(h)'s truncation error many times over) plus the rounding
    error 8 ε max|p| Σ|c_j| / h².  An analytic p̈ that is right satisfies max_error ≤ bound.
    """
    t = np.asarray(t, dtype=float)
    pos = lambda tt: traj.point_position(tt, x)  # noqa: E731
    exact = traj.point_acceleration(t, x)
    fd1 = fd_second_derivative(pos, t, h)
    fd2 = fd_second_derivative(pos, t, 2 * h)
    pmax = float(np.abs(pos(t)).max())
    rounding = 8 * np.finfo(float).eps * pmax * float(np.abs(_FD8).sum()) / (h * h)
    bound = float(np.abs(fd1 - fd2).max()) + rounding
    return {"max_error": float(np.abs(exact - fd1).max()), "bound": bound, "rounding": rounding,
            "truncation_estimate": float(np.abs(fd1 - fd2).max())}


# ============================================================================ cases

def draw_settings(rng: np.random.Generator, **overrides) -> dict:
    """Recording settings of one case: T (samples), rate (Hz), sigma_a (m/s²), sigma_g (rad/s),
    omega_rms (rad/s), acc_rms (m/s²).  Keyword overrides replace the random draws (None = draw)."""
    s = {
        "T": int(rng.integers(1500, 3001)),
        "rate": float(rng.uniform(100.0, 250.0)),
        "sigma_a": float(rng.uniform(0.01, 0.04)),
        "sigma_g": float(rng.uniform(0.05, 0.15)) * DEG,
        "omega_rms": float(rng.uniform(250.0, 600.0)) * DEG,
        "acc_rms": float(rng.uniform(2.0, 8.0)),
    }
    for k, v in overrides.items():
        if k not in s:
            raise ValueError(f"settings: unknown key {k!r}; expected one of {sorted(s)}")
        if v is not None:
            s[k] = type(s[k])(v)
    return s


@dataclass
class ConcealedCase:
    """One blind test case: the recording the detector sees, and the truth it must not."""

    recording: object  # accel_bayes.data.recording.Recording
    truth: dict = field(default_factory=dict)
    clean_acc: np.ndarray | None = None   # noise-free outputs with the effect (for tests)
    clean_gyro: np.ndarray | None = None


def make_case(board_name: str | Board = "mimu8", effect: str = "none", seed: int = 0, *,
              T: int | None = None, rate: float | None = None, sigma_a: float | None = None,
              sigma_g: float | None = None, omega_rms: float | None = None, acc_rms: float | None = None,
              imu: int | None = None, axis: int | None = None, magnitude: float | None = None,
              noise: bool = True, position_error: tuple = (1e-4, 3e-4),
              trajectory: RotvecTrajectory | None = None) -> ConcealedCase:
    """Generate one recording hiding ``effect`` (one of :data:`EFFECTS`, or ``"none"``).

    Settings not given are drawn from the seed (:func:`draw_settings`: T 1500–3000, rate
    100–250 Hz, σ_a 0.01–0.04 m/s², σ_g 0.05–0.15 °/s, RMS |ω| 250–600 °/s).  ``imu``
    (a non-reference label), ``axis`` (0, 1, 2) and ``magnitude`` (signed, SI units; for
    ``axis_displacement``/``triad_orientation`` the length of the vector) override the random
    effect draw.  ``noise=False`` gives noise-free outputs (noise_level then only changes the
    truth).  ``trajectory`` replaces the random motion.  Every IMU's true position is its design
    position plus a random direction × U(position_error) m.

    Returns a :class:`ConcealedCase`: ``recording`` holds the design (nominal) poses, the stated
    noise and the outputs, nothing of the truth; ``truth`` has ``effect``, ``imu``, ``axis``
    ("x"/"y"/"z" or None), ``magnitude``, ``parameters`` (DESIGN §7.2 names), the true positions
    (absolute and relative to the reference IMU) and orientations, the settings and the
    trajectory.
    """
    from accel_bayes.data.recording import Recording

    if effect != "none" and effect not in EFFECTS + OUT_OF_VOCABULARY:
        raise ValueError(f"effect: expected 'none' or one of {EFFECTS + OUT_OF_VOCABULARY}, got {effect!r}")
    b = board_name if isinstance(board_name, Board) else board(board_name)
    K, ref = b.K, b.reference_imu
    ss = np.random.SeedSequence(int(seed)).spawn(5)
    rng_set, rng_traj, rng_geo, rng_noise, rng_eff = (np.random.default_rng(s) for s in ss)

    st = draw_settings(rng_set, T=T, rate=rate, sigma_a=sigma_a, sigma_g=sigma_g, omega_rms=omega_rms,
                       acc_rms=acc_rms)
    t = np.arange(st["T"]) / st["rate"]
    if trajectory is None:
        peak = 0.6 * b.gyro_range if b.gyro_range else None
        trajectory = RotvecTrajectory.random(rng_traj, t, omega_rms=st["omega_rms"], acc_rms=st["acc_rms"],
                                             omega_peak_max=peak)

    # True geometry: design + a random 0.1–0.3 mm offset per IMU (the reference too: only
    # positions relative to it are identifiable, and the truth records both).
    offs = _random_unit(rng_geo, K) * rng_geo.uniform(*position_error, size=(K, 1))
    true_pos = b.positions + offs
    true_R = b.rotations.copy()
    points = np.repeat(true_pos[:, None, :], 3, axis=1)
    time_offset = np.zeros(K)

    # Base noise drawn before anything effect-specific, so that the effect="none" case with the
    # same seed is the exact clean twin.
    e_acc = rng_noise.standard_normal((st["T"], K, 3))
    e_gyro = rng_noise.standard_normal((st["T"], K, 3))

    # Effect draw: IMU, axis, sign, magnitude (always drawn in the same order, so overrides of
    # one do not change the others).
    k_draw = int(rng_eff.choice([j for j in range(K) if j != ref]))
    i_draw = int(rng_eff.integers(0, 3))
    sign = float(rng_eff.choice([-1.0, 1.0]))
    u_mag = float(rng_eff.uniform())
    direction = _random_unit(rng_eff)
    j_other = int(rng_eff.choice([j for j in range(3) if j != (i_draw if axis is None else int(axis))]))
    k = k_draw if imu is None else int(imu)
    i = i_draw if axis is None else int(axis)
    if effect != "none" and (k == ref or not 0 <= k < K):
        raise ValueError(f"imu: expected a non-reference IMU label in 0..{K - 1} (reference {ref}), got {k}")
    if not 0 <= i < 3:
        raise ValueError(f"axis: expected 0, 1 or 2, got {i}")
    mag = None
    if effect != "none":
        lo, hi = EFFECT_RANGES[effect]
        mag = lo + (hi - lo) * u_mag
        if effect in _SIGNED:
            mag *= sign
        if magnitude is not None:
            mag = float(magnitude)

    params: dict = {}
    truth_axis = AXES[i] if effect in AXIS_EFFECTS else None
    truth_imu = k if effect != "none" else None

    # --- effects on the kinematics: where/when/how the sensor looks at the rigid body
    if effect == "time_offset":
        time_offset[k] = mag
        params = {"offset": mag}
    elif effect == "axis_displacement":
        d = direction * mag  # sensor frame
        points[k, i] = true_pos[k] + true_R[k].T @ d
        params = {"displacement": d}
    elif effect == "triad_orientation":
        rho = direction * mag  # sensor frame
        true_R[k] = so3_exp(rho) @ true_R[k]
        params = {"rotation_vector": rho}

    acc, gyro = sensor_outputs(trajectory, t, true_R, points, time_offset)
    if effect == "sampling_jitter":
        # the IMU looks at the rigid body at its own random instants (exact kinematics there)
        delta = rng_eff.uniform(-0.5 * mag, 0.5 * mag, size=t.shape[0])
        a_k, g_k = sensor_outputs(trajectory, t + delta, true_R[k:k + 1], points[k:k + 1])
        acc[:, k], gyro[:, k] = a_k[:, 0], g_k[:, 0]
        params = {"width": mag}
    elif effect == "timing_wander":
        # one IMU's gyroscope reads the rigid body at instants t + δ_t, δ a stationary AR(1)
        # process (std width/√12, lag-one correlation ρ drawn in 0.5–0.95): exact kinematics there
        rho = float(rng_eff.uniform(0.5, 0.95))
        sd = mag / math.sqrt(12.0)
        e = rng_eff.standard_normal(t.shape[0])
        delta = np.empty(t.shape[0])
        delta[0] = sd * e[0]
        for j in range(1, t.shape[0]):
            delta[j] = rho * delta[j - 1] + math.sqrt(1.0 - rho * rho) * sd * e[j]
        _, g_k = sensor_outputs(trajectory, t + delta, true_R[k:k + 1], points[k:k + 1])
        gyro[:, k] = g_k[:, 0]
        params = {"width": mag, "correlation": rho, "sensor": "gyro"}
    f_true = acc.copy()  # the specific force each accelerometer axis sees (before sensor errors)

    # --- sensor errors on the noise-free signal
    if effect == "acc_bias":
        acc[:, k, i] += mag
        params = {"bias": _vec(i, mag)}
    elif effect == "acc_scale":
        acc[:, k, i] *= 1.0 + mag
        params = {"scale": _vec(i, mag)}
    elif effect == "acc_misalignment":
        acc[:, k, i] += mag * f_true[:, k, j_other]
        params = {"coupling": mag, "from_axis": AXES[j_other]}
    elif effect == "acc_nonlinearity":
        acc[:, k, i] += mag * f_true[:, k, i] ** 2
        params = {"k2": _vec(i, mag)}
    elif effect == "gyro_bias":
        gyro[:, k, i] += mag
        params = {"bias": _vec(i, mag)}
    elif effect == "gyro_scale":
        gyro[:, k, i] *= 1.0 + mag
        params = {"scale": _vec(i, mag)}
    elif effect == "gyro_g_sensitivity":
        gyro[:, k, i] += mag * f_true[:, k, i]
        params = {"sensitivity": _vec(i, mag)}
    elif effect == "gyro_lowpass":
        gyro[:, k, :] = lowpass_output(trajectory, t, true_R[k], true_pos[k], mag, "gyro")
        params = {"time_constant": mag}
    elif effect == "acc_lowpass":
        acc[:, k, :] = lowpass_output(trajectory, t, true_R[k], true_pos[k], mag, "acc")
        params = {"time_constant": mag}
    elif effect == "acc_drift":
        # a bias that drifts linearly in time (a sensor warming up): −drift at the first sample,
        # +drift at the last, zero on average over uniformly spaced samples — no constant bias
        # and no term of the package's catalogue describes it
        acc[:, k, i] += mag * (2.0 * (t - t[0]) / (t[-1] - t[0]) - 1.0)
        params = {"drift": mag}
    elif effect == "gyro_nonlinearity":
        # the rate the axis truly feels, squared: w_true is the gyro output before any error
        w_true = gyro[:, k, i].copy()
        gyro[:, k, i] = w_true + mag * w_true * w_true
        params = {"k2": mag}
    clean_acc, clean_gyro = acc.copy(), gyro.copy()

    # --- noise, then clipping
    acc_factor = np.ones(K)
    if effect == "noise_level":
        acc_factor[k] = mag
        params = {"factor": mag}
    if noise:
        acc = acc + e_acc * (st["sigma_a"] * acc_factor)[None, :, None]
        gyro = gyro + e_gyro * st["sigma_g"]
    if effect == "saturation":
        limit = mag * float(np.abs(acc[:, k, :]).max())
        clipped = np.abs(acc[:, k, :]) >= limit
        acc[:, k, :] = np.clip(acc[:, k, :], -limit, limit)
        i = int(np.argmax(clipped.sum(0)))
        truth_axis = AXES[i]
        params = {"limit": limit, "limit_fraction_of_peak": mag, "clipped_fraction": float(clipped.any(-1).mean()),
                  "clipped_fraction_per_axis": clipped.mean(0)}

    rec = Recording(
        time=t,
        acc=acc,
        gyro=gyro,
        nominal_position=b.positions.copy(),
        nominal_orientation=b.orientations.copy(),
        acc_noise_std=np.full(K, st["sigma_a"]),
        gyro_noise_std=np.full(K, st["sigma_g"]),
        reference_imu=ref,
        acc_range=b.acc_range,
        gyro_range=b.gyro_range,
        description=f"blind mismatch test recording ({b.name} board)",
        source="experiments/_conceal.py: independent first-principles simulator; ground truth in the sidecar",
    )
    true_q = np.stack([rotmat_to_quat(Rk) for Rk in true_R])
    w = trajectory.omega_body(t)
    truth = {
        "generator": "experiments/_conceal.py",
        "board": b.name,
        "seed": int(seed),
        "effect": effect,
        "imu": truth_imu,
        "axis": truth_axis,
        "magnitude": mag,
        "parameters": params,
        "true_position": true_pos,
        "true_relative_position": true_pos - true_pos[ref],
        "true_orientation": true_q,
        "nominal_position": b.positions,
        "settings": {**st, "omega_rms_achieved": float(np.sqrt((w * w).sum(-1).mean())),
                     "omega_peak_component": float(np.abs(w).max()), "noise": bool(noise)},
        "trajectory": trajectory.to_dict(),
    }
    return ConcealedCase(rec, truth, clean_acc, clean_gyro)


def lowpass_output(traj: RotvecTrajectory, t: np.ndarray, R: np.ndarray, point: np.ndarray, tau: float,
                   sensor: str = "gyro", oversample: int = 32, settle: float = 20.0) -> np.ndarray:
    """One IMU's gyroscope (``sensor="gyro"``) or accelerometer (``"acc"``) behind a first-order
    low-pass filter, τ ẏ = x − y, sampled at ``t`` (s): (T, 3) rad/s or m/s² in the sensor frame
    of rotation ``R`` (array → sensor; the accelerometer senses at ``point``, array frame, m);
    ``tau`` s.

    Independent of the package: the unfiltered output x(t) of the continuous trajectory on a grid
    ``oversample``× finer than the samples, starting ``settle``·τ before the first sample (the
    filter's start state has then decayed by e^−20), and the exact solution of the ODE for an
    input linear between grid points (step h, a = e^{−h/τ}, g = τ(1 − a)/h):

        y(s + h) = a·y(s) + (g − a)·x(s) + (1 − g)·x(s + h).
    """
    from scipy.signal import lfilter, lfilter_zi

    t = np.asarray(t, dtype=float)
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1e-2
    h = dt / oversample
    n_pre = int(math.ceil(settle * tau / h))
    grid = t[0] + h * np.arange(-n_pre, oversample * (len(t) - 1) + 1)
    acc, gyro = sensor_outputs(traj, grid, R[None], np.repeat(np.asarray(point, float)[None, None, :], 3, axis=1))
    x = (gyro if sensor == "gyro" else acc)[:, 0, :]
    a = math.exp(-h / tau)
    g = tau * (1.0 - a) / h
    b, den = [1.0 - g, g - a], [1.0, -a]
    zi = lfilter_zi(b, den)[:, None] * x[0][None, :]  # start in the steady state of x(grid[0])
    y, _ = lfilter(b, den, x, axis=0, zi=zi)
    return y[n_pre + oversample * np.arange(len(t))]


def _vec(i: int, value: float) -> list:
    v = [0.0, 0.0, 0.0]
    v[i] = float(value)
    return v


def save_case(case: ConcealedCase, path, overwrite: bool = False) -> Path:
    """Write the recording (format v1) and its ground-truth sidecar ``<stem>.truth.json``."""
    from accel_bayes.data.io import write_recording, write_truth

    path = write_recording(case.recording, path, overwrite=overwrite)
    write_truth(path, case.truth, overwrite=True)
    return path


def oracle_noncentrality(case: ConcealedCase, twin: ConcealedCase) -> float:
    """How visible the concealed effect is at all: λ = Σ (Δy/σ)² over every output, Δy = case −
    clean twin (same seed, effect "none"; the noise draws cancel exactly), σ the stated std.

    It is the non-centrality of the likelihood-ratio statistic of a detector that knew the
    effect's exact shape and had nothing else to fit; a real detector also fits the geometry and
    motion, which can absorb part of Δy, so its statistic is at most about λ + (number of effect
    parameters).  An effect with λ below the detector's threshold cannot be found reliably by any
    method.  For ``noise_level`` (no mean change) λ is the expected variance-ratio statistic
    n (r² − 1 − 2 ln r) over the n = 3T accelerometer samples of the IMU, r = factor.
    """
    tr = case.truth
    rec, rec0 = case.recording, twin.recording
    if tr["effect"] == "noise_level":
        r = float(tr["magnitude"])
        return float(3 * rec.T * (r * r - 1 - 2 * math.log(r)))
    sa = np.asarray(rec.acc_noise_std)[None, :, None]
    sg = np.asarray(rec.gyro_noise_std)[None, :, None]
    return float((((rec.acc - rec0.acc) / sa) ** 2).sum() + (((rec.gyro - rec0.gyro) / sg) ** 2).sum())


# ============================================================================ multi-effect cases

# The new effects of vocabulary 1.1 and the extension seen on the real MIMU data, one of which a
# multi-effect case hides on top of the linear gyro errors of every IMU (issue #11 item 6).
MULTI_EFFECTS = ("sampling_jitter", "gyro_nonlinearity", "timing_wander")
# Ranges of a multi-effect case (SI units), chosen to mimic the real MIMU4444 recordings
# (experiments/mimu_mismatch.md): vigorous hand shaking at 62.5 Hz, rest noise levels, gyro
# scale/misalignment errors of a few per cent and the timing wander the detector found there.
MULTI_RANGES = {
    "T": (3000, 5000),                         # samples
    "rate": 62.5,                              # Hz (the MIMU4444 host rate)
    "sigma_a": (0.03, 0.05),                   # m/s², the rests' accelerometer noise (≈ 0.04)
    "sigma_g": (0.002, 0.006),                 # rad/s, the rests' gyro noise
    "omega_rms": (600 * DEG, 1200 * DEG),      # rad/s, RMS |ω| (real: 1700–1900 °/s, clipped)
    "acc_rms": (5.0, 15.0),                    # m/s², RMS |p̈₀| of the board origin
    "freq_range": (0.5, 7.0),                  # Hz, frequencies of the rotation-vector sinusoids
    "omega_peak_fraction": 0.95,               # largest |ω| component ≤ this × the gyro range
    "gyro_linear_max": (0.015, 0.027),         # largest |entry| of an IMU's gyro error matrix E_k
    "gyro_bias": (0.05 * DEG, 0.5 * DEG),      # rad/s, |b| per gyro axis
    "sampling_jitter": (1e-4, 1e-3),           # s, full width of the uniform instant error
    "gyro_nonlinearity": (2.0, 6.0),           # k2·ω² at the axis' largest |ω|, in units of σ_g
    "timing_wander": (1.1e-3, 1.35e-3),        # s, √12 × the std of the gyro's instant error
    "timing_wander_correlation": (0.70, 0.87),  # lag-one correlation of that instant error
}


def make_multi_case(seed: int = 0, effect: str = "none", board_name: str | Board = "mimu8", *,
                    T: int | None = None, noise: bool = True, gyro_linear: bool | float = True,
                    position_error: tuple = (1e-4, 3e-4)) -> ConcealedCase:
    """A MIMU-like recording with linear gyro errors on every IMU plus at most one new effect.

    What it hides (sensor frame, SI units; the recording states none of it):

    * **linear gyro errors on every IMU** (the reference too): ω_out = (I + E_k) ω + b_k, with ω
      the true sensor-frame rate at the gyro's sampling instant.  E_k (3 × 3, relative; diagonal =
      scale-factor errors, off-diagonal = cross-axis couplings, DESIGN §7.2 ``gyro_scale``) is
      c_k · M/max|M|, M uniform in [−1, 1]^(3×3) and c_k = 1.5–2.7 %: the largest entry is c_k,
      the size of the couplings seen on the real MIMU4444 gyros.  b_k: every axis ±(0.05–0.5) °/s
      (``gyro_bias``).  The recording has no rests, so the detector's preparation cannot remove
      the biases either.
    * **one new effect** (``effect`` in :data:`MULTI_EFFECTS`, or ``"none"`` for the clean twin)
      on one random non-reference IMU:

      - ``sampling_jitter``: every sample of the IMU (acc and gyro) is the exact kinematics at
        t + δ_t, δ_t ~ U(−w/2, w/2) i.i.d., w = 0.1–1 ms;
      - ``gyro_nonlinearity``: gyro axis i (random) gains k₂ ω_i² (ω_i the true rate of that
        axis, before the linear errors), |k₂| chosen so that k₂ max ω_i² = m σ_g, m = 2–6, random
        sign: the term reaches a few times the gyro noise at the rate peaks;
      - ``timing_wander``: the IMU's gyroscope is the exact kinematics at t + δ_t, δ a stationary
        AR(1) process with std w/√12, w = 1.1–1.35 ms, lag-one correlation 0.70–0.87 (what the
        detector found on the real gyros).

    ``gyro_linear=False`` switches the linear gyro errors off (E_k = 0, b_k = 0; still drawn, so
    everything else stays the same): the control that tells what the new effect alone looks like
    on the same motion.  A number scales E_k and b_k instead (``True`` = 1: the real magnitudes).

    Settings (seeded): rate 62.5 Hz; T 3000–5000 samples (``T`` overrides); σ_a 0.03–0.05 m/s²,
    σ_g 0.002–0.006 rad/s (stated = true); RMS |ω| 600–1200 °/s from rotation-vector sinusoids
    of 0.5–7 Hz, each |ω| component below 95 % of the gyro range (no clipping); RMS origin
    acceleration 5–15 m/s²; every IMU's true position off the design by 0.1–0.3 mm.

    Randomness: the seed is split into independent streams (settings, trajectory, geometry,
    noise, linear gyro errors, new effect), so ``effect="none"`` with the same seed is the exact
    clean twin (same motion, geometry, linear errors and noise draws), and the three effects of
    one seed share everything but the effect stream's use.

    Returns a :class:`ConcealedCase` whose ``truth`` has ``effect``, ``imu``, ``axis`` (the
    nonlinear gyro axis, else None), ``magnitude`` (width s, or k₂ (rad/s)⁻¹), ``parameters``
    (DESIGN §7.2 names; ``instants`` = the sampling-instant errors δ_t (s) for the timing
    effects), ``gyro_linear`` {"matrix": E (K, 3, 3), "bias": b (K, 3) rad/s}, the true geometry,
    the settings and the trajectory.
    """
    from accel_bayes.data.recording import Recording

    if effect != "none" and effect not in MULTI_EFFECTS:
        raise ValueError(f"effect: expected 'none' or one of {MULTI_EFFECTS}, got {effect!r}")
    b = board_name if isinstance(board_name, Board) else board(board_name)
    K, ref = b.K, b.reference_imu
    ss = np.random.SeedSequence(int(seed)).spawn(6)
    rng_set, rng_traj, rng_geo, rng_noise, rng_lin, rng_eff = (np.random.default_rng(s) for s in ss)
    R = MULTI_RANGES

    lo, hi = R["T"]
    st = {"T": int(rng_set.integers(lo, hi + 1)), "rate": float(R["rate"]),
          "sigma_a": float(rng_set.uniform(*R["sigma_a"])), "sigma_g": float(rng_set.uniform(*R["sigma_g"])),
          "omega_rms": float(rng_set.uniform(*R["omega_rms"])), "acc_rms": float(rng_set.uniform(*R["acc_rms"]))}
    if T is not None:
        st["T"] = int(T)
    t = np.arange(st["T"]) / st["rate"]
    peak = R["omega_peak_fraction"] * b.gyro_range if b.gyro_range else None
    traj = RotvecTrajectory.random(rng_traj, t, omega_rms=st["omega_rms"], acc_rms=st["acc_rms"],
                                   freq_range=R["freq_range"], omega_peak_max=peak)

    offs = _random_unit(rng_geo, K) * rng_geo.uniform(*position_error, size=(K, 1))
    true_pos = b.positions + offs
    true_R = b.rotations
    points = np.repeat(true_pos[:, None, :], 3, axis=1)
    e_acc = rng_noise.standard_normal((st["T"], K, 3))
    e_gyro = rng_noise.standard_normal((st["T"], K, 3))

    # Linear gyro errors of every IMU (drawn whatever the effect: the twin shares them).
    M = rng_lin.uniform(-1.0, 1.0, size=(K, 3, 3))
    c = rng_lin.uniform(*R["gyro_linear_max"], size=K)
    E = c[:, None, None] * M / np.abs(M).max(axis=(1, 2), keepdims=True)
    bias = rng_lin.choice([-1.0, 1.0], size=(K, 3)) * rng_lin.uniform(*R["gyro_bias"], size=(K, 3))
    if float(gyro_linear) != 1.0:
        E, bias = float(gyro_linear) * E, float(gyro_linear) * bias

    # New-effect draws, always in the same order (the stream is the effect's alone).
    k = int(rng_eff.choice([j for j in range(K) if j != ref]))
    i = int(rng_eff.integers(0, 3))
    sign = float(rng_eff.choice([-1.0, 1.0]))
    u_mag = float(rng_eff.uniform())
    u_rho = float(rng_eff.uniform())
    e_inst = rng_eff.standard_normal(st["T"])  # the instant errors' driving draws

    acc, gyro = sensor_outputs(traj, t, true_R, points)
    mag, params, delta = None, {}, None
    if effect == "sampling_jitter":
        lo, hi = R["sampling_jitter"]
        mag = lo + (hi - lo) * u_mag
        # δ uniform in ±w/2 from the standard-normal draw through Φ (keeps one draw per sample)
        from scipy.special import ndtr

        delta = mag * (ndtr(e_inst) - 0.5)
        a_k, g_k = sensor_outputs(traj, t + delta, true_R[k:k + 1], points[k:k + 1])
        acc[:, k], gyro[:, k] = a_k[:, 0], g_k[:, 0]
        params = {"width": mag}
    elif effect == "timing_wander":
        lo, hi = R["timing_wander"]
        mag = lo + (hi - lo) * u_mag
        rlo, rhi = R["timing_wander_correlation"]
        rho = rlo + (rhi - rlo) * u_rho
        sd = mag / math.sqrt(12.0)
        # stationary AR(1): δ_0 ~ N(0, sd²), δ_j = ρ δ_{j−1} + √(1 − ρ²) sd e_j  (scipy's lfilter
        # runs the recursion; its initial state puts δ_0 = sd e_0)
        from scipy.signal import lfilter

        drive = math.sqrt(1.0 - rho * rho) * sd * e_inst
        drive[0] = sd * e_inst[0]
        delta = lfilter([1.0], [1.0, -rho], drive)
        _, g_k = sensor_outputs(traj, t + delta, true_R[k:k + 1], points[k:k + 1])
        gyro[:, k] = g_k[:, 0]
        params = {"width": mag, "correlation": rho, "sensor": "gyro"}
    w_true = gyro.copy()  # the rate each gyro axis truly feels at its sampling instant
    gyro = np.einsum("kij,tkj->tki", np.eye(3)[None] + E, w_true) + bias[None]
    if effect == "gyro_nonlinearity":
        lo, hi = R["gyro_nonlinearity"]
        m = lo + (hi - lo) * u_mag
        w2 = w_true[:, k, i] ** 2
        mag = sign * m * st["sigma_g"] / float(w2.max())
        gyro[:, k, i] += mag * w2
        params = {"k2": mag, "peak_over_sigma_g": m}
    clean_acc, clean_gyro = acc.copy(), gyro.copy()
    if noise:
        acc = acc + e_acc * st["sigma_a"]
        gyro = gyro + e_gyro * st["sigma_g"]

    rec = Recording(
        time=t, acc=acc, gyro=gyro,
        nominal_position=b.positions.copy(), nominal_orientation=b.orientations.copy(),
        acc_noise_std=np.full(K, st["sigma_a"]), gyro_noise_std=np.full(K, st["sigma_g"]),
        reference_imu=ref, acc_range=b.acc_range, gyro_range=b.gyro_range,
        description=f"blind multi-effect test recording ({b.name} board, MIMU-like)",
        source="experiments/_conceal.py make_multi_case: independent first-principles simulator; ground truth in "
               "the sidecar",
    )
    w = traj.omega_body(t)
    truth = {
        "generator": "experiments/_conceal.py:make_multi_case",
        "board": b.name, "seed": int(seed), "effect": effect, "gyro_linear_factor": float(gyro_linear),
        "imu": k if effect != "none" else None,
        "axis": AXES[i] if effect == "gyro_nonlinearity" else None,
        "magnitude": mag,
        "parameters": {**params, **({"instants": delta} if delta is not None else {})},
        "gyro_linear": {"matrix": E, "bias": bias},
        "true_position": true_pos, "true_relative_position": true_pos - true_pos[ref],
        "true_orientation": b.orientations.copy(), "nominal_position": b.positions,
        "settings": {**st, "omega_rms_achieved": float(np.sqrt((w * w).sum(-1).mean())),
                     "omega_peak_component": float(np.abs(w).max()), "noise": bool(noise)},
        "trajectory": traj.to_dict(),
    }
    return ConcealedCase(rec, truth, clean_acc, clean_gyro)
