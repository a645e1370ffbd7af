"""Generic (physics-free) residual models for held-out scoring (DESIGN §7.2.1), and the same
models with the ``unresolved_motion`` term added to their covariance (the physics model's
remainders).

Every model is a zero-mean density of one sensor's array-frame residuals of a sample,
y_t (K, 3) in the sensor's units, with an |ω| band b(t) in [0, B) (edges from the source); all
K triads enter (the held-out scoring keeps the samples where they do):

- :class:`BandedWhite`   — y_kt ~ N(0, v_kb I₃) independently per IMU;
- :class:`TriadT`        — y_kt ~ t_ν_k(0, v_kb I₃) independently per IMU (one scale mixture per triad);
- :class:`SampleT`       — y_t (3K) ~ t_ν(0, diag(v_kb) ⊗ I₃) (one scale mixture per sample);
- :class:`FullCov`       — y_t (3K) ~ N(0, Σ_b), a full cross-IMU covariance per band.

``BandedWhite``, ``SampleT`` and ``FullCov`` take optional centred data ages d (T, K) s and a
scale s_b per band: the covariance (scale matrix for ``SampleT``) gains s²_b (d dᵀ ⊗ I₃), the
unresolved motion of :mod:`accel_bayes.mismatch.unresolved`, evaluated by its exact low-rank
identity.  Fits are maximum likelihood: closed form (white, full covariance), EM with the degrees
of freedom by ECME (t models), EM for the full covariance with the low-rank term, L-BFGS for the
multivariate t with it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from scipy.optimize import minimize_scalar

from .unresolved import fit_scales, gauss_logpdf, loadings, lowrank_terms, t_logpdf

__all__ = ["BandedWhite", "TriadT", "SampleT", "FullCov", "describe"]

_NU_BOUNDS = (math.log(0.3), math.log(1e4))  # degrees of freedom searched (a t at 1e4 is Gaussian)


def _band_mean(x: torch.Tensor, lab: torch.Tensor, B: int, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Per band the (weighted) mean over samples of x (T, ...) → (B, ...)."""
    oh = torch.nn.functional.one_hot(lab, B).to(x.dtype)
    if weights is not None:
        oh = oh * weights[:, None]
    num = torch.einsum("tb,t...->b...", oh, x)
    return num / oh.sum(0).clamp_min(1e-300).reshape((B,) + (1,) * (x.dim() - 1))


def _fit_nu(loglik_of_nu) -> float:
    """The degrees of freedom maximising ``loglik_of_nu(nu)`` (a float), searched on log ν."""
    r = minimize_scalar(lambda x: -loglik_of_nu(math.exp(x)), bounds=_NU_BOUNDS, method="bounded",
                        options={"xatol": 1e-3})
    return float(math.exp(r.x))


def _no_term(y, d, s2):
    return d is None or s2 is None or not bool((torch.as_tensor(s2) > 0).any())


@dataclass
class BandedWhite:
    """White variance per IMU and |ω| band, v (K, B) units²; with ``s`` (B,) the unresolved
    motion's scale per band (units/s) added through the data ages."""

    v: torch.Tensor
    s: torch.Tensor | None = None

    @classmethod
    def fit(cls, y, lab, B, d=None) -> "BandedWhite":
        """ML fit; with d (T, K) also the unresolved scales (:func:`~.unresolved.fit_scales`)."""
        w = torch.ones(y.shape[:2], dtype=y.dtype)
        if d is None:
            return cls(_band_mean((y ** 2).mean(-1), lab, B).T.contiguous())
        _, lv, ls, *_ = fit_scales(y, d, w, lab, B, std=False)
        return cls(torch.exp(lv), torch.exp(0.5 * ls))

    def logpdf(self, y, lab, d=None) -> torch.Tensor:
        """Per-sample log density (nats, (T,))."""
        v = self.v[:, lab].T[:, :, None].expand_as(y).reshape(len(y), -1)
        if self.s is None or d is None:
            quad = (y.reshape(len(y), -1) ** 2 / v).sum(-1)
            return gauss_logpdf(quad, torch.log(v).sum(-1), v.shape[1])
        quad, ld = lowrank_terms(y.reshape(len(y), -1), loadings(d), (self.s[lab] ** 2)[:, None].expand(len(y), 3), v=v)
        return gauss_logpdf(quad, ld, v.shape[1])


@dataclass
class TriadT:
    """Student-t per triad: y_kt ~ t_ν_k(0, v_kb I₃); v (K, B) units², nu (K,)."""

    v: torch.Tensor
    nu: torch.Tensor

    def logpdf_triads(self, y, lab) -> torch.Tensor:
        """(T, K) log density of each triad (nats)."""
        v = self.v[:, lab].T
        return t_logpdf((y ** 2).sum(-1) / v, 3 * torch.log(v), 3, self.nu[None, :])

    def logpdf(self, y, lab, d=None) -> torch.Tensor:
        """Per-sample log density (nats, (T,)); ``d`` is ignored (no low-rank term in this model)."""
        return self.logpdf_triads(y, lab).sum(1)

    @classmethod
    def fit(cls, y, lab, B, *, n_iter: int = 60, tol: float = 1e-7) -> "TriadT":
        """ML by EM (weights u = (ν + 3)/(ν + |y|²/v)) with ν_k by ECME, per IMU."""
        r2 = (y ** 2).sum(-1)  # (T, K)
        K = y.shape[1]
        model = cls(_band_mean(r2 / 3, lab, B).T.contiguous(), torch.full((K,), 10.0, dtype=y.dtype))
        prev = -math.inf
        for _ in range(n_iter):
            q = r2 / model.v[:, lab].T
            u = (model.nu[None, :] + 3) / (model.nu[None, :] + q)
            model.v = torch.stack([_band_mean(u[:, k] * r2[:, k] / 3, lab, B) for k in range(K)])
            nu = []
            for k in range(K):
                vk = model.v[k, lab]
                qk, ldk = r2[:, k] / vk, 3 * torch.log(vk)
                nu.append(_fit_nu(lambda n: float(t_logpdf(qk, ldk, 3, n).sum())))
            model.nu = torch.as_tensor(nu, dtype=y.dtype)
            cur = float(model.logpdf(y, lab).sum())
            if abs(cur - prev) < tol * abs(cur):
                break
            prev = cur
        return model


@dataclass
class SampleT:
    """Multivariate t per sample: y_t ~ t_ν(0, diag(v_kb) ⊗ I₃ [+ s²_b d dᵀ ⊗ I₃]); v (K, B)
    units², nu scalar, ``s`` (B,) units/s or None."""

    v: torch.Tensor
    nu: float
    s: torch.Tensor | None = None

    def _terms(self, y, lab, d):
        T = len(y)
        v = self.v[:, lab].T[:, :, None].expand_as(y).reshape(T, -1)
        if self.s is None or d is None:
            return (y.reshape(T, -1) ** 2 / v).sum(-1), torch.log(v).sum(-1)
        return lowrank_terms(y.reshape(T, -1), loadings(d), (self.s[lab] ** 2)[:, None].expand(T, 3), v=v)

    def logpdf(self, y, lab, d=None) -> torch.Tensor:
        """Per-sample log density (nats, (T,))."""
        quad, ld = self._terms(y, lab, d)
        return t_logpdf(quad, ld, y.shape[1] * 3, self.nu)

    @classmethod
    def fit(cls, y, lab, B, d=None, *, n_iter: int = 60, tol: float = 1e-7, start: "BandedWhite | None" = None) -> "SampleT":
        """ML.  Without ``d``: EM (u = (ν + n)/(ν + q)) with ν by ECME.  With ``d``: the EM fit
        without the term, then L-BFGS on (log v, log s², log ν) from it and ``start``'s scales."""
        T, K, _ = y.shape
        n = 3 * K
        r2 = (y ** 2).sum(-1)
        model = cls(_band_mean(r2 / 3, lab, B).T.contiguous(), 10.0)
        prev = -math.inf
        for _ in range(n_iter):
            quad, ld = model._terms(y, lab, None)
            u = (model.nu + n) / (model.nu + quad)
            model.v = torch.stack([_band_mean(u * r2[:, k] / 3, lab, B) for k in range(K)])
            quad, ld = model._terms(y, lab, None)
            model.nu = _fit_nu(lambda nu: float(t_logpdf(quad, ld, n, nu).sum()))
            cur = float(model.logpdf(y, lab).sum())
            if abs(cur - prev) < tol * abs(cur):
                break
            prev = cur
        if d is None:
            return model
        s0 = start.s if start is not None and start.s is not None else torch.full((B,), 1.0, dtype=y.dtype)
        lv = torch.log(model.v).clone().requires_grad_(True)
        ls = (2 * torch.log(s0.clamp_min(1e-12))).clone().requires_grad_(True)
        lnu = torch.tensor(math.log(model.nu), dtype=y.dtype, requires_grad=True)
        opt = torch.optim.LBFGS([lv, ls, lnu], max_iter=200, line_search_fn="strong_wolfe", tolerance_grad=1e-9,
                                tolerance_change=1e-12)
        U = loadings(d)
        yf = y.reshape(T, -1)

        def closure():
            opt.zero_grad()
            v = torch.exp(lv)[:, lab].T[:, :, None].expand(T, K, 3).reshape(T, -1)
            quad, ld = lowrank_terms(yf, U, torch.exp(ls)[lab][:, None].expand(T, 3), v=v)
            loss = -t_logpdf(quad, ld, n, torch.exp(lnu).clamp(*map(math.exp, _NU_BOUNDS))).sum()
            loss.backward()
            return loss

        for _ in range(2):
            opt.step(closure)
        return cls(torch.exp(lv.detach()), float(torch.exp(lnu.detach()).clamp(*map(math.exp, _NU_BOUNDS))),
                   torch.exp(0.5 * ls.detach()))


@dataclass
class FullCov:
    """A full cross-IMU covariance per |ω| band, Σ (B, 3K, 3K) units² (channels (IMU, axis)),
    with ``s`` (B,) units/s the unresolved motion's scale or None."""

    cov: torch.Tensor
    s: torch.Tensor | None = None

    def logpdf(self, y, lab, d=None) -> torch.Tensor:
        """Per-sample log density (nats, (T,))."""
        T = len(y)
        L = torch.linalg.cholesky(self.cov)[lab]
        if self.s is None or d is None:
            U, s2 = torch.zeros(T, y.shape[1] * 3, 1, dtype=y.dtype), torch.zeros(T, 1, dtype=y.dtype)
        else:
            U, s2 = loadings(d), (self.s[lab] ** 2)[:, None].expand(T, 3)
        quad, ld = lowrank_terms(y.reshape(T, -1), U, s2, chol=L)
        return gauss_logpdf(quad, ld, y.shape[1] * 3)

    @classmethod
    def fit(cls, y, lab, B, d=None, *, n_iter: int = 100, tol: float = 1e-8, start: "BandedWhite | None" = None) -> "FullCov":
        """ML: the band's second-moment matrix; with ``d``, EM on the unresolved motion m_t
        (E: its Gaussian posterior; M: Σ_b the expected second moment of y − U m, s²_b the
        expected |m|²/3), from ``start``'s scales."""
        T = len(y)
        yf = y.reshape(T, -1)
        outer = yf[:, :, None] * yf[:, None, :]
        model = cls(_band_mean(outer, lab, B))
        if d is None:
            return model
        U = loadings(d)
        model.s = (start.s.clone() if start is not None and start.s is not None
                   else torch.full((B,), 1.0, dtype=y.dtype))
        prev = -math.inf
        eye = torch.eye(3, dtype=y.dtype)
        for _ in range(n_iter):
            Sinv = torch.linalg.inv(model.cov)[lab]  # (T, n, n)
            s2 = (model.s ** 2)[lab]
            # posterior of m_t: precision I/s² + Uᵀ Σ⁻¹ U, mean P Uᵀ Σ⁻¹ y
            prec = eye / s2[:, None, None].clamp_min(1e-300) + U.transpose(1, 2) @ Sinv @ U
            P = torch.linalg.inv(prec)
            m = (P @ (U.transpose(1, 2) @ (Sinv @ yf[..., None])))[..., 0]
            e = yf - (U @ m[..., None])[..., 0]
            model.cov = _band_mean(e[:, :, None] * e[:, None, :] + U @ P @ U.transpose(1, 2), lab, B)
            model.s = torch.sqrt(_band_mean(((m ** 2).sum(-1) + torch.diagonal(P, dim1=1, dim2=2).sum(-1)) / 3, lab, B))
            cur = float(model.logpdf(y, lab, d).sum())
            if abs(cur - prev) < tol * abs(cur):
                break
            prev = cur
        return model


def describe(model) -> dict:
    """JSON-ready parameters of a fitted model (degrees of freedom, unresolved scales)."""
    out = {"model": type(model).__name__}
    if isinstance(model, TriadT):
        out["nu"] = [float(x) for x in model.nu]
    if isinstance(model, SampleT):
        out["nu"] = float(model.nu)
    s = getattr(model, "s", None)
    if s is not None:
        out["unresolved_scale"] = [float(x) for x in s]
    return out

