"""The rig signal model: a continuous-time motion through which every IMU's samples are predicted
at their own clock-corrected instants (see :mod:`accel_bayes.inference.rig` for the model and its
assumptions).

Motion knots τ_j = τ₀ + j·h carry the local state x_j = [ω, ω̇, f, ḟ] (12 numbers, array frame:
rad/s, rad/s², m/s², m/s³); between two knots ω(t) and f(t) are the cubic Hermite interpolants of
(value, derivative) at both ends — the posterior mean of the white-noise-on-jerk Gauss–Markov
prior whose increments :func:`process_residual` scores.  Each interval [τ_j, τ_{j+1}) is one
:class:`~accel_bayes.inference.lm.ChainResidual` row holding the (padded) samples whose corrected
instants fall in it, so the package's structured LM eliminates the knots block-tridiagonally.

Each non-reference IMU's relative biases b_g,k(t), b_a,k(t) are globals on a coarse grid of their
own (:class:`BiasGrid`, one per sensor kind, seconds apart rather than the motion's milliseconds),
linear between bias knots; consecutive bias knots differ by N(0, q_k H) per axis
(:func:`walk_residual`), q_k the IMU's and the reference's random-walk densities squared and summed
(the reference's walk is absorbed in ω, f).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ...physics.geometry import quat_to_matrix, skew

__all__ = ["RigData", "BiasGrid", "bucket_samples", "hermite", "sample_time", "measurement_residual",
           "process_matrices", "measurement_jacobian", "process_residual", "process_jacobian", "full_globals",
           "D_LOCAL", "timing_noise_directions", "stamp_jitter_std", "walk_residual", "mean_biases",
           "LINEAR_BLOCKS", "symmetric"]

D_LOCAL = 12  # [ω, ω̇, f, ḟ] per knot

#: global block of each sensor kind's linear error (scale and non-orthogonality) per non-reference IMU
LINEAR_BLOCKS = {"gyro": "mg", "acc": "ma"}
_SYM = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def symmetric(m: torch.Tensor) -> torch.Tensor:
    """Symmetric 3×3 matrices (..., 3, 3) from their upper triangles m (..., 6) ordered
    (xx, xy, xz, yy, yz, zz): an IMU's linear error M (y = (I + M) R v).  Symmetric because the
    antisymmetric part of a small linear error is a rotation, which R already holds."""
    E = torch.zeros(6, 3, 3, dtype=m.dtype)
    for i, (a, b) in enumerate(_SYM):
        E[i, a, b] = E[i, b, a] = 1.0
    return torch.einsum("...i,iab->...ab", m, E)


@dataclass(frozen=True)
class BiasGrid:
    """The bias knots of one sensor kind: n ≥ 2 knots t0 + m·H (s, − t₀ of the recording); the
    global block ("bg" or "ba") is (K − 1, n, 3), the biases of IMUs 1..K−1 at the knots."""

    t0: float
    H: float
    n: int

    def locate(self, t):
        """Knot index m (long, the interval's left knot) and weight u ∈ [0, 1] of the right one at
        instants t (s); outside the grid the end interval's line is extended."""
        s = (t - self.t0) / self.H
        m = torch.clamp(torch.floor(s.detach()), 0, self.n - 2).long()
        return m, s - m.to(s.dtype)


@dataclass
class RigData:
    """Samples of all IMUs bucketed by motion interval (leading dim J−1 intervals, S slots).

    imu (J−1, S) long: internal IMU index (0 = reference) of the slot; ds (J−1, S): stamp − t₀ (s);
    tau (J−1,): interval start τ_j (s) − t₀; yg, ya (J−1, S, 3): gyro (rad/s), acc (m/s²) readings;
    wg, wa (J−1, S): 1/σ (0 for padding and left-out samples); h: knot spacing (s); n_imu: K;
    u (J−1, S, 6) or None: the whitened timing-noise direction σ_j ∂r/∂t of each slot (stamp jitter,
    :func:`timing_noise_directions`), held fixed while LM runs; grids: the gyro and acc
    :class:`BiasGrid`.
    """

    imu: torch.Tensor
    ds: torch.Tensor
    tau: torch.Tensor
    yg: torch.Tensor
    ya: torch.Tensor
    wg: torch.Tensor
    wa: torch.Tensor
    h: float
    n_imu: int
    grids: tuple = None
    u: torch.Tensor | None = None


def sample_time(ds, o, d):
    """Reference-clock instant − t₀ (s) of a sample stamped t₀ + ds by a clock with lag o (s) at t₀
    and rate error d (DESIGN §7.3: s − t₀ = (t − t₀ − o)(1 + d))."""
    return o + ds / (1.0 + d)


def bucket_samples(samples, o, d, tau0: float, h: float, n_knots: int, grids: tuple) -> RigData:
    """Put each sample into the motion interval that holds its corrected instant.

    samples : list over internal IMU index of dicts with ds (N,), yg (N, 3), ya (N, 3), wg (N,),
    wa (N,) (numpy); o, d : per-IMU clock parameters (numpy, internal order) used only to choose
    the interval (the residual re-evaluates the instant from the current o, d, so a sample whose
    instant moves a little out of its interval is still predicted by that interval's cubic);
    grids : (gyro, acc) :class:`BiasGrid`.
    """
    K = len(samples)
    idx, slot_rows = [], []
    for k, smp in enumerate(samples):
        t = sample_time(smp["ds"], o[k], d[k])
        j = np.clip(np.floor((t - tau0) / h).astype(np.int64), 0, n_knots - 2)
        idx.append(j)
        slot_rows.append(np.full(len(j), k))
    j = np.concatenate(idx)
    kk = np.concatenate(slot_rows)
    cat = {key: np.concatenate([s[key] for s in samples]) for key in ("ds", "yg", "ya", "wg", "wa")}
    order = np.argsort(j, kind="stable")
    j, kk = j[order], kk[order]
    cat = {key: v[order] for key, v in cat.items()}
    counts = np.bincount(j, minlength=n_knots - 1)
    S = max(int(counts.max()), 1)
    start = np.concatenate(([0], np.cumsum(counts)[:-1]))
    slot = np.arange(len(j)) - start[j]
    J1 = n_knots - 1

    def scatter(v, fill=0.0):
        out = np.full((J1, S) + v.shape[1:], fill, dtype=v.dtype)
        out[j, slot] = v
        return out

    t = lambda a, dt=torch.float64: torch.as_tensor(a, dtype=dt)  # noqa: E731
    return RigData(imu=t(scatter(kk, 0), torch.long), ds=t(scatter(cat["ds"])),
                   tau=t(tau0 + h * np.arange(J1)), yg=t(scatter(cat["yg"])), ya=t(scatter(cat["ya"])),
                   wg=t(scatter(cat["wg"])), wa=t(scatter(cat["wa"])), h=float(h), n_imu=K, grids=tuple(grids))


def hermite(u):
    """Cubic Hermite basis on u ∈ [0, 1] and its first two u-derivatives: three (..., 4) tensors
    ordered (h00, h10, h01, h11) — value at 0, slope at 0, value at 1, slope at 1."""
    u2, u3 = u * u, u * u * u
    b = torch.stack((2 * u3 - 3 * u2 + 1, u3 - 2 * u2 + u, -2 * u3 + 3 * u2, u3 - u2), -1)
    db = torch.stack((6 * u2 - 6 * u, 3 * u2 - 4 * u + 1, -6 * u2 + 6 * u, 3 * u2 - 2 * u), -1)
    ddb = torch.stack((12 * u - 6, 6 * u - 4, -12 * u + 6, 6 * u - 2), -1)
    return b, db, ddb


def full_globals(g: dict, R0: torch.Tensor):
    """Per-IMU (internal order, reference first) R (K, 3, 3), r, o, d from the free blocks (which
    hold IMUs 1..K−1); the reference's R is its fixed nominal R0, the rest zero."""
    z3 = g["r"].new_zeros(1, 3)
    z1 = g["o"].new_zeros(1)
    R = torch.cat((R0[None], quat_to_matrix(g["q"])), 0)
    return R, torch.cat((z3, g["r"]), 0), torch.cat((z1, g["o"]), 0), torch.cat((z1, g["d"]), 0)


def _grid_weights(data: RigData, grid: BiasGrid, t):
    """Flat knot index c = (k − 1)·n + m of each slot's left bias knot (J−1, S), the weight u of the
    right one, and a mask (J−1, S) that is 0 on the reference's slots (no bias of its own)."""
    m, u = grid.locate(t)
    c = torch.clamp(data.imu - 1, min=0) * grid.n + m
    return c, u, (data.imu > 0).to(t.dtype)


def _slot_biases(g: dict, data: RigData, t):
    """Each slot's IMU's biases [b_g, b_a] at its instant t (J−1, S, 6), linear between bias knots,
    and their rate (J−1, S, 6) (per s)."""
    val, rate = [], []
    for name, grid in zip(("bg", "ba"), data.grids):
        flat = g[name].reshape(-1, 3)
        c, u, mask = _grid_weights(data, grid, t)
        bl, br = flat[c], flat[c + 1]
        val.append((bl + u[..., None] * (br - bl)) * mask[..., None])
        rate.append((br - bl) * (mask / grid.H)[..., None])
    return torch.cat(val, -1), torch.cat(rate, -1)


def _bias_jacobian(data: RigData, grid: BiasGrid, t, rows: slice, w):
    """∂(whitened slot residual)/∂(bias block) (J−1, S, 6, (K−1)·n·3) of one sensor kind: weights
    1 − u and u on the two bias knots around t, on the identity of that sensor's three rows."""
    c, u, mask = _grid_weights(data, grid, t)
    C = (data.n_imu - 1) * grid.n
    wt = (torch.nn.functional.one_hot(c, C).to(t.dtype) * (1.0 - u)[..., None]
          + torch.nn.functional.one_hot(c + 1, C).to(t.dtype) * u[..., None]) * (mask * w)[..., None]
    J1, S = c.shape
    out = t.new_zeros(J1, S, 6, C, 3)
    for a in range(3):
        out[:, :, rows.start + a, :, a] = wt
    return out.reshape(J1, S, 6, 3 * C)


def walk_residual(grid: BiasGrid, walk) -> tuple:
    """Whitened random-walk increments of one sensor kind's bias knots: (b_{m+1} − b_m)/(K √H) per
    IMU and axis; walk: (K − 1,) densities (per √s).  Returns (residual function of the block
    (K−1, n, 3), its constant Jacobian (rows, (K−1)·n·3))."""
    walk = np.asarray(walk, dtype=float).reshape(-1)
    n = grid.n
    D = np.zeros((n - 1, n))
    D[np.arange(n - 1), np.arange(n - 1)] = -1.0
    D[np.arange(n - 1), np.arange(1, n)] = 1.0
    inv = 1.0 / (walk * math.sqrt(grid.H))
    J = torch.as_tensor(np.kron(np.diag(inv), np.kron(D, np.eye(3))))
    return (lambda b: J @ b.reshape(-1)), J


def mean_biases(b: torch.Tensor) -> np.ndarray:
    """Time means (K − 1, 3) of the linear bias interpolants whose knots are b (K − 1, n, 3)."""
    w = torch.ones(b.shape[1], dtype=b.dtype)
    w[0] = w[-1] = 0.5
    return ((b * w[None, :, None]).sum(1) / w.sum()).numpy()


def _interp(xp, xn, data: RigData, t):
    """ω, ω̇, ω̈, f, ḟ at instants t (J−1, S) from the knots bracketing each interval."""
    h = data.h
    u = (t - data.tau[:, None]) / h
    b, db, ddb = hermite(u)

    def comb(B, scale, i):  # i: column offset of the (value, slope) pair in the 12-vector
        vp, sp, vn, sn = xp[:, None, i:i + 3], xp[:, None, i + 3:i + 6], xn[:, None, i:i + 3], xn[:, None, i + 3:i + 6]
        return (B[..., 0:1] * vp + h * B[..., 1:2] * sp + B[..., 2:3] * vn + h * B[..., 3:4] * sn) / scale

    w, wd, wdd = comb(b, 1.0, 0), comb(db, h, 0), comb(ddb, h * h, 0)
    f, fd = comb(b, 1.0, 6), comb(db, h, 6)
    return (b, db), w, wd, wdd, f, fd


def _jitter_whiten(data: RigData, m):
    """Apply W = (I + u uᵀ)^{-1/2} = I − κ u uᵀ, κ = 1/(√(1+‖u‖²)(1 + √(1+‖u‖²))), to the 6-row slot
    blocks m (J−1, S, 6) or (J−1, S, 6, n): the residual's covariance with stamp jitter is
    I + u uᵀ (one time error ε ~ N(0, σ_j²) moves all six readings of a sample along ∂r/∂t)."""
    if data.u is None:
        return m
    u = data.u
    s = torch.sqrt(1.0 + (u * u).sum(-1))
    kappa = 1.0 / (s * (1.0 + s))
    if m.dim() == 3:
        return m - (kappa * (u * m).sum(-1))[..., None] * u
    return m - (kappa[..., None, None] * u[..., :, None]) * (u[..., None, :] @ m)


def _slot_state(g, data: RigData, R0):
    R, r, o, d = full_globals(g, R0)
    k = data.imu
    return R[k], r[k], o[k], d[k]


def _sensor_maps(g, data: RigData, R):
    """Each slot's gyro and acc maps from the array frame, (I + M) R per sensor kind with a
    linear-error block in g ("mg", "ma"; the reference's M is 0: its own errors are absorbed in ω
    and f), else R."""
    out = []
    for name in ("mg", "ma"):
        if name not in g:
            out.append(R)
            continue
        M = symmetric(torch.cat((g[name].new_zeros(1, 6), g[name]), 0))[data.imu]
        out.append(R + M @ R)
    return out


def _instants(g, data: RigData, o, d):
    """Reference-clock instants − t₀ of each slot's gyro and acc readings (J−1, S): the acc's later
    by the IMU's acc delay δ_k where g has the block "oa" (the reference's δ is 0: its acc timing is
    absorbed in f)."""
    t = sample_time(data.ds, o, d)
    if "oa" not in g:
        return t, t
    delta = torch.cat((g["oa"].new_zeros(1), g["oa"]), 0)[data.imu]
    return t, t + delta


def _predictions(g, xp, xn, data: RigData, R0, t):
    """Unwhitened predicted gyro and acc readings (J−1, S, 3) each, all evaluated at instants t."""
    R, r, _, _ = _slot_state(g, data, R0)
    Rg, Ra = _sensor_maps(g, data, R)
    _, w, wd, _, f, _ = _interp(xp, xn, data, t)
    b, _ = _slot_biases(g, data, t)
    v = f + torch.cross(wd, r, -1) + torch.cross(w, torch.cross(w, r, -1), -1)
    return (Rg @ w.unsqueeze(-1)).squeeze(-1) + b[..., :3], (Ra @ v.unsqueeze(-1)).squeeze(-1) + b[..., 3:]


def measurement_residual(g: dict, xp, xn, data: RigData, R0) -> torch.Tensor:
    """Whitened gyro and acc residuals (J−1, 6·S): per slot [r_g (3), r_a (3)] with
    r_g = (R ω(t) + b_g(t) − y_g)/σ_g and r_a = (R [f(t) + ω̇(t)×r + ω(t)×(ω(t)×r)] + b_a(t) − y_a)/σ_a,
    R replaced by (I + M) R per sensor kind with a linear-error block ("mg", "ma" in g:
    :func:`symmetric`), and the acc's t by t + δ_k with an acc-delay block ("oa")."""
    _, _, o, d = _slot_state(g, data, R0)
    tg, ta = _instants(g, data, o, d)
    pg, pa = _predictions(g, xp, xn, data, R0, tg)
    if ta is not tg:
        _, pa = _predictions(g, xp, xn, data, R0, ta)
    rg = (pg - data.yg) * data.wg[..., None]
    ra = (pa - data.ya) * data.wa[..., None]
    return _jitter_whiten(data, torch.cat((rg, ra), -1)).reshape(rg.shape[0], -1)


def _slot_jacobian(g: dict, xp, xn, data: RigData, R0, t) -> dict:
    """Unwhitened per-slot Jacobians of [r_g, r_a] (J−1, S, 6, ·) with every reading evaluated at
    instants t: "A", "B" (the bracketing knots), the slot IMU's "q", "r", "o" (= ∂r/∂t), "d", "mg",
    "ma" (where in g), and "bg", "ba" (the whole bias block)."""
    R, r, o, d = _slot_state(g, data, R0)
    Rg, Ra = _sensor_maps(g, data, R)
    (b, db), w, wd, wdd, f, fd = _interp(xp, xn, data, t)
    _, brate = _slot_biases(g, data, t)
    h = data.h
    J1, S = data.imu.shape
    I3 = torch.eye(3, dtype=w.dtype)
    Sw, Swd, Sr = skew(w), skew(wd), skew(r)
    wxr = torch.cross(w, r, -1)
    v = f + torch.cross(wd, r, -1) + torch.cross(w, wxr, -1)
    # ∂[ω×(ω×r)]/∂ω = (ω·r) I + ω rᵀ − 2 r ωᵀ ; ∂[ω̇×r]/∂ω̇ = −[r]×
    Dw = (w * r).sum(-1)[..., None, None] * I3 + w.unsqueeze(-1) * r.unsqueeze(-2) - 2 * r.unsqueeze(-1) * w.unsqueeze(-2)
    Dwd = -Sr
    wg, wa = data.wg[..., None, None], data.wa[..., None, None]
    RG, RA = wg * Rg, wa * Ra                     # (J−1, S, 3, 3)
    RADw, RADwd = RA @ Dw, RA @ Dwd
    # coefficient of each knot quantity in ω (value) and ω̇ (slope): value basis b, slope basis db/h
    cv = torch.stack((b[..., 0], h * b[..., 1], b[..., 2], h * b[..., 3]), -1)          # ∂ω/∂(ωp, ω̇p, ωn, ω̇n)
    cs = torch.stack((db[..., 0] / h, db[..., 1], db[..., 2] / h, db[..., 3]), -1)      # ∂ω̇/∂(…)
    Z = R.new_zeros(J1, S, 3, 3)
    blocks = []  # per knot quantity: (6, 3) gyro/acc rows × that quantity
    for i in range(4):
        cvi, csi = cv[..., i, None, None], cs[..., i, None, None]
        jg_w = RG * cvi
        ja_w = RADw * cvi + RADwd * csi
        ja_f = RA * cvi
        blocks.append((torch.cat((jg_w, ja_w), -2), torch.cat((Z, ja_f), -2)))
    out = {}
    # x layout [ω, ω̇, f, ḟ]: the value entries (i = 0, 2) multiply ω / f, the slopes (1, 3) ω̇ / ḟ
    out["A"] = torch.cat((blocks[0][0], blocks[1][0], blocks[0][1], blocks[1][1]), -1)  # (J−1, S, 6, 12)
    out["B"] = torch.cat((blocks[2][0], blocks[3][0], blocks[2][1], blocks[3][1]), -1)
    wdiag = torch.diag_embed(torch.cat((data.wg[..., None].expand(-1, -1, 3), data.wa[..., None].expand(-1, -1, 3)), -1))
    out["q"] = torch.cat((-(RG @ Sw), -(RA @ skew(v))), -2)                          # (J−1, S, 6, 3)
    out["r"] = torch.cat((Z, RA @ (Swd + Sw @ Sw)), -2)
    # d/dt of the prediction: gyro R ω̇ + ḃ_g, acc R (ḟ + ω̈×r + ω̇×(ω×r) + ω×(ω̇×r)) + ḃ_a
    dv = fd + torch.cross(wdd, r, -1) + torch.cross(wd, wxr, -1) + torch.cross(w, torch.cross(wd, r, -1), -1)
    jt = torch.cat(((RG @ wd.unsqueeze(-1)), (RA @ dv.unsqueeze(-1))), -2)          # (J−1, S, 6, 1)
    out["o"] = jt + (wdiag @ brate.unsqueeze(-1))
    out["d"] = out["o"] * (-data.ds / (1.0 + d) ** 2)[..., None, None]
    # ∂[(I + M) R v]/∂m_i = E_i R v, E_i the i-th basis matrix of :func:`symmetric`
    for name, Rv, wt, top in (("mg", R @ w.unsqueeze(-1), wg, True), ("ma", R @ v.unsqueeze(-1), wa, False)):
        if name in g:
            Em = symmetric(torch.eye(6, dtype=w.dtype))                                # (6, 3, 3)
            jm = wt * torch.einsum("iab,...bc->...ai", Em, Rv)                         # (J−1, S, 3, 6)
            Z6 = jm.new_zeros(jm.shape)
            out[name] = torch.cat((jm, Z6) if top else (Z6, jm), -2)
    for name, grid, rows, wgt in (("bg", data.grids[0], slice(0, 3), data.wg), ("ba", data.grids[1], slice(3, 6), data.wa)):
        out[name] = _bias_jacobian(data, grid, t, rows, wgt)
    return out


def _merged_jacobian(g: dict, xp, xn, data: RigData, R0) -> dict:
    """:func:`_slot_jacobian` with the gyro rows at the gyro's instants and the acc rows at the acc's
    (and "oa", the acc rows' ∂r/∂t, where g has an acc delay)."""
    _, _, o, d = _slot_state(g, data, R0)
    tg, ta = _instants(g, data, o, d)
    out = _slot_jacobian(g, xp, xn, data, R0, tg)
    if ta is tg:
        return out
    at_a = _slot_jacobian(g, xp, xn, data, R0, ta)
    for key in out:
        out[key] = torch.cat((out[key][..., :3, :], at_a[key][..., 3:, :]), -2)
    out["oa"] = torch.cat((torch.zeros_like(at_a["o"][..., :3, :]), at_a["o"][..., 3:, :]), -2)
    return out


def measurement_jacobian(g: dict, xp, xn, data: RigData, R0):
    """Analytic Jacobians of :func:`measurement_residual`: (dict block → (J−1, 6S, tangent size),
    A (J−1, 6S, 12) w.r.t. x_j, B (J−1, 6S, 12) w.r.t. x_{j+1}).  Orientation tangent: δ with
    R ← R·Exp(δ) (the LM's right box-plus), so ∂(R v)/∂δ = −R [v]×."""
    raw = _merged_jacobian(g, xp, xn, data, R0)
    J1, S = data.imu.shape
    K1 = data.n_imu - 1
    onehot = torch.nn.functional.one_hot(data.imu, data.n_imu)[..., 1:].to(raw["A"].dtype)  # reference: no globals
    oh = onehot[:, :, None, :, None]                                               # (J−1, S, 1, K−1, 1)

    def spread(jb):
        jb = _jitter_whiten(data, jb)
        return (jb.unsqueeze(-2) * oh).reshape(J1, 6 * S, K1 * jb.shape[-1])

    jac = {name: spread(raw[name]) for name in ("q", "r", "o", "d", "mg", "ma", "oa") if name in raw}
    for name in ("bg", "ba"):  # already laid out over every IMU's bias knots
        jb = _jitter_whiten(data, raw[name])
        jac[name] = jb.reshape(J1, 6 * S, jb.shape[-1])
    A, B = _jitter_whiten(data, raw["A"]), _jitter_whiten(data, raw["B"])
    D = A.shape[-1]
    return jac, A.reshape(J1, 6 * S, D), B.reshape(J1, 6 * S, D)


def timing_noise_directions(g: dict, xp, xn, data: RigData, R0, sigma_j) -> torch.Tensor:
    """u (J−1, S, 6) = σ_j,k · ∂r/∂t of each slot: the whitened change of its six readings per second
    of timing error, times the stamp-jitter std σ_j,k (s) of the slot's IMU (sigma_j: (K,) internal
    order; padding slots get 0 through their zero weights)."""
    jt = _merged_jacobian(g, xp, xn, data, R0)["o"][..., 0]
    sj = torch.as_tensor(np.asarray(sigma_j, dtype=float))[data.imu]
    return jt * sj[..., None]


def stamp_jitter_std(ds: np.ndarray) -> float:
    """Std (s) of the stamping error of one IMU's own stamps ds (s), from their second differences.

    An IMU ticks regularly on its own crystal (the clock model's constant offset and drift), so
    Δ²s_n = ε_{n+1} − 2ε_n + ε_{n−1} for iid stamping errors ε (a host's latency in stamping): its
    variance is 6σ_j², while a constant rate and slow wander cancel.  Robust (MAD) and restricted to
    triples without a dropped sample (both steps within 25 % of the median period p), which keeps
    it unbiased for σ_j ≲ p/10 (at σ_j = p/5 it reads about half the jitter).  Stamps that
    are irregular because the samples really were taken irregularly are read as jitter too: that
    only down-weights the fast-moving samples (a conservative std).
    """
    ds = np.asarray(ds, dtype=float)
    if len(ds) < 8:
        return 0.0
    st = np.diff(ds)
    p = float(np.median(st))
    ok = (np.abs(st[1:] - p) < 0.25 * p) & (np.abs(st[:-1] - p) < 0.25 * p)
    d2 = (st[1:] - st[:-1])[ok]
    if len(d2) < 8:
        return 0.0
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0))


def process_matrices(h: float, qc_w: float, qc_f: float, dtype=torch.float64):
    """(Aw, Bw) (12, 12) such that the whitened prior increments are Aw x_j + Bw x_{j+1}: per motion
    axis the white-noise-on-jerk e = [v_{j+1} − v_j − h ṡ_j ; ṡ_{j+1} − ṡ_j],
    Cov(e) = q_c [[h³/3, h²/2], [h²/2, h]]."""
    A = torch.zeros(D_LOCAL, D_LOCAL, dtype=dtype)
    B = torch.zeros(D_LOCAL, D_LOCAL, dtype=dtype)
    I3 = torch.eye(3, dtype=dtype)
    for off, qc in ((0, qc_w), (6, qc_f)):
        Q = qc * torch.tensor([[h ** 3 / 3, h ** 2 / 2], [h ** 2 / 2, h]], dtype=dtype)
        Li = torch.linalg.inv(torch.linalg.cholesky(Q))   # whitening: Li e ~ N(0, I)
        Ea = torch.tensor([[-1.0, -h], [0.0, -1.0]], dtype=dtype)
        Eb = torch.eye(2, dtype=dtype)
        A[off:off + 6, off:off + 6] = torch.kron(Li @ Ea, I3)
        B[off:off + 6, off:off + 6] = torch.kron(Li @ Eb, I3)
    return A, B


def process_residual(xp, xn, AB) -> torch.Tensor:
    """Whitened motion-prior increments (J−1, 12) between consecutive knots."""
    A, B = AB
    return xp @ A.T + xn @ B.T


def process_jacobian(xp, AB):
    """(A, B) expanded to (J−1, 12, 12): the prior is linear in the knots and free of globals."""
    A, B = AB
    n = xp.shape[0]
    return {}, A.expand(n, *A.shape), B.expand(n, *B.shape)
