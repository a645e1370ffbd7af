"""MAP estimate of the [C21] array geometry with its Laplace covariance (DESIGN §4, §6).

Model ([C21] eq. 5; DESIGN §3.1, §4), per sample t, array frame, A accelerometer triads::

    y_t = G(θ) u(ω_t) + H(θ) φ_t + e_t,   e_t ~ N(0, Q),  Λ = Q⁻¹ diagonal,
    φ_t = [ω̇_t; s_t]              flat prior → integrated out in closed form,
    ω_t ~ N(ω̄_t, P_t)             the gyroscope posterior p(ω_t | y_t^g) ([C21] eq. 15, 30),
    θ = {r_k − r_ref, k ≠ ref} ~ N(μ, σ_r² I)   Gaussian prior (σ_r = 3 mm by default).

The MAP is the mode of the *same* posterior the PmMH sampler targets, jointly in (θ, ω_{1:T})::

    −log p(θ, ω | y) = ½ Σ_t ‖y_t − G u(ω_t)‖²_S + (T/2) log|M(θ)|
                       + ½ Σ_t ‖L_t⁻¹(ω_t − ω̄_t)‖² + ½ ‖(θ − μ)/σ_r‖² + const,

with M = HᵀΛH and S = Λ − ΛHM⁻¹HᵀΛ.  Note the (T/2)·log|M(θ)| — the corrected power −½ of
DESIGN §4, not [C21] eq. 25's |M|¹.  The S-norm is written as a least-squares residual by
variable projection: r_t = Λ^{1/2}(y_t − G u(ω_t) − H φ̂_t), φ̂_t = M⁻¹HᵀΛ(y_t − G u(ω_t)), whose
squared norm is exactly ‖y_t − G u(ω_t)‖²_S; differentiating through φ̂_t (autodiff) gives the
full variable-projection Jacobian (Golub–Pereyra), so LM sees the right derivatives.  The
log-determinant is an :class:`~accel_bayes.inference.lm.ExtraCost` with exact gradient and
Hessian.  Solved by the structured LM of :mod:`accel_bayes.inference.lm`: θ global, ω_t local
(block-diagonal), cost per iteration linear in T.

Laplace covariance: the exact Hessian of −log p(θ, ω | y) at the mode (autodiff, all second-order
terms, the log|M| Hessian included), ω marginalised by the Schur complement
S_θ = H_θθ − Σ_t H_θω_t H_ω_tω_t⁻¹ H_ω_tθ, covariance S_θ⁻¹.  ``hessian="gauss_newton"`` gives the
Gauss–Newton variant (what the Cramér–Rao bound is the expectation of).

Constants: ``log_posterior`` is −(the cost above) — the Gaussian normalisers (which do not depend
on θ or ω) are dropped, as in :mod:`accel_bayes.model.likelihood`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from ..constants import DEFAULT_PRIOR_STD
from ..errors import DivergenceError, UserError
from ..physics.geometry import skew
from ..model.likelihood import as_acc_tensor, positions_from_theta, theta_from_positions
from ..physics.models import G_matrix, H_matrix, acc_noise_std_per_axis, per_axis, u_of_omega
from ..physics.jacobians import d2u_domega2, df_dr, du_domega
from .lm import ExtraCost, GlobalResidual, LevenbergMarquardt, LMResult, Problem, SampleResidual, Variable
from .lm.linear import NotPositiveDefinite, SchurComplementSolver, cholesky

__all__ = ["MAPResult", "MAPDivergence", "fit_map", "fit_map_recording", "build_map_problem"]


class MAPDivergence(DivergenceError):
    """The MAP left the region where the model makes sense (DESIGN §6, [S16] §VI): positions far
    outside the prior, collapsed/degenerate geometry or non-finite values."""


@dataclass
class MAPResult:
    """Outcome of :func:`fit_map`.

    positions : (A, 3) m, array frame, relative to the reference triad (its row is 0).
    theta : (A−1, 3) m — the same without the reference row ([C21] θ).
    omega : (T, 3) rad/s — the ω_t at the joint mode.
    laplace_cov : (3(A−1), 3(A−1)) m² — Laplace covariance of vec(θ) (row-major: triad, axis),
        ω marginalised (Schur complement of the exact Hessian, log|M| term included).
    log_posterior : float — −cost at the mode (θ-free constants dropped, module docstring).
    cost_terms : dict — the cost split: "acc" (½Σ‖·‖²_S), "logdetM" ((T/2) log|M|), "gyro", "prior".
    log : per-iteration LM log; converged, reason, n_iter : LM outcome.
    reference : int; imu_labels : tuple of the IMU labels of the rows (fit_map_recording) or None.
    selection, sample_index : (fit_map_recording) the :class:`~accel_bayes.prep.selection.Selection`
        of the samples fitted and its kept indices into the recording; None otherwise.
    phi_prior : the :class:`~accel_bayes.model.phi_prior.PhiPrior` of the target, None for flat φ.
    lm : the :class:`~accel_bayes.inference.lm.LMResult` (problem included) for further use.
    """

    positions: torch.Tensor
    theta: torch.Tensor
    omega: torch.Tensor
    laplace_cov: torch.Tensor
    log_posterior: float
    cost_terms: dict
    log: list
    converged: bool
    reason: str
    n_iter: int
    reference: int
    imu_labels: tuple | None = None
    lm: LMResult | None = field(default=None, repr=False)
    selection: object = field(default=None, repr=False)
    sample_index: object = field(default=None, repr=False)
    phi_prior: object = field(default=None, repr=False)

    def position_cov(self) -> torch.Tensor:
        """(A, 3, 3) per-triad marginal covariance blocks (zeros for the reference)."""
        A = self.positions.shape[0]
        blocks = self.laplace_cov.reshape(A - 1, 3, A - 1, 3).diagonal(dim1=0, dim2=2).permute(2, 0, 1)
        return torch.cat((blocks[:self.reference], blocks.new_zeros(1, 3, 3), blocks[self.reference:]), 0)

    def position_std(self) -> torch.Tensor:
        """(A, 3) m marginal standard deviations (zeros for the reference)."""
        return torch.sqrt(torch.diagonal(self.position_cov(), dim1=-2, dim2=-1).clamp_min(0))


def build_map_problem(acc, omega_mean, omega_cov, acc_noise_std, *, reference=0, prior_mean=None, prior_std=DEFAULT_PRIOR_STD,
                      init_positions=None, init_omega=None, analytic: bool = True, local_newton: bool = True,
                      phi_prior=None, dtype=torch.float64, device=None) -> Problem:
    """The [C21] MAP as an LM :class:`~accel_bayes.inference.lm.Problem` (see :func:`fit_map`).

    Globals: "theta" (A−1, 3).  Locals: ω (T, 3).  Residual groups "acc" (T, 3A), "gyro" (T, 3),
    "prior" (3(A−1),) if ``prior_std`` is not None; extra term "logdetM".

    analytic : use the closed-form derivatives below (default; ~10× faster than autodiff at the
        32-IMU size); False leaves every derivative to autodiff (tests compare the two).
    local_newton : give LM the exact ω_t–ω_t Hessian blocks (``SampleResidual.local_hessian``;
        cheap because u(ω) is quadratic: Σ_m r_m ∂²r_m/∂ω² = −(r_tᵀGw) ∂²u).  Default True: on
        real recordings the residuals are large (model mismatch) and Gauss–Newton alone then
        crawls; the optimum is the same either way.

    Closed forms (whitened: Hw = Λ^{1/2}H, Gw = Λ^{1/2}G, M = HwᵀHw, z_t = Λ^{1/2}y_t − Gw u(ω_t),
    φ̂_t = M⁻¹Hwᵀz_t, r_t = z_t − Hw φ̂_t = P⊥ z_t):

    * ∂r_t/∂ω_t = −P⊥ Gw ∂u/∂ω (P⊥ does not depend on ω).
    * ∂r_t/∂r_k = −P⊥ Q_t,k − Hw M⁻¹ C_t,k (variable projection, Golub–Pereyra), with
      Q_t,k = Λ_k^{1/2}(Ω(ω_t)² + Ω(ω̂̇_t)) in the rows of triad k (the kinematic Jacobian
      ∂f_k/∂r_k at φ = φ̂_t) and C_t,k = [−Ω(Λ_k^{1/2} r_t,k); 0] (= ∂Hwᵀ/∂r_k applied to r_t).
    * log|M|: ∂ = tr(M⁻¹ ∂M), ∂² = tr(M⁻¹ ∂²M) − tr(M⁻¹ ∂M M⁻¹ ∂M), with
      ∂M/∂r_k,a = E_aᵀΛ_kH_k + H_kᵀΛ_kE_a, E_a = [−Ω(e_a) 0], and ∂²M within one triad only.

    phi_prior : None (flat φ, [C21]) or a proper prior N(0, F) on φ_t (anything
    :meth:`~accel_bayes.model.phi_prior.PhiPrior.coerce` takes).  It enters as six pseudo-
    observations 0 = W φ_t + v_t per sample (WᵀW = F⁻¹, v_t ~ N(0, I)): the stacked design
    H' = [Hw; W] (θ-free extra rows), z' = [z; 0], G' = [Gw; 0], so M becomes M + F⁻¹ everywhere
    and the "acc" residual gets 6 more columns, r' = [z − Hwφ̂; −Wφ̂] with ‖r'‖² = ‖y − Gu‖²_{S_F}
    (:class:`~accel_bayes.model.likelihood.RaoBlackwellLikelihood` with ``phi_prior``).  The closed forms
    above carry over with H' for H and zeros in the extra rows of Q and K: the extra rows have no
    θ- or ω-dependence of their own.
    """
    acc = as_acc_tensor(acc, dtype=dtype, device=device)
    T, A, _ = acc.shape
    if not 0 <= int(reference) < A:
        raise UserError(f"reference: expected an index in 0..{A - 1}, got {reference}")
    reference = int(reference)
    wbar = torch.as_tensor(omega_mean, dtype=dtype, device=acc.device)
    P = torch.as_tensor(omega_cov, dtype=dtype, device=acc.device)
    if wbar.shape != (T, 3):
        raise UserError(f"omega_mean: expected shape ({T}, 3), got {tuple(wbar.shape)}")
    if P.shape == (3, 3):
        P = P.expand(T, 3, 3)
    if P.shape != (T, 3, 3):
        raise UserError(f"omega_cov: expected shape ({T}, 3, 3) or (3, 3), got {tuple(P.shape)}")
    LP, info = torch.linalg.cholesky_ex(P)
    if bool((info != 0).any()):
        raise UserError("omega_cov: expected symmetric positive-definite 3×3 covariances")
    Linv = torch.linalg.solve_triangular(LP, torch.eye(3, dtype=dtype, device=acc.device).expand(T, 3, 3), upper=False)
    sqrt_lam = acc_noise_std_per_axis(acc_noise_std, A, dtype=dtype, device=acc.device).reshape(3 * A).reciprocal()

    if prior_mean is not None:
        prior_mean = torch.as_tensor(prior_mean, dtype=dtype, device=acc.device)
        if prior_mean.shape != (A, 3):
            raise UserError(f"prior_mean: expected positions of shape ({A}, 3), got {tuple(prior_mean.shape)}")
    if init_positions is None:
        if prior_mean is None:
            raise UserError("fit_map: give prior_mean or init_positions (a starting geometry)")
        init_positions = prior_mean
    init_positions = torch.as_tensor(init_positions, dtype=dtype, device=acc.device)
    if init_positions.shape != (A, 3):
        raise UserError(f"init_positions: expected shape ({A}, 3), got {tuple(init_positions.shape)}")
    theta0 = theta_from_positions(init_positions, reference)
    omega0 = wbar.clone() if init_omega is None else torch.as_tensor(init_omega, dtype=dtype, device=acc.device)

    y = acc.reshape(T, 3 * A)
    from ..model.phi_prior import PhiPrior

    phi_prior = PhiPrior.coerce(phi_prior, dtype=dtype, device=acc.device)
    # F⁻¹ (6, 6) and W with WᵀW = F⁻¹ (the pseudo-observation rows); zeros for the flat prior
    Fi = torch.zeros(6, 6, dtype=dtype, device=acc.device) if phi_prior is None else phi_prior.precision
    W = None if phi_prior is None else torch.linalg.cholesky(Fi).T

    def normal_matrix(Hw):
        return Hw.transpose(-1, -2) @ Hw + Fi  # M + F⁻¹ (M for the flat prior)

    def with_prior_rows(res, phi):
        return res if W is None else torch.cat((res, -(phi @ W.T)), -1)

    def acc_residual(g, x, data):
        r = positions_from_theta(g["theta"], reference, A)
        Hw = sqrt_lam.unsqueeze(-1) * H_matrix(r)  # Λ^{1/2} H
        Gw = sqrt_lam.unsqueeze(-1) * G_matrix(r)
        L = torch.linalg.cholesky(normal_matrix(Hw))
        z = sqrt_lam * data - u_of_omega(x) @ Gw.transpose(-1, -2)  # Λ^{1/2}(y − G u)
        phi = torch.cholesky_solve((z @ Hw).transpose(-1, -2), L).transpose(-1, -2)
        return with_prior_rows(z - phi @ Hw.transpose(-1, -2), phi)

    def gyro_residual(g, x, data):
        wb, Li = data
        return (Li @ (x - wb).unsqueeze(-1)).squeeze(-1)

    def gyro_jac(g, x, data):
        return {}, data[1]

    def logdet(g):
        r = positions_from_theta(g["theta"], reference, A)
        Hw = sqrt_lam.unsqueeze(-1) * H_matrix(r)
        L = torch.linalg.cholesky(normal_matrix(Hw))
        return T * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)

    keep = [k for k in range(A) if k != reference]
    n = 3 * (A - 1)
    slA = sqrt_lam.reshape(A, 3)
    lamA = slA * slA
    eye3 = torch.eye(3, dtype=dtype, device=acc.device)
    Om = skew(eye3)  # Ω(e_a), (3, 3, 3)
    Ea = torch.cat((-Om, torch.zeros_like(Om)), -1)  # ∂H_k/∂r_k,a = [−Ω(e_a) 0], (3, 3, 6)

    def acc_jac(g, x, data):
        r = positions_from_theta(g["theta"], reference, A)
        Hw = sqrt_lam.unsqueeze(-1) * H_matrix(r)
        Gw = sqrt_lam.unsqueeze(-1) * G_matrix(r)
        L = torch.linalg.cholesky(normal_matrix(Hw))
        Tn = x.shape[0]
        Lb = L.expand(Tn, 6, 6)
        z = sqrt_lam * data - u_of_omega(x) @ Gw.T
        phi = torch.cholesky_solve((z @ Hw).T, L).T
        res = z - phi @ Hw.T
        Hs = Hw if W is None else torch.cat((Hw, W), 0)  # H' = [Hw; W]
        K = Gw @ du_domega(x)  # (T, 3A, 3)
        Jw = Hs @ torch.cholesky_solve(Hw.T @ K, Lb)
        Jw[:, :3 * A] -= K
        Jr = df_dr(x, phi[:, :3])  # ∂f_k/∂r_k at φ̂, (T, 3, 3)
        Qk = slA[None, :, :, None] * Jr[:, None]  # (T, A, 3, 3): rows of triad k, column axis a
        HtQ = torch.einsum("kif,tkia->tfka", Hw.reshape(A, 3, 6), Qk)[:, :, keep]  # (T, 6, A−1, 3)
        rho = (res.reshape(Tn, A, 3) * slA)[:, keep]  # Λ_k^{1/2} r_t,k
        C = torch.zeros_like(HtQ)
        C[:, :3] = -skew(rho).permute(0, 2, 1, 3)
        Jth = Hs @ torch.cholesky_solve((HtQ - C).reshape(Tn, 6, n), Lb)
        Jq = Jth[:, :3 * A].reshape(Tn, A, 3, A - 1, 3)  # a view: the −Q part goes into the data rows
        for j, k in enumerate(keep):  # A is small; the block-diagonal −Q part
            Jq[:, k, :, j, :] -= Qk[:, k]
        return {"theta": Jth}, Jw

    D2u = d2u_domega2(dtype, acc.device)  # ∂²u/∂ω_i∂ω_j (constant: u is quadratic), (6, 3, 3)

    def acc_local_hessian(g, x, data, res):
        # Σ_m r_m ∂²r_m/∂ω² with r = P⊥ z, ∂²r/∂ω² = −P⊥ Gw ∂²u and P⊥ r = r: −(rᵀGw) ∂²u
        Gw = sqrt_lam.unsqueeze(-1) * G_matrix(positions_from_theta(g["theta"], reference, A))
        return -torch.einsum("tf,fij->tij", res[..., :3 * A] @ Gw, D2u)  # G' is 0 in the prior rows

    def logdet_grad_hess(g):
        r = positions_from_theta(g["theta"], reference, A)
        Hk = H_matrix(r).reshape(A, 3, 6)
        M = torch.einsum("kif,ki,kig->fg", Hk, lamA, Hk) + Fi
        L = torch.linalg.cholesky(M)
        Minv = torch.cholesky_inverse(L)
        dM = torch.einsum("aif,ki,kig->kafg", Ea, lamA, Hk)[keep].reshape(n, 6, 6)
        dM = dM + dM.transpose(-1, -2)
        X = Minv @ dM
        grad = 0.5 * T * torch.diagonal(X, dim1=-2, dim2=-1).sum(-1)
        hess = -0.5 * T * torch.einsum("iab,jba->ij", X, X)
        P3 = Minv[:3, :3]
        d2 = 2 * torch.einsum("ij,amj,km,bmi->kab", P3, Om, lamA, Om)[keep]  # (A−1, 3, 3)
        hess = hess + 0.5 * T * torch.block_diag(*d2.unbind(0))
        value = T * torch.log(torch.diagonal(L)).sum()
        return value, grad, 0.5 * (hess + hess.T)

    residuals = [SampleResidual(acc_residual, data=y, jac=acc_jac if analytic else None, name="acc",
                                local_hessian=acc_local_hessian if local_newton else None),
                 SampleResidual(gyro_residual, data=(wbar, Linv), jac=gyro_jac if analytic else None, name="gyro")]
    if prior_std is not None:
        if prior_mean is None:
            raise UserError("prior_std given without prior_mean")
        ps = per_axis(prior_std, A, "prior_std", dtype=dtype, device=acc.device)
        ps_t = torch.cat((ps[:reference], ps[reference + 1:]), 0)
        if bool((ps_t <= 0).any()):
            raise UserError("prior_std: expected > 0")
        mu = theta_from_positions(prior_mean, reference)
        prior_jac = torch.diag(ps_t.reshape(-1).reciprocal())
        residuals.append(GlobalResidual(lambda g: ((g["theta"] - mu) / ps_t).reshape(-1),
                                        jac=(lambda g: {"theta": prior_jac}) if analytic else None, name="prior"))
    prob = Problem({"theta": Variable(theta0)}, omega0, residuals,
                   ExtraCost(logdet, grad_hess=logdet_grad_hess if analytic else None, name="logdetM"),
                   dtype=dtype, device=device)
    prob.map_info = {"A": A, "T": T, "reference": reference, "prior_mean": prior_mean, "prior_std": prior_std,
                     "omega_mean": wbar, "omega_chol": LP, "phi_prior": phi_prior}
    return prob


def _check_divergence(res: LMResult, prob: Problem, prior_mean, prior_std, reference, max_sigma=50.0) -> str | None:
    theta = res.values["theta"]
    if not (bool(torch.isfinite(theta).all()) and bool(torch.isfinite(res.locals).all()) and math.isfinite(res.cost)):
        return "non-finite positions or angular rates"
    pos = positions_from_theta(theta, reference, theta.shape[-2] + 1)
    span = float((pos - pos.mean(0)).norm(dim=-1).max())
    if span < 1e-6:
        return f"the triads collapsed to one point (span {span:.2e} m)"
    if prior_mean is not None and prior_std is not None:
        mu = theta_from_positions(torch.as_tensor(prior_mean, dtype=theta.dtype, device=theta.device), reference)
        z = float(((theta - mu).abs() / float(torch.as_tensor(prior_std).max())).max())
        if z > max_sigma:
            return f"positions moved {z:.0f} prior standard deviations from the prior mean"
    info = prob.map_info
    LP = info["omega_chol"]
    dev = torch.linalg.solve_triangular(LP, (res.locals - info["omega_mean"]).unsqueeze(-1), upper=False)
    zw = float(dev.squeeze(-1).norm(dim=-1).max())
    if zw > 1e3:
        return f"angular rates left the gyroscope posterior ({zw:.0f} standard deviations)"
    return None


def fit_map(acc, omega_mean, omega_cov, acc_noise_std, *, reference: int = 0, prior_mean=None,
            prior_std=DEFAULT_PRIOR_STD, init_positions=None, init_omega=None, max_iter: int = 100, progress: bool = False,
            hessian: str = "exact", on_divergence: str = "raise", ftol: float = 1e-12, xtol: float = 1e-10,
            gtol: float = 1e-9, damping=None, analytic: bool = True, local_newton: bool = True,
            phi_prior=None, dtype=torch.float64, device=None) -> MAPResult:
    """MAP of the accelerometer positions under the [C21] model with φ projected out (module docstring).

    Parameters
    ----------
    acc : (T, A, 3) m/s² — accelerometer triad outputs, **array frame** (rotate sensor-frame data
        with R(q)ᵀ of the orientations first, e.g. ``Recording.acc_tensor("array")``).
    omega_mean : (T, 3) rad/s, omega_cov : (T, 3, 3) or (3, 3) (rad/s)² — the gyroscope posterior
        N(ω̄_t, P_t) ([C21] eq. 15/30; :func:`accel_bayes.model.gyro_posterior.gyro_posterior`).
    acc_noise_std : scalar, (A,) or (A, 3) m/s² — white-noise std per triad/axis (Λ = diag σ⁻²).
    reference : row of the reference triad (origin, r_ref ≡ 0).
    prior_mean : (A, 3) m positions (taken relative to the reference); prior_std : scalar, (A,)
        or (A, 3) m (default 3 mm), or None for a flat prior.
    init_positions : (A, 3) starting geometry (default: prior_mean); init_omega : (T, 3) (default ω̄).
    max_iter, ftol, xtol, gtol, damping, progress : LM settings (:class:`~.lm.LevenbergMarquardt`).
    hessian : "exact" (default) or "gauss_newton" — which Hessian the Laplace covariance uses.
    analytic, local_newton : derivative options of :func:`build_map_problem` (defaults: closed
        forms, Newton model in the ω blocks).
    phi_prior : None (flat φ, [C21]) or a proper prior N(0, F) on φ_t = [ω̇_t; s_t] (a
        :class:`~accel_bayes.model.phi_prior.PhiPrior` or what it coerces); the same target as
        :class:`~accel_bayes.model.likelihood.RaoBlackwellLikelihood` with that ``phi_prior``.
    on_divergence : "raise" (default, :class:`MAPDivergence`), "warn" or "ignore" — what to do
        when the solution is detectably diverged (DESIGN §6); with "warn"/"ignore" the result has
        ``converged=False`` and ``reason`` starting with "diverged".

    Returns a :class:`MAPResult`.
    """
    if on_divergence not in ("raise", "warn", "ignore"):
        raise UserError(f"on_divergence: expected 'raise', 'warn' or 'ignore', got {on_divergence!r}")
    prob = build_map_problem(acc, omega_mean, omega_cov, acc_noise_std, reference=reference, prior_mean=prior_mean,
                             prior_std=prior_std, init_positions=init_positions, init_omega=init_omega,
                             analytic=analytic, local_newton=local_newton, phi_prior=phi_prior, dtype=dtype,
                             device=device)
    reference = prob.map_info["reference"]
    lm = LevenbergMarquardt(damping, max_iter=max_iter, ftol=ftol, xtol=xtol, gtol=gtol, progress=progress,
                            desc="MAP").solve(prob)
    converged, reason = lm.converged, lm.reason
    why = _check_divergence(lm, prob, prior_mean, prior_std, reference)
    if why is not None:
        msg = f"MAP diverged: {why}; restart from a better init_positions (e.g. the nominal design)"
        if on_divergence == "raise":
            raise MAPDivergence(msg)
        if on_divergence == "warn":
            import warnings

            warnings.warn(msg, RuntimeWarning, stacklevel=2)
        converged, reason = False, f"diverged: {why}"
        cov = torch.full((prob.n_free, prob.n_free), float("nan"), dtype=dtype, device=lm.locals.device)
    else:
        try:
            cov = lm.covariance(hessian)
        except NotPositiveDefinite:
            cov = torch.full((prob.n_free, prob.n_free), float("nan"), dtype=dtype, device=lm.locals.device)
            converged, reason = False, f"{reason}; Hessian not positive definite at the end point (not a minimum)"
    theta = lm.values["theta"]
    terms = prob.cost_terms(lm.values, lm.locals)
    return MAPResult(positions=positions_from_theta(theta, reference, theta.shape[-2] + 1), theta=theta, omega=lm.locals,
                     laplace_cov=cov, log_posterior=-lm.cost, cost_terms=terms, log=lm.log, converged=converged,
                     reason=reason, n_iter=lm.n_iter, reference=reference, lm=lm,
                     phi_prior=prob.map_info["phi_prior"])


def fit_map_recording(prepared, *, gyro_method: str = "sample_cov", prior_std=DEFAULT_PRIOR_STD, prior_mean=None,
                      phi_prior="empirical", dtype=torch.float64, device=None, **kw) -> MAPResult:
    """:func:`fit_map` on a :class:`~accel_bayes.prep.prepared.PreparedRecording` (or a Recording,
    prepared with :func:`~accel_bayes.prep.prepared.prepare_recording`'s defaults).

    Data preparation is the record's (which IMUs, which samples, the array frame); the gyroscope
    posterior is ``gyro_method``'s ("sample_cov" = [C21] eq. 30 as printed, "sample_cov_mean",
    "calibrated"), as in :meth:`accel_bayes.model.likelihood.RaoBlackwellLikelihood.from_recording`.
    The prior mean is the nominal design of the used IMUs (relative to the reference) unless
    given.  Rows of the result follow ``result.imu_labels``; ``result.selection`` is the Selection
    used and ``result.sample_index`` its kept indices.  ``phi_prior``: None or "flat" (flat φ,
    [C21]), "empirical" (:func:`accel_bayes.model.phi_prior.empirical_phi_prior` at the prior mean,
    with the recording's stated noise; as ``calibrate`` does) or a given prior; the one used is
    ``result.phi_prior``.  Other keywords go to :func:`fit_map`; the sample-selection keywords of
    0.1 (``select=``, ``min_rotation=``, ``drop_clipped=``, …) are a TypeError.
    """
    import dataclasses

    from ..model.likelihood import RaoBlackwellLikelihood
    from ..prep.prepared import refuse_removed_keywords

    refuse_removed_keywords("fit_map_recording", kw)
    lik = RaoBlackwellLikelihood.from_recording(prepared, num_draws=1, gyro_method=gyro_method, dtype=dtype,
                                                device=device)
    if prior_mean is None:
        prior_mean = lik.nominal_positions.to(dtype=dtype, device=device)
    if isinstance(phi_prior, str):
        from ..model.phi_prior import PHI_PRIOR_CHOICES, empirical_phi_prior

        if phi_prior not in PHI_PRIOR_CHOICES:
            raise UserError(f"phi_prior: expected one of {PHI_PRIOR_CHOICES} or a prior covariance, got {phi_prior!r}")
        phi_prior = None if phi_prior == "flat" else empirical_phi_prior(lik.acc, lik.omega.mean, lik.acc_noise_std,
                                                                           torch.as_tensor(prior_mean, dtype=dtype))
    res = fit_map(lik.acc, lik.omega.mean, lik.omega.cov, lik.acc_noise_std, reference=lik.reference,
                  prior_mean=prior_mean, prior_std=prior_std, phi_prior=phi_prior, dtype=dtype, device=device, **kw)
    return dataclasses.replace(res, imu_labels=tuple(lik.imu_labels), sample_index=lik.sample_index,
                               selection=lik.selection)
