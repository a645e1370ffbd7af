"""The per-sample unresolved-motion covariance (issue #30 item 5; physics: issue #27 item 3,
:mod:`accel_bayes.mismatch.unresolved`): the exact low-rank Gaussian algebra of residuals whose
covariance per sample is a base plus U diag(s²) Uᵀ, U the data-age loading d ⊗ I₃ of a board-common
3-vector (unresolved jerk, m/s³, or angular acceleration, rad/s²).

The same algebra carries each triad's own sampling-instant error ε_kt (the part of its sampling
instant no clock gives) times the rate of its output, :func:`instant_error_loadings`: a block
loading of rank K that :func:`lowrank_terms` evaluates on residuals and the calibration's
likelihood projects out beside the age-loaded jerk.

This module is the one implementation of that covariance.  The detector's refit, budget and
held-out scoring (:mod:`accel_bayes.mismatch.unresolved`, :mod:`accel_bayes.mismatch.generic`)
evaluate it on residuals with :func:`lowrank_terms` / :func:`marginal_loglik`; the calibration's
likelihood (:class:`accel_bayes.model.likelihood_percov.PerSampleCovLikelihood`) projects the same
term out with the motion φ_t, using :func:`centred_ages` for the loading d and the same Woodbury
identity and determinant lemma in the φ-projected metric.
"""
from __future__ import annotations

import math

import torch

__all__ = ["lowrank_terms", "gauss_logpdf", "t_logpdf", "loadings", "rotational_loadings", "instant_error_loadings",
           "marginal_loglik", "centred_ages", "age_prior_blocks"]


def lowrank_terms(y: torch.Tensor, U: torch.Tensor, s2: torch.Tensor, *, v: torch.Tensor | None = None,
                  w: torch.Tensor | None = None, prec: torch.Tensor | None = None,
                  lab: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(quad (T,), logdet (T,)): yᵀC⁻¹y and log det C per sample for C = A + U diag(s2) Uᵀ.

    y (T, n); U (T, n, r); s2 (T, r) ≥ 0 (zero allowed: the term is then absent).  The base A is
    either ``v`` (T, n) diagonal variances, with optional ``w`` (T, n) 0/1 marking the channels
    that enter (the density is then the marginal of those channels), or full per group: ``prec``
    (B, n, n) the inverses A_b⁻¹ and ``lab`` (T,) each sample's group (every channel enters).
    Units: those of y² for A and of (y/U)² for s2.  Exact: C⁻¹ = A⁻¹ − A⁻¹Ũ M⁻¹ŨᵀA⁻¹ and
    det C = det A det M with Ũ = U S^½ and M = I + ŨᵀA⁻¹Ũ, which stays positive definite at
    s2 = 0; per sample only r × r matrices are factorised."""
    Us = U * torch.sqrt(s2.clamp_min(0))[:, None, :]
    if prec is None:
        if v is None:
            raise ValueError("lowrank_terms: give v (diagonal base) or prec and lab (full base)")
        inv = 1.0 / v if w is None else w / v
        Ay = y * inv
        AU = Us * inv[..., None]
        ld = torch.log(v).sum(-1) if w is None else (w * torch.log(v)).sum(-1)
    else:
        Ay = torch.empty_like(y)
        AU = torch.empty_like(Us)
        for b in range(prec.shape[0]):
            sel = lab == b
            Ay[sel] = y[sel] @ prec[b]  # A⁻¹ is symmetric
            AU[sel] = torch.matmul(prec[b], Us[sel])
        ld = -torch.linalg.slogdet(prec)[1][lab]
    r = U.shape[-1]
    M = torch.eye(r, dtype=y.dtype, device=y.device) + Us.transpose(-1, -2) @ AU
    Lm = torch.linalg.cholesky(M)
    b = torch.einsum("tnr,tn->tr", Us, Ay)
    z = torch.cholesky_solve(b[..., None], Lm)[..., 0]
    quad = (y * Ay).sum(-1) - (b * z).sum(-1)
    logdet = ld + 2 * torch.log(torch.diagonal(Lm, dim1=-2, dim2=-1)).sum(-1)
    return quad, logdet


def gauss_logpdf(quad: torch.Tensor, logdet: torch.Tensor, n) -> torch.Tensor:
    """Zero-mean Gaussian log density (nats) from :func:`lowrank_terms`' output; n channels."""
    return -0.5 * (quad + logdet + n * math.log(2 * math.pi))


def t_logpdf(quad: torch.Tensor, logdet: torch.Tensor, n, nu) -> torch.Tensor:
    """Zero-mean multivariate-t log density (nats), scale matrix C (quad, logdet as for the
    Gaussian), ``nu`` degrees of freedom; n channels."""
    nu = torch.as_tensor(nu, dtype=quad.dtype)
    n = torch.as_tensor(n, dtype=quad.dtype)
    return (torch.lgamma((nu + n) / 2) - torch.lgamma(nu / 2) - n / 2 * torch.log(nu * math.pi) - logdet / 2
            - (nu + n) / 2 * torch.log1p(quad / nu))


def loadings(d: torch.Tensor) -> torch.Tensor:
    """U (T, 3K, 3) = d ⊗ I₃: the centred data ages d (T, K) s as the loading of a per-sample
    3-vector on the K triads, channels ordered (IMU, axis)."""
    T, K = d.shape
    eye = torch.eye(3, dtype=d.dtype, device=d.device)
    return (d[:, :, None, None] * eye).reshape(T, 3 * K, 3)


def rotational_loadings(d: torch.Tensor, r: torch.Tensor, about: torch.Tensor | None = None) -> torch.Tensor:
    """U (T, 3K, 3): the centred data ages d (T, K) s as the loading of the board's unresolved
    angular jerk ω̈_t (rad/s³) on the K accelerometer triads at positions r (K, 3) m.

    Rigid-body kinematics: the specific force at triad k changes at the rate j_t + ω̈_t × r_k (plus
    terms in ω and ω̇ that the outputs resolve), so a triad read at age d_kt errs by −d_kt(j_t + ω̈_t × r_k)
    to first order.  :func:`loadings` carries the j_t part; this is the ω̈_t × r_k part, rows of
    triad k = d_kt [r_k − r̄]× (sign immaterial for a zero-mean prior).  Positions are taken about
    their centroid r̄: an origin shift o adds d_kt [o]×, which lies in the span of :func:`loadings`,
    so only the split of variance between the two terms depends on it.  A common age is absorbed
    by the motion states' ω̇ column as for the jerk, hence d centred (:func:`centred_ages`).
    ``about`` (3,) m: the point the lever arms are taken about instead of the centroid of ``r``
    (the detector's term keeps the centroid of the clocked triads when it loads all K)."""
    d = torch.as_tensor(d)
    r = torch.as_tensor(r, dtype=d.dtype, device=d.device)
    T, K = d.shape
    if r.shape != (K, 3):
        raise ValueError(f"rotational_loadings: r must be ({K}, 3) positions (m), got {tuple(r.shape)}")
    rc = r - (r.mean(0, keepdim=True) if about is None else torch.as_tensor(about, dtype=d.dtype).reshape(1, 3))
    z = torch.zeros(K, dtype=d.dtype, device=d.device)
    cross = torch.stack([torch.stack([z, -rc[:, 2], rc[:, 1]], -1),
                         torch.stack([rc[:, 2], z, -rc[:, 0]], -1),
                         torch.stack([-rc[:, 1], rc[:, 0], z], -1)], -2)  # (K, 3, 3): [r_k]× w = r_k × w
    return (d[:, :, None, None] * cross).reshape(T, 3 * K, 3)


def instant_error_loadings(rate: torch.Tensor, std) -> torch.Tensor:
    """U (T, 3K, K): each triad's own sampling-instant error ε_kt ~ (0, e_k²) (s) as the loading of
    a unit-variance scalar per triad on that triad's three channels, column k = e_k ρ_kt on the
    rows of triad k, zero elsewhere: a triad read at t + ε_kt errs by ε_kt ρ_kt to first order,
    ρ_kt (T, K, 3) the rate of change of its output (units/s), ``std`` e scalar or (K,) s.  Its
    covariance U Uᵀ is block-diagonal, e_k² ρ_kt ρ_ktᵀ per triad: the instant errors of different
    triads are independent, so unlike the data ages they carry no common part."""
    rate = torch.as_tensor(rate)
    T, K, _ = rate.shape
    e = torch.as_tensor(std, dtype=rate.dtype, device=rate.device).expand(K)
    eye = torch.eye(K, dtype=rate.dtype, device=rate.device)
    return ((rate * e[:, None])[..., None] * eye[:, None, :]).reshape(T, 3 * K, K)


def marginal_loglik(y: torch.Tensor, d: torch.Tensor, w: torch.Tensor, v: torch.Tensor, s2: torch.Tensor) -> torch.Tensor:
    """Per-sample log density (nats, (T,)) of the model in the module docstring, the motion m_t
    marginalised.  y (T, K, 3) array-frame residuals (sensor units); d (T, K) centred data ages
    (s); w (T, K) 1 where IMU k's triad enters sample t, else 0; v (T, K) white variances (units²);
    s2 (T,) the unresolved motion's variance per axis ((units/s)²; 0 gives the white model)."""
    # lowrank_terms with U = d ⊗ I₃ and a per-triad isotropic base has M = (1 + s² c) I₃, c = Σ_k d²/v:
    # the closed form below (checked against lowrank_terms in the tests) is several times faster
    # inside the fits' autograd
    inv = w / v
    quad = (y ** 2).sum(-1).mul(inv).sum(1)
    c = (d ** 2 * inv).sum(1)
    proj = torch.einsum("tk,tki->ti", d * inv, y)  # (T, 3)
    quad = quad - s2 / (1 + s2 * c) * (proj ** 2).sum(-1)
    logdet = 3 * ((w * torch.log(v)).sum(1) + torch.log1p(s2 * c))
    return gauss_logpdf(quad, logdet, 3 * w.sum(1))


def centred_ages(age: torch.Tensor) -> torch.Tensor:
    """d (T, K) s: the data ages (T, K) s minus their mean over the K IMUs of each sample.  A
    common age is absorbed by the motion states (it moves every triad alike), so only the
    centred age loads the unresolved motion (:mod:`accel_bayes.mismatch.unresolved`)."""
    age = torch.as_tensor(age)
    return age - age.mean(-1, keepdim=True)


def age_prior_blocks(age_var, jerk_std, angjerk_std=None, lever=None,
                     rate=None) -> tuple[torch.Tensor, torch.Tensor]:
    """(triads (C,) int64, columns (T, C, 3)): the loading of a random data age on the triads
    whose age the report does not give (issue #30, IMUs without a ``sampling_clock`` finding).

    Such a triad samples on its own clock too: its data age is uniform over the register hold
    [0, 1/f), not 0, so its centred age is d̄_k + δ_kt with d̄_k the expected age (loaded with the
    other triads' ages by :func:`loadings`) and δ_kt zero-mean with variance v_k = (1/f)²/12 (s²),
    independent of the motion.  Its product with the board's jerk m_t ~ N(0, s_t² I₃) (m/s³) and
    angular jerk ω̈_t ~ N(0, a_t² I₃) (rad/s³) adds, exactly in the second moment, the covariance
    v_k (s_t² I₃ + a_t² [c_k]×[c_k]×ᵀ) on triad k's rows alone (c_k = r_k − r̄ about the centroid of
    ``lever``): δ is independent of d̄, so the cross terms with the other triads vanish, and the
    common part δ_kt/K that centring spreads over every triad is absorbed by φ_t like any common age.
    The part of the motion the outputs do resolve is read late by δ_kt too: the clocks' mean
    correction takes off d̄_k ρ_kt only, so δ_kt ρ_kt remains, ρ_kt the rate of triad k's output
    (m/s³, ``rate`` (T, K, 3), :func:`~accel_bayes.model.likelihood_percov.triad_rates`): the
    covariance v_k ρ_kt ρ_ktᵀ, one more column v_k^½ ρ_kt on the triad (an instant error of std
    v_k^½, :func:`instant_error_loadings`' form).

    age_var (K,) s² (0 for a triad with a clock: no columns); jerk_std scalar or (T,) m/s³;
    angjerk_std scalar or (T,) rad/s³ with lever (K, 3) m, or neither.  Each loaded triad gets the
    3 columns of the symmetric square root of that 3×3 block (closed form: eigenvalues s² along c_k
    and s² + a²|c_k|² across it), plus the rate's column when ``rate`` is given, column j living on
    the rows of triad ``triads[j]``."""
    v = torch.as_tensor(age_var)
    s = torch.as_tensor(jerk_std, dtype=v.dtype).reshape(-1)
    idx = torch.nonzero(v > 0).reshape(-1)
    T = len(s) if angjerk_std is None else max(len(s), torch.as_tensor(angjerk_std).reshape(-1).shape[0])
    s = s.expand(T)
    eye = torch.eye(3, dtype=v.dtype, device=v.device)
    cols, tri = [], []
    for k in idx.tolist():
        sd = v[k].sqrt()
        block = (sd * s)[:, None, None] * eye  # (T, 3, 3); symmetric, so its columns are its rows
        if angjerk_std is not None:
            a = torch.as_tensor(angjerk_std, dtype=v.dtype).reshape(-1).expand(T)
            lev = torch.as_tensor(lever, dtype=v.dtype)
            c = lev[k] - lev.mean(0)
            n = c.norm()
            if float(n) > 0.0:  # a triad at the centroid: the angular jerk does not load it
                pc = torch.outer(c / n, c / n)
                across = torch.sqrt(s.square() + (a * n).square())
                block = sd * (across[:, None, None] * (eye - pc) + s[:, None, None] * pc)
        cols.append(block)
        tri += [k] * 3
        if rate is not None:
            cols.append(sd * torch.as_tensor(rate, dtype=v.dtype)[:, k:k + 1, :])  # (T, 1, 3)
            tri.append(k)
    if not cols:
        return torch.zeros(0, dtype=torch.long), torch.zeros(T, 0, 3, dtype=v.dtype)
    return torch.as_tensor(tri, dtype=torch.long, device=v.device), torch.cat(cols, 1)
