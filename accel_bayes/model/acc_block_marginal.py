"""The accelerometers' linear errors integrated out of the likelihood (issue #30 item 4: blind
calibration with the detector's own report).

Why.  Where a recording rests in one orientation only, the preparation cannot calibrate the
triads, and ``calibrate --model`` inverts the accelerometer blocks the detector estimated
(:class:`~accel_bayes.physics.effects.AccLinear`: y = (I + E_k) f + b_k per triad) as if they were
exact.  What the estimate misses moves the positions without widening the posterior: on the
concealed clock recordings calibrated blind, the error is 1.4× the oracle's at the same posterior
std (``experiments/percov_blind_acc.md``).  Every triad's linear error is uncertain, so every triad
gets one here, the blocks the report gives as the prior's centre.  Where the rests do calibrate the
triads, ``mismatch --acc-linear`` estimates what they leave on the rest-calibrated outputs (a chip's
rotation on the board: ``experiments/mimu_blind_acc.md``) and the same term carries those blocks.

Model.  Per sample t, the likelihood's outputs y_t (3A, array frame, already corrected by the
report's blocks Ê_k, b̂_k and divided by the noise model's per-sample scale s_t) err to first order
by X_t β, β_k = [vec(E_k − Ê_k) (row-major, 9); b_k − b̂_k (3)] in the array frame::

    y_t = (the likelihood's model at ω_t) + X_t β + (its noise and per-sample terms),
    X_t rows of triad k = [I₃ ⊗ f̂_ktᵀ,  I₃ / s_t]  (3 × 12, zero on the other triads' columns),
    E_k ~ N(0, τ_M² I₉),  b_k ~ N(0, τ_b² I₃),  i.e.  β ~ N(μ, P),  μ_k = −[vec(Ê_k); b̂_k].

The prior is on the errors themselves (a tolerance of the sensor type, the same for every triad:
iid entries, so the array frame's rotation of E_k keeps it), centred at zero; the report's blocks
only shift where β is centred.  Second-order terms (E − Ê)·(Ê, f − y) are dropped: ≤ 1e-4 of the
outputs at the percent-level errors of MEMS triads.

Regressor.  A linear error multiplies the specific force f, not the output; f̂_t = G u(ω̄_t) + Hφ̂_t,
the model's fit at θ₀ with φ̂_t by generalised least squares under the sample's covariance.  The
outputs themselves (f ≈ y) would be errors-in-variables: once φ is projected out, what is left of y
in the direction every triad shares is mostly noise, and type-II ML then fitted a common shrink of the
data that cancels it (τ_M 34–47 % on the concealed clock recordings).  f̂'s own noise lies in the span
of H under the GLS weights, orthogonal to the projected residual, so it does not correlate with it.

Integrating β out at ω = ω̄ (the gyro posterior mean), with the regressor X_t held at a reference θ₀
(the mode so far), the log-likelihood gains, exactly for a Gaussian linear model,

    Δ(θ) = ½ h(θ)ᵀ(K(θ) + P⁻¹)⁻¹h(θ) − ½ μᵀP⁻¹μ − ½ log|I + PK(θ)|,
    K(θ) = Σ_t X_tᵀW_t(θ)X_t,   h(θ) = Σ_t X_tᵀW_t(θ)(y_t − G(θ)u(ω̄_t)) + P⁻¹μ,

W_t = Σ_t⁻¹ − Σ_t⁻¹H(HᵀΣ_t⁻¹H + F⁻¹)⁻¹HᵀΣ_t⁻¹, Σ_t = Q + Ũ_tŨ_tᵀ: the likelihood's own noise, φ prior
N(0, F) (F⁻¹ = 0: the flat prior) and per-sample covariance
(:meth:`~.likelihood_percov.PerSampleCovLikelihood.loading_matrix`), φ integrated out.

Positions.  θ enters twice: through the centripetal model G(θ)u, and through W_t, since φ holds the
angular acceleration ω̇_t and H(θ) its lever arms.  The second is not small: W_tH = 0 makes
∂W_t·(y_t − Gu_t) = −W_t(∂H)φ_t, as large as the recording's angular acceleration, and a common error
E reads E(ω̇ × r_k) on triad k.  (Until 2026-11-29 W_t was held at θ₀: on the concealed clock recordings
the mode's response to the accelerometers' common error was a fifth of the refitted one, and the
positions' posterior barely widened.)  Evaluating Δ(θ) exactly costs a pass over the samples, so the
chains get its second-order expansion at θ₀: the exact value, the gradient (autograd) and the Hessian
(central differences of the gradient) — deterministic, O(A²) per θ, so p̂·e^Δ is still an unbiased
estimator of its target and pseudo-marginal MH stays exact for it.  What is approximate: the
expansion's third order over the posterior's width (10⁻⁴ m against centimetres of lever arm), X_t at θ₀,
and the β integral at ω̄ rather than inside the per-sample average over ω draws (the draws spread ω by
the gyro noise, far less than the motion that makes K).  A linear expansion of h alone (K fixed) is not
enough: where τ is large against what the data say of β, its Jᵀ(K + P⁻¹)⁻¹J outgrows the likelihood's
own curvature and the target has no mode.

What is common.  The integral runs over the triads' deviations from their mean, β = Zγ
(:func:`deviation_basis`; prior N(Zᵀμ, τ²I) on γ).  The part every triad shares, c (12 numbers: a 3×3
and an offset), is *cut* (Plummer 2015's cut distribution): the data are not let inform it, and its
prior alone, N(0, τ²/A) per entry (the mean of A iid errors), is propagated to the positions.  Why: its
isotropic part is the array's size (y → (1 + δ)y is r → (1 + δ)r), which no motion shows, and the rest
the data see only through the lever-arm terms, where every other unmodelled effect of the recording
lands too — and under a proper φ prior (fitted to these outputs with c = 0) a common shrink of every
output lowers its penalty on φ by about Σ_t φ_tᵀF⁻¹φ_t ≈ 3T nats per unit of scale, a pull that says
nothing about the sensors (fitted, it drove τ_M to 34–47 %).  Fitted with the deviations, its posterior
sat within 0.3 % (1 std) of the report's common part and 0.5–0.8 % from the generator's on a concealed
clock recording, while taking the generator's
common part off the outputs alone brought that case's error/std RMS from 1.55 to 0.96
(``experiments/percov_blind_acc.md``).  The chains run with c at the report's value; :func:`common_shifts`
then moves each draw by the mode's linear response to c − ĉ (through both ways the positions enter,
``Positions``), c drawn from its prior — the positions' marginal under the cut, to first order in c.

τ_M and τ_b by type-II ML (``fit``, the default): the same Δ at θ₀ is the log evidence of the
tolerance, maximised over (log τ_M, log τ_b) — an exchangeable prior whose spread the triads'
identifiable parts measure and which the array's size then inherits.  Or given (sensor datasheet).

Related: the blocks' estimation (:mod:`accel_bayes.mismatch.acc_linear`); their inversion
(:func:`.report_terms.corrected_array`); the likelihoods that carry the term (``block_marginal``
of :class:`~.likelihood.RaoBlackwellLikelihood`, added to ``log_phat`` and
``log_lik_given_omega``); ``tests/model/test_acc_block_marginal.py`` checks Δ against the dense
Gaussian with β in its covariance.
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import torch

from ..errors import UserError
from ..physics.models import G_matrix, H_matrix, u_of_omega

__all__ = ["BlockMarginal", "block_prior_mean", "build_block_marginal", "common_shifts", "deviation_basis",
           "marginal_scores", "with_block_marginal"]

# samples per chunk of the per-sample products: (τ, 12A, 3A) and (τ, 3A, 3A) blocks, ~20 MB at A = 8
_CHUNK = 1024


@dataclass
class BlockMarginal:
    """Δ(θ) of the module docstring as a quadratic in the relative positions r (A, 3) m about θ₀:
    ``value`` Δ(θ₀) nats, ``grad`` (3A,) nats/m and ``hess`` (3A, 3A) nats/m² of the exact Δ there,
    ``r0`` (3A,) θ₀ flattened (the reference row zero); ``cov`` (K + P⁻¹)⁻¹ (n, n) at θ₀ in the
    deviations' coordinates γ (n = 12(A − 1)); ``tau`` (τ_M, τ_b) and ``record`` what was used
    (provenance); the cut common part: ``common_J`` (12, 3A) its map on the positions, ``common_center``
    ĉ (12,) the report's value, ``common_std`` (12,) its prior std (:func:`common_shifts`); what
    :func:`marginal_scores` rebuilds the exact Δ from: ``fhat`` (T, 3A) the regressor, ``inv_scale`` (T,)
    1/s_t, ``mu_dev`` (n,) the prior's centre and ``pvar`` (n,) its variances in the deviations' coordinates."""

    value: float
    grad: torch.Tensor
    hess: torch.Tensor
    r0: torch.Tensor
    cov: torch.Tensor
    tau: tuple
    record: dict
    common_J: torch.Tensor = None
    common_center: torch.Tensor = None
    common_std: torch.Tensor = None
    fhat: torch.Tensor = None
    inv_scale: torch.Tensor = None
    mu_dev: torch.Tensor = None
    pvar: torch.Tensor = None

    def __call__(self, r: torch.Tensor) -> torch.Tensor:
        """Δ (...) nats for relative positions r (..., A, 3) m (the reference row zero)."""
        d = r.reshape(*r.shape[:-2], -1).to(self.grad.dtype) - self.r0
        return self.value + d @ self.grad + 0.5 * ((d @ self.hess) * d).sum(-1)


def block_prior_mean(blocks, orientations, imu_labels) -> torch.Tensor:
    """μ (12A,) of the module docstring: −[vec(R_kᵀÊ_kR_k); R_kᵀb̂_k] per triad with a report block
    (``blocks`` [(IMU label, AccLinear)], ``orientations`` (A, 4) nominal quaternions array → sensor of
    the likelihood's triads ``imu_labels``), zero for the others."""
    from ..physics.geometry import quat_to_matrix

    labels = [int(k) for k in imu_labels]
    R = quat_to_matrix(torch.as_tensor(np.asarray(orientations, dtype=np.float64)))
    mu = torch.zeros(len(labels), 12, dtype=torch.float64)
    for k, e in blocks:
        if int(k) not in labels:
            continue
        i = labels.index(int(k))
        M = torch.as_tensor(e.params["matrix"], dtype=torch.float64).detach()
        b = torch.as_tensor(e.params["bias"], dtype=torch.float64).detach()
        mu[i, :9] = -(R[i].T @ M @ R[i]).reshape(9)
        mu[i, 9:] = -(R[i].T @ b)
    return mu.reshape(-1)


def _design(acc: torch.Tensor, inv_scale: torch.Tensor) -> torch.Tensor:
    """X_t (τ, 3A, 12A) of the module docstring from the outputs ``acc`` (τ, A, 3) and 1/s_t (τ,)."""
    tau, A, _ = acc.shape
    eye = torch.eye(3, dtype=acc.dtype)
    blk = torch.cat((torch.einsum("ij,tkl->tkijl", eye, acc).reshape(tau, A, 3, 9),
                     eye.expand(tau, A, 3, 3) * inv_scale[:, None, None, None]), -1)  # (τ, A, 3, 12)
    X = torch.zeros(tau, A, 3, A, 12, dtype=acc.dtype)
    idx = torch.arange(A)
    X[:, idx, :, idx] = blk.permute(1, 0, 2, 3)
    return X.reshape(tau, 3 * A, 12 * A)


def _scales(lik, sample_scale) -> torch.Tensor:
    T = lik.T
    s = torch.ones(T, dtype=lik.dtype) if sample_scale is None else torch.as_tensor(
        np.asarray(sample_scale, dtype=np.float64), dtype=lik.dtype)
    if s.shape != (T,) or not bool(torch.isfinite(s).all()) or bool((s <= 0).any()):
        raise UserError(f"sample_scale: expected ({T},) finite positive per-sample scales")
    return s


def _chunks(T):
    return [(t0, min(T, t0 + _CHUNK)) for t0 in range(0, T, _CHUNK)]


def _regressor(lik, r0, U) -> torch.Tensor:
    """f̂_t = G u(ω̄_t) + Hφ̂_t (T, 3A) at relative positions r0 (A, 3) m: the specific force the model
    fits, φ̂_t its generalised-least-squares (under a proper φ prior: MAP) estimate under the sample's
    noise and per-sample loading ``U`` (T, 3A, R) or None — the blocks' regressor, held at θ₀ (module
    docstring, "Regressor")."""
    H, G = H_matrix(r0), G_matrix(r0)
    out = []
    for t0, t1 in _chunks(lik.T):
        SH = _noise_precision(lik, t0, t1, None if U is None else U[t0:t1]) @ H  # (τ, 3A, 6)
        M = _phi_normal(lik, H, SH)
        Gu = u_of_omega(lik.omega.mean[t0:t1]) @ G.T  # (τ, 3A)
        phi = torch.linalg.solve(M, SH.transpose(-1, -2) @ (lik.y[t0:t1] - Gu)[..., None])[..., 0]
        out.append(Gu + phi @ H.T)
    return torch.cat(out)


def _phi_normal(lik, H: torch.Tensor, SH: torch.Tensor) -> torch.Tensor:
    """M_t = HᵀS_tH (+ F⁻¹ under a proper φ prior) (τ, 6, 6) from SH = S_tH (τ, 3A, 6): φ_t's posterior
    precision, the matrix W_t and φ̂_t both solve with."""
    M = H.T @ SH
    return M if lik.phi_prior_prec is None else M + lik.phi_prior_prec


def _noise_precision(lik, t0: int, t1: int, U: torch.Tensor | None) -> torch.Tensor:
    """S_t = (Q + Ũ_tŨ_tᵀ)⁻¹ (τ, 3A, 3A) for the samples t0:t1 (Woodbury; ``U`` those samples' loading
    or None): the part of W_t the positions do not move."""
    lam = lik.lam
    S = torch.diag(lam).expand(t1 - t0, *lam.shape, *lam.shape).clone()
    if U is not None and U.shape[-1] > 0:
        LU = lam[:, None] * U
        N = torch.eye(U.shape[-1], dtype=lam.dtype) + U.transpose(-1, -2) @ LU
        S = S - LU @ torch.linalg.solve(N, LU.transpose(-1, -2))
    return S


class _ExactDelta:
    """Δ(r) of the module docstring with K(r) and g(r) exact in the positions (W_t at r; X_t held) in
    the deviations' coordinates, and its gradient by autograd.  W_t = S_t − S_tH M_t⁻¹HᵀS_t with
    M_t = HᵀS_tH (+ F⁻¹), S_t the noise's precision, so with XS_t = X_tᵀS_t (n × 3A, stored once)

        K(r) = Σ_t X_tᵀS_tX_t − Σ_t V_tV_tᵀ,   g(r) = Σ_t XS_t e_t − Σ_t V_t L_t⁻¹HᵀS_te_t,

    V_t = XS_tH L_t⁻ᵀ (M_t = L_tL_tᵀ), e_t = y_t − G(r)u_t: the n × n products with W_t (4× the work)
    are left out of every evaluation."""

    def __init__(self, lik, fhat, inv_scale, U, Z):
        self.lik, self.fhat, self.inv_scale, self.U, self.Z = lik, fhat, inv_scale, U, Z
        self.u = u_of_omega(lik.omega.mean)
        n, m = Z.shape[1], 3 * lik.A
        # S_t and XS_t kept between evaluations unless they would take more than _STORE_BYTES (A ≳ 16)
        self.store = lik.T * (n * m + m * m) * 8 <= _STORE_BYTES
        self.parts = []
        K0 = torch.zeros(n, n, dtype=lik.dtype)
        for t0, t1 in _chunks(lik.T):
            S, XS, X = self._part(t0, t1)
            K0 += torch.einsum("tni,tim->nm", XS, X)
            self.parts.append((t0, t1, S, XS) if self.store else (t0, t1, None, None))
        self.K0 = 0.5 * (K0 + K0.T)

    def _part(self, t0: int, t1: int):
        """(S_t (τ, 3A, 3A), XS_t (τ, n, 3A), X_t (τ, 3A, n)) of the samples t0:t1."""
        S = _noise_precision(self.lik, t0, t1, None if self.U is None else self.U[t0:t1])
        X = _design(self.fhat[t0:t1].view(t1 - t0, self.lik.A, 3), self.inv_scale[t0:t1]) @ self.Z
        return S, X.transpose(-1, -2) @ S, X

    def _projected(self, rv: torch.Tensor):
        """Per chunk of samples at the flattened relative positions rv (3A,) m: (t0, t1, G, S_tH, XS_t, L_t, V_t),
        M_t = L_tL_tᵀ and V_t = L_t⁻¹(XS_tH)ᵀ (τ, 6, n) — what K, g and their per-sample terms are made of."""
        lik = self.lik
        Rm = rv.view(lik.A, 3)
        H, G = H_matrix(Rm), G_matrix(Rm)
        for t0, t1, S, XS in self.parts:
            if S is None:
                S, XS, _ = self._part(t0, t1)
            SH = S @ H  # (τ, 3A, 6)
            L = torch.linalg.cholesky(_phi_normal(lik, H, SH))
            V = torch.linalg.solve_triangular(L, (XS @ H).transpose(-1, -2), upper=False)  # (τ, 6, n)
            yield t0, t1, G, SH, XS, L, V

    def _g_terms(self, t0, t1, G, SH, XS, L, V, dy=None):
        """(X_tᵀS_te_t, V_tᵀL_t⁻¹HᵀS_te_t) (τ, n) each, e_t = y_t − G(r)u_t (− dy_t): X_tᵀW_te_t is their difference."""
        e = self.lik.y[t0:t1] - self.u[t0:t1] @ G.T  # (τ, 3A)
        if dy is not None:
            e = e - dy[t0:t1]
        c = torch.linalg.solve_triangular(L, SH.transpose(-1, -2) @ e[..., None], upper=False)  # (τ, 6, 1)
        return (XS @ e[..., None])[..., 0], (V.transpose(-1, -2) @ c)[..., 0]

    def sums(self, rv: torch.Tensor):
        """(K(r) (n, n), g(r) (n,)) at the flattened relative positions rv (3A,) m (differentiable)."""
        K, g = self.K0, 0.0
        for t0, t1, G, SH, XS, L, V in self._projected(rv):
            Vf = V.reshape(-1, V.shape[-1])
            K = K - Vf.T @ Vf
            a, b = self._g_terms(t0, t1, G, SH, XS, L, V)
            g = g + a.sum(0) - b.sum(0)
        return 0.5 * (K + K.T), g

    def posterior_vv(self, rv: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
        """(T,) ‖V_tR‖²_F at the flattened relative positions rv (3A,) m (differentiable): with C = RRᵀ,
        the θ-dependent part of −tr(C X_tᵀW_tX_t) per sample (:func:`marginal_scores`)."""
        return torch.cat([(V @ R).square().sum((-1, -2)) for *_, V in self._projected(rv)])

    def g_per_sample(self, rv: torch.Tensor, dy: torch.Tensor) -> torch.Tensor:
        """(T, n): the terms X_tᵀW_t(e_t − dy_t) of g at the flattened relative positions rv (3A,) m, dy (T, 3A)
        subtracted from each residual e_t — with dy = X_tZm, γ's per-sample scores at m (:func:`marginal_scores`)."""
        out = []
        for part in self._projected(rv):
            a, b = self._g_terms(*part, dy=dy)
            out.append(a - b)
        return torch.cat(out)

    def delta(self, r: torch.Tensor, mu, pvar, with_grad: bool):
        """(Δ nats, its gradient (3A,) nats/m or None) at relative positions r (A, 3) m, prior N(μ, diag(pvar))."""
        rv = r.detach().reshape(-1).clone().requires_grad_(with_grad)
        with torch.set_grad_enabled(with_grad):
            val = evidence(*self.sums(rv), mu, pvar)
            grad = torch.autograd.grad(val, rv)[0] if with_grad else None
        return float(val.detach()), grad


#: bytes: the most :class:`_ExactDelta` keeps of S_t and XS_t between evaluations (else recomputed)
_STORE_BYTES = 256 * 2 ** 20

#: m: the step of the central differences of Δ's gradient that give its Hessian (the positions'
#: posterior std is 10⁻⁴ m and more; Δ's third-order terms over 10⁻⁵ m are below 10⁻⁶ of the second)
_HESS_STEP = 1e-5


def deviation_basis(A: int, dtype=torch.float64) -> torch.Tensor:
    """Z (12A, 12(A − 1)) orthonormal: β = Zγ are the per-triad blocks whose sum over the triads is
    zero, entry by entry (the triads' deviations from their mean; module docstring, "What is common").
    An iid N(0, τ²) prior on the entries restricted to that subspace is N(0, τ²) on γ."""
    one = torch.ones(A, 1, dtype=dtype) / math.sqrt(A)
    q, _ = torch.linalg.qr(torch.cat((one, torch.eye(A, dtype=dtype)), 1))
    D = q[:, 1:A].contiguous()  # (A, A − 1) orthonormal, orthogonal to the first column ±1/√A
    return torch.kron(D, torch.eye(12, dtype=dtype))


def _prior_var(tau, A):
    """diag(P) (12A,): τ_M² on each triad's nine matrix entries, τ_b² on its three offsets (tensors
    keep their graph: the type-II ML differentiates through them)."""
    tm, tb = (torch.as_tensor(v, dtype=torch.float64) for v in tau)
    return torch.cat((tm.pow(2).expand(9), tb.pow(2).expand(3))).repeat(A)


def evidence(K, g, mu, pvar):
    """Δ of the module docstring for g = g(θ) as given: ½hᵀ(K + P⁻¹)⁻¹h − ½μᵀP⁻¹μ − ½log|I + PK|,
    h = g + P⁻¹μ, with P = diag(``pvar``); differentiable in pvar (the type-II ML of τ)."""
    h = g + mu / pvar
    sp = pvar.sqrt()
    B = torch.eye(len(g), dtype=K.dtype) + sp[:, None] * K * sp[None, :]  # I + P^½KP^½ (SPD)
    L = torch.linalg.cholesky(B)
    w = torch.cholesky_solve((sp * h)[:, None], L)[:, 0]  # (K + P⁻¹)⁻¹h = P^½ B⁻¹ P^½ h
    return 0.5 * (sp * h * w).sum() - 0.5 * (mu * mu / pvar).sum() - torch.log(torch.diagonal(L)).sum()


def fit_tau(K, g, mu, A, start=(0.01, 0.1)):
    """(τ_M, τ_b, log evidence gain over τ → 0) by type-II ML of Δ at θ₀ over (log τ_M, log τ_b)."""
    x = torch.tensor([math.log(start[0]), math.log(start[1])], dtype=K.dtype, requires_grad=True)
    opt = torch.optim.LBFGS([x], max_iter=200, line_search_fn="strong_wolfe", tolerance_grad=1e-9,
                            tolerance_change=1e-12)

    def closure():
        opt.zero_grad()
        # the line search may try any step: outside [1e-6, 1] the evidence is flat (and, for τ ≫ 1,
        # I + PK loses its positive definiteness to round-off)
        xc = x.clamp(math.log(1e-6), math.log(1.0))
        v = -evidence(K, g, mu, _prior_var((xc[0].exp(), xc[1].exp()), A))
        v.backward()
        return v

    for _ in range(3):
        opt.step(closure)
    x = x.detach().clamp(math.log(1e-6), math.log(1.0))
    tau = (float(x[0].exp()), float(x[1].exp()))
    with torch.no_grad():
        gain = float(evidence(K, g, mu, _prior_var(tau, A)) - evidence(K, g, mu, _prior_var((1e-6, 1e-6), A)))
    return tau[0], tau[1], gain


def build_block_marginal(lik, positions, mu, *, tau="fit", sample_scale=None) -> BlockMarginal:
    """The :class:`BlockMarginal` of ``lik`` at θ₀ = ``positions`` (A, 3) m: ``mu`` (12A,) the prior's
    centre (:func:`block_prior_mean`), ``tau`` "fit" (type-II ML) or (τ_M, τ_b) (1, m/s²),
    ``sample_scale`` (T,) the noise model's per-sample scale the outputs were divided by."""
    if getattr(lik, "nu", None) is not None:
        raise UserError("acc_blocks: the block marginal is Gaussian; expected a likelihood without a scale mixture")
    A = lik.A
    mu = torch.as_tensor(mu, dtype=lik.dtype).reshape(-1)
    if mu.shape != (12 * A,):
        raise UserError(f"mu: expected the prior centre of 12 per triad, ({12 * A},), got {tuple(mu.shape)}")
    r0 = lik._positions(torch.as_tensor(positions, dtype=lik.dtype))
    s = _scales(lik, sample_scale)
    U = lik.loading_matrix() if hasattr(lik, "loading_matrix") else None  # once, not per chunk
    fhat = _regressor(lik, r0, U)
    # the integral runs over the deviations β = Zγ; what every triad shares is cut (module docstring,
    # "What is common"): its map on the positions (through both ways they enter, "Positions") and the
    # report's value are kept for :func:`common_shifts`
    Z = deviation_basis(A, dtype=lik.dtype)
    exact = _ExactDelta(lik, fhat, 1.0 / s, U, Z)
    common = _ExactDelta(lik, fhat, 1.0 / s, U, torch.eye(12, dtype=lik.dtype).repeat(A, 1))
    Jc = -torch.autograd.functional.jacobian(lambda rv: common.sums(rv)[1], r0.reshape(-1), vectorize=True,
                                             strategy="forward-mode")
    c_hat = -mu.view(A, 12).mean(0)
    mu = Z.T @ mu
    with torch.no_grad():
        K, g = exact.sums(r0.reshape(-1))
    gain = None
    if isinstance(tau, str):
        if tau != "fit":
            raise UserError(f"acc_blocks: expected 'fit' or (tau_matrix, tau_bias), got {tau!r}")
        tm, tb, gain = fit_tau(K, g, mu, A - 1)  # the evidence at θ₀
    else:
        tm, tb = (float(v) for v in tau)
        if not (tm > 0 and tb > 0 and math.isfinite(tm) and math.isfinite(tb)):
            raise UserError(f"acc_blocks: expected tolerances > 0 (1, m/s²), got {tau!r}")
    pvar = _prior_var((tm, tb), A - 1)
    cov = torch.linalg.inv(K + torch.diag(1.0 / pvar))
    cov = 0.5 * (cov + cov.T)
    # Δ's value, gradient and Hessian at θ₀ with the weights moving with the positions (module
    # docstring, "Positions"): the gradient by autograd, the Hessian by central differences of it
    value, grad = exact.delta(r0, mu, pvar, with_grad=True)
    free = [c for c in range(3 * A) if c // 3 != lik.reference]
    hess = torch.zeros(3 * A, 3 * A, dtype=lik.dtype)
    for c in free:
        e = torch.zeros(3 * A, dtype=lik.dtype)
        e[c] = _HESS_STEP
        gp = exact.delta(r0 + e.view(A, 3), mu, pvar, with_grad=True)[1]
        gm = exact.delta(r0 - e.view(A, 3), mu, pvar, with_grad=True)[1]
        hess[:, c] = (gp - gm) / (2 * _HESS_STEP)
    hess[:, [c for c in range(3 * A) if c not in free]] = 0.0
    hess = 0.5 * (hess + hess.T)
    grad[[c for c in range(3 * A) if c not in free]] = 0.0
    term = BlockMarginal(value=value, grad=grad, hess=hess, r0=r0.reshape(-1).clone(), cov=cov, tau=(tm, tb),
                         record={}, common_J=Jc, common_center=c_hat,
                         common_std=_prior_var((tm, tb), 1).sqrt() / math.sqrt(A), fhat=fhat, inv_scale=1.0 / s,
                         mu_dev=mu, pvar=pvar)
    sd = (Z @ cov @ Z.T).diagonal().clamp_min(0).sqrt().reshape(A, 12)
    term.record = {
        "how": "every triad's linear error E_k, b_k ~ N(0, tau^2) (array frame, iid entries), the report's blocks "
               "its centre; the triads' deviations from their mean integrated out at omega-bar (the regressor held at "
               "the mode, the weights moving with the positions: the exact integral's value, gradient and Hessian "
               "there), the part they share cut (see 'common')",
        "tau_matrix": tm, "tau_bias_m_s2": tb, "tau_from": "type-II ML" if gain is not None else "given",
        "evidence_gain_nats": gain,
        "posterior_std_matrix_median": float(sd[:, :9].median()),
        "triads": A,
        "common": "cut: the 3x3 and offset every triad shares are not fitted; the report's common part "
                  "(max |entry| %.4f) is replaced by draws from the prior's common part N(0, tau^2/A), "
                  "propagated to the positions linearly at the mode" % float(c_hat[:9].abs().max()),
    }
    return term


def marginal_scores(lik, term: BlockMarginal, positions, free_columns) -> torch.Tensor:
    """(T, F) nats/m: per-sample scores of ``lik`` (the likelihood ``term`` was built on, without the
    term) with the triads' deviations γ integrated out, at relative positions ``positions`` (A, 3) m
    (reference row zero), over the free coordinates ``free_columns`` of r (A, 3) flattened — the
    meat of a sandwich for the chains' target ℓ + Δ.  Each keeps ``lik.log_lik_per_sample``'s share
    of the common determinant (the caller's convention).

    Fisher's identity, ∇_θ log ∫ p(y | θ, γ) p(γ) dγ = E_{γ | y, θ}[∇_θ log p(y | θ, γ)], sample by sample
    for the Gaussian linear model of the module docstring (X_t held)::

        E_γ[log p(y_t | θ, γ)] = log p(y_t − X_tZm | θ) − ½ tr(C X_tᵀW_t(θ)X_t) + (θ-free),

    m = (K + P⁻¹)⁻¹h, C = (K + P⁻¹)⁻¹ the posterior moments of γ at θ, held when differentiating.  So
    ψ_t = ∂_θ of ``lik``'s own term on the outputs corrected by X_tZm, plus ½∂_θ‖V_tR‖² (C = RRᵀ;
    :meth:`_ExactDelta.posterior_vv`; the latter's sum over the samples shared out evenly: per sample it is
    about 1 % of a score, and differentiating it sample by sample cost 7 s of 17 on a real recording).

    These terms are not what a meat needs: m is fitted to every sample, and ψ_t varies along γ's own
    per-sample scores s_t = Zᵀ X_tᵀW_t(e_t − X_tZm) (− P⁻¹(m − μ)/T, the prior's pull shared out, so
    that Σ_t s_t = 0), a variance the fit of m takes up.  The efficient scores (the part of ψ_t
    orthogonal to s_t in the Fisher metric) are returned:

        ψ̃_t = ψ_t + J C s_t,   J = ∂_θ(g(θ) − K(θ)m) (F × n, the joint log-likelihood's cross derivative),

    whose Newey–West meat is, for a correctly specified model, the curvature of ℓ + Δ: on data simulated
    from the model the sandwich/Laplace variance ratio is 0.98–1.04, against 2.6–2.8 with ψ_t
    (``tests/model/test_acc_block_marginal.py``).  Σ_t ψ̃_t = Σ_t ψ_t = ∇(ℓ + Δ)(θ) exactly (tested)."""
    from .unresolved_fit import per_sample_scores

    if term.fhat is None:
        raise UserError("term: expected a BlockMarginal from build_block_marginal (it keeps its regressor)")
    A, T = lik.A, lik.T
    free = list(free_columns)
    U = lik.loading_matrix() if hasattr(lik, "loading_matrix") else None
    Z = deviation_basis(A, dtype=lik.dtype)
    exact = _ExactDelta(lik, term.fhat, term.inv_scale, U, Z)
    r = lik._positions(torch.as_tensor(positions, dtype=lik.dtype))
    with torch.no_grad():
        K, g = exact.sums(r.reshape(-1))
        C = torch.linalg.inv(K + torch.diag(1.0 / term.pvar))
        C = 0.5 * (C + C.T)
        m = C @ (g + term.mu_dev / term.pvar)
        beta = (Z @ m).view(A, 12)
        E, b = beta[:, :9].reshape(A, 3, 3), beta[:, 9:]
        # X_tβ per triad k: E_k f̂_kt + b_k / s_t (module docstring, "Model")
        dy = torch.einsum("kij,tkj->tki", E, term.fhat.view(T, A, 3)) + term.inv_scale[:, None, None] * b
    if not hasattr(lik, "log_lik_per_sample"):  # the flat likelihood: the per-sample form with nothing loaded
        from .likelihood_percov import with_unresolved_motion

        lik = with_unresolved_motion(lik.untempered_copy(), torch.zeros(T, A, dtype=lik.dtype), 0.0)
    corrected = lik.with_outputs(lik.acc - dy)
    R = torch.linalg.cholesky(C)
    r0 = r.reshape(-1)

    def full(th):
        rv = r0.detach().clone().to(th.dtype)
        rv = rv.index_put((torch.as_tensor(free),), th)
        return rv

    th = r0[free].detach()
    S = per_sample_scores(lambda t: corrected.log_lik_per_sample(full(t).view(A, 3), corrected.omega.mean), th)
    # the trace term's gradient, shared out evenly like the determinant's: per sample it is ~1 % of a score
    # (its sum over the samples is tr(CK) ≤ n nats against the scores' ~T·n), a negligible part of the meat
    rv = r0.detach().clone().requires_grad_(True)
    S = S + 0.5 * torch.autograd.grad(exact.posterior_vv(rv, R).sum(), rv)[0][free] / T
    # efficient scores: less their projection on γ's own per-sample scores (see the docstring)
    dyf = dy.reshape(T, 3 * A)
    with torch.no_grad():
        sg = exact.g_per_sample(r0, dyf) + (term.mu_dev - m).div(term.pvar).div(T)  # −P⁻¹(m − μ)/T: Σ_t = 0 at m
    # J = ∂_θ(g − Km) = ∂_θ Σ_t X_tᵀW_t(e_t − X_tZm): the same sum with dy = X_tZm (no n × n per direction)
    Jg = torch.autograd.functional.jacobian(lambda v: exact.g_per_sample(v, dyf).sum(0), r0, vectorize=True,
                                            strategy="forward-mode")[:, free]  # (n, F)
    return S + sg @ (C @ Jg)


def common_shifts(term: BlockMarginal, laplace_cov, free_columns, n: int, generator: torch.Generator):
    """(n, F) position shifts (m) of the free coordinates for n draws of the common error (module
    docstring, "What is common"): β_c = c − ĉ, c ~ N(0, τ²/A) per entry, ĉ the report's common part,
    mapped by the mode's response δθ = −Σ_θ J_cᵀ β_c (Σ_θ the Laplace covariance, m², of the free
    coordinates ``free_columns`` of r (A, 3) flattened).  Added to the chains' draws of θ they give
    the cut posterior: the positions given the data, the common error from its prior alone."""
    Jc = term.common_J[:, free_columns]  # (12, F)
    S = -torch.as_tensor(laplace_cov, dtype=Jc.dtype) @ Jc.T  # (F, 12)
    eps = torch.randn(n, Jc.shape[0], generator=generator, dtype=Jc.dtype)
    beta = -term.common_center + eps * term.common_std
    return beta @ S.T


def with_block_marginal(lik, term: BlockMarginal):
    """A shallow copy of ``lik`` whose ``log_phat`` and ``log_lik_given_omega`` add ``term`` (Δ(θ))."""
    new = copy.copy(lik)
    new.block_marginal = term
    return new
