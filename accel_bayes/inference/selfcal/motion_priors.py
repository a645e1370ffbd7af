"""The motion priors of the [S16] self-calibration: x_{i+1} = f(x_i) + w, the transition f of the
motion state (:func:`process_model`, linear: :func:`process_transition`; layouts
:data:`MOTION_STATE_DIMS`), the covariance of the process noise w, and the whitening W
(W Cov Wᵀ = I) that turns it into the process factor of :mod:`.factors`.

Every motion-prior family of the package is here:

* **[S16] eq. 8** (``process_noise="s16"``): Cov(w_i) = Δt² diag(σ_a², σ_int², σ_ω̇²) with the
  paper's fixed variances (:data:`S16_PROCESS_VARIANCES`, :func:`process_covariance`,
  :func:`process_sqrt_information`);
* the same **bridged** over left-out samples, their states integrated out exactly
  (:func:`bridged_process_whitening`);
* **white noise on the jerk** (``"estimate"``): ω the exact integral of ω̇, intensities q_a, q_ω
  (:func:`wnoj_process_covariance`, :func:`wnoj_process_whitening`);
* **white noise on the snap** and on ä_lin (``"estimate-snap"``, state width 15; width 12: snap
  only): chains of integrators, exact discretisation (:func:`integrated_wiener_covariance`,
  :func:`continuous_process_covariance`, :func:`continuous_process_whitening`).

:func:`motion_prior` reads the ``process_noise`` / ``process_variances`` options of
:func:`~accel_bayes.inference.selfcal.self_calibrate` into a :class:`MotionPrior`.  The
intensities of the continuous-time families are estimated in :mod:`.noise_em`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch


__all__ = [
    "MOTION_STATE_DIMS",
    "process_model",
    "process_transition",
    "S16_PROCESS_VARIANCES",
    "process_variances",
    "process_covariance",
    "process_sqrt_information",
    "bridged_process_whitening",
    "PROCESS_NOISE_MODES",
    "MOTION_MODEL_DIMS",
    "wnoj_process_covariance",
    "wnoj_process_whitening",
    "integrated_wiener_covariance",
    "continuous_process_covariance",
    "continuous_process_whitening",
    "MotionPrior",
    "motion_prior",
]

# Motion-state layouts by width: the [S16] state [a_lin, ω, ω̇] (9), with ω̈ appended (12: white
# noise on the snap ω⃛ drives the angular chain) and with ȧ_lin appended after ω̈ (15: white noise on
# ä_lin drives the linear chain too).  The first 9 entries are always [a_lin, ω, ω̇]: the triad model
# reads only those, the extra derivatives enter the process model alone.
MOTION_STATE_DIMS = (9, 12, 15)


def process_model(state: torch.Tensor, dt: torch.Tensor | float) -> torch.Tensor:
    """[S16] eq. 7: x_{i+1} = [a_lin,i ; ω_i + ω̇_i Δt ; ω̇_i] for states (..., 9).

    For the smoother layouts of :data:`MOTION_STATE_DIMS` the exact transition of the chains of
    integrators (Taylor polynomials, no truncation): states (..., 12) = [a_lin, ω, ω̇, ω̈] give
    ω + ω̇Δt + ω̈Δt²/2, ω̇ + ω̈Δt, ω̈; states (..., 15) = [a_lin, ω, ω̇, ω̈, ȧ_lin] also
    a_lin + ȧ_lin Δt, ȧ_lin.  Units: m/s², rad/s, rad/s², rad/s³, m/s³; Δt in s.
    """
    dt = torch.as_tensor(dt, dtype=state.dtype, device=state.device)
    if dt.dim() > 0:
        dt = dt.unsqueeze(-1)
    a, w, wd = state[..., 0:3], state[..., 3:6], state[..., 6:9]
    d = state.shape[-1]
    if d == 9:
        return torch.cat((a, w + wd * dt, wd), -1)
    if d not in MOTION_STATE_DIMS:
        raise ValueError(f"state: expected a last dimension in {MOTION_STATE_DIMS}, got {d}")
    wdd = state[..., 9:12]
    out = [a, w + wd * dt + wdd * (dt * dt / 2), wd + wdd * dt, wdd]
    if d == 15:
        ad = state[..., 12:15]
        out[0] = a + ad * dt
        out.append(ad)
    return torch.cat(out, -1)


def process_transition(dt: torch.Tensor, dim: int = 9) -> torch.Tensor:
    """F_i (T−1, dim, dim) with :func:`process_model`(x, Δt_i) = F_i x (the model is linear).

    dt (T−1,) s; dim one of :data:`MOTION_STATE_DIMS`.  Entries Δt^k/k! along each chain of
    integrators ([S16] eq. 7 for dim 9)."""
    if dim not in MOTION_STATE_DIMS:
        raise ValueError(f"dim: expected one of {MOTION_STATE_DIMS}, got {dim}")
    n = dt.shape[0]
    F = torch.eye(dim, dtype=dt.dtype, device=dt.device).expand(n, dim, dim).clone()
    idx = torch.arange(3, device=dt.device)
    F[:, 3 + idx, 6 + idx] = dt.unsqueeze(-1)
    if dim >= 12:
        F[:, 3 + idx, 9 + idx] = (dt * dt / 2).unsqueeze(-1)
        F[:, 6 + idx, 9 + idx] = dt.unsqueeze(-1)
    if dim == 15:
        F[:, idx, 12 + idx] = dt.unsqueeze(-1)
    return F


# [S16] §IV-B tuning, used "as given" (DESIGN §3.3): σ_a² = 10³, σ_int² = 10⁻⁷, σ_ω̇² = 10³.
S16_PROCESS_VARIANCES = {"acc": 1e3, "int": 1e-7, "omega_dot": 1e3}


def process_variances(variances: dict | None = None) -> dict:
    """The [S16] eq. 8 variances ``acc``, ``int``, ``omega_dot``: the paper's values
    (:data:`S16_PROCESS_VARIANCES`) updated by ``variances``; unknown keys are refused."""
    v = dict(S16_PROCESS_VARIANCES)
    if variances:
        unknown = set(variances) - set(v)
        if unknown:
            raise ValueError(f"variances: unknown keys {sorted(unknown)}; expected acc, int, omega_dot")
        v.update(variances)
    return v


def process_covariance(dt: torch.Tensor | float, variances: dict | None = None, dtype=torch.float64, device=None) -> torch.Tensor:
    """[S16] eq. 8: Cov(w_i) = Δt² diag(σ_a² I, σ_int² I, σ_ω̇² I), shape (..., 9, 9).

    ``variances`` has keys ``acc``, ``int``, ``omega_dot`` (defaults: the paper's values).
    """
    v = process_variances(variances)
    dt = torch.as_tensor(dt, dtype=dtype, device=device)
    diag = torch.tensor([v["acc"]] * 3 + [v["int"]] * 3 + [v["omega_dot"]] * 3, dtype=dtype, device=device)
    return torch.diag_embed(dt.unsqueeze(-1) ** 2 * diag)


def process_sqrt_information(dt: torch.Tensor, variances: dict | None = None) -> torch.Tensor:
    """Diagonal of L⁻¹ for the eq. 8 covariance: 1 / (Δt_i σ), shape (T−1, 9)."""
    cov = process_covariance(dt, variances, dtype=dt.dtype, device=dt.device)
    d = torch.diagonal(cov, dim1=-2, dim2=-1)
    if bool((d <= 0).any()):
        raise ValueError("process variances and time steps must be > 0")
    return d.rsqrt()


def bridged_process_whitening(dt: torch.Tensor, steps, variances: dict | None = None) -> torch.Tensor:
    """Whitening of the process factors when samples between two fitted ones were left out.

    Between kept samples i and i+1 lie ``steps_i`` steps of the recording's grid, each of
    δ = Δt_i / steps_i.  Leaving those samples' states in the graph without measurements and
    integrating them out is exact for the linear [S16] process model: x_{i+1} = F(Δt_i) x_i + w
    with Cov(w) = Σ_{j<n} F(jδ) Q(δ) F(jδ)ᵀ, n = steps_i, Q(δ) = δ² diag(σ_a², σ_int², σ_ω̇²)
    (eq. 8).  Per axis this is

        Var(a) = n δ² σ_a²,  Var(ω̇) = n δ² σ_ω̇²,
        Var(ω) = n δ² σ_int² + δ⁴ σ_ω̇² Σj²,  Cov(ω, ω̇) = δ³ σ_ω̇² Σj   (j = 0 … n−1),

    the ω–ω̇ coupling being what a single step of length Δt_i (a constant ω̇ across the gap)
    would miss.  Returns W (T−1, 9, 9) with W Cov Wᵀ = I (the inverse Cholesky factor); for
    ``steps_i = 1`` it is eq. 8's diagonal.
    """
    v = process_variances(variances)
    n = torch.as_tensor(steps, dtype=dt.dtype, device=dt.device)
    if n.shape != dt.shape or bool((n < 1).any()) or bool((n != torch.round(n)).any()):
        raise ValueError(f"steps: expected whole numbers >= 1 of shape {tuple(dt.shape)}")
    d = dt / n
    s1 = n * (n - 1) / 2  # Σ j
    s2 = (n - 1) * n * (2 * n - 1) / 6  # Σ j²
    cov = torch.zeros(dt.shape + (9, 9), dtype=dt.dtype, device=dt.device)
    idx = torch.arange(3, device=dt.device)
    cov[:, idx, idx] = (n * d ** 2 * v["acc"]).unsqueeze(-1)
    cov[:, 3 + idx, 3 + idx] = (n * d ** 2 * v["int"] + d ** 4 * v["omega_dot"] * s2).unsqueeze(-1)
    cov[:, 6 + idx, 6 + idx] = (n * d ** 2 * v["omega_dot"]).unsqueeze(-1)
    cov[:, 3 + idx, 6 + idx] = cov[:, 6 + idx, 3 + idx] = (d ** 3 * v["omega_dot"] * s1).unsqueeze(-1)
    L, info = torch.linalg.cholesky_ex(cov)
    if bool((info != 0).any()):
        raise ValueError("process variances and time steps must be > 0")
    eye = torch.eye(9, dtype=dt.dtype, device=dt.device).expand_as(cov)
    return torch.linalg.solve_triangular(L, eye, upper=False)


# ---------------------------------------------------------------------------- continuous-time models

# process_noise modes of :func:`self_calibrate`: the paper's fixed eq. 8 variances, or the
# continuous-time model below with its two intensities estimated from the recording.
PROCESS_NOISE_MODES = ("s16", "estimate", "estimate-snap")

# Width of the motion state of each continuous-time model (layouts: MOTION_STATE_DIMS).
# "estimate": white noise on the jerk ω̈ and on ȧ_lin, x = [a_lin, ω, ω̇] (9);
# "estimate-snap": white noise on the snap ω⃛ and on ä_lin, x = [a_lin, ω, ω̇, ω̈, ȧ_lin] (15) —
# smooth ω̇ and a_lin, as hand motion has (issue #12; ω̇ is a Brownian path under the jerk model).
MOTION_MODEL_DIMS = {"estimate": 9, "estimate-snap": 15}
# (order of the a_lin chain, order of the ω chain) per state width: the white noise drives the
# order-th derivative of a_lin / ω.
_CHAIN_ORDERS = {9: (1, 2), 12: (1, 3), 15: (2, 3)}
# first state column of each element of the chains (a_lin, ȧ_lin) and (ω, ω̇, ω̈)
_ACC_CHAIN = (0, 12)
_OMEGA_CHAIN = (3, 6, 9)


def wnoj_process_covariance(dt: torch.Tensor, intensities: dict) -> torch.Tensor:
    """Covariance (T−1, 9, 9) of the process noise of the continuous-time motion model.

    The model behind ``process_noise="estimate"``: ω̈ (the jerk) is white noise of intensity
    q_ω ((rad/s³)²·s) and ȧ_lin white noise of intensity q_a ((m/s³)²·s), per axis of the array
    frame.  ω is then *exactly* the integral of ω̇ (no σ_int), and the exact discretisation over a
    step Δt has the transition of [S16] eq. 7, x_{i+1} = [a ; ω + ω̇ Δt ; ω̇] + w, with

        Cov(w_a) = q_a Δt I,   Cov([w_ω; w_ω̇]) = q_ω [[Δt³/3, Δt²/2], [Δt²/2, Δt]] ⊗ I

    (the white-noise-on-jerk prior of continuous-time estimation).  Exact for any Δt, so left-out
    samples need no bridge: the step to the next kept sample is just longer.
    """
    qa = torch.as_tensor(intensities["acc"], dtype=dt.dtype, device=dt.device)
    qw = torch.as_tensor(intensities["omega"], dtype=dt.dtype, device=dt.device)
    if not bool(qa > 0) or not bool(qw > 0) or not bool(torch.isfinite(qa) & torch.isfinite(qw)):
        raise ValueError(f"process intensities must be finite and > 0, got {intensities}")
    cov = torch.zeros(dt.shape + (9, 9), dtype=dt.dtype, device=dt.device)
    idx = torch.arange(3, device=dt.device)
    cov[:, idx, idx] = (qa * dt).unsqueeze(-1)
    cov[:, 3 + idx, 3 + idx] = (qw * dt ** 3 / 3).unsqueeze(-1)
    cov[:, 6 + idx, 6 + idx] = (qw * dt).unsqueeze(-1)
    cov[:, 3 + idx, 6 + idx] = cov[:, 6 + idx, 3 + idx] = (qw * dt ** 2 / 2).unsqueeze(-1)
    return cov


def integrated_wiener_covariance(dt: torch.Tensor, order: int) -> torch.Tensor:
    """Q(Δt)/q (n, p, p) of a chain of p = ``order`` integrators driven by unit-intensity white noise.

    y^(p) = w(t) with E[w(t) w(s)] = δ(t − s); the state (y, y′, …, y^(p−1)) moves over a step Δt
    by F_kl = Δt^(l−k)/(l−k)! (l ≥ k) plus a noise of covariance

        Q_kl = ∫₀^Δt τ^(p−1−k) τ^(p−1−l) / ((p−1−k)! (p−1−l)!) dτ
             = Δt^(2p−1−k−l) / ((2p−1−k−l) (p−1−k)! (p−1−l)!)   (k, l = 0 … p−1),

    the exact discretisation of the integrated Wiener process (p = 2: [[Δt³/3, Δt²/2], [Δt²/2, Δt]];
    p = 3: [[Δt⁵/20, Δt⁴/8, Δt³/6], [Δt⁴/8, Δt³/3, Δt²/2], [Δt³/6, Δt²/2, Δt]]).  dt (n,) s.
    """
    k = torch.arange(order, device=dt.device)
    e = (2 * order - 1 - k[:, None] - k[None, :]).to(dt.dtype)
    fact = torch.tensor([float(math.factorial(order - 1 - i)) for i in range(order)], dtype=dt.dtype, device=dt.device)
    den = e * fact[:, None] * fact[None, :]
    return dt[:, None, None] ** e / den


def continuous_process_covariance(dt: torch.Tensor, intensities: dict, dim: int = 9) -> torch.Tensor:
    """Covariance (T−1, dim, dim) of the process noise of a continuous-time motion model.

    Per axis of the array frame, white noise of intensity q_a drives the chain (a_lin, ȧ_lin) at its
    top derivative and white noise of intensity q_ω the chain (ω, ω̇, ω̈); the orders follow the
    state width ``dim`` (:data:`MOTION_STATE_DIMS`): 9 — ȧ_lin and the
    jerk ω̈ white (q_a (m/s³)²·s, q_ω (rad/s³)²·s; :func:`wnoj_process_covariance`); 12 — the snap
    ω⃛ white (q_ω (rad/s⁴)²·s); 15 — ä_lin white too (q_a (m/s⁴)²·s).  Each chain's block is
    q · :func:`integrated_wiener_covariance`, exact for any Δt; the chains are independent.  The
    transition is :func:`process_model` of the same width.
    """
    if dim == 9:
        return wnoj_process_covariance(dt, intensities)
    if dim not in _CHAIN_ORDERS:
        raise ValueError(f"dim: expected one of {tuple(_CHAIN_ORDERS)}, got {dim}")
    qa = torch.as_tensor(intensities["acc"], dtype=dt.dtype, device=dt.device)
    qw = torch.as_tensor(intensities["omega"], dtype=dt.dtype, device=dt.device)
    if not bool(qa > 0) or not bool(qw > 0) or not bool(torch.isfinite(qa) & torch.isfinite(qw)):
        raise ValueError(f"process intensities must be finite and > 0, got {intensities}")
    pa, pw = _CHAIN_ORDERS[dim]
    cov = torch.zeros(dt.shape + (dim, dim), dtype=dt.dtype, device=dt.device)
    idx = torch.arange(3, device=dt.device)
    for starts, q in ((_ACC_CHAIN[:pa], qa), (_OMEGA_CHAIN[:pw], qw)):
        Qc = q * integrated_wiener_covariance(dt, len(starts))
        for u, su in enumerate(starts):
            for v, sv in enumerate(starts):
                cov[:, su + idx[:, None], sv + idx[None, :]] = Qc[:, u, v, None, None] * torch.eye(
                    3, dtype=dt.dtype, device=dt.device)
    return cov


def continuous_process_whitening(dt: torch.Tensor, intensities: dict, dim: int = 9) -> torch.Tensor:
    """W (T−1, dim, dim) with W Cov Wᵀ = I for :func:`continuous_process_covariance` (inverse
    Cholesky factor; it keeps the two chains apart, so each intensity owns its whitened rows)."""
    if dim == 9:
        return wnoj_process_whitening(dt, intensities)
    cov = continuous_process_covariance(dt, intensities, dim)
    L, info = torch.linalg.cholesky_ex(cov)
    if bool((info != 0).any()):
        raise ValueError("process intensities and time steps must be > 0")
    eye = torch.eye(dim, dtype=dt.dtype, device=dt.device).expand_as(cov)
    return torch.linalg.solve_triangular(L, eye, upper=False)


def _intensity_rows(dim: int) -> dict:
    """Rows of the whitened process residual that belong to each intensity (the chains' rows)."""
    pa, pw = _CHAIN_ORDERS[dim]
    acc = [s + i for s in _ACC_CHAIN[:pa] for i in range(3)]
    om = [s + i for s in _OMEGA_CHAIN[:pw] for i in range(3)]
    return {"acc": acc, "omega": om}


def wnoj_process_whitening(dt: torch.Tensor, intensities: dict) -> torch.Tensor:
    """W (T−1, 9, 9) with W Cov Wᵀ = I for :func:`wnoj_process_covariance` (inverse Cholesky
    factor; block-diagonal between the a_lin rows 0–2 and the ω, ω̇ rows 3–8)."""
    cov = wnoj_process_covariance(dt, intensities)
    L, info = torch.linalg.cholesky_ex(cov)
    if bool((info != 0).any()):
        raise ValueError("process intensities and time steps must be > 0")
    eye = torch.eye(9, dtype=dt.dtype, device=dt.device).expand_as(cov)
    return torch.linalg.solve_triangular(L, eye, upper=False)


@dataclass(frozen=True)
class MotionPrior:
    """The motion model that ``process_noise`` names.

    mode : "s16" (eq. 8, fixed variances), "estimate" / "estimate-snap" (continuous-time, the
        intensities estimated) or "fixed" (continuous-time with given intensities).
    dim : width of the motion state (:data:`MOTION_STATE_DIMS`).
    intensities : the given {"acc", "omega"} of mode "fixed", else None.
    variances : the eq. 8 overrides of mode "s16" (None: the paper's).
    """

    mode: str
    dim: int
    intensities: dict | None = None
    variances: dict | None = None

    @property
    def estimated(self) -> bool:
        """Whether the intensities are estimated from the recording (:mod:`.noise_em`)."""
        return self.mode in MOTION_MODEL_DIMS


def motion_prior(process_noise, process_variances: dict | None = None) -> MotionPrior:
    """Read ``process_noise`` (a mode of :data:`PROCESS_NOISE_MODES` or a dict ``{"acc": q_a,
    "omega": q_ω}`` with optional ``"dim"``) and the eq. 8 ``process_variances`` (mode "s16" only)
    into a :class:`MotionPrior`; raises ValueError naming the option otherwise."""
    if isinstance(process_noise, dict):
        mode, intensities = "fixed", {k: float(process_noise[k]) for k in ("acc", "omega")}
        dim = int(process_noise.get("dim", 9))
        if dim not in _CHAIN_ORDERS:
            raise ValueError(f"process_noise: 'dim' expected one of {tuple(_CHAIN_ORDERS)}, got {dim}")
    elif process_noise in PROCESS_NOISE_MODES:
        mode, intensities = process_noise, None
        dim = MOTION_MODEL_DIMS.get(mode, 9)
    else:
        raise ValueError(f"process_noise: expected one of {PROCESS_NOISE_MODES} or a dict of intensities "
                         f"acc, omega, got {process_noise!r}")
    if mode != "s16" and process_variances is not None:
        raise ValueError("process_variances are the [S16] eq. 8 variances: give them with process_noise='s16'")
    return MotionPrior(mode, dim, intensities, process_variances)
