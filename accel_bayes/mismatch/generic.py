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
identity.  Their densities also take the ages' predictive moments instead
(:class:`~accel_bayes.mismatch.age_predictive.AgeMoments`: the age marginalised, the covariance
gaining the age variance's terms).  Fits are maximum likelihood: closed form (white, full covariance), EM with the degrees
of freedom by ECME (t models), EM for the full covariance with the low-rank term, L-BFGS for the
multivariate t with it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .age_predictive import AgeMoments, moment_loadings
from .unresolved import fit_scales, gauss_logpdf, loadings, lowrank_terms, t_logpdf

__all__ = ["BandedWhite", "TriadT", "SampleT", "FullCov", "describe"]

_NU_BOUNDS = (math.log(0.3), math.log(1e4))  # degrees of freedom searched (a t at 1e4 is Gaussian)


def _band_mean(x: torch.Tensor, lab: torch.Tensor, B: int, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Per band the (weighted) mean over samples of x (T, ...) → (B, ...)."""
    wts = torch.ones(len(x), dtype=x.dtype) if weights is None else weights
    num = torch.zeros((B,) + tuple(x.shape[1:]), dtype=x.dtype).index_add_(0, lab, x * wts.reshape((-1,) + (1,) * (x.dim() - 1)))
    den = torch.zeros(B, dtype=x.dtype).index_add_(0, lab, wts)
    return num / den.clamp_min(1e-300).reshape((B,) + (1,) * (x.dim() - 1))


def _fit_nu(quad: torch.Tensor, logdet: torch.Tensor, n) -> torch.Tensor:
    """The degrees of freedom maximising Σ_t log t_ν(quad_t, logdet_t) for each column of quad
    (T,) or (T, K) (one ν per column): a grid of step 0.08 on log ν, refined by the parabola
    through the best grid point and its neighbours."""
    grid = torch.linspace(*_NU_BOUNDS, 136, dtype=quad.dtype)
    shape = (-1,) + (1,) * quad.dim()
    ll = t_logpdf(quad[None], logdet[None], n, torch.exp(grid).reshape(shape)).sum(1)  # (G, [K])
    i = ll.argmax(0).clamp(1, len(grid) - 2)
    l0, l1, l2 = (ll.gather(0, (i + o)[None] if ll.dim() > 1 else (i + o).reshape(1)).squeeze(0) for o in (-1, 0, 1))
    h = grid[1] - grid[0]
    den = l0 - 2 * l1 + l2
    off = torch.where(den < 0, 0.5 * h * (l0 - l2) / den, torch.zeros_like(den)).clamp(-h, h)
    return torch.exp(grid[i] + off)


def _age_term(d, s2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(U, s2 per column) of the unresolved term for :func:`lowrank_terms`: ``d`` the centred data
    ages (T, K) s, or their predictive :class:`~.age_predictive.AgeMoments` (the age marginalised,
    :func:`~.age_predictive.moment_loadings`); ``s2`` (T,) the scale² per sample."""
    if isinstance(d, AgeMoments):
        return moment_loadings(d, s2)
    return loadings(d), s2[:, None].expand(len(d), 3)


def _ridged(cov: torch.Tensor) -> torch.Tensor:
    """cov (B, n, n) + 1e-6 × its mean diagonal: keeps a band with fewer samples than channels
    invertible, negligible otherwise."""
    m = torch.diagonal(cov, dim1=-2, dim2=-1).mean(-1)
    return cov + 1e-6 * m[:, None, None] * torch.eye(cov.shape[-1], dtype=cov.dtype)


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
        quad, ld = lowrank_terms(y.reshape(len(y), -1), *_age_term(d, self.s[lab] ** 2), v=v)
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
    def fit(cls, y, lab, B, *, n_iter: int = 50, tol: float = 1e-5) -> "TriadT":
        """ML by EM (weights u = (ν + 3)/(ν + |y|²/v)) with ν_k by ECME, per IMU."""
        r2 = (y ** 2).sum(-1)  # (T, K)
        K = y.shape[1]
        model = cls(_band_mean(r2 / 3, lab, B).T.contiguous(), torch.full((K,), 10.0, dtype=y.dtype))
        prev = -math.inf
        for _ in range(n_iter):
            q = r2 / model.v[:, lab].T
            u = (model.nu[None, :] + 3) / (model.nu[None, :] + q)
            model.v = torch.stack([_band_mean(u[:, k] * r2[:, k] / 3, lab, B) for k in range(K)])
            v = model.v[:, lab].T
            model.nu = _fit_nu(r2 / v, 3 * torch.log(v), 3)
            cur = float(model.logpdf(y, lab).sum())
            if abs(cur - prev) < tol * len(y):
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
        return lowrank_terms(y.reshape(T, -1), *_age_term(d, self.s[lab] ** 2), v=v)

    def logpdf(self, y, lab, d=None) -> torch.Tensor:
        """Per-sample log density (nats, (T,))."""
        quad, ld = self._terms(y, lab, d)
        return t_logpdf(quad, ld, y.shape[1] * 3, self.nu)

    @classmethod
    def fit(cls, y, lab, B, d=None, *, n_iter: int = 50, tol: float = 1e-5, start: "BandedWhite | None" = None) -> "SampleT":
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
            model.nu = float(_fit_nu(quad, ld, n))
            cur = float(model.logpdf(y, lab).sum())
            if abs(cur - prev) < tol * T:
                break
            prev = cur
        if d is None:
            return model
        if start is not None and start.s is not None:
            s0 = start.s
        else:  # the unresolved part at a tenth of the white variance, as fit_scales starts
            s0 = torch.full((B,), math.sqrt(0.1 * float(model.v.mean()) / float((d ** 2).mean().clamp_min(1e-300))),
                            dtype=y.dtype)
        lv = torch.log(model.v).clone().requires_grad_(True)
        ls = (2 * torch.log(s0.clamp_min(1e-12))).clone().requires_grad_(True)
        lnu = torch.tensor(math.log(model.nu), dtype=y.dtype, requires_grad=True)
        opt = torch.optim.LBFGS([lv, ls, lnu], max_iter=80, line_search_fn="strong_wolfe", tolerance_grad=1e-9,
                                tolerance_change=1e-12)
        U = loadings(d)
        yf = y.reshape(T, -1)

        def closure():
            opt.zero_grad()
            v = torch.exp(lv.clamp(-60, 60))[:, lab].T[:, :, None].expand(T, K, 3).reshape(T, -1)
            # bounded log-parameters keep a line search's trial point finite
            s2 = torch.exp(ls.clamp(-60, 60))[lab][:, None].expand(T, 3)
            quad, ld = lowrank_terms(yf, U, s2, v=v)
            loss = -t_logpdf(quad, ld, n, torch.exp(lnu.clamp(*_NU_BOUNDS))).sum()
            loss.backward()
            return loss

        opt.step(closure)
        return cls(torch.exp(lv.detach().clamp(-60, 60)), float(torch.exp(lnu.detach().clamp(*_NU_BOUNDS))),
                   torch.exp(0.5 * ls.detach().clamp(-60, 60)))


@dataclass
class FullCov:
    """A full cross-IMU covariance per |ω| band, Σ (B, 3K, 3K) units² (channels (IMU, axis)),
    with ``s`` (B,) units/s the unresolved motion's scale or None."""

    cov: torch.Tensor
    s: torch.Tensor | None = None

    def logpdf(self, y, lab, d=None) -> torch.Tensor:
        """Per-sample log density (nats, (T,))."""
        T = len(y)
        if self.s is None or d is None:
            U, s2 = torch.zeros(T, y.shape[1] * 3, 1, dtype=y.dtype), torch.zeros(T, 1, dtype=y.dtype)
        else:
            U, s2 = _age_term(d, self.s[lab] ** 2)
        quad, ld = lowrank_terms(y.reshape(T, -1), U, s2, prec=torch.linalg.inv(self.cov), lab=lab)
        return gauss_logpdf(quad, ld, y.shape[1] * 3)

    @classmethod
    def fit(cls, y, lab, B, d=None, *, n_iter: int = 200, tol: float = 1e-5, start: "BandedWhite | None" = None) -> "FullCov":
        """ML: the band's second-moment matrix; with ``d``, EM on the unresolved motion m_t
        (E: its Gaussian posterior; M: Σ_b the expected second moment of y − U m, s²_b the
        expected |m|²/3), from ``start``'s scales; stops when the log likelihood gains less than
        ``tol`` nats per sample."""
        T, K, _ = y.shape
        yf = y.reshape(T, -1)
        model = cls(_ridged(torch.stack([_second_moment(yf[lab == b]) for b in range(B)])))
        if d is None:
            return model
        model.s = (start.s.clone() if start is not None and start.s is not None
                   else torch.full((B,), 1.0, dtype=y.dtype))
        prev = -math.inf
        eye = torch.eye(3, dtype=y.dtype)
        for _ in range(n_iter):
            cov, s_new, cur = [], [], 0.0
            for b in range(B):
                sel = lab == b
                yb, db = yf[sel], d[sel]
                Pb = torch.linalg.inv(model.cov[b])
                # posterior of m_t: precision I/s² + Uᵀ Σ⁻¹ U, mean P Uᵀ Σ⁻¹ y (U = d ⊗ I₃)
                P4 = Pb.reshape(K, 3, K, 3)
                dd = (db[:, :, None] * db[:, None, :]).reshape(len(db), K * K)
                UtSU = (dd @ P4.permute(0, 2, 1, 3).reshape(K * K, 9)).reshape(-1, 3, 3)
                UtSy = torch.einsum("tk,tki->ti", db, (yb @ Pb).reshape(-1, K, 3))
                s2 = model.s[b] ** 2
                Mb = eye + s2 * UtSU  # = s² × posterior precision
                Lm = torch.linalg.cholesky(Mb)
                m = s2 * torch.cholesky_solve(UtSy[..., None], Lm)[..., 0]
                Pm = s2 * torch.cholesky_inverse(Lm)  # posterior covariance (T_b, 3, 3)
                # marginal log likelihood at the current parameters (Woodbury, as lowrank_terms)
                quad = (yb @ Pb * yb).sum(-1) - s2 * (UtSy * torch.cholesky_solve(UtSy[..., None], Lm)[..., 0]).sum(-1)
                ld = -torch.linalg.slogdet(Pb)[1] + 2 * torch.log(torch.diagonal(Lm, dim1=-2, dim2=-1)).sum(-1)
                cur += float(gauss_logpdf(quad, ld, 3 * K).sum())
                e = yb - (db[:, :, None] * m[:, None, :]).reshape(len(yb), -1)
                extra = (dd.T @ Pm.reshape(-1, 9)).reshape(K, K, 3, 3).permute(0, 2, 1, 3).reshape(3 * K, 3 * K)
                cov.append((e.T @ e + extra) / max(len(yb), 1))
                s_new.append(torch.sqrt(((m ** 2).sum(-1) + torch.diagonal(Pm, dim1=1, dim2=2).sum(-1)).mean() / 3))
            model.cov, model.s = _ridged(torch.stack(cov)), torch.stack(s_new)
            if abs(cur - prev) < tol * T:
                break
            prev = cur
        return model


def _second_moment(x: torch.Tensor) -> torch.Tensor:
    """xᵀx / n (n, m) → (m, m): the zero-mean ML covariance."""
    return x.T @ x / max(len(x), 1)


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

