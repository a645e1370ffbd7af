"""Cramér–Rao bound of a concealed rig's parameters from the generator's exact kinematics (issue #28
item 1, "error/CRB RMS"), computed independently of the solver.

What is bounded.  The data of ``experiments/clockgen.rig`` are, per sample i of IMU k, six readings
y = [Q_k ω(t_i) + b_g,k ; Q_k F(t_i, r_k) + b_a,k] + e_i at the true instant
t_i = t_f + o_k + (s_i − t_f)/(1 + d_k) (s_i its exact stamp, t_f the recording's first stamp: the
DESIGN §7.3 offset that ``experiments/rig_proof.py`` scores), with F(t, r) the exact specific force
at lever arm r (the generator's :meth:`~experiments.clockgen.motion.Motion.specific_force`).  The
noise e_i has covariance diag(σ_g² I, σ_a² I) + σ_j,k² ẏ_i ẏ_iᵀ: white noise plus the stamping error
as a timing error of the whole sample (σ_j,k the generator's jitter std).  The biases b_g,k(t),
b_a,k(t) walk: with ``bias_walk`` (default) they are a nuisance, linear between knots of the
motion's spacing h, whose increments have the generator's walk variance (K_k² + K_ref²) h per
axis (the reference's walk enters through the motion, so the relative bias walks with both) — a
hybrid (Bayesian) bound: the walk is random with a known law, its starting value and the motion are
deterministic unknowns; without it the biases are constants among the globals.

Parameters: per non-reference IMU the sensor-frame rotation error ε (Q̂ = Exp(ε) Q), r, o, d (where
the IMU has its own stamps), b_g, b_a; and the unknown motion as a nuisance: corrections δω(t),
δf(t) (array frame, at the reference) in a cubic B-spline of knot spacing h (the solver's), which
enter every IMU through the rigid-body formula (δf + δω̇×r + δω×(ω×r) + ω×(δω×r)).  The motion is a
deterministic unknown here (no prior), so the bound holds for any estimator that does not know
the motion beyond that spline class; it grows as h shrinks.  Nominal-orientation and lever-arm
priors are left out (5° and 1 m against stds of hundredths of a degree and of a millimetre).

How.  The global columns of the Jacobian are central finite differences of the exact prediction
(the generator's kinematics re-evaluated at moved instants and lever arms); the nuisance columns
are the spline basis times the linearised rigid-body terms (the prediction is linear in them).
Each sample's six rows are whitened by the Cholesky factor of its 6×6 covariance, and the motion is
eliminated by the Schur complement of the sparse Fisher information (``scipy.sparse`` LU): the
bound on the globals is the inverse of that Schur complement.  Nothing of ``accel_bayes.inference``
is used.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from experiments.clockgen.cases import motion_of
from experiments.clockgen.motion import exp_so3

__all__ = ["rig_crb", "spline_basis", "spline_span", "exact_stamps", "GLOBAL_NAMES"]

#: per non-reference IMU, in this order (d only where the IMU has its own stamps)
GLOBAL_NAMES = ("q", "r", "o", "d", "bg", "ba")


def spline_basis(t, lo, h):
    """Uniform cubic B-spline on knots lo + h·j: for each t (N,) the first of its four nonzero
    coefficients j0 (N,) and the four basis values and t-derivatives (N, 4) (coefficient j0 + i)."""
    x = (np.asarray(t, float) - lo) / h
    j0 = np.floor(x).astype(np.int64)
    u = x - j0
    B = np.stack(((1 - u) ** 3, 3 * u ** 3 - 6 * u ** 2 + 4, -3 * u ** 3 + 3 * u ** 2 + 3 * u + 1, u ** 3), -1) / 6
    dB = np.stack((-3 * (1 - u) ** 2, 9 * u ** 2 - 12 * u, -9 * u ** 2 + 6 * u + 3, 3 * u ** 2), -1) / (6 * h)
    return j0, B, dB


def spline_span(t, h):
    """(lo, number of coefficients) of a cubic B-spline of spacing h over instants t: the intervals
    are centred on the data, so that no end coefficient rests on a sample at the edge of its
    support alone (a near-null direction)."""
    span = float(np.max(t) - np.min(t))
    n_int = int(np.floor(span / h)) + 1
    return float(np.min(t)) - 0.5 * (n_int * h - span), n_int + 3


def exact_stamps(truth, k):
    """Unjittered stamps (s) of IMU k's samples: s = (t − o)(1 + d) with the generator's t₀ = 0."""
    t = np.asarray(truth["true_time"][k], float)
    return (t - float(truth["time_offset"][k])) * (1.0 + float(truth["clock_drift"][k]))


def rig_crb(rec, truth, h, *, own_stamps=None, fd_step=None, bias_walk=True):
    """CRB (covariance) of the non-reference IMUs' parameters of a clockgen rig.

    rec, truth : :func:`experiments.clockgen.draw_case` ``("rig", …)`` output; h : nuisance knot
    spacing (s).  own_stamps : (K,) bool, which IMUs have a drift parameter (default: all but the
    reference, as the generator's recordings carry every IMU's own stamps).  Returns
    (cov (P, P), labels [(imu k, name, component)]) in the units rad, m, s, 1, rad/s, m/s².
    bias_walk : the biases as the generator's random walks (``truth["errors"]`` ``rw_std``; then no
    ``bg``/``ba`` labels) rather than constants (also what a walk-free truth gives).
    """
    K = int(truth["n_imu"])
    own = np.r_[False, np.ones(K - 1, bool)] if own_stamps is None else np.asarray(own_stamps, bool)
    motion = motion_of(truth)
    Q = [_quat_to_matrix(q) for q in truth["orientation"]]
    pos = np.asarray(truth["position"], float)
    o_t, d_t = np.asarray(truth["time_offset"], float), np.asarray(truth["clock_drift"], float)
    tf = float(rec.time[0])
    sg, sa = np.asarray(rec.gyro_noise_std, float), np.asarray(rec.acc_noise_std, float)
    sj = np.asarray(truth["stamp_jitter_std"], float)
    step = {"q": 1e-6, "r": 1e-5, "o": 1e-6, "d": 1e-6, **(fd_step or {})}
    t_all = np.concatenate([np.asarray(truth["true_time"][k], float) for k in range(K)])
    lo, n_coef = spline_span(t_all, h)
    err = truth["errors"]
    rw = np.array([[err["gyro"][k]["rw_std"], err["acc"][k]["rw_std"]] for k in range(K)], float)
    walk = bool(bias_walk) and bool((rw > 0).any())
    # walk knots: spacing h over all instants, 6 columns [b_g, b_a] per knot and non-reference IMU
    lo_b, n_b = float(t_all.min()) - 1e-9, int(np.floor((t_all.max() - t_all.min()) / h)) + 2
    col_b0 = 6 * n_coef

    labels = []
    for k in range(1, K):
        for name in GLOBAL_NAMES:
            if (name == "d" and not own[k]) or (walk and name in ("bg", "ba")):
                continue
            n = 3 if name in ("q", "r", "bg", "ba") else 1
            labels += [(k, name, c) for c in range(n)]
    col = {lab: i for i, lab in enumerate(labels)}
    P = len(labels)
    Jg_rows, rows, cols, vals = [], [], [], []
    row0 = 0
    for k in range(K):
        s = exact_stamps(truth, k)
        # the §7.3 offset at the first stamp: o' = o − t_f·d/(1 + d); t = t_f + o' + (s − t_f)/(1 + d)
        base = {"eps": np.zeros(3), "r": pos[k].copy(), "o": o_t[k] - tf * d_t[k] / (1.0 + d_t[k]), "d": d_t[k]}

        def predict(**moved):
            p = dict(base, **moved)
            t = tf + p["o"] + (s - tf) / (1.0 + p["d"])
            f, w = motion.specific_force(t, p["r"][None])
            M = exp_so3(p["eps"]) @ Q[k]
            return np.concatenate((w @ M.T, f[:, 0] @ M.T), 1)          # (N, 6)

        def central(name, delta):
            return (predict(**{name: base[name] + delta}) - predict(**{name: base[name] - delta})) / (2 * np.linalg.norm(delta))

        N = len(s)
        J = np.zeros((N, 6, P))
        # ẏ (the jitter covariance's direction): the prediction's rate of change with the instant
        ydot = central("o", step["o"])
        if k > 0:
            for c in range(3):
                e = np.eye(3)[c]
                J[:, :, col[(k, "q", c)]] = central("eps", step["q"] * e)
                J[:, :, col[(k, "r", c)]] = central("r", step["r"] * e)
                if not walk:
                    J[:, c, col[(k, "bg", c)]] = 1.0
                    J[:, 3 + c, col[(k, "ba", c)]] = 1.0
            J[:, :, col[(k, "o", 0)]] = ydot
            if own[k]:
                J[:, :, col[(k, "d", 0)]] = central("d", step["d"])
        # nuisance columns at the true instants: δy_g = M δω, δy_a = M (δf + δω̇×r + δω×(ω×r) + ω×(δω×r))
        t = np.asarray(truth["true_time"][k], float)
        j0, B, dB = spline_basis(t, lo, h)
        _, w = motion.specific_force(t, pos[k][None])
        r, M = pos[k], Q[k]
        Jm = np.zeros((N, 6, 4, 6))                                     # (sample, row, local coef, [δω, δf])
        for c in range(3):
            e = np.eye(3)[c]
            rot = np.cross(e, np.cross(w, r)) + np.cross(w, np.cross(e, r))   # (N, 3): ∂[δω×(ω×r) + ω×(δω×r)]
            Jm[:, 0:3, :, c] = M[:, c][None, :, None] * B[:, None, :]
            Jm[:, 3:6, :, c] = (M @ np.cross(e, r))[None, :, None] * dB[:, None, :] + (rot @ M.T)[:, :, None] * B[:, None, :]
            Jm[:, 3:6, :, 3 + c] = M[:, c][None, :, None] * B[:, None, :]
        # whitening by each sample's 6×6 covariance (white noise + stamp jitter along ẏ)
        Sig = np.zeros((N, 6, 6))
        Sig[:, [0, 1, 2], [0, 1, 2]] = sg[k] ** 2
        Sig[:, [3, 4, 5], [3, 4, 5]] = sa[k] ** 2
        Sig += sj[k] ** 2 * ydot[:, :, None] * ydot[:, None, :]
        L = np.linalg.cholesky(Sig)
        Jg_rows.append(np.linalg.solve(L, J).reshape(N * 6, P))
        Jw = np.linalg.solve(L, Jm.reshape(N, 6, 24)).reshape(N, 6, 4, 6)
        cc = (6 * (j0[:, None] + np.arange(4))[:, :, None] + np.arange(6)).reshape(N, 1, 24)
        rr = row0 + 6 * np.arange(N)[:, None, None] + np.arange(6)[None, :, None]
        rows.append(np.broadcast_to(rr, (N, 6, 24)).ravel())
        cols.append(np.broadcast_to(cc, (N, 6, 24)).ravel())
        vals.append(Jw.ravel())
        if walk and k > 0:
            # the walking biases at the true instant: (1 − u) on knot jb, u on jb + 1, one per row
            x = (t - lo_b) / h
            jb = np.clip(np.floor(x).astype(np.int64), 0, n_b - 2)
            u = x - jb
            Jb = np.zeros((N, 6, 2, 6))
            Jb[:, np.arange(6), 0, np.arange(6)] = (1 - u)[:, None]
            Jb[:, np.arange(6), 1, np.arange(6)] = u[:, None]
            Jbw = np.linalg.solve(L, Jb.reshape(N, 6, 12))
            base_c = col_b0 + 6 * n_b * (k - 1)
            cb = (base_c + 6 * (jb[:, None, None] + np.arange(2)[None, :, None]) + np.arange(6)).reshape(N, 1, 12)
            rows.append(np.broadcast_to(rr, (N, 6, 12)).ravel())
            cols.append(np.broadcast_to(cb, (N, 6, 12)).ravel())
            vals.append(Jbw.ravel())
        row0 += 6 * N
    Jg = np.concatenate(Jg_rows)
    n_cols = col_b0 + (6 * n_b * (K - 1) if walk else 0)
    Jm = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(row0, n_cols))
    A = Jg.T @ Jg
    Bm = np.asarray((Jm.T @ Jg))                                      # (nuisance, P)
    C = Jm.T @ Jm
    if walk:
        # the walk's prior: whitened increments (b_{j+1} − b_j)/√(q h), q = K_k² + K_ref² per axis
        Dif = sp.diags([-np.ones(n_b - 1), np.ones(n_b - 1)], [0, 1], shape=(n_b - 1, n_b))
        Wp = sp.block_diag([sp.kron(Dif, sp.diags(1.0 / np.sqrt(np.repeat(rw[k] ** 2 + rw[0] ** 2, 3) * h)))
                            for k in range(1, K)])
        C = C + sp.block_diag([sp.csr_matrix((col_b0, col_b0)), Wp.T @ Wp])
    C = C.tocsc()
    schur = A - Bm.T @ splu(C).solve(Bm)
    return np.linalg.inv(0.5 * (schur + schur.T)), labels


def _quat_to_matrix(q):
    """Rotation matrix (array → sensor) of a unit quaternion [w, x, y, z] (DESIGN §7.0)."""
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
