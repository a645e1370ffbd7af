"""The Rao-Blackwellized marginal likelihood of the accelerometer positions (DESIGN §4, [C21] §III-B).

Model ([C21] eq. 5, DESIGN §3.1), per sample t, array frame, stacked over the A accelerometer
triads (3A numbers)::

    y_t = G(θ) u(ω_t) + H(θ) φ_t + e_t,    e_t ~ N(0, Q),  Λ = Q⁻¹ (diagonal),
    φ_t = [ω̇_t; s_t]  (flat prior, integrated out in closed form),
    ω_t ~ p(ω_t | y_t^g)  (Gaussian, from the gyroscopes: :func:`gyro_posterior`).

Integrating φ_t out with the prior N(f, βF) and letting β → ∞ ([C21] eq. 17–24) gives::

    p(y_t | ω_t, θ) ∝ |M(θ)|^(-1/2) exp(-½ ‖y_t − G u(ω_t)‖²_S),
    M = Hᵀ Λ H (6×6),  S = Λ − Λ H M⁻¹ Hᵀ Λ.

**The determinant enters with the power −1/2**, not −1 as printed in [C21] eq. 25–26: the
Gaussian normaliser |2π M_t|^(-1/2) of eq. 19 carries the square root, and eq. 21/23 only
rescale what is under it.  The printed form adds (T/2)·log|M(θ)| to the log-likelihood, which
pulls the geometry (larger arrays have larger |M|).  :meth:`RaoBlackwellLikelihood.log_lik_paper_eq25`
keeps the printed form for comparison tests only; ``tests/test_likelihood.py`` checks ours
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
(:meth:`RaoBlackwellLikelihood.projection`).  S is never formed: S r = Λ(r − Hφ̂) with
φ̂ = M⁻¹HᵀΛr the least-squares [ω̇; s], so with r_t = y_t − G u(ω̄_t) (centred at the gyro
posterior mean) and d = u(ω) − u(ω̄_t),

    q_tn = c_t − 2 b_tᵀ d_tn + d_tnᵀ C d_tn,  c_t = r_tᵀSr_t, b_t = GᵀSr_t, C = GᵀSG,

all three computed from φ-projected residuals (no cancellation between the large φ part of y
and the small remainder).  Let R_t be the upper-triangular factor of the 7×7 matrix
[[C, −b_t], [−b_tᵀ, c_t]]; C does not depend on t, so R_t = [[R_C, w_t], [0, R_77,t]] with
R_C the factor of C (one 6×6 Cholesky per θ), w_t = −R_C⁻ᵀb_t and R_77,t² = c_t − ‖w_t‖².  Then
q_tn − R_77² = ‖R_C d_tn + w_t‖², a sum of squares (never negative), whatever A is.  For a
few draws (N ≤ 32) d_tn is formed directly from v = L_t z_tn (d_ij = ω_i v_j + ω̄_j v_i, ω = ω̄ + v);
for many, per draw d_tn = D_t f(z_tn) with f = [z; u(z); 1] and q_tn − R_77² = ‖F_t f(z_tn)‖²
with F_t = R_t[:6] D_t (6×10).  R_77² = min_d q_t is a lower bound of every q_tn, so
exp(−½(q − R_77²)) ≤ 1 cannot overflow; samples where every term underflows fall back to a
max-shifted log-sum-exp.  (Where C is singular, A ≤ 3, or a remainder comes out negative by
rounding, R_t comes from a 7×7 Cholesky or eigendecomposition per sample instead.)

One log p̂ at N = 1 on exp_1 (T = 5885, A = 8) costs ≈ 0.9 ms on one core
(experiments/bench_iteration.py): the projection (two matrix products over the data, ≈ 0.45 ms)
and the per-draw work (≈ 0.2 ms).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
import numpy as np
import torch

from ..errors import UserError
from ..physics.models import G_matrix, H_matrix, acc_noise_std_per_axis, u_of_omega
from .phi_prior import PhiPrior
from ..prep.selection import DEFAULT_MIN_ROTATION, Selection, select_samples

__all__ = [
    "positions_from_theta",
    "theta_from_positions",
    "GyroPosterior",
    "gyro_posterior",
    "RaoBlackwellLikelihood",
    "choose_num_draws",
    "choose_correlation",
    "DEFAULT_MIN_ROTATION",
]

# DEFAULT_MIN_ROTATION (0.5 rad/s) lives with THE sample selection (accel_bayes.prep.selection) and
# is re-exported here, where select="rotation" uses it.

# Budget (number of float64 elements) of one chunk of per-draw temporaries: keeps memory at
# ~tens of MB whatever T·N·batch is, without a Python loop per sample.
_CHUNK_ELEMS = 1 << 19

# Up to this many draws per sample, log_phat evaluates q directly from d = u(ω) − u(ω̄)
# (_lse_direct); above it the per-sample 6×10 maps F_t (_lse_shared) are cheaper per draw.
# The direct path works in smaller chunks (its temporaries then stay in cache).
_DIRECT_MAX_DRAWS = 32
_DIRECT_CHUNK_ELEMS = 1 << 18


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


# ---------------------------------------------------------------------------- gyro posterior


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

@dataclass
class GyroPosterior:
    """Gaussian p(ω_t | y_t^g) per sample ([C21] eq. 15, 26b, 30).

    mean : (T, 3) rad/s, array frame;  cov : (T, 3, 3) (rad/s)²;  method : how it was built.
    """

    mean: torch.Tensor
    cov: torch.Tensor
    method: str

    @property
    def T(self) -> int:
        return int(self.mean.shape[0])

    def select(self, index) -> "GyroPosterior":
        """The posterior of the samples ``index`` (bool mask or integer indices)."""
        idx = torch.as_tensor(np.asarray(index), device=self.mean.device)
        return GyroPosterior(self.mean[idx], self.cov[idx], self.method)

    def to(self, dtype=None, device=None) -> "GyroPosterior":
        return GyroPosterior(self.mean.to(dtype=dtype, device=device), self.cov.to(dtype=dtype, device=device),
                             self.method)


_GYRO_METHODS = ("sample_cov", "sample_cov_mean", "calibrated")


def gyro_posterior(gyro_array: torch.Tensor, gyro_noise_std, method: str = "sample_cov") -> GyroPosterior:
    """Gaussian posterior of ω_t from the G gyroscope triads of one sample (flat prior on ω_t).

    gyro_array : (T, G, 3) rad/s, already rotated into the array frame.
    gyro_noise_std : (G,) rad/s (or a scalar), white noise std per axis.
    method :
      * ``"calibrated"`` — gyros with known, calibrated noise: the inverse-variance weighted mean,
        covariance (Σ_k σ_k⁻²)⁻¹ I (= Q_g/G for equal noise).
      * ``"sample_cov"`` (default) — [C21] eq. 30 **as printed**: mean ȳ_t = plain average of the
        G gyros (eq. 30a); covariance Q̄_t = per-sample sample covariance across the gyros with
        1/(G−1) (eq. 30b), **not divided by G**.  That is the spread of a single gyro, not the
        uncertainty of the mean, so it is deliberately wide (the paper uses it to absorb
        uncalibrated gyro scale/misalignment errors that grow with |ω|, [C21] §IV-B).
      * ``"sample_cov_mean"`` — the same divided by G (the standard error of the mean).

    Floor (sample-covariance methods): with few gyros Q̄_t is rank-deficient (rank ≤ G−1) or
    tiny by chance, so its eigenvalues are raised to at least the calibrated variance
    (Σ_k σ_k⁻²)⁻¹: Q̄_t ← V diag(max(λ_i, σ²_cal)) Vᵀ.  The result is never singular and never
    narrower than what the stated gyro noise alone allows.  Needs G ≥ 2.
    """
    if gyro_array.dim() != 3 or gyro_array.shape[-1] != 3:
        raise UserError(f"gyro_array: expected shape (T, G, 3), got {tuple(gyro_array.shape)}")
    T, G, _ = gyro_array.shape
    dtype, device = gyro_array.dtype, gyro_array.device
    std = torch.as_tensor(gyro_noise_std, dtype=dtype, device=device)
    std = std.expand(G) if std.dim() == 0 else std
    if std.shape != (G,):
        raise UserError(f"gyro_noise_std: expected shape ({G},) for G={G} gyros, got {tuple(std.shape)}")
    if bool((std <= 0).any()):
        raise UserError("gyro_noise_std: expected > 0 for every gyro")
    if G < 1:
        raise UserError("gyro_array: no gyroscope triad (G = 0); the likelihood needs at least one")
    if bool(torch.isnan(gyro_array).any()):
        raise UserError("gyro_array: contains NaN; select samples/IMUs with gyro data first")
    w = std.pow(-2)
    var_cal = 1.0 / w.sum()
    eye = torch.eye(3, dtype=dtype, device=device)
    if method == "calibrated":
        mean = (gyro_array * w[:, None]).sum(-2) / w.sum()
        cov = (var_cal * eye).expand(T, 3, 3).clone()
        return GyroPosterior(mean, cov, method)
    if method not in _GYRO_METHODS:
        raise UserError(f"method: expected one of {_GYRO_METHODS}, got {method!r}")
    if G < 2:
        raise UserError(f"method={method!r}: the sample covariance needs at least 2 gyros, got G={G}; "
                        "use method='calibrated'")
    mean = gyro_array.mean(-2)
    dev = gyro_array - mean.unsqueeze(-2)
    cov = dev.transpose(-1, -2) @ dev / (G - 1)
    if method == "sample_cov_mean":
        cov = cov / G
    lam, V = torch.linalg.eigh(cov)
    lam = lam.clamp_min(var_cal)
    cov = (V * lam.unsqueeze(-2)) @ V.transpose(-1, -2)
    cov = 0.5 * (cov + cov.transpose(-1, -2))
    return GyroPosterior(mean, cov, method)


# ---------------------------------------------------------------------------- likelihood

class RaoBlackwellLikelihood:
    """Rao-Blackwellized Monte Carlo estimator of p(y^a | y^g, θ) ([C21] eq. 26, corrected; DESIGN §4).

    Parameters
    ----------
    acc : (T, A, 3) tensor, m/s² — accelerometer triad outputs rotated into the **array frame**.
    omega : :class:`GyroPosterior` with T samples — p(ω_t | y_t^g) ([C21] eq. 26b).
    acc_noise_std : (A,) or (A, 3) m/s² — white-noise std per triad (per axis); Q = diag(σ²).
    num_draws : int — N, Monte Carlo draws of ω per sample (choose it with :func:`choose_num_draws`).
    reference : int — row of the reference triad (origin, r_ref ≡ 0).
    dtype, device — float64 CPU by default.
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
        self.imu_labels = tuple(range(A))
        self.sample_index = None  # indices into the source recording, set by from_recording
        self.selection = None  # the Selection behind sample_index, set by from_recording
        self.gyro_labels = None  # set by from_recording
        self.nominal_positions = None  # (A, 3) design positions of the rows, set by from_recording
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
    def from_recording(
        cls,
        rec,
        num_draws: int = 1000,
        gyro_method: str = "sample_cov",
        select=None,
        min_rotation: float | None = None,
        drop_clipped: bool = False,
        acc_imus=None,
        gyro_imus=None,
        dtype=torch.float64,
        device=None,
        phi_prior=None,
        selection: "Selection | None" = None,
    ) -> "RaoBlackwellLikelihood":
        """Build the likelihood from a :class:`~accel_bayes.data.recording.Recording`.

        Accelerometer and gyroscope outputs are rotated into the array frame with the nominal
        orientations (R(q)ᵀ, DESIGN §7.0).  The A triads are the IMUs with accelerometer data
        (or ``acc_imus``, a list of labels), kept in ``self.imu_labels`` in ascending order;
        positions passed to the methods follow that order.  The gyroscope posterior uses the
        gyros of the IMUs that have one (or ``gyro_imus``) with ``gyro_method`` (see
        :func:`gyro_posterior`; default "sample_cov" = [C21] eq. 30 as printed).  The reference
        row is the recording's ``reference_imu``.  ``self.nominal_positions`` (A, 3) holds the
        design positions of the rows (a natural central θ), ``self.gyro_labels`` the gyros used.

        Sample selection (explicit, never hidden; ``self.sample_index`` records what was kept and
        ``self.selection`` the :class:`~accel_bayes.prep.selection.Selection` it came from):

        * ``selection`` — a :class:`~accel_bayes.prep.selection.Selection` (e.g. the one of
          :func:`accel_bayes.prep.preprocess.preprocess`) is used as it is; ``select``,
          ``min_rotation`` and ``drop_clipped`` must then be left at their defaults.
        * otherwise :func:`~accel_bayes.prep.selection.select_samples` is called on the IMUs used
          (no rests): ``select=None`` keeps every sample with a finite gyro reading; a bool mask
          (T,) or integer indices keeps those; ``select="rotation"`` keeps samples with
          |ω̄_t| ≥ ``min_rotation`` rad/s (default :data:`DEFAULT_MIN_ROTATION` = 0.5 rad/s;
          ω̄_t the inverse-variance-weighted gyro mean).  Samples without rotation carry no
          information on θ ([C21] §IV-C: G u(ω) ≈ 0, and the rotational part of H carries only
          ω̇, which is integrated out) but still cost time.
        * ``drop_clipped=True`` further drops samples with ``acc_clipped``/``gyro_clipped`` set for
          any used IMU.  By default clipped samples are **kept** (the recording says they are at
          the range; the caller decides).
        """
        has_acc = np.asarray(rec.has_acc)
        labels = np.flatnonzero(has_acc) if acc_imus is None else np.asarray(sorted(int(k) for k in acc_imus))
        if len(labels) < 3:
            raise UserError(f"acc_imus: at least 3 IMUs with accelerometer data are needed, got {labels.tolist()}")
        if not has_acc[labels].all():
            raise UserError(f"acc_imus: IMUs {labels[~has_acc[labels]].tolist()} have no accelerometer data")
        ref_label = int(rec.reference_imu)
        if ref_label not in labels:
            raise UserError(f"reference_imu: IMU {ref_label} is not among the accelerometer IMUs used "
                            f"{labels.tolist()}")
        if rec.gyro is None:
            raise UserError("gyro: the Rao-Blackwellized likelihood needs gyroscope data ([C21] eq. 26b)")
        has_gyro = np.asarray(rec.has_gyro)
        glabels = np.flatnonzero(has_gyro) if gyro_imus is None else np.asarray(sorted(int(k) for k in gyro_imus))
        if len(glabels) == 0 or not has_gyro[glabels].all():
            raise UserError(f"gyro_imus: expected IMUs with gyroscope data, got {glabels.tolist()}")

        T = rec.T
        if selection is not None:
            if not isinstance(selection, Selection) or selection.T != T:
                raise UserError(f"selection: expected a Selection of the recording's {T} samples")
            if select is not None or min_rotation is not None or drop_clipped:
                raise UserError("selection: given together with select/min_rotation/drop_clipped; pass one or the other")
        else:
            if isinstance(select, str) and select != "rotation":
                raise UserError(f"select: expected None, a mask, indices or 'rotation', got {select!r}")
            rot = isinstance(select, str)
            thr = (DEFAULT_MIN_ROTATION if min_rotation is None else float(min_rotation)) if rot else 0.0
            selection = select_samples(rec, drop_static=False, drop_clipped=bool(drop_clipped), min_rotation=thr,
                                       user=None if (select is None or rot) else select, acc_imus=labels,
                                       gyro_imus=glabels)
        idx = np.array(selection.index)
        if len(idx) == 0:
            raise UserError("select: no samples left after selection")

        acc_all = rec.acc_tensor("array", dtype=dtype, device=device)
        gyro_all = rec.gyro_tensor("array", dtype=dtype, device=device)
        gstd = torch.as_tensor(np.asarray(rec.gyro_noise_std)[glabels], dtype=dtype, device=device)
        gyro = gyro_all[torch.as_tensor(idx, device=gyro_all.device)][:, torch.as_tensor(glabels)]
        acc = acc_all[torch.as_tensor(idx, device=acc_all.device)][:, torch.as_tensor(labels)]
        omega = gyro_posterior(gyro, gstd, gyro_method)
        astd = np.asarray(rec.acc_noise_std)[labels]
        lik = cls(acc, omega, astd, num_draws, reference=int(np.flatnonzero(labels == ref_label)[0]),
                  dtype=dtype, device=device, phi_prior=phi_prior)
        lik.imu_labels = tuple(int(k) for k in labels)
        lik.gyro_labels = tuple(int(k) for k in glabels)
        lik.sample_index = idx
        lik.selection = selection
        lik.nominal_positions = torch.as_tensor(np.asarray(rec.nominal_position)[labels], dtype=dtype,
                                                device=lik.device)
        return lik

    def with_phi_prior(self, phi_prior) -> "RaoBlackwellLikelihood":
        """A shallow copy with another prior on φ (anything ``phi_prior`` of the constructor takes;
        None: flat).  The data, the gyro posterior and its cached draw maps are shared."""
        import copy

        new = copy.copy(self)
        new.phi_prior = PhiPrior.coerce(phi_prior, dtype=self.dtype, device=self.device)
        new.phi_prior_prec = None if new.phi_prior is None else new.phi_prior.precision
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

    def _projection_hot(self, r: torch.Tensor) -> dict:
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
        if reuse:
            c = e.sub_(yu[:, :n]).square_().sum(-1)  # ‖Λ^½ e‖² (the sign of e is immaterial)
        else:
            e = yu[:, :n] - e  # Λ^½ e (B, T, 3A)
            c = (e * e).sum(-1)
        if self.phi_prior_prec is not None:
            c = c + ((phi @ self.phi_prior_prec) * phi).sum(-1)
        return {"c": c, "b": b, "C": C, "logdetM": logdetM}

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
        return -0.5 * quad - 0.5 * self.T * logdet

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
        if z is None:
            zb = batch if independent_draws else ()
            z = self.sample_z(zb, num_draws, generator)
        else:
            z = torch.as_tensor(z, dtype=self.dtype, device=self.device)
            if z.dim() < 3 or z.shape[-3] != self.T or z.shape[-1] != 3:
                raise UserError(f"z: expected shape (..., T={self.T}, N, 3), got {tuple(z.shape)}")
        N = z.shape[-2]
        B = int(np.prod(batch)) if len(batch) else 1
        proj = self._projection_hot(r.reshape(B, self.A, 3))
        zt = z.transpose(-1, -2)  # (..., T, 3, N); a view of sample_z's storage
        zbatch = zt.shape[:-3]
        if len(zbatch):
            zt = zt.expand(*batch, *zt.shape[-3:]).reshape(B, self.T, 3, N)
        fac = self._factor(proj["c"], proj["b"], proj["C"])
        if fac is not None and N <= _DIRECT_MAX_DRAWS:
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
        return out.reshape(batch)

    def _factor(self, c, b, C):
        """(R_C, w, floor) with R_t = [[R_C, w_t], [0, √floor_t]] the upper-triangular factor of
        C'_t = [[C, −b_t], [−b_tᵀ, c_t]] (see :meth:`_draw_maps`), or None when C is singular or
        some remainder floor_t = c_t − ‖w_t‖² comes out negative by rounding (then the caller
        takes the general 7×7 path).  R_C (B, 6, 6), w (B, 6, T), floor (B, T) ≥ 0.

        C is the same at every t, so this is one 6×6 Cholesky and one triangular solve per θ: the
        same arithmetic as the last row of a 7×7 Cholesky, without T factorisations.
        """
        Lc, info = torch.linalg.cholesky_ex(C)  # C = Lc Lcᵀ, R_C = Lcᵀ
        if bool((info != 0).any()):
            return None
        w = torch.linalg.solve_triangular(Lc, b.transpose(-1, -2), upper=False).neg()  # −R_C⁻ᵀ b_t
        floor = c - (w * w).sum(-2)
        if not bool((floor >= 0).all()):
            return None
        return Lc.transpose(-1, -2), w, floor

    def _lse_direct(self, zt, Rc, w, inplace=True):
        """log Σ_n exp(−½(q_tn − floor_t)) → (B, T), with q_tn − floor_t = ‖R_C d_tn + w_t‖².

        d_tn = u(ω_tn) − u(ω̄_t) is formed from v = L_t z_tn (ω = ω̄ + v) as
        d_ij = ω_i v_j + ω̄_j v_i (exact for the quadratic u, no cancellation), θ-free and so
        shared by all B positions when zt (T, 3, N) is; zt (B, T, 3, N) gives one per position.
        Per draw that is ~40 flops for d plus a 6×6 triangular product per θ (one matrix product
        over all t and n), instead of the 6×10 map F_t per (θ, t) of :meth:`_lse_shared`.
        For N = 1 the log-sum-exp is the term itself (no exp/log).
        """
        B = Rc.shape[0]
        T, N = zt.shape[-3], zt.shape[-1]
        shared = zt.dim() == 3
        zb = () if shared else (B,)
        Lt, mt = self._chol_t, self._mean_t  # (3, 3, T), (3, T)
        pi, pj = self._pairs
        out = []
        step = max(1, _DIRECT_CHUNK_ELEMS // (16 * N * B))  # ~16 numbers per (draw, θ) in flight
        # Without autograd the temporaries live in buffers reused across chunks and calls (fresh
        # multi-100-kB allocations cost page faults comparable to the arithmetic).
        ws = self._workspace if inplace else (lambda name, shape: None)
        for t0 in range(0, T, step):
            t1 = min(T, t0 + step)
            tau = t1 - t0
            zc = zt[..., t0:t1, :, :].transpose(-3, -2)  # (…, 3, τ, N) view
            m = mt[:, t0:t1, None]  # (3, τ, 1)
            # v_i = Σ_j L_ij z_j  (…, 3, τ, N)
            prod = torch.mul(Lt[:, :, t0:t1, None], zc.unsqueeze(-4), out=ws("prod", (*zb, 3, 3, tau, N)))
            v = torch.sum(prod, -3, out=ws("v", (*zb, 3, tau, N)))
            om = torch.add(v, m, out=ws("om", (*zb, 3, tau, N)))
            d = torch.index_select(om, -3, pi, out=ws("d", (*zb, 6, tau, N)))
            tmp = torch.index_select(v, -3, pj, out=ws("tmp", (*zb, 6, tau, N)))
            d = d.mul_(tmp) if inplace else d * tmp
            tmp = torch.index_select(v, -3, pi, out=ws("tmp", (*zb, 6, tau, N)))
            tmp = tmp.mul_(m.index_select(0, pj)) if inplace else tmp * m.index_select(0, pj)
            d = d.add_(tmp) if inplace else d + tmp  # d_ij = ω_i v_j + ω̄_j v_i
            y = torch.matmul(Rc, d.view(*zb, 6, tau * N), out=ws("y", (B, 6, tau * N)))
            y = y.view(B, 6, tau, N)
            y = y.add_(w[:, :, t0:t1, None]) if inplace else y + w[:, :, t0:t1, None]
            y = y.mul_(y) if inplace else y * y
            s = torch.sum(y, 1, out=ws("s", (B, tau, N)))  # (B, τ, N)
            out.append(s[..., 0] * -0.5 if N == 1 else self._log_mean_exp_shifted(s))
        return torch.cat(out, 1)

    def _workspace(self, name: str, shape: tuple) -> torch.Tensor:
        """A scratch tensor of ``shape`` named ``name``, reused across calls (grown as needed)."""
        cache = self.__dict__.setdefault("_ws_cache", {})
        n = math.prod(shape)
        buf = cache.get(name)
        if buf is None or buf.numel() < n:
            buf = cache[name] = torch.empty(n, dtype=self.dtype, device=self.device)
        return buf[:n].view(shape)

    @property
    def _chol_t(self) -> torch.Tensor:
        """chol(cov_t) stored (3, 3, T) (cached)."""
        if getattr(self, "_chol_t_cache", None) is None:
            self._chol_t_cache = self.omega_chol.permute(1, 2, 0).contiguous()
            self._mean_t_cache = self.omega.mean.T.contiguous()
        return self._chol_t_cache

    @property
    def _mean_t(self) -> torch.Tensor:
        """ω̄_t stored (3, T) (cached)."""
        self._chol_t
        return self._mean_t_cache

    @property
    def _pairs(self):
        if getattr(self, "_pairs_cache", None) is None:
            self._pairs_cache = (torch.tensor(_PAIRS_I, device=self.device), torch.tensor(_PAIRS_J, device=self.device))
        return self._pairs_cache

    def _draw_maps(self, c, b, C):
        """(F, floor): q_tn = ‖F_t f(z_tn)‖² + floor_t, F (B, T, 6, 10), floor (B, T) ≥ 0.

        R_t is an upper-triangular factor of C'_t = [[C, −b_t], [−b_tᵀ, c_t]] = R_tᵀR_t, so the
        last row of R_t D_t is (0, …, 0, R_77) and floor = R_77² = min_d q is a lower bound of
        every q_tn: exp(−½(q − floor)) ≤ 1 never overflows (see :meth:`_lse_shared`).
        R_t comes from :meth:`_factor` (one shared 6×6 Cholesky) or, where that declines, from
        :meth:`_draw_maps_eig` (a 7×7 factor per sample).
        """
        fac = self._factor(c, b, C)
        if fac is None:
            return self._draw_maps_eig(c, b, C)
        return self._maps_from_factor(*fac[:2]), fac[2]

    def _maps_from_factor(self, Rc, w):
        """F_t = R_t[:6] D_t = [R_C D_t[:6, :9], w_t] (D_t's last row is e_10 and its last column
        is zero above it) → (B, T, 6, 10), stored (T, B, 6, 10) so that :meth:`_lse_shared`'s
        (T, 6B, 10) view needs no copy."""
        B, T = w.shape[0], w.shape[-1]
        F = torch.empty(T, B, 6, 10, dtype=w.dtype, device=w.device)
        F[..., :9] = (Rc @ self._D6).view(B, 6, T, 9).permute(2, 0, 1, 3)
        F[..., 9] = w.permute(2, 0, 1)
        return F.permute(1, 0, 2, 3)

    @property
    def _D6(self) -> torch.Tensor:
        """D_t[:6, :9] stored (6, T·9) (θ-free, cached): R_C @ _D6 is one matrix product."""
        if getattr(self, "_D6_cache", None) is None:
            self._D6_cache = self._D[:, :6, :9].permute(1, 0, 2).reshape(6, self.T * 9)
        return self._D6_cache

    def _draw_maps_eig(self, c, b, C):
        """:meth:`_draw_maps` through a 7×7 factor per sample (the general path: Cholesky, and
        for singular or rounding-indefinite C'_t an eigendecomposition square root)."""
        B, T = c.shape
        Cp = torch.empty(B, T, 7, 7, dtype=self.dtype, device=self.device)
        Cp[..., :6, :6] = C.unsqueeze(1)
        Cp[..., :6, 6] = -b
        Cp[..., 6, :6] = -b
        Cp[..., 6, 6] = c
        Lc, info = torch.linalg.cholesky_ex(Cp)
        R = Lc.transpose(-1, -2)
        bad = info != 0
        if bool(bad.any()):
            # Singular (e.g. A ≤ 4: rank S = 3A − 6 < 7) or indefinite by rounding: a square root
            # from the eigendecomposition (negative rounding eigenvalues clipped to 0), made
            # upper-triangular by QR (RᵀR is unchanged).
            lam, V = torch.linalg.eigh(Cp[bad])
            R0 = lam.clamp_min(0).sqrt().unsqueeze(-1) * V.transpose(-1, -2)
            R = R.clone()
            R[bad] = torch.linalg.qr(R0).R
        F = R[..., :6, :] @ self._D  # (B, T, 6, 10)
        return F, R[..., 6, 6].square()

    @property
    def _D(self) -> torch.Tensor:
        """D_t (T, 7, 10): [u(ω̄_t + L_t z) − u(ω̄_t); 1] = D_t [z; u(z); 1] (θ-free, cached)."""
        if getattr(self, "_D_cache", None) is None:
            m, Lg = self.omega.mean, self.omega_chol
            T = self.T
            mx, my, mz = m.unbind(-1)
            o = torch.zeros_like(mx)
            J = torch.stack(  # ∂u/∂ω at the mean (T, 6, 3)
                (
                    torch.stack((2 * mx, o, o), -1),
                    torch.stack((o, 2 * my, o), -1),
                    torch.stack((o, o, 2 * mz), -1),
                    torch.stack((my, mx, o), -1),
                    torch.stack((mz, o, mx), -1),
                    torch.stack((o, mz, my), -1),
                ),
                -2,
            )
            pi = torch.tensor(_PAIRS_I, device=self.device)
            pj = torch.tensor(_PAIRS_J, device=self.device)
            fk = torch.tensor(_FEAT_I, device=self.device)
            fl = torch.tensor(_FEAT_J, device=self.device)
            # (Lz)_i (Lz)_j = Σ_(k≤l) P[(i,j),(k,l)] z_k z_l with P = L_ik L_jl (+ L_il L_jk if k ≠ l).
            Li, Lj = Lg[:, pi, :], Lg[:, pj, :]  # (T, 6, 3): rows i and j of L for each output pair
            P = Li[:, :, fk] * Lj[:, :, fl]  # (T, 6, 6) over feature pairs (k, l)
            cross = (fk != fl).to(self.dtype)
            P = P + cross * (Li[:, :, fl] * Lj[:, :, fk])
            D = torch.zeros(T, 7, 10, dtype=self.dtype, device=self.device)
            D[:, :6, :3] = J @ Lg
            D[:, :6, 3:9] = P
            D[:, 6, 9] = 1.0
            self._D_cache = D
        return self._D_cache

    @staticmethod
    def _features(zt: torch.Tensor, buf: torch.Tensor | None = None) -> torch.Tensor:
        """f = [z; zx², zy², zz², zx zy, zy zz, zx zz; 1] for zt (..., τ, 3, N) → (..., τ, 10, N).

        ``buf`` (a previous result of the same shape) is reused: its constant row is kept.
        """
        if buf is None or buf.shape[:-2] != zt.shape[:-2] or buf.shape[-1] != zt.shape[-1]:
            buf = torch.empty(*zt.shape[:-2], 10, zt.shape[-1], dtype=zt.dtype, device=zt.device)
            buf[..., 9, :] = 1.0
        buf[..., 0:3, :] = zt
        torch.mul(zt, zt, out=buf[..., 3:6, :])
        torch.mul(zt[..., 0:2, :], zt[..., 1:3, :], out=buf[..., 6:8, :])
        torch.mul(zt[..., 0, :], zt[..., 2, :], out=buf[..., 8, :])
        return buf

    def _chunk(self, N, per_draw):
        return max(1, _CHUNK_ELEMS // max(1, N * per_draw))

    @staticmethod
    def _log_mean_exp_shifted(s: torch.Tensor) -> torch.Tensor:
        """log Σ_n exp(−½ s_n) over the last dim for s ≥ 0 (q minus its floor).

        exp(−½ s) ≤ 1 cannot overflow, so the max-shift of a general logsumexp is skipped; rows
        where every term underflows (all s ≳ 1400: a θ or sample far from fitting) are redone
        with the shifted form.  ``s`` is overwritten.
        """
        h = s.mul_(-0.5) if not s.requires_grad else s * -0.5
        tot = torch.exp(h).sum(-1)
        out = tot.log()
        low = tot < 1e-280
        if bool(low.any()):
            out[low] = torch.logsumexp(h[low], -1)
        return out

    def _lse_shared(self, zt, F, inplace=True):
        """log Σ_n exp(−½(q_tn − floor_t)) with one zt (T, 3, N) for all B positions → (B, T)."""
        B = F.shape[0]
        T, _, N = zt.shape
        Fs = F.permute(1, 0, 2, 3).reshape(T, 6 * B, 10)  # one (6B × 10) map per t
        out, buf = [], None
        step = self._chunk(N, 10 + 6 * B)
        for t0 in range(0, T, step):
            t1 = min(T, t0 + step)
            buf = self._features(zt[t0:t1], buf if inplace else None)  # (τ, 10, N)
            Y = torch.bmm(Fs[t0:t1], buf)  # (τ, 6B, N)
            Y = Y.mul_(Y) if inplace else Y * Y
            s = Y.reshape(t1 - t0, B, 6, N).sum(2)  # (τ, B, N)
            out.append(self._log_mean_exp_shifted(s))
        return torch.cat(out, 0).T

    def _lse_per_batch(self, zt, F, inplace=True):
        """As :meth:`_lse_shared` with its own zt (B, T, 3, N) per position → (B, T)."""
        B, T, _, N = zt.shape
        out, buf = [], None
        step = self._chunk(N * B, 16)
        for t0 in range(0, T, step):
            t1 = min(T, t0 + step)
            buf = self._features(zt[:, t0:t1], buf if inplace else None)  # (B, τ, 10, N)
            Y = F[:, t0:t1] @ buf  # (B, τ, 6, N)
            s = (Y.mul_(Y) if inplace else Y * Y).sum(-2)
            out.append(self._log_mean_exp_shifted(s))
        return torch.cat(out, 1)


# Index pairs (i, j) of u(ω) = [xx, yy, zz, xy, xz, yz] (models.u_of_omega order): the rows of D.
_PAIRS_I = (0, 1, 2, 0, 0, 1)
_PAIRS_J = (0, 1, 2, 1, 2, 2)
# Pairs (k, l) of the feature vector f[3:9] = [xx, yy, zz, xy, yz, xz] (the order _features
# computes them in, two vectorised products): the columns of D.
_FEAT_I = (0, 1, 2, 0, 1, 0)
_FEAT_J = (0, 1, 2, 1, 2, 2)


# ---------------------------------------------------------------------------- tuning N

def choose_num_draws(
    likelihood,
    positions: torch.Tensor,
    target: float = 1.0,
    accept: tuple[float, float] = (0.1, 3.0),
    repeats: int = 40,
    start: int = 8,
    max_draws: int = 100_000,
    max_rounds: int = 4,
    seed: int = 0,
) -> tuple[int, list[dict]]:
    """Pick N so that Var[log p̂] at a central θ is ≈ ``target`` ([C21] §III-C; DESIGN §5).

    ``likelihood`` is a :class:`RaoBlackwellLikelihood` (its N is overridden per trial) or a
    factory ``N -> likelihood``; ``positions`` (A, 3) m is the central θ (e.g. the prior mean or
    the MAP).  Var[log p̂] is measured from ``repeats`` independent estimates (generator seeded
    with ``seed``) at N = ``start``; N is then extrapolated with the asymptotic 1/N law,
    N ← ceil(N · Var / target), and re-measured, until the measured variance is within a factor
    1.5 of ``target`` or ``max_rounds`` re-measurements are spent.  (The 1/N law only holds once
    Var ≲ 1; extrapolating from a tiny N overshoots, hence the re-measurement.)  [C21] aimed at
    Var ≈ 0.1; [43] of [C21] recommends ≈ 3.3 at 7 % acceptance; the default 1.0 sits between.

    Returns (N, table): N is, among the measured N whose variance lies in ``accept``, the one
    closest to ``target`` (log scale); if none did, the last N tried (check the table).
    ``table`` lists {"num_draws", "var", "repeats"} per measurement, in the order measured.
    The relative standard error of each variance is about sqrt(2/(repeats−1)) (0.23 at 40).
    """
    if not accept[0] <= target <= accept[1]:
        raise UserError(f"target: expected within accept={accept}, got {target}")
    if repeats < 3:
        raise UserError(f"repeats: expected >= 3, got {repeats}")
    is_lik = isinstance(likelihood, RaoBlackwellLikelihood)
    if not is_lik and not callable(likelihood):
        raise UserError("likelihood: expected a RaoBlackwellLikelihood or a callable N -> likelihood")

    def measure(N):
        lik = likelihood if is_lik else likelihood(N)
        gen = torch.Generator(device=lik.device)
        gen.manual_seed(int(seed) * 1_000_003 + N)
        vals = torch.stack([lik.log_phat(positions, generator=gen, num_draws=N) for _ in range(repeats)])
        return float(vals.var(0).max())

    table = []
    N = max(1, int(start))
    for _ in range(max_rounds + 1):
        v = measure(N)
        table.append({"num_draws": N, "var": v, "repeats": repeats})
        if abs(math.log(max(v, 1e-300) / target)) < math.log(1.5):
            break
        newN = int(min(max_draws, max(1, math.ceil(N * v / target))))
        if newN == N or any(row["num_draws"] == newN for row in table):
            break
        N = newN
    ok = [row for row in table if accept[0] <= row["var"] <= accept[1]]
    if not ok:
        return table[-1]["num_draws"], table
    best = min(ok, key=lambda row: abs(math.log(row["var"] / target)))
    return best["num_draws"], table


def choose_correlation(
    likelihood,
    positions: torch.Tensor,
    num_draws: int,
    target: float = 1.0,
    pairs: int = 32,
    seed: int = 0,
    min_gap: float = 1e-4,
) -> tuple[float, list[dict]]:
    """ρ of the correlated pseudo-marginal kernel (Deligiannidis, Doucet & Pitt 2018) such that
    Var[log p̂(θ, z') − log p̂(θ, z)] ≈ ``target`` at a central θ, z' = ρ z + √(1 − ρ²) ε.

    ``likelihood`` is a :class:`RaoBlackwellLikelihood` (or anything with ``sample_z`` and
    ``log_phat(positions, z=...)``); ``positions`` (A, 3) m the central θ (e.g. the MAP);
    ``num_draws`` N per estimate.  ``pairs`` seeded pairs (z, ε) (generator seeded with ``seed``,
    so the same seed gives the same ρ) are evaluated in one batch at a pilot gap
    1 − ρ = 2⁻⁸, where the variance of the difference is linear in the gap (z' − z ≈ −δz + √(2δ)ε
    for δ = 1 − ρ small: Var ≈ 2δ·E‖∇_z log p̂‖²); the gap is scaled to ``target`` by that law
    (clamped to [``min_gap``, 1]) and the variance re-measured there with the same pairs.

    Returns (ρ, table) with table rows {"rho", "var", "pairs"} in the order measured.  The
    relative standard error of each variance is about sqrt(2/(pairs−1)) (0.25 at 32).
    """
    if not target > 0:
        raise UserError(f"target: expected a variance > 0, got {target!r}")
    if int(pairs) < 3:
        raise UserError(f"pairs: expected >= 3, got {pairs!r}")
    gen = torch.Generator(device=likelihood.device)
    gen.manual_seed(int(seed) * 1_000_003 + 7 * int(num_draws) + 1)
    z = likelihood.sample_z((int(pairs),), int(num_draws), gen)
    eps = likelihood.sample_z((int(pairs),), int(num_draws), gen)
    pos = torch.as_tensor(positions, dtype=likelihood.dtype, device=likelihood.device)
    pos = pos.expand(int(pairs), *pos.shape[-2:])
    l0 = likelihood.log_phat(pos, z=z)

    def measure(gap):
        rho = 1.0 - gap
        zp = rho * z + math.sqrt(gap * (2.0 - gap)) * eps
        return float((likelihood.log_phat(pos, z=zp) - l0).var()), rho

    table = []
    pilot = 2.0 ** -8
    v, rho = measure(pilot)
    table.append({"rho": rho, "var": v, "pairs": int(pairs)})
    gap = 1.0 if not v > 0 else min(1.0, max(float(min_gap), pilot * float(target) / v))
    v, rho = measure(gap)
    table.append({"rho": rho, "var": v, "pairs": int(pairs)})
    return max(0.0, rho), table
