"""Type-II maximum likelihood of the per-sample covariance's scales: the unresolved jerk's scale per
|ω| band and, optionally, the board's angular jerk's scale per band, the triads' instant-error std
or the scale mixture's ν (issue #30 item 1: "a proper Gaussian prior whose scale per band is
fitted"), on the calibration's own likelihood.

The scales are fitted on the exact log p(y | ω, θ) of
:class:`~accel_bayes.model.likelihood_percov.PerSampleCovLikelihood` at a fixed geometry θ and
rates ω (the MAP's, or the gyro mean), φ_t and m_t integrated out — the same empirical-Bayes step
as the noise levels of :mod:`accel_bayes.model.noise` (with ~10⁴ samples per band the scales'
own uncertainty is ignored by the sampler).  Parameters are log s_b and log ν, by L-BFGS with
autograd; the start is a moment estimate.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..errors import UserError
from .likelihood import RaoBlackwellLikelihood
from .likelihood_percov import with_unresolved_motion
from .unresolved_cov import centred_ages

__all__ = ["UnresolvedFit", "fit_unresolved_scales", "fixed_omega_mode", "per_sample_scores"]

_LOG_NU_BOUNDS = (math.log(0.05), math.log(1e4))
_LOG_E_BOUNDS = (math.log(1e-9), math.log(1e-2))  # s: the instant error's std


@dataclass
class UnresolvedFit:
    """jerk_rms (B,) m/s³ per band; angjerk_rms (B,) rad/s³ per band or None; nu (None without
    the mixture); noise_factor the common factor
    on the noise levels chosen; loglik and loglik_flat (nats, the flat model's at the same θ, ω and
    the given noise, constants included) and their difference gain."""

    jerk_rms: torch.Tensor
    nu: float | None
    loglik: float
    loglik_flat: float
    noise_factor: float = 1.0
    instant_std: float | None = None
    loglik_no_instant: float | None = None
    angjerk_rms: torch.Tensor | None = None
    loglik_no_angjerk: float | None = None

    @property
    def gain(self) -> float:
        return self.loglik - self.loglik_flat

    @property
    def gain_instant(self) -> float | None:
        """nats the triads' instant error adds over the jerk alone (both refitted); None without it."""
        return None if self.loglik_no_instant is None else self.loglik - self.loglik_no_instant

    @property
    def gain_angjerk(self) -> float | None:
        """nats the angular jerk adds over the jerk alone (both refitted, before any instant error);
        None without it."""
        if self.loglik_no_angjerk is None:
            return None
        with_it = self.loglik if self.loglik_no_instant is None else self.loglik_no_instant
        return with_it - self.loglik_no_angjerk


def fit_unresolved_scales(lik: RaoBlackwellLikelihood, age, band, positions, omega=None, *, fit_nu: bool = False,
                          noise_factors=(1.0,), max_iter: int = 100, rate=None, fit_instant: bool = False,
                          instant_start: float = 1e-4, lever=None, age_prior=None) -> UnresolvedFit:
    """Fit the jerk scale per band (and ν with ``fit_nu``) on ``lik``'s data (module docstring).

    age (T, A) s the rows' data ages; band (T,) integer |ω| band of each sample (0 … B − 1, e.g.
    ``torch.bucketize(|ω̄|, edges, right=True)``); positions (A, 3) m; omega (T, 3) rad/s (default:
    the gyro posterior mean).  Bands without samples keep scale 0.  ``noise_factors``: common
    factors f on ``lik``'s noise levels to try (the best fit over them is returned): the scale
    mixture's spread is not the Gaussian's rms, so with ``fit_nu`` the noise level moves too.
    ``fit_instant`` with ``rate`` (T, A, 3) m/s³ (the triads' output rates): one std e (s) of
    the triads' own instant error fitted with the scales, from the jerk-only fit and
    ``instant_start`` s (:class:`~.likelihood_percov.PerSampleCovLikelihood`'s general path).
    ``lever`` (A, 3) m, the triads' nominal positions: the board's angular jerk loaded by them is
    fitted too, its own scale per band, from the jerk-only fit (then the instant error, if asked,
    from that fit).  ``age_prior`` None or {"age_var": (A,) s², "age_rate": (T, A, 3) m/s³ or None}:
    the random data age of triads without a clock (``PerSampleCovLikelihood``'s "Unknown ages"),
    loaded with the scales being fitted."""
    kw = {"age_prior": age_prior}
    if fit_instant or lever is not None:
        if fit_instant and rate is None:
            raise UserError("rate: fit_instant needs the triads' output rates (T, A, 3) m/s³")
        if len(noise_factors) != 1 or float(noise_factors[0]) != 1.0 or fit_nu:
            raise UserError("fit_instant, lever: expected the given noise levels and no scale mixture")
        jerk = _fit_one(lik, age, band, positions, omega, False, max_iter, **kw)
        last = jerk
        if lever is not None:
            last = _fit_one(lik, age, band, positions, omega, False, max_iter, lever=lever, start=jerk.jerk_rms, **kw)
            last.loglik_no_angjerk = jerk.loglik
        if fit_instant:
            both = _fit_one(lik, age, band, positions, omega, False, max_iter, rate=rate, instant_start=instant_start,
                            start=last.jerk_rms, lever=lever, start_rot=last.angjerk_rms, **kw)
            both.loglik_no_instant, both.loglik_no_angjerk = last.loglik, last.loglik_no_angjerk
            last = both
        return last
    best = None
    for f in noise_factors:
        f = float(f)
        if not (math.isfinite(f) and f > 0):
            raise UserError(f"noise_factors: expected factors > 0, got {f!r}")
        scaled = lik if f == 1.0 else RaoBlackwellLikelihood(lik.acc, lik.omega, lik.acc_noise_std * f, 1,
                                                             reference=lik.reference, phi_prior=lik.phi_prior)
        fit = _fit_one(scaled, age, band, positions, omega, fit_nu, max_iter, **kw)
        fit.noise_factor = f
        if best is None or fit.loglik > best.loglik:
            best = fit
    if best.noise_factor != 1.0:  # the flat reference stays the one at the given noise
        with torch.no_grad():
            pos = torch.as_tensor(positions, dtype=lik.dtype, device=lik.device)
            w = lik.omega.mean if omega is None else torch.as_tensor(omega, dtype=lik.dtype, device=lik.device)
            best.loglik_flat = float(lik.log_lik_given_omega(pos, w)) + lik.log_constant
    return best


def _fit_one(lik, age, band, positions, omega, fit_nu, max_iter, rate=None, instant_start=None,
             start=None, lever=None, start_rot=None, age_prior=None) -> UnresolvedFit:
    band = torch.as_tensor(band, device=lik.device)
    if band.shape != (lik.T,) or band.dtype in (torch.float32, torch.float64) or bool((band < 0).any()):
        raise UserError(f"band: expected ({lik.T},) non-negative integers (|omega| band per sample)")
    B = int(band.max()) + 1
    omega = lik.omega.mean if omega is None else torch.as_tensor(omega, dtype=lik.dtype, device=lik.device)
    pos = torch.as_tensor(positions, dtype=lik.dtype, device=lik.device)
    with torch.no_grad():
        flat = float(lik.log_lik_given_omega(pos, omega)) + lik.log_constant
        # start: a tenth of the flat residual variance per triad explained by the term
        d2 = centred_ages(torch.as_tensor(age, dtype=lik.dtype, device=lik.device)).square().mean()
    s0 = math.sqrt(0.1 * float(lik.acc_noise_std.square().mean()) / max(float(d2), 1e-30))
    counts = torch.bincount(band, minlength=B)
    x = torch.full((B,), math.log(s0), dtype=lik.dtype, device=lik.device)
    if start is not None:  # a band fitted to 0 would start where the gradient vanishes: from s0 there
        st = torch.as_tensor(start, dtype=lik.dtype, device=lik.device)
        x = torch.where(st > 1e-3 * s0, st.clamp_min(1e-300).log(), x)
    x.requires_grad_(True)
    xr = None
    if lever is not None:
        lev = torch.as_tensor(lever, dtype=lik.dtype, device=lik.device)
        # the same start for ω̈ × r: a tenth of the residual variance over the mean squared lever arm
        r2 = float((lev - lev.mean(0)).square().sum(-1).mean() * 2 / 3)
        xr = torch.full((B,), math.log(s0 / math.sqrt(max(r2, 1e-12))), dtype=lik.dtype, device=lik.device)
        if start_rot is not None:
            st = torch.as_tensor(start_rot, dtype=lik.dtype, device=lik.device)
            xr = torch.where(st > 1e-3 * xr.exp(), st.clamp_min(1e-300).log(), xr)
        xr.requires_grad_(True)
    xn = torch.tensor(math.log(10.0), dtype=lik.dtype, device=lik.device, requires_grad=fit_nu)
    xe = None if rate is None else torch.tensor(math.log(instant_start), dtype=lik.dtype, device=lik.device,
                                                requires_grad=True)
    params = [x, xn] if fit_nu else [x]
    params += [] if xe is None else [xe]
    params += [] if xr is None else [xr]
    opt = torch.optim.LBFGS(params, max_iter=max_iter, line_search_fn="strong_wolfe", tolerance_grad=1e-7,
                            tolerance_change=1e-10)
    scale = float(lik.T)  # the objective per sample keeps L-BFGS's tolerances meaningful

    def model(x_, xn_):
        s = torch.where(counts[band] > 0, torch.exp(x_)[band], torch.zeros((), dtype=lik.dtype))
        nu = torch.exp(xn_.clamp(*_LOG_NU_BOUNDS)) if fit_nu else None
        rot = {} if xr is None else {"angjerk_std": torch.where(counts[band] > 0, torch.exp(xr)[band],
                                                                torch.zeros((), dtype=lik.dtype)), "lever": lev}
        if xe is None:
            return with_unresolved_motion(lik, age, s, nu=nu, **(age_prior or {}), **rot)
        # e below ~1 ns loads nothing measurable: the bound keeps the line search finite as e → 0
        return with_unresolved_motion(lik, age, s, nu=nu, rate=rate, instant_std=torch.exp(xe.clamp(*_LOG_E_BOUNDS)),
                                      **(age_prior or {}), **rot)

    def closure():
        opt.zero_grad()
        loss = -model(x, xn).log_lik_given_omega(pos, omega) / scale
        loss.backward()
        return loss

    for _ in range(3):
        opt.step(closure)
    with torch.no_grad():
        fitted = model(x, xn)
        ll = float(fitted.log_lik_given_omega(pos, omega)) + fitted.log_constant
        s = torch.where(counts > 0, torch.exp(x), torch.zeros((), dtype=lik.dtype))
    out = UnresolvedFit(s.detach(), float(torch.exp(xn.detach().clamp(*_LOG_NU_BOUNDS))) if fit_nu else None, ll,
                        flat)
    if xe is not None:
        out.instant_std = float(torch.exp(xe.detach().clamp(*_LOG_E_BOUNDS)))
    if xr is not None:
        out.angjerk_rms = torch.where(counts > 0, torch.exp(xr.detach()), torch.zeros((), dtype=lik.dtype))
    return out


def fixed_omega_mode(lik, pos0, *, z=None, prior_mean=None, prior_std=None, newton: bool = False):
    """(θ̂ (A, 3) m, Laplace covariance (3(A−1), 3(A−1)) m² of the free coordinates, IMU-major) of
    log p(y | ω̄, θ) (ω fixed at ``lik``'s gyro posterior mean), or with ``z`` (standard normals
    (T, N, 3)) of log p̂(y | θ) on those draws (ω integrated with common random numbers: a smooth
    function of θ).  ``prior_mean`` (A, 3) m and ``prior_std`` m add the Gaussian prior on the
    positions (the calibration's).  L-BFGS from ``pos0`` (A, 3) m, Hessian by autograd; any
    likelihood of :mod:`.likelihood` or :mod:`.likelihood_percov`.  ``newton``: damped Newton steps
    with the autograd Hessian instead (halved until the objective falls), for a start near the mode
    where the gradient is steep: L-BFGS's first step is the raw gradient, metres when the gradient is
    ~10⁴ nats/m, which can land on collinear positions (the accelerometers' block term of
    :mod:`.acc_block_marginal` added at the previous mode)."""
    A, ref = lik.A, lik.reference
    free = [k for k in range(A) if k != ref]
    dtype = lik.dtype
    pos0 = torch.as_tensor(pos0, dtype=dtype)
    mu = None if prior_mean is None else torch.as_tensor(prior_mean, dtype=dtype)
    mu = None if mu is None else (mu - mu[ref])[free].reshape(-1)

    def full(th):
        P = torch.zeros(A, 3, dtype=th.dtype)
        P[free] = th.reshape(A - 1, 3)
        return P

    def nll(th):
        out = -lik.log_phat(full(th), z=z) if z is not None else -lik.log_lik_given_omega(full(th), lik.omega.mean)
        if mu is not None:
            out = out + 0.5 * ((th - mu) / float(prior_std)).square().sum()
        return out

    th = (pos0 - pos0[ref])[free].reshape(-1).clone().requires_grad_(True)
    if newton:
        x = th.detach().clone()
        f = float(nll(x))
        for _ in range(50):
            g = torch.autograd.functional.jacobian(nll, x)
            H = torch.autograd.functional.hessian(nll, x)
            L, info = torch.linalg.cholesky_ex(0.5 * (H + H.T))
            d = -torch.cholesky_solve(g[:, None], L)[:, 0] if int(info) == 0 else -g / float(H.diagonal().abs().max())
            if float(-(g @ d)) < 1e-10:  # the Newton decrement: at the mode to round-off
                break
            for _ in range(40):
                f_new = float(nll(x + d))
                if math.isfinite(f_new) and f_new <= f:
                    break
                d = 0.5 * d
            else:
                break
            x, f = x + d, f_new
        H = torch.autograd.functional.hessian(nll, x)
        return full(x), torch.linalg.inv(H)
    opt = torch.optim.LBFGS([th], max_iter=100, line_search_fn="strong_wolfe", tolerance_grad=1e-10,
                            tolerance_change=1e-14)

    def closure():
        opt.zero_grad()
        loss = nll(th)
        loss.backward()
        return loss

    for _ in range(3):
        opt.step(closure)
    H = torch.autograd.functional.hessian(nll, th.detach())
    return full(th.detach()), torch.linalg.inv(H)


def per_sample_scores(log_density, theta: torch.Tensor) -> torch.Tensor:
    """(T, n): the Jacobian ∂ℓ_t/∂θ of ``log_density`` (θ (n,) ↦ (T,) per-sample log-densities,
    nats), by forward-mode products (n ≪ T: one pass per coordinate of θ)."""
    th = torch.as_tensor(theta, dtype=torch.float64).detach()
    cols = [torch.autograd.functional.jvp(log_density, th, torch.eye(len(th), dtype=th.dtype)[i])[1]
            for i in range(len(th))]
    return torch.stack(cols, -1)
