"""Rigs of separately clocked IMUs with their own stamps (issue #28's blind tests).

IMU k samples at its own output rate f_k (100–400 Hz, mixed within a rig) on its own clock:
its n-th stamp is s = t₀ + n/f_k, and by DESIGN §7.3 (s − t₀ = (t − t₀ − o_k)(1 + d_k)) the
sample was taken at the reference-clock instant t = t₀ + o_k + (s − t₀)/(1 + d_k).  The file
holds the stamp plus a stamp jitter (the host's latency in stamping, not a sampling error), so
the recording's ``time`` is the union of the jittered stamps, NaN where an IMU has no sample.
IMU 0 is the reference (o = d = 0, at the origin, sensor frame = array frame).  No low-pass and
no vibration by default: the rig model is about orientation, lever arm and clock.
"""
from __future__ import annotations

import numpy as np

from accel_bayes.data.recording import Recording

from .motion import exp_so3
from .sensing import ACC_LSB, GYRO_LSB, SensorErrors, quantise


def _random_rotation(rng):
    q = rng.normal(size=4)
    from .cases import quat_to_matrix
    return quat_to_matrix(q / np.linalg.norm(q))


def _without_walk(e: SensorErrors) -> SensorErrors:
    return SensorErrors(M=e.M, bias=e.bias, noise_std=e.noise_std)


def draw_rig(seed, *, duration=30.0, n_imu=None, noise=True, quantised=True, jitter=True, bias_walk=True,
             vibration=False, rot_axes=(0, 1, 2), rates=None, offset_wander=0.0):
    """A seeded rig case → (Recording, truth).  Ranges: K ∈ {2, 3, 4}; rates from 100, 125, 200,
    250, 400 Hz (at least two distinct); o_k ~ U(±10 ms), d_k ~ U(±100 ppm); lever arms 1–20 cm in
    random directions; random orientations; nominal orientation given on half the IMUs, 1–5° off,
    else identity (missing); nominal positions off by N(0, 2 mm); stamp jitter N(0, 20–100 µs);
    acc/gyro white noise 0.02–0.06 m/s², 0.2–0.6 °/s; bias random walks 1e-4 m/s²/√s and
    1e-5 rad/s/√s (effects the rig model lacks).  ``rot_axes=(2,)``: an under-excited rig that
    rotates about the array (reference sensor) z axis only.  ``rates`` (Hz per IMU) replaces the
    drawn rates (benchmarks at one rate); every other draw stays the same.  ``offset_wander`` (s): each
    non-reference IMU's offset also wanders, o_k + w_k(t) with w_k three sinusoids of 0.2–1 Hz, random
    phases, RMS ``offset_wander`` (a time-varying timing the rig model's constant offset cannot hold;
    drawn from a stream of its own, so every other draw stays the same); truth keeps the constant o_k."""
    from .cases import ACC_RANGE, GYRO_RANGE, RIG_RATES, matrix_to_quat
    rng = np.random.default_rng([seed, 28])
    K = int(n_imu or rng.integers(2, 5))
    while True:  # drawn even where ``rates`` replaces them, so that every later draw stays the same
        drawn = rng.choice(RIG_RATES, K)
        if K == 1 or len(set(drawn)) > 1:
            break
    rates = drawn if rates is None else np.asarray(rates, dtype=float)
    o = np.r_[0.0, rng.uniform(-0.01, 0.01, K - 1)]
    d = np.r_[0.0, rng.uniform(-1e-4, 1e-4, K - 1)]
    Q = np.array([np.eye(3)] + [_random_rotation(rng) for _ in range(K - 1)])
    dirs = rng.normal(size=(K, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pos = dirs * rng.uniform(0.01, 0.20, (K, 1))
    pos[0] = 0.0
    nom_Q = []
    for k in range(K):
        if k == 0 or rng.random() < 0.5:
            ax = rng.normal(size=3)
            off = exp_so3(ax / np.linalg.norm(ax) * np.deg2rad(rng.uniform(1, 5))) if k else np.eye(3)
            nom_Q.append(off @ Q[k])
        else:
            nom_Q.append(np.eye(3))
    nom_pos = pos + np.r_[[np.zeros(3)], rng.normal(0, 0.002, (K - 1, 3))]
    sj = rng.uniform(20e-6, 100e-6, K) * jitter
    from .cases import motion_of
    motion = motion_of({"seed": seed, "duration": duration, "vibration": vibration, "rot_axes": rot_axes})
    t0 = 0.0
    stamps, true_t, acc, gyro, clip_a, clip_g, errs = [], [], [], [], [], [], []
    for k in range(K):
        # stamps whose true instants lie in [0.02, duration] (the motion is defined throughout)
        n = np.arange(int(np.ceil((0.02 - o[k]) * (1 + d[k]) * rates[k])),
                      int(np.floor((duration - o[k]) * (1 + d[k]) * rates[k])) + 1)
        s = t0 + n / rates[k]
        t = t0 + o[k] + (s - t0) / (1 + d[k])
        if offset_wander and k:
            vr = np.random.default_rng([seed, 7, k])
            f_w, ph = vr.uniform(0.2, 1.0, 3), vr.uniform(0, 2 * np.pi, 3)
            t = t + offset_wander * np.sqrt(2.0 / 3.0) * np.sin(2 * np.pi * f_w[None] * t[:, None] + ph[None]).sum(1)
        f, w = motion.specific_force(t, pos[k:k + 1])
        erng = np.random.default_rng([seed, 5, k])
        ea = SensorErrors(noise_std=erng.uniform(0.02, 0.06) * noise, rw_std=1e-4 * bias_walk)
        eg = SensorErrors(noise_std=np.deg2rad(erng.uniform(0.2, 0.6)) * noise, rw_std=1e-5 * bias_walk)
        # the walks from a stream of their own, drawn whether or not they are applied: with the walk
        # drawn from erng, ``bias_walk=False`` shifted the gyro noise and the stamp jitter to other
        # draws, and a comparison of the two variants compared noise realisations too
        wrng = np.random.default_rng([seed, 6, k])
        dt = np.sqrt(np.diff(t, prepend=t[0]))[:, None]
        walk_a = np.cumsum(ea.rw_std * dt * wrng.normal(size=(len(t), 3)), axis=0)
        walk_g = np.cumsum(eg.rw_std * dt * wrng.normal(size=(len(t), 3)), axis=0)
        a, ca = quantise(_without_walk(ea).apply(f[:, 0] @ Q[k].T, t, erng) + walk_a, ACC_LSB, quantised)
        g, cg = quantise(_without_walk(eg).apply(w @ Q[k].T, t, erng) + walk_g, GYRO_LSB, quantised)
        stamps.append(s + erng.normal(0, sj[k], len(s)) if sj[k] > 0 else s)
        true_t.append(t)
        acc.append(a), gyro.append(g), clip_a.append(ca), clip_g.append(cg), errs.append((ea, eg))
    time = np.unique(np.concatenate(stamps))
    A, G = np.full((len(time), K, 3), np.nan), np.full((len(time), K, 3), np.nan)
    CA, CG = np.zeros((len(time), K), bool), np.zeros((len(time), K), bool)
    off = np.full((len(time), K), np.nan)
    for k in range(K):
        i = np.searchsorted(time, stamps[k])
        A[i, k], G[i, k], CA[i, k], CG[i, k], off[i, k] = acc[k], gyro[k], clip_a[k], clip_g[k], 0.0
    rec = Recording(time=time, acc=A, gyro=G, nominal_position=nom_pos,
                    nominal_orientation=np.array([matrix_to_quat(q) for q in nom_Q]),
                    acc_noise_std=np.array([e[0].noise_std for e in errs]) if noise else np.full(K, 1e-3),
                    gyro_noise_std=np.array([e[1].noise_std for e in errs]) if noise else np.full(K, 1e-4),
                    acc_clipped=CA, gyro_clipped=CG, imu_time_offset=off, acc_range=ACC_RANGE,
                    gyro_range=GYRO_RANGE, description=f"clockgen rig, seed {seed}",
                    source="experiments/clockgen (independent first-principles generator)",
                    # what a user's array description states (unit/√s = unit/s/√Hz): the sensors' figure,
                    # also where ``bias_walk=False`` leaves the walk out of the data (only the data change)
                    attrs={"acc_random_walk": [1e-4] * K, "gyro_random_walk": [1e-5] * K})
    truth = {"generator": "experiments/clockgen", "kind": "rig", "seed": int(seed), "n_imu": K,
             "duration": duration, "vibration": vibration, "rot_axes": list(rot_axes), "offset_wander": offset_wander,
             "rate": rates.tolist(), "t0": t0, "time_offset": o, "clock_drift": d,
             "convention": "s - t0 = (t - t0 - o_k)(1 + d_k) (DESIGN 7.3)",
             "stamp_jitter_std": sj, "stamps": stamps, "true_time": true_t,
             "position": pos, "orientation": np.array([matrix_to_quat(q) for q in Q]),
             "nominal_orientation_given": [bool(not np.allclose(q, np.eye(3)) or k == 0) for k, q in enumerate(nom_Q)],
             "errors": {"acc": [e[0].params() for e in errs], "gyro": [e[1].params() for e in errs]}}
    return rec, truth
