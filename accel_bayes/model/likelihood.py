"""The Rao-Blackwellized marginal likelihood of the accelerometer positions (DESIGN §4, [C21] §III-B).

Model ([C21] eq. 5, DESIGN §3.1), per sample t, array frame, stacked over the A accelerometer
triads (3A numbers)::

    y_t = G(θ) u(ω_t) + H(θ) φ_t + e_t,    e_t ~ N(0, Q),  Λ = Q⁻¹ (diagonal),
    φ_t = [ω̇_t; s_t]  (flat prior, integrated out in closed form),
    ω_t ~ p(ω_t | y_t^g)  (Gaussian, from the gyroscopes: :func:`~.gyro_posterior.gyro_posterior`).

Integrating φ_t out with the prior N(f, βF) and letting β → ∞ ([C21] eq. 17–24) gives::

    p(y_t | ω_t, θ) ∝ |M(θ)|^(-1/2) exp(-½ ‖y_t − G u(ω_t)‖²_S),
    M = Hᵀ Λ H (6×6),  S = Λ − Λ H M⁻¹ Hᵀ Λ.

**The determinant enters with the power −1/2**, not −1 as printed in [C21] eq. 25–26: the
Gaussian normaliser |2π M_t|^(-1/2) of eq. 19 carries the square root, and eq. 21/23 only
rescale what is under it.  The printed form adds (T/2)·log|M(θ)| to the log-likelihood, which
pulls the geometry (larger arrays have larger |M|).  :meth:`RaoBlackwellLikelihood.log_lik_paper_eq25`
keeps the printed form for comparison tests only; ``tests/model/test_likelihood.py`` checks ours
against the brute-force β → ∞ limit of the exact Gaussian.

The ω_t integral is done by Monte Carlo with draws from p(ω_t | y_t^g) ([C21] eq. 26)::

    log p̂(y | θ) = Σ_t [logsumexp_n(−½ q_tn) − log N] − (T/2) log|M(θ)|,
    q_tn = ‖y_t − G u(ω_t^(n))‖²_S.

p̂ (not log p̂) is an unbiased estimator of p(y^a | y^g, θ) up to the θ-free constant below,
which is what pseudo-marginal MH needs ([C21] §III-A).

Constants dropped (they do not depend on θ; every value this module returns omits them)
-----------------------------------------------------------------------------------------
With a flat prior of unit density on φ_t, the exact per-sample density is
``(2π)^(-(3A-6)/2) |Q|^(-1/2) |M|^(-1/2) exp(-½ q)``; the returned values omit
``Σ_t [-(3A-6)/2 · log 2π − ½ log|Q|]``, available as :attr:`RaoBlackwellLikelihood.log_constant`
(add it to compare fits with *different noise levels* or different triad sets).  With the proper
prior N(f, βF) of [C21] eq. 17 the omitted constant has a further −½ log|βF| per sample, which
diverges as β → ∞ ([C21] eq. 23).  The gyroscope evidence p(y_t^g) ([C21] eq. 15) is also
omitted.

Cost and numerics
-----------------
Everything that touches the 3A-dimensional data is computed once per (θ, t), O(T·A) per θ
(:meth:`RaoBlackwellLikelihood.projection`); the per-draw work, O(1) per draw whatever A is, and
its numerics are described in :mod:`.draw_sums`.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from ..errors import UserError
from ..physics.models import G_matrix, H_matrix, acc_noise_std_per_axis, u_of_omega
from ..prep.prepared import as_prepared, refuse_removed_keywords
from ..prep.selection import DEFAULT_MIN_ROTATION  # noqa: F401  (re-exported, see below)
from .draw_sums import DIRECT_MAX_DRAWS, DrawSums
from .gyro_posterior import GyroPosterior, gyro_posterior
from .phi_prior import PhiPrior

__all__ = [
    "positions_from_theta",
    "theta_from_positions",
    "as_acc_tensor",
    "RaoBlackwellLikelihood",
    "DEFAULT_MIN_ROTATION",
]

# DEFAULT_MIN_ROTATION (0.5 rad/s) lives with THE sample selection (accel_bayes.prep.selection) and
# is re-exported here for code that imported it from the likelihood before prepare_recording took
# the sample selection over.


# ---------------------------------------------------------------------------- parameterisation

def positions_from_theta(theta: torch.Tensor, reference: int, A: int) -> torch.Tensor:
    """Positions (..., A, 3) from θ (..., A−1, 3) by inserting a zero row at ``reference``.

    θ = {r_k − r_ref, k ≠ ref} is the [C21] parameterisation (r_ref ≡ 0 is the origin).
    """
    if theta.shape[-2:] != (A - 1, 3):
        raise UserError(f"theta: expected shape (..., {A - 1}, 3) for A={A}, got {tuple(theta.shape)}")
    if not 0 <= reference < A:
        raise UserError(f"reference: expected an index in 0..{A - 1}, got {reference}")
    zero = torch.zeros(*theta.shape[:-2], 1, 3, dtype=theta.dtype, device=theta.device)
    return torch.cat((theta[..., :reference, :], zero, theta[..., reference:, :]), -2)


def theta_from_positions(positions: torch.Tensor, reference: int) -> torch.Tensor:
    """θ (..., A−1, 3): positions (..., A, 3) relative to row ``reference``, that row removed."""
    A = positions.shape[-2]
    if not 0 <= reference < A:
        raise UserError(f"reference: expected an index in 0..{A - 1}, got {reference}")
    rel = positions - positions[..., reference : reference + 1, :]
    return torch.cat((rel[..., :reference, :], rel[..., reference + 1 :, :]), -2)


# ---------------------------------------------------------------------------- data


def as_acc_tensor(acc, *, dtype=torch.float64, device=None) -> torch.Tensor:
    """The accelerometer outputs (T, A, 3) in m/s² as a checked tensor: the input checks shared by
    the likelihood and the MAP (at least 3 triads, every value finite: samples or IMUs without
    accelerometer data must be selected away before either is built)."""
    acc = torch.as_tensor(acc, dtype=dtype, device=device)
    if acc.dim() != 3 or acc.shape[-1] != 3:
        raise UserError(f"acc: expected shape (T, A, 3), got {tuple(acc.shape)}")
    if acc.shape[1] < 3:
        raise UserError(f"acc: at least 3 accelerometer triads are needed, got A={acc.shape[1]}")
    if not bool(torch.isfinite(acc).all()):
        raise UserError("acc: contains NaN/inf; select samples and IMUs with accelerometer data first")
    return acc

# ---------------------------------------------------------------------------- likelihood

class RaoBlackwellLikelihood(DrawSums):
    """Rao-Blackwellized Monte Carlo estimator of p(y^a | y^g, θ) ([C21] eq. 26, corrected; DESIGN §4).

    Parameters
    ----------
    acc : (T, A, 3) tensor, m/s² — accelerometer triad outputs rotated into the **array frame**.
    omega : :class:`~.gyro_posterior.GyroPosterior` with T samples — p(ω_t | y_t^g) ([C21] eq. 26b).
    acc_noise_std : (A,) or (A, 3) m/s² — white-noise std per triad (per axis); Q = diag(σ²).
    num_draws : int — N, Monte Carlo draws of ω per sample (choose it with :func:`~.draw_tuning.choose_num_draws`).
    reference : int — row of the reference triad (origin, r_ref ≡ 0).
    dtype, device — float64 CPU by default.
    prepared : the :class:`~accel_bayes.prep.prepared.PreparedRecording` the data came from (gives
        ``imu_labels``, ``gyro_labels``, ``sample_index``, ``selection``, ``nominal_positions``),
        or None for arrays not from a recording.
    phi_prior : None (the flat prior on φ_t = [ω̇_t; s_t] of [C21] and DESIGN §4) or a proper
        zero-mean Gaussian prior N(0, F) on φ_t: a :class:`~accel_bayes.model.phi_prior.PhiPrior`
        (e.g. :func:`~accel_bayes.model.phi_prior.empirical_phi_prior`, what ``calibrate`` uses by
        default), a pair (σ_ω̇ rad/s², σ_s m/s²), six standard deviations or a (6, 6) F.  Then M(θ) becomes M + F⁻¹ in S and in the determinant (Woodbury:
        (Σ + HFHᵀ)⁻¹ = Λ − ΛH(M + F⁻¹)⁻¹HᵀΛ and |Σ + HFHᵀ| = |Σ||F||M + F⁻¹|), which is [C21]
        eq. 19–21 at finite β with f = 0.  The flat prior is the β → ∞ limit.  A proper prior
        matters for the array scale: the flat prior's −(T/2)·log|M(θ)| alone favours smaller
        arrays (|M| grows like the squared size), while under a proper prior the φ̂ᵀF⁻¹φ̂ term
        (ω̇̂ grows as the array shrinks) pulls the other way; with weak rotation or noisy data
        the flat-prior posterior is visibly shrunk (experiments/c21_coverage.py and
        experiments/phi_prior_probe.py measure it; :mod:`accel_bayes.model.phi_prior` says why
        F = E[φφᵀ] makes the estimate consistent).

    Positions passed to the methods are (..., A, 3) metres, array frame, any leading batch
    (chains × proposals …); they are taken relative to row ``reference`` (the likelihood is
    invariant to a common translation anyway: it moves only the φ part).  See the module
    docstring for the constants that are dropped.
    """

    # Δ(θ) of accel_bayes.model.acc_block_marginal (the accelerometers' linear errors integrated out), added
    # to log_phat and log_lik_given_omega when set (model.acc_block_marginal.with_block_marginal); None: nothing
    block_marginal = None

    def __init__(
        self,
        acc: torch.Tensor,
        omega: GyroPosterior,
        acc_noise_std,
        num_draws: int,
        reference: int = 0,
        dtype=torch.float64,
        device=None,
        phi_prior=None,
        prepared=None,
    ):
        acc = as_acc_tensor(acc, dtype=dtype, device=device)
        T, A, _ = acc.shape
        if omega.mean.shape != (T, 3) or omega.cov.shape != (T, 3, 3):
            raise UserError(f"omega: expected a GyroPosterior with mean (T, 3) and cov (T, 3, 3) for T={T}, "
                            f"got {tuple(omega.mean.shape)} and {tuple(omega.cov.shape)}")
        std = acc_noise_std_per_axis(acc_noise_std, A, dtype=dtype, device=device)
        num_draws = int(num_draws)
        if num_draws < 1:
            raise UserError(f"num_draws: expected an integer >= 1, got {num_draws}")
        if not 0 <= int(reference) < A:
            raise UserError(f"reference: expected an index in 0..{A - 1}, got {reference}")

        self.dtype, self.device = dtype, acc.device
        self.T, self.A = int(T), int(A)
        self.num_draws = num_draws
        self.reference = int(reference)
        # what the rows and samples are in the recording: known only when built from a PreparedRecording
        self.prepared = prepared
        self.imu_labels = tuple(range(A)) if prepared is None else prepared.imu_labels
        self.sample_index = None if prepared is None else prepared.sample_index
        self.selection = None if prepared is None else prepared.selection
        self.gyro_labels = None if prepared is None else prepared.gyro_labels
        self.nominal_positions = None if prepared is None else prepared.nominal_positions  # (A, 3) m
        self.acc = acc
        self.y = acc.reshape(T, 3 * A)  # stacked y_t, triad-major like models.G_matrix/H_matrix
        self.acc_noise_std = std.contiguous()
        self.lam = std.reshape(3 * A).pow(-2)  # diagonal of Λ
        self.omega = omega.to(dtype=dtype, device=self.device)
        # ω_t^(n) = mean_t + chol(cov_t) z_tn ([C21] eq. 26b); a singular cov is refused.
        chol, info = torch.linalg.cholesky_ex(self.omega.cov)
        if bool((info != 0).any()):
            raise UserError("omega.cov: expected symmetric positive-definite 3×3 covariances")
        self.omega_chol = chol
        self.phi_prior = PhiPrior.coerce(phi_prior, dtype=dtype, device=self.device)
        self.phi_prior_prec = None if self.phi_prior is None else self.phi_prior.precision  # F⁻¹ (6, 6)
        # θ-free constant omitted from every value (flat unit-density prior on φ), see module doc.
        self.log_constant = float(
            T * (-(3 * A - 6) / 2 * math.log(2 * math.pi) + self.lam.log().sum().item() / 2)
        )

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_recording(cls, prepared, num_draws: int = 1000, gyro_method: str = "sample_cov", dtype=torch.float64,
                       device=None, phi_prior=None, **removed) -> "RaoBlackwellLikelihood":
        """Build the likelihood from a :class:`~accel_bayes.prep.prepared.PreparedRecording` (or a
        Recording, prepared with :func:`~accel_bayes.prep.prepared.prepare_recording`'s defaults:
        every sample with a finite gyro reading and no importer flag).

        The IMUs, the samples, the array-frame outputs and their checks are the record's: the A
        triads are ``prepared.imu_labels`` (ascending; positions passed to the methods follow that
        order), the reference row is ``prepared.reference``, ``self.sample_index`` and
        ``self.selection`` say which samples were kept, ``self.nominal_positions`` (A, 3) holds
        the design positions of the rows (a natural central θ) and ``self.gyro_labels`` the gyros
        used.  Samples without rotation carry no information on θ ([C21] §IV-C) but still cost
        time: ``prepare_recording(rec, select="rotation")`` leaves them out.  The gyroscope
        posterior uses ``gyro_method`` (see :func:`~.gyro_posterior.gyro_posterior`; default
        "sample_cov" = [C21] eq. 30 as printed).  ``select=``, ``min_rotation=``,
        ``drop_clipped=``, ``selection=``, ``acc_imus=``, ``gyro_imus=`` (before 0.2.0) are a TypeError.
        """
        refuse_removed_keywords("RaoBlackwellLikelihood.from_recording", removed)
        if removed:
            raise TypeError(f"RaoBlackwellLikelihood.from_recording: unexpected keyword(s) {sorted(removed)}")
        prep = as_prepared(prepared, "RaoBlackwellLikelihood.from_recording", dtype=dtype, device=device)
        omega = gyro_posterior(prep.gyro, prep.gyro_noise_std, gyro_method)
        return cls(prep.acc, omega, prep.acc_noise_std, num_draws, reference=prep.reference, dtype=dtype,
                   device=device, phi_prior=phi_prior, prepared=prep)

    def with_phi_prior(self, phi_prior) -> "RaoBlackwellLikelihood":
        """A shallow copy with another prior on φ (anything ``phi_prior`` of the constructor takes;
        None: flat).  The data, the gyro posterior and its cached draw maps are shared."""
        import copy

        new = copy.copy(self)
        new.phi_prior = PhiPrior.coerce(phi_prior, dtype=self.dtype, device=self.device)
        new.phi_prior_prec = None if new.phi_prior is None else new.phi_prior.precision
        return new

    def untempered_copy(self) -> "RaoBlackwellLikelihood":
        """A plain :class:`RaoBlackwellLikelihood` (one ω draw) on the same data, gyro posterior, noise levels and
        φ prior: what a subclass's per-sample machinery builds on.  A likelihood tempered by κ ≠ 1 is refused
        (its density is not this one's); the calibration hands its untempered flat likelihood over as a
        :class:`~.tempering.TemperedLikelihood` with κ = 1, the same density."""
        if float(getattr(self, "kappa", 1.0)) != 1.0:
            raise UserError(f"lik: expected an untempered likelihood, got one tempered by kappa = {self.kappa:g}")
        return RaoBlackwellLikelihood(self.acc, self.omega, self.acc_noise_std, 1, reference=self.reference,
                                      dtype=self.dtype, device=self.device, phi_prior=self.phi_prior,
                                      prepared=self.prepared)

    def with_outputs(self, acc) -> "RaoBlackwellLikelihood":
        """A shallow copy on other accelerometer outputs ``acc`` (T, A, 3) m/s² of the same shape (the
        samples, noise levels, gyro posterior, φ prior and any per-sample terms kept).  Only the outputs'
        own cache is dropped: the per-sample terms' covariates (ages, rates) stay what they were built
        from, as regressors do (:mod:`.acc_block_marginal`'s scores on corrected outputs)."""
        import copy

        acc = as_acc_tensor(acc, dtype=self.dtype, device=self.device)
        if acc.shape != self.acc.shape:
            raise UserError(f"acc: expected outputs of shape {tuple(self.acc.shape)} (T, A, 3) m/s², "
                            f"got {tuple(acc.shape)}")
        new = copy.copy(self)
        new.acc = acc
        new.y = acc.reshape(self.T, 3 * self.A)
        new._yu_cache = None
        return new

    def to(self, device) -> "RaoBlackwellLikelihood":
        """A copy whose tensors live on ``device`` (e.g. "cuda"); the chains then run there.

        Every tensor attribute (the data, Λ, the gyro posterior and its Cholesky factors, the
        prior on φ, the nominal positions) is moved; the lazily built caches (names ``_*``) are
        dropped and rebuilt on first use on the new device.  Subclasses (the tempered and the
        per-sample-scaled likelihoods) keep their extra attributes the same way.  ``self`` is
        unchanged; on the same device the copy shares its tensors."""
        import copy

        device = torch.device(device)
        new = copy.copy(self)
        for name, value in list(vars(self).items()):
            if name.startswith("_"):
                delattr(new, name)  # caches: rebuilt on the new device when first needed
            elif isinstance(value, torch.Tensor):
                setattr(new, name, value.to(device))
            elif isinstance(value, GyroPosterior):
                setattr(new, name, value.to(device=device))
            elif isinstance(value, PhiPrior):
                setattr(new, name, PhiPrior.coerce(value, dtype=self.dtype, device=device))
        new.device = new.acc.device
        return new

    # ------------------------------------------------------------------ helpers
    def _positions(self, positions: torch.Tensor) -> torch.Tensor:
        positions = torch.as_tensor(positions, dtype=self.dtype, device=self.device)
        if positions.shape[-2:] != (self.A, 3):
            raise UserError(f"positions: expected shape (..., {self.A}, 3), got {tuple(positions.shape)}")
        return positions - positions[..., self.reference : self.reference + 1, :]

    def sample_z(self, batch_shape=(), num_draws: int | None = None, generator: torch.Generator | None = None):
        """Standard normals z (*batch_shape, T, N, 3), exactly as :meth:`log_phat` draws them.

        Drawn as float32 normals and cast to the likelihood's dtype: 3× faster than float64
        normals on CPU, and the float32 rounding (relative 6e-8 of each draw) is immaterial for
        a Monte Carlo average.  Stored (…, T, 3, N) and returned as a transposed view, the layout
        the estimator works in.
        """
        N = self.num_draws if num_draws is None else int(num_draws)
        if N < 1:
            raise UserError(f"num_draws: expected an integer >= 1, got {N}")
        zt = torch.randn(*tuple(batch_shape), self.T, 3, N, generator=generator, dtype=torch.float32,
                         device=self.device)
        return zt.to(self.dtype).transpose(-1, -2)

    def omega_draws(self, z: torch.Tensor) -> torch.Tensor:
        """ω_t^(n) = mean_t + chol(cov_t) z_tn for z (..., T, N, 3) → (..., T, N, 3) rad/s."""
        return self.omega.mean.unsqueeze(-2) + (self.omega_chol.unsqueeze(-3) @ z.unsqueeze(-1)).squeeze(-1)

    def projection(self, positions: torch.Tensor, center: torch.Tensor | None = None) -> dict:
        """The φ-projection quantities at θ, batched over positions (..., A, 3).

        Returns a dict with
          ``M`` (..., 6, 6) = HᵀΛH, ``L`` its Cholesky factor, ``logdetM`` (...);
          ``C`` (..., 6, 6) = GᵀSG;
          ``c`` (..., T) = r_tᵀ S r_t and ``b`` (..., T, 6) = Gᵀ S r_t, where
          r_t = y_t − G u(center_t) (``center`` (..., T, 3) rad/s; None means r_t = y_t, i.e. the
          uncentred c_t = y_tᵀSy_t, b_t = GᵀSy_t of DESIGN §4);
          ``phi`` (..., T, 6) = M⁻¹HᵀΛr_t, the least-squares [ω̇; s] given ω = center.
        With them ‖y_t − G u(ω)‖²_S = c_t − 2 b_tᵀ d + dᵀ C d, d = u(ω) − u(center_t).

        S is never formed.  S r = Λ(r − Hφ̂) with φ̂ = M⁻¹HᵀΛr, so c = eᵀΛe and b = GᵀΛe with
        e = r − Hφ̂ the φ-projected residual (no cancellation between the large φ part of y and
        the small remainder); likewise C = ẼᵀΛẼ with Ẽ = G − H M⁻¹HᵀΛG.  Cost O(T·A) per θ.
        """
        r = self._positions(positions)
        H = H_matrix(r)  # (..., 3A, 6)
        G = G_matrix(r)
        lam = self.lam
        LH = lam.unsqueeze(-1) * H  # ΛH
        M = self._with_phi_prior(H.transpose(-1, -2) @ LH)
        L, info = torch.linalg.cholesky_ex(M)
        if bool((info != 0).any()):
            raise UserError("positions: H(θ)ᵀΛH(θ) is singular — the triads are (nearly) collinear "
                            "or coincide, so ω̇ and s cannot be separated")
        logdetM = 2 * torch.diagonal(L, dim1=-2, dim2=-1).log().sum(-1)
        PG = torch.cholesky_solve(LH.transpose(-1, -2) @ G, L)  # M⁻¹HᵀΛG
        Gt = G - H @ PG  # Ẽ = (I − HM⁻¹HᵀΛ)G
        C = Gt.transpose(-1, -2) @ (lam.unsqueeze(-1) * Gt)
        if self.phi_prior_prec is not None:  # GᵀS_F G = ẼᵀΛẼ + (M⁻¹HᵀΛG)ᵀF⁻¹(M⁻¹HᵀΛG)
            C = C + PG.transpose(-1, -2) @ self.phi_prior_prec @ PG
        C = 0.5 * (C + C.transpose(-1, -2))
        if center is None:
            res = self.y  # (T, 3A)
        else:
            center = torch.as_tensor(center, dtype=self.dtype, device=self.device)
            res = self.y - u_of_omega(center) @ G.transpose(-1, -2)
        res = res.expand(*r.shape[:-2], self.T, 3 * self.A)
        phi = torch.cholesky_solve(((res * lam) @ H).transpose(-1, -2), L).transpose(-1, -2)
        e = res - phi @ H.transpose(-1, -2)  # (..., T, 3A)
        Le = e * lam
        c = (e * Le).sum(-1)
        if self.phi_prior_prec is not None:  # rᵀS_F r = eᵀΛe + φ̂ᵀF⁻¹φ̂ (GᵀS_F r = GᵀΛe still)
            c = c + ((phi @ self.phi_prior_prec) * phi).sum(-1)
        b = Le @ G
        return {"M": M, "L": L, "logdetM": logdetM, "C": C, "c": c, "b": b, "phi": phi}

    def _projection_hot(self, r: torch.Tensor, extras: bool = False) -> dict:
        """``c``, ``b``, ``C``, ``logdetM`` of :meth:`projection` centred at the gyro posterior
        mean, for r (B, A, 3): log_phat's hot path, two passes over the data instead of five.

        In the Λ^½-weighted coordinates (y_w = Λ^½y, H_w = Λ^½H, G_w = Λ^½G, cached θ-free
        [y_w, u(ω̄)]) and with K_w = M⁻¹H_wᵀ, Ẽ_w = G_w − H_w K_w G_w (= Λ^½Ẽ), the centred
        residual r_t = y_t − G u(ω̄_t) gives

            [φ̂_t, b_t] = [y_w,t, u(ω̄_t)] · [[K_wᵀ, Ẽ_w], [−(K_w G_w)ᵀ, −C]]   (b = GᵀSr = ẼᵀΛr)
            Λ^½ e_t = y_w,t − [u(ω̄_t), φ̂_t] · [G_wᵀ; H_wᵀ],   c_t = ‖Λ^½ e_t‖² (+ φ̂ᵀF⁻¹φ̂),

        so c keeps the sum-of-squares form of the projected residual (no cancellation between
        the large φ part of y and the remainder).  Same quantities as :meth:`projection`, to
        round-off, including a φ prior (M → M + F⁻¹, C += (K_wG_w)ᵀF⁻¹(K_wG_w)).  Without
        autograd ``b`` is a view of a scratch buffer that the next call overwrites.
        ``extras=True`` also returns ``Hw`` (B, 3A, 6), ``Gt`` = Λ^½Ẽ (B, 3A, 6), ``L`` the
        Cholesky factor of M (B, 6, 6) and ``e_w`` = Λ^½e (B, T, 3A), which the per-sample
        covariance of :mod:`.likelihood_percov` projects further.
        """
        sl = self._sqrt_lam
        Hw = sl.unsqueeze(-1) * H_matrix(r)  # (B, 3A, 6)
        Gw = sl.unsqueeze(-1) * G_matrix(r)
        M = self._with_phi_prior(Hw.transpose(-1, -2) @ Hw)
        L, info = torch.linalg.cholesky_ex(M)
        if bool((info != 0).any()):
            raise UserError("positions: H(θ)ᵀΛH(θ) is singular — the triads are (nearly) collinear "
                            "or coincide, so ω̇ and s cannot be separated")
        logdetM = 2 * torch.diagonal(L, dim1=-2, dim2=-1).log().sum(-1)
        K = torch.cholesky_solve(Hw.transpose(-1, -2), L)  # M⁻¹H_wᵀ (B, 6, 3A)
        PG = K @ Gw  # M⁻¹HᵀΛG
        Gt = Gw - Hw @ PG  # Λ^½Ẽ
        C = Gt.transpose(-1, -2) @ Gt
        if self.phi_prior_prec is not None:
            C = C + PG.transpose(-1, -2) @ self.phi_prior_prec @ PG
        C = 0.5 * (C + C.transpose(-1, -2))
        n = 3 * self.A
        W = torch.cat((torch.cat((K.transpose(-1, -2), Gt), -1),
                       torch.cat((-PG.transpose(-1, -2), -C), -1)), -2)  # (B, 3A + 6, 12)
        yu = self._yu_w
        Bn, T = W.shape[0], self.T
        # Without autograd the (B, T, ·) temporaries live in reused buffers (fresh MB-sized
        # allocations cost page faults comparable to the arithmetic).
        reuse = not (torch.is_grad_enabled() and r.requires_grad)
        ws = self._workspace if reuse else (lambda name, shape: None)
        # (B, T, 12): φ̂, b — one (T, 3A+6) × (3A+6, 12B) product for the whole batch
        pb = torch.mm(yu, W.permute(1, 0, 2).reshape(n + 6, Bn * 12), out=ws("pb", (T, Bn * 12)))
        pb = pb.view(T, Bn, 12).transpose(0, 1)
        phi, b = pb[..., :6], pb[..., 6:]
        V = torch.cat((Gw, Hw), -1).transpose(-1, -2)  # (B, 12, 3A)
        U = torch.cat((yu[:, n:].expand(Bn, T, 6), phi), -1, out=ws("U", (Bn, T, 12)))
        e = torch.matmul(U, V, out=ws("e", (Bn, T, n)))  # Λ^½ (y − e)
        if reuse and not extras:
            c = e.sub_(yu[:, :n]).square_().sum(-1)  # ‖Λ^½ e‖² (the sign of e is immaterial)
        elif reuse:
            e = torch.sub(yu[:, :n], e, out=e)  # Λ^½ e, kept for the caller
            c = torch.mul(e, e, out=ws("e2", (Bn, T, n))).sum(-1)
        else:
            e = yu[:, :n] - e  # Λ^½ e (B, T, 3A)
            c = (e * e).sum(-1)
        if self.phi_prior_prec is not None:
            c = c + ((phi @ self.phi_prior_prec) * phi).sum(-1)
        out = {"c": c, "b": b, "C": C, "logdetM": logdetM}
        if extras:
            out.update(Hw=Hw, Gt=Gt, L=L, e_w=e)
        return out

    @property
    def _sqrt_lam(self) -> torch.Tensor:
        if getattr(self, "_sqrt_lam_cache", None) is None:
            self._sqrt_lam_cache = self.lam.sqrt()
        return self._sqrt_lam_cache

    @property
    def _yu_w(self) -> torch.Tensor:
        """[Λ^½ y_t, u(ω̄_t)] (T, 3A + 6), θ-free (cached)."""
        if getattr(self, "_yu_cache", None) is None:
            self._yu_cache = torch.cat((self.y * self._sqrt_lam, u_of_omega(self.omega.mean)), -1)
        return self._yu_cache

    # ------------------------------------------------------------------ exact given ω
    def log_lik_given_omega(self, positions: torch.Tensor, omega: torch.Tensor) -> torch.Tensor:
        """log p(y^a | ω_{1:T}, θ) with φ integrated out (flat prior, β → ∞; [C21] eq. 18–24 with
        the corrected −½ power of DESIGN §4), up to the dropped constants of the module docstring:

            Σ_t −½ ‖y_t − G(θ) u(ω_t)‖²_S − (T/2) log|M(θ)|.

        positions (..., A, 3) m; omega (..., T, 3) rad/s (batch dims broadcast).  Returns (...).
        Differentiable in both (used by the MAP/Laplace code).
        """
        quad, logdet = self._quad_given_omega(positions, omega)
        return -0.5 * quad - 0.5 * self.T * logdet + self._block_term(positions)

    def _block_term(self, positions) -> torch.Tensor | float:
        """Δ(θ) (...) of :attr:`block_marginal` for positions (..., A, 3) m, or 0 without one."""
        if self.block_marginal is None:
            return 0.0
        return self.block_marginal(self._positions(positions))

    def log_lik_paper_eq25(self, positions: torch.Tensor, omega: torch.Tensor) -> torch.Tensor:
        """[C21] eq. 25 **as printed** (|M|⁻¹ instead of |M|^(−1/2)):
        Σ_t −½ ‖y_t − G u(ω_t)‖²_S − T log|M(θ)|.

        WRONG (DESIGN §4): it disagrees with the β → ∞ limit of the Gaussian by (T/2) log|M(θ)|,
        which biases θ.  Kept only so tests can show the difference; do not use it for inference.
        """
        quad, logdet = self._quad_given_omega(positions, omega)
        return -0.5 * quad - self.T * logdet

    def _quad_given_omega(self, positions, omega):
        """(Σ_t ‖y_t − G u(ω_t)‖²_S, log|M|), via the φ-projected residual e = r − H M⁻¹HᵀΛr."""
        r = self._positions(positions)
        omega = torch.as_tensor(omega, dtype=self.dtype, device=self.device)
        H = H_matrix(r)
        G = G_matrix(r)
        lam = self.lam
        M = self._with_phi_prior(H.transpose(-1, -2) @ (lam.unsqueeze(-1) * H))
        L = torch.linalg.cholesky(M)
        logdetM = 2 * torch.diagonal(L, dim1=-2, dim2=-1).log().sum(-1)
        res = self.y - u_of_omega(omega) @ G.transpose(-1, -2)  # (..., T, 3A)
        phi = torch.cholesky_solve(((res * lam) @ H).transpose(-1, -2), L).transpose(-1, -2)
        e = res - phi @ H.transpose(-1, -2)
        quad = (e * e * lam).sum((-1, -2))
        if self.phi_prior_prec is not None:
            quad = quad + ((phi @ self.phi_prior_prec) * phi).sum((-1, -2))
        return quad, logdetM

    def _with_phi_prior(self, M: torch.Tensor) -> torch.Tensor:
        """M + F⁻¹ under a proper prior on φ (``phi_prior``), else M."""
        if self.phi_prior_prec is None:
            return M
        return M + self.phi_prior_prec

    # ------------------------------------------------------------------ Monte Carlo estimator
    def _draws(self, batch, z, num_draws, generator, independent_draws: bool) -> torch.Tensor:
        """The standard normals of :meth:`log_phat` for a positions batch ``batch``: ``z`` checked
        (..., T, N, 3) when given, else drawn by :meth:`sample_z` (one z for the whole batch, or one
        per element with ``independent_draws``)."""
        if z is None:
            return self.sample_z(batch if independent_draws else (), num_draws, generator)
        z = torch.as_tensor(z, dtype=self.dtype, device=self.device)
        if z.dim() < 3 or z.shape[-3] != self.T or z.shape[-1] != 3:
            raise UserError(f"z: expected shape (..., T={self.T}, N, 3), got {tuple(z.shape)}")
        return z

    def log_phat(
        self,
        positions: torch.Tensor,
        generator: torch.Generator | None = None,
        z: torch.Tensor | None = None,
        num_draws: int | None = None,
        independent_draws: bool = False,
    ) -> torch.Tensor:
        """log p̂(y^a | y^g, θ) ([C21] eq. 26 with the −½ power; DESIGN §4), batched over positions.

            Σ_t [logsumexp_n(−½ q_tn) − log N] − (T/2) log|M(θ)|,
            q_tn = ‖y_t − G u(ω_t^(n))‖²_S,  ω_t^(n) = mean_t + chol(cov_t) z_tn.

        positions : (..., A, 3) m (taken relative to the reference row).
        generator : torch.Generator for z ~ N(0, I) (global RNG if None), drawn by
            :meth:`sample_z`; same seed → same value.
        z : optional standard normals (T, N, 3), or (*zb, T, N, 3) with zb broadcasting against
            the positions' batch: common random numbers / correlated pseudo-marginal proposals.
            N is then z.shape[-2].
        num_draws : overrides N when z is drawn here.
        independent_draws : when z is drawn here, False (default) shares one z across the whole
            positions batch (common random numbers: the estimates at the batch's θ are correlated,
            good for comparing proposals); True draws an independent z per batch element (use it
            for independent chains).
        Returns (...) — the dropped constants are listed in the module docstring.

        Implementation: with d' = [u(ω) − u(ω̄_t); 1], q_tn = ‖R_t d'_tn‖² where
        R_tᵀR_t = [[C, −b_t], [−b_tᵀ, c_t]] (7×7, PSD, R_t upper-triangular; its last row only
        adds the constant R_77²).  R_t = [[R_C, w_t], [0, R_77]] from one shared 6×6 factor
        (:meth:`_factor`); for N ≤ 32 q − R_77² = ‖R_C d + w_t‖² with d from ω directly
        (:meth:`_lse_direct`), otherwise d' = D_t f(z), f = [z; u(z); 1] and a 6×10 map per
        sample (:meth:`_draw_maps`, :meth:`_lse_shared`).  Either way one draw costs O(1)
        whatever A is, and q − R_77² ≥ 0 is a sum of squares (no cancellation).
        """
        r = self._positions(positions)
        batch = r.shape[:-2]
        z = self._draws(batch, z, num_draws, generator, independent_draws)
        N = z.shape[-2]
        B = int(np.prod(batch)) if len(batch) else 1
        proj = self._projection_hot(r.reshape(B, self.A, 3))
        zt = z.transpose(-1, -2)  # (..., T, 3, N); a view of sample_z's storage
        zbatch = zt.shape[:-3]
        if len(zbatch):
            zt = zt.expand(*batch, *zt.shape[-3:]).reshape(B, self.T, 3, N)
        fac = self._factor(proj["c"], proj["b"], proj["C"])
        if fac is not None and N <= DIRECT_MAX_DRAWS:
            Rc, w, floor = fac
            inplace = not (torch.is_grad_enabled() and (Rc.requires_grad or zt.requires_grad))
            lse = self._lse_direct(zt, Rc, w, inplace)  # (B, T)
        else:
            if fac is None:
                F, floor = self._draw_maps_eig(proj["c"], proj["b"], proj["C"])  # (B, T, 6, 10), (B, T)
            else:
                F, floor = self._maps_from_factor(fac[0], fac[1]), fac[2]
            # In-place temporaries and a reused feature buffer, unless autograd needs the originals.
            inplace = not (torch.is_grad_enabled() and (F.requires_grad or zt.requires_grad))
            if len(zbatch) == 0:
                lse = self._lse_shared(zt, F, inplace)  # (B, T)
            else:
                lse = self._lse_per_batch(zt, F, inplace)
        out = (lse - 0.5 * floor).sum(-1) - self.T * math.log(N) - 0.5 * self.T * proj["logdetM"]
        return out.reshape(batch) + self._block_term(positions)

