"""An independent Laplace approximation of the [C21] geometry posterior (a cross-check only).

Written from scratch, deliberately sharing no numerical code with :mod:`accel_bayes.model.likelihood`
or :mod:`accel_bayes.inference` (the kinematics, the frames and the φ projection are re-derived
here), so that the PmMH posterior and the MAP helper's Laplace covariance can be checked against
something that would not repeat their mistakes.

Target, for ω_t held fixed (the true ω, or the mean of the array-frame gyro readings)::

    log p(θ | y^a, ω) = Σ_t −½ (y_t − h_t(θ))ᵀ S(θ) (y_t − h_t(θ)) − (T/2) log|M(θ)| + log p(θ) + const

    h_t = [ω_t × (ω_t × r_k)]_k  (3A),   H(θ) = [−Ω(r_k)  I₃]_k  (3A × 6),   Λ = diag(σ⁻²),
    M = HᵀΛH,   S = Λ − ΛH M⁻¹ HᵀΛ  (formed densely),  p(θ) = N(m, σ_r² I).

This is [C21] eq. 18–24 with φ_t = [ω̇_t; s_t] integrated out under a flat prior (the −½ power
of |M| is the β → ∞ limit of eq. 19/21, DESIGN §4).  With σ_g = 0.06 °/s and 32 gyros the
ω_t uncertainty is ~2·10⁻⁴ rad/s against |ω| ~ 30 rad/s, so fixing ω changes the posterior
negligibly at σ_a = 0.79 m/s² (and little at 0.04 m/s²).

The mode is found by damped Newton steps (exact Hessian by
:func:`torch.autograd.functional.hessian`); the covariance is the inverse negative Hessian there.
θ is (A−1, 3): positions of the non-reference triads relative to the reference one, metres.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["LaplaceResult", "log_posterior", "laplace", "laplace_from_recording", "array_frame",
           "gyro_mean_array_frame"]


def _rot(q: torch.Tensor) -> torch.Tensor:
    """R(q) of DESIGN §7.0 (array → sensor), q (..., 4) = (w, x, y, z) → (..., 3, 3)."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack((
        torch.stack((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)), -1),
        torch.stack((2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)), -1),
        torch.stack((2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)), -1),
    ), -2)


def array_frame(v_sensor: np.ndarray, q: np.ndarray) -> torch.Tensor:
    """Sensor-frame readings (T, K, 3) → array frame with the nominal orientations q (K, 4): Rᵀ v."""
    R = _rot(torch.as_tensor(q, dtype=torch.float64))
    v = torch.as_tensor(v_sensor, dtype=torch.float64)
    return torch.einsum("kji,tkj->tki", R, v)


def gyro_mean_array_frame(rec) -> torch.Tensor:
    """Plain average of the array-frame gyro readings, (T, 3) rad/s (IMUs with a gyro only)."""
    g = array_frame(rec.gyro, rec.nominal_orientation)
    keep = ~torch.isnan(g).any(-1).any(0)
    return g[:, keep].mean(1)


def _skew(r: torch.Tensor) -> torch.Tensor:
    x, y, z = r.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack((torch.stack((o, -z, y), -1), torch.stack((z, o, -x), -1),
                        torch.stack((-y, x, o), -1)), -2)


def log_posterior(theta: torch.Tensor, acc: torch.Tensor, omega: torch.Tensor, acc_std: torch.Tensor,
                  prior_mean: torch.Tensor, prior_std: float, reference: int = 0) -> torch.Tensor:
    """log p(θ | y^a, ω) up to a constant (module docstring), dense S, scalar.

    theta (A−1, 3) m; acc (T, A, 3) m/s² array frame; omega (T, 3) rad/s array frame;
    acc_std (A,) m/s²; prior_mean (A−1, 3) m; prior_std m (float).
    """
    T, A, _ = acc.shape
    zero = torch.zeros(1, 3, dtype=theta.dtype)
    r = torch.cat((theta[:reference], zero, theta[reference:]), 0)  # (A, 3)
    w = omega.unsqueeze(1).expand(T, A, 3)
    rb = r.unsqueeze(0).expand(T, A, 3)
    h = torch.linalg.cross(w, torch.linalg.cross(w, rb, dim=-1), dim=-1)  # centripetal, (T, A, 3)
    res = (acc - h).reshape(T, 3 * A)
    eye = torch.eye(3, dtype=theta.dtype).expand(A, 3, 3)
    H = torch.cat((-_skew(r), eye), -1).reshape(3 * A, 6)
    lam = (acc_std.to(theta.dtype) ** -2).repeat_interleave(3)  # triad-major, like res
    LH = lam[:, None] * H
    M = H.T @ LH
    S = torch.diag(lam) - LH @ torch.linalg.solve(M, LH.T)
    quad = torch.einsum("ti,ij,tj->", res, S, res)
    logdet = torch.linalg.slogdet(M)[1]
    lp = -0.5 * (((theta - prior_mean) / prior_std) ** 2).sum()
    return -0.5 * quad - 0.5 * T * logdet + lp


@dataclass
class LaplaceResult:
    """mode (A−1, 3) m; cov (d, d) m², d = 3(A−1), row-major vec θ; std (A−1, 3) m;
    std_mean_um: std averaged over the d coordinates, µm (NaN when ``diverged``); newton_steps;
    grad_norm at the mode (relative to the prior scale); diverged: None, or why no local mode
    near the start was found (see :func:`laplace`)."""

    mode: torch.Tensor
    cov: torch.Tensor
    std: torch.Tensor
    std_mean_um: float
    newton_steps: int
    grad_norm: float
    diverged: str | None = None


def laplace(acc, omega, acc_std, prior_mean, prior_std, reference: int = 0, start=None,
            max_steps: int = 30, tol: float = 1e-12, max_step: float = 5e-4) -> LaplaceResult:
    """Laplace approximation N(mode, (−∇²log p)⁻¹) of :func:`log_posterior` at the local mode
    nearest the start.

    Damped Newton from ``start`` (default: the prior mean): step δ = (−∇²)⁻¹∇ (Levenberg-damped
    when −∇² is not positive definite), shortened so that no coordinate moves more than
    ``max_step`` m, then halved until the log posterior does not decrease; stops when the Newton
    decrement ∇ᵀ(−∇²)⁻¹∇ < ``tol``.

    Why the cap: with the flat prior on φ the target is not a proper density everywhere.  When
    all triads draw together (r → s·r, s → 0) the ω̇ block of M = HᵀΛH vanishes like s², so
    −(T/2) log|M| grows like −3T log s while the data misfit stays bounded: for T > A − 1 the
    posterior has a non-integrable spike at the collapsed geometry (ω̇ becomes unidentifiable
    and its flat prior has infinite mass).  Real data keep the local mode near the design behind
    a barrier of thousands of nats, but with weak motion and large T an uncapped Newton step can
    jump the barrier.  A result whose geometry has shrunk (span < ½ of the start's), moved more
    than 10 prior std from the prior mean, or whose −∇² is not positive definite is returned
    with ``diverged`` set and NaN std.
    """
    acc = torch.as_tensor(acc, dtype=torch.float64)
    omega = torch.as_tensor(omega, dtype=torch.float64)
    acc_std = torch.as_tensor(acc_std, dtype=torch.float64).expand(acc.shape[1])
    m = torch.as_tensor(prior_mean, dtype=torch.float64)
    shape = m.shape
    f = lambda x: log_posterior(x.reshape(shape), acc, omega, acc_std, m, prior_std, reference)  # noqa: E731
    x = (m if start is None else torch.as_tensor(start, dtype=torch.float64)).reshape(-1).clone()

    def grad_hess(x):
        xg = x.clone().requires_grad_(True)
        val = f(xg)
        (g,) = torch.autograd.grad(val, xg)
        Hs = torch.autograd.functional.hessian(f, x, vectorize=True)
        return val.detach(), g.detach(), 0.5 * (Hs + Hs.T)

    def span(th):
        r = torch.cat((th, torch.zeros(1, 3, dtype=th.dtype)), 0)
        return float((r - r.mean(0)).norm(dim=-1).max())

    start_theta = x.reshape(shape).clone()
    span0 = span(start_theta)
    val, g, Hs = grad_hess(x)
    steps = 0
    for steps in range(1, max_steps + 1):
        P = -Hs
        damp = 0.0
        scale = float(torch.diagonal(P).abs().mean())
        while True:
            L, info = torch.linalg.cholesky_ex(P + damp * scale * torch.eye(P.shape[0], dtype=P.dtype))
            if int(info) == 0:
                break
            damp = 1e-8 if damp == 0 else damp * 10
        delta = torch.cholesky_solve(g[:, None], L)[:, 0]
        dec = float(g @ delta)
        if dec < tol:
            break
        big = float(delta.abs().max())
        t = min(1.0, max_step / big) if big > 0 else 1.0
        while t > 1e-6:
            xn = x + t * delta
            vn = f(xn).detach()
            if bool(torch.isfinite(vn)) and vn >= val - 1e-9 * abs(float(val)):
                break
            t *= 0.5
        x = xn
        if span(x.reshape(shape)) < 0.5 * span0:  # running into the collapse spike: stop early
            break
        val, g, Hs = grad_hess(x)
    why = None
    theta = x.reshape(shape)
    if not bool(torch.isfinite(theta).all()):
        why = "non-finite positions"
    elif span(theta) < 0.5 * span0:
        why = f"geometry collapsed (span {span(theta) * 1e3:.3g} mm from {span0 * 1e3:.3g} mm)"
    elif float(((theta - m).abs() / prior_std).max()) > 10:
        why = "moved more than 10 prior std from the prior mean"
    elif int(torch.linalg.cholesky_ex(-Hs)[1]) != 0:
        why = "−Hessian not positive definite at the end point"
    if why is not None:
        nan = torch.full_like(Hs, float("nan"))
        return LaplaceResult(mode=theta, cov=nan, std=torch.full(shape, float("nan"), dtype=torch.float64),
                             std_mean_um=float("nan"), newton_steps=steps, grad_norm=float(g.norm()) * prior_std,
                             diverged=why)
    cov = torch.linalg.inv(-Hs)
    cov = 0.5 * (cov + cov.T)
    std = torch.diagonal(cov).clamp_min(0).sqrt()
    return LaplaceResult(mode=theta, cov=cov, std=std.reshape(shape),
                         std_mean_um=float(std.mean()) * 1e6, newton_steps=steps,
                         grad_norm=float(g.norm()) * prior_std)


def laplace_from_recording(rec, prior_mean_positions, prior_std: float, omega=None, **kw) -> LaplaceResult:
    """:func:`laplace` for a :class:`~accel_bayes.data.recording.Recording` (all IMUs with an
    accelerometer; the recording's reference IMU is the origin).

    prior_mean_positions (K, 3) m: absolute positions whose offsets from the reference row are the
    prior mean; omega (T, 3) rad/s array frame, default the plain gyro average.
    """
    has = ~np.isnan(np.asarray(rec.acc)).any(-1).any(0)
    idx = np.flatnonzero(has)
    ref = int(np.flatnonzero(idx == int(rec.reference_imu))[0])
    acc = array_frame(rec.acc, rec.nominal_orientation)[:, idx]
    if omega is None:
        omega = gyro_mean_array_frame(rec)
    pm = torch.as_tensor(np.asarray(prior_mean_positions), dtype=torch.float64)[idx]
    rel = pm - pm[ref]
    prior_mean = torch.cat((rel[:ref], rel[ref + 1:]), 0)
    acc_std = torch.as_tensor(np.asarray(rec.acc_noise_std), dtype=torch.float64)[idx]
    return laplace(acc, omega, acc_std, prior_mean, prior_std, reference=ref, **kw)
