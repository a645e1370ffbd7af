"""The Rao-Blackwellized likelihood with a per-sample covariance: the board's unresolved jerk,
loaded on each IMU by its data age, projected out with φ_t; heavy tails as a scale mixture
(issue #30 item 1; the physics: issue #27 items 2–3, :mod:`accel_bayes.mismatch.unresolved`).

Model, per sample t, array frame, stacked over the A triads (3A numbers)::

    y_t = G(θ) u(ω_t) + H(θ) φ_t + D_t m_t + e_t,   e_t ~ N(0, Q/λ_t),  m_t ~ N(0, s_t² I₃/λ_t),
    D_t = d_t ⊗ I₃,   d_kt = age_kt − mean_k age_kt  (s),

age_kt the data age of triad k's output at t (its sampling clock's sawtooth, plus the acc − gyro
filter delay: :func:`ages_from_clocks`), m_t the board's jerk that the outputs do not resolve
(m/s³) with scale s_t (its |ω| band's ``jerk_rms``, :func:`band_scale`), φ_t = [ω̇_t; s_t] with
the prior of :class:`~.likelihood.RaoBlackwellLikelihood` (flat, or N(0, F/λ_t)), and λ_t a
per-sample precision scale: λ_t ≡ 1 (``nu=None``, Gaussian) or λ_t ~ Gamma(ν/2, rate ν/2) (mean
1), which makes y_t a multivariate t with ν degrees of freedom given ω_t: heavy tails as a scale
mixture, not a post-hoc inflation.  The loading is centred because a common age moves every triad
alike, which φ_t's s_t absorbs; with the flat prior centring changes nothing.

Integrating φ_t and m_t out (m first with its prior; the determinant lemma, DESIGN §4's −½
exponent for the φ part) gives, with S the flat likelihood's φ-projection, Ũ_t = s_t D_t,
r_t = y_t − G u(ω_t), N_t = I₃ + Ũ_tᵀSŨ_t (3×3) and, for λ_t = 1,

    log p(y_t | ω_t, θ) = −½ q̃_t − ½ log|M(θ)| − ½ log|N_t(θ)|,
    q̃_t = r_tᵀSr_t − ‖L_t⁻¹Ũ_tᵀSr_t‖²,   N_t = L_t L_tᵀ,

up to the base class's θ-free constants (:attr:`log_constant`; the same ones, so values compare
with the flat likelihood's).  |N_t| depends on θ through S: it is the per-sample determinant, with
exponent −½ like |M|.  With s_t d_t = 0, N_t = I and q̃ = q: the flat likelihood exactly.  With the
scale mixture, per sample and draw (closed form, exact; n = 3A − 6 flat prior, 3A proper)::

    log ∫ p(y_t | ω, θ, λ) Gamma(λ; ν/2, ν/2) dλ
        = lgamma(a + n/2) − lgamma(a) − (n/2) log a − (a + n/2) log1p(q̃/(2a)) − ½ log|M| − ½ log|N_t|,

a = ν/2 (λ scales Q, the jerk prior and a proper φ prior together; the determinants do not
depend on λ beyond λ^(n/2)).  The ω_t integral stays the [C21] Monte Carlo average over draws from
the gyro posterior, so p̂ is still unbiased (pseudo-marginal MH stays exact).

Cost.  Per θ on top of the flat projection: the 3×3 N_t and the 3×6 and 3-vector maps
V_t = L_t⁻¹Ũ_tᵀSG, v_t = L_t⁻¹Ũ_tᵀSr̄_t (r̄ centred at the gyro mean), all from the flat
projection's weighted residuals by sums over the A triads (O(T·A)), the 3×3 Choleskys in
closed form elementwise over the samples (a batched LAPACK call per 3×3 costs more than the rest);
per draw q̃ = q − ‖V_t δ − v_t‖², δ = u(ω) − u(ω̄_t), on top of the flat path's shared 6×6 factor
(:mod:`.draw_sums`).  Samples with s_t d_t = 0 get zero corrections; a recording with none
takes the flat path unchanged.  ``experiments/bench_likelihood_percov.py`` times it on exp_1.

Instant error.  Each triad's own sampling instant errs by ε_kt ~ N(0, e_k²) (s), independent
across triads and samples — the part of the instant no clock gives (the detector's
``age_error_rms_s``).  Read at t + ε_kt, triad k errs by ε_kt ρ_kt to first order, ρ_kt the rate of
its output (m/s³: the board's jerk, ω̈ × r_k and the rotation terms, which grow with |ω| and |ω̇|
and differ by triad; :func:`triad_rates` takes it from the outputs).  With ``rate`` and
``instant_std`` the loading gains one column per triad, e_k ρ_kt on triad k's rows
(:func:`~.unresolved_cov.instant_error_loadings`): Ũ_t = [s_t D_t, E_t] of rank R = 3 + A, a
per-triad covariance e_k² ρ_kt ρ_ktᵀ beside the jerk's; the same algebra with R × R N_t
(Cholesky over the samples column by column), V_t of R rows.  ρ is a covariate fixed from the
data, like the ages.  The instant error also multiplies the unresolved jerk (ε_kt m_t, variance
e² s_t² I per triad); that isotropic part is not carried (a per-triad isotropic variance per
sample has no low-rank form; the per-|ω̄|-band level factor that would approximate it made the
real board's std less honest, ``experiments/mimu_model_calibrate.md``, ``with_bins``).

Angular jerk.  Rigid-body kinematics moves triad k's specific force at j_t + ω̈_t × r_k (plus
terms in ω and ω̇ that the outputs resolve), so a triad read at centred age d_kt also errs by
d_kt ω̈_t × (r_k − r̄): the board's unresolved angular jerk ω̈_t ~ N(0, a_t² I₃) (rad/s³, its scale
per |ω| band like the jerk's) loaded by rows d_kt [r_k − r̄]×
(:func:`~.unresolved_cov.rotational_loadings`).  With ``angjerk_std`` and ``lever`` (the triads'
positions, a covariate fixed from the nominal geometry: the θ being inferred moves them by
millimetres, the loading by that fraction of a lever arm of centimetres) Ũ_t = [s_t D_t, a_t D^r_t]
of rank 6 (plus the instant error's A columns if given) by the general path below.  On vibrating
boards read at different instants this is the larger part of the misfit (ω̈ ~ 10⁴–10⁵ rad/s³ ×
2–5 cm × 0.5 ms ≈ 1–3 m/s²; ``experiments/angjerk_probe.md``, ``experiments/percov_conceal.md``);
on the six real experiments it brings every sandwich ratio down a little
(``experiments/mimu_model_calibrate.md``).  On by default in ``calibrate --model`` (option
``angular_jerk``, ``--no-angular-jerk``) since one log p̂ with it meets the 4× bar on exp_1
(``experiments/bench_likelihood_percov.md``).

Cost of the general path (R columns, J = 3 or 6 of them age-loaded, scales c_t).  Per θ: N_t − I =
diag(c_t)[Σ_k d_kt² P_kᵀP_k − (L⁻¹H_wᵀW_t)ᵀ(L⁻¹H_wᵀW_t)]diag(c_t) by one matrix product of a J² × A(A+1)/2
coefficient matrix with the θ-free age pairs d_kt d_lt (all columns age-loaded, A ≤ 12; else the
elementwise Gram over the six φ components) and the R × R Choleskys right-looking, one elementwise op
per column over all samples.  Per draw: u = W_tᵀ(Ẽ_w δ − Λ^½e_t) by a (3A × 6) and a (J × 3A) product
over the samples and ‖L_N⁻¹u‖² by forward substitution (at calibrate's N ≤ 6 draws fewer operations
than the R × 7 maps per θ).  No (·, T) allocation without autograd.  Exact: the same log p̂ to
round-off (the dense-Gaussian tests of ``tests/model/test_angular_jerk.py``).

Unknown ages.  A triad whose data age the report does not give (no ``sampling_clock`` finding)
still samples on its own clock: its age is d̄_k + δ_kt, δ uniform over the register hold, so
``age_var`` v_k = (1/f)²/12 adds v_k (s_t² I₃ + a_t² [r_k − r̄]×[r_k − r̄]×ᵀ) on its rows — three
columns on that triad alone — and, with ``age_rate`` ρ_kt (the rate of its output, which the
clocks' mean correction takes off only at the expected age), v_k ρ_kt ρ_ktᵀ, a fourth
(:func:`~.unresolved_cov.age_prior_blocks`), carried with the
instant-error columns as per-triad blocks of the general path (the expected age d̄_k is in
``age``; :func:`.report_terms.unresolved_terms` gives both).

Related: the scales s_b and ν fitted by type-II ML (:mod:`.unresolved_fit`); a report's clocks
and scales read at the samples (:func:`.report_terms.unresolved_terms`); the gyro twin, the
unresolved angular acceleration in the posterior of ω (:func:`.gyro_posterior.gyro_posterior_timing`);
the same covariance on residuals, as the detector scores it (:mod:`.unresolved_cov`).
"""
from __future__ import annotations

import copy
import math

import numpy as np
import torch

from ..errors import UserError
from ..physics.models import u_of_omega
from .likelihood import RaoBlackwellLikelihood
from .percov_covariates import ages_from_clocks, band_scale, triad_rates  # noqa: F401 — re-exported
from .unresolved_cov import age_prior_blocks, centred_ages, instant_error_loadings, loadings, rotational_loadings

# the distinct entries (j, k) of the symmetric 3×3 N_t, in the order the Cholesky below reads them
_PAIRS = ((0, 0), (1, 1), (2, 2), (1, 0), (2, 0), (2, 1))

# N_t from the age pairs d_kt d_lt (k ≤ l) up to this many pairs (A ≤ 12): that product grows as A², the Gram
# only as A (measured at A = 8 only: 0.3 against 0.7 ms on exp_1; the cap is an estimate from the growths).
_MAX_AGE_PAIRS = 78

__all__ = ["PerSampleCovLikelihood", "with_unresolved_motion", "ages_from_clocks", "band_scale", "triad_rates"]


def with_unresolved_motion(lik: RaoBlackwellLikelihood, age, jerk_std, nu=None, *, rate=None,
                           instant_std=None, angjerk_std=None, lever=None, age_var=None,
                           age_rate=None) -> "PerSampleCovLikelihood":
    """The per-sample-covariance likelihood on ``lik``'s data (shared, not copied): ``age`` (T, A)
    s the rows' data ages, ``jerk_std`` scalar or (T,) m/s³, ``nu`` None or the degrees of
    freedom of the scale mixture; ``rate`` (T, A, 3) m/s³ and ``instant_std`` (s, scalar or (A,))
    the triads' own instant error (module docstring, "Instant error"); ``angjerk_std`` scalar or (T,)
    rad/s³ and ``lever`` (A, 3) m the board's angular jerk and the triads' positions that load it
    (module docstring, "Angular jerk"); ``age_var`` (A,) s² the variance of the data age of triads
    whose age is not known (0 where it is) and ``age_rate`` None or (T, A, 3) m/s³ their outputs'
    rates (module docstring, "Unknown ages")."""
    if type(lik) is not RaoBlackwellLikelihood and not isinstance(lik, PerSampleCovLikelihood):
        # a subclass (the tempered likelihood) would silently lose its own log_phat here
        raise UserError(f"lik: expected an untempered RaoBlackwellLikelihood, got {type(lik).__name__}")
    new = copy.copy(lik)
    new.__class__ = PerSampleCovLikelihood
    new._set_terms(age, jerk_std, nu, rate, instant_std, angjerk_std, lever, age_var, age_rate)
    return new


class PerSampleCovLikelihood(RaoBlackwellLikelihood):
    """:class:`~.likelihood.RaoBlackwellLikelihood` with the unresolved jerk loaded by the data
    ages and an optional scale mixture (module docstring).

    Extra parameters: ``age`` (T, A) s, the data age of each row's output (centred here);
    ``jerk_std`` scalar or (T,) m/s³, the jerk's scale per axis at each sample (0: absent);
    ``nu`` None (Gaussian) or ν > 0, the degrees of freedom of the per-sample scale mixture;
    ``angjerk_std`` scalar or (T,) rad/s³ with ``lever`` (A, 3) m: the angular jerk (module docstring).
    The tempered likelihood (:mod:`.tempering`) does not combine with it.
    """

    def __init__(self, acc, omega, acc_noise_std, num_draws, age, jerk_std, nu=None, reference: int = 0,
                 dtype=torch.float64, device=None, phi_prior=None, rate=None, instant_std=None, angjerk_std=None,
                 lever=None, age_var=None, age_rate=None):
        super().__init__(acc, omega, acc_noise_std, num_draws, reference=reference, dtype=dtype, device=device,
                         phi_prior=phi_prior)
        self._set_terms(age, jerk_std, nu, rate, instant_std, angjerk_std, lever, age_var, age_rate)

    def _set_terms(self, age, jerk_std, nu, rate=None, instant_std=None, angjerk_std=None, lever=None, age_var=None,
                   age_rate=None):
        age = torch.as_tensor(np.asarray(age, dtype=np.float64) if not torch.is_tensor(age) else age,
                              dtype=self.dtype, device=self.device)
        if age.shape != (self.T, self.A):
            raise UserError(f"age: expected shape (T, A) = ({self.T}, {self.A}) s, got {tuple(age.shape)}")
        if not bool(torch.isfinite(age).all()):
            raise UserError("age: expected finite data ages (s)")
        s = self._per_sample_scale(jerk_std, "jerk_std", "m/s³")
        if nu is not None:
            # a tensor that requires grad is kept (fits of ν); anything else becomes a float
            nu = nu if torch.is_tensor(nu) and nu.requires_grad else float(nu)
            v = float(nu.detach()) if torch.is_tensor(nu) else nu
            if not (math.isfinite(v) and v > 0):
                raise UserError(f"nu: expected degrees of freedom > 0 or None, got {v!r}")
        self.age = age
        self.jerk_std = s
        self.nu = nu
        # Ũ_t = s_t D_t only through the product u_kt = s_t d_kt (m/s² per unit-variance jerk)
        self.loading = centred_ages(age) * s[:, None]
        self.rate, self.instant_std, self.W = None, None, None
        self.angjerk_std, self.lever, self.loading_rot, self._cross = None, None, None, None
        if (rate is None) != (instant_std is None):
            raise UserError("rate, instant_std: give both (the triads' own instant error) or neither")
        if (angjerk_std is None) != (lever is None):
            raise UserError("angjerk_std, lever: give both (the board's angular jerk) or neither")
        if angjerk_std is not None:
            self._set_angular_jerk(angjerk_std, lever)
        self.age_var = None
        if age_var is not None:
            v = torch.as_tensor(age_var, dtype=self.dtype, device=self.device)
            if v.shape != (self.A,) or not bool(torch.isfinite(v).all()) or bool((v < 0).any()):
                raise UserError(f"age_var: expected finite variances >= 0 of shape (A,) = ({self.A},) s², got "
                                f"{tuple(v.shape)}")
            self.age_var = v if bool((v > 0).any()) else None  # all clocked: nothing to add
        if age_rate is not None:
            age_rate = torch.as_tensor(age_rate, dtype=self.dtype, device=self.device)
            if age_rate.shape != (self.T, self.A, 3) or not bool(torch.isfinite(age_rate).all()):
                raise UserError(f"age_rate: expected finite output rates of shape (T, A, 3) = ({self.T}, {self.A}, 3) "
                                f"m/s³, got {tuple(age_rate.shape)}")
        self.age_rate = age_rate
        self.general = rate is not None or angjerk_std is not None or self.age_var is not None
        if self.general:
            self._set_general(rate, instant_std)
        self.active = torch.nonzero((self.loading != 0).any(-1)).reshape(-1)
        if self.general:  # the general path loads every sample
            self.active = torch.arange(self.T, device=self.device)
        self._tf_cache = None

    def _per_sample_scale(self, value, field, unit) -> torch.Tensor:
        s = torch.as_tensor(value, dtype=self.dtype, device=self.device)
        s = s.expand(self.T) if s.dim() == 0 else s
        if s.shape != (self.T,) or not bool(torch.isfinite(s).all()) or bool((s < 0).any()):
            raise UserError(f"{field}: expected a finite scale >= 0 ({unit}), scalar or ({self.T},), got shape "
                            f"{tuple(s.shape)}")
        return s

    def _set_angular_jerk(self, angjerk_std, lever):
        """The angular jerk's loading (module docstring, "Angular jerk"): a_t d_kt per triad and the
        lever arms' cross-product matrices [r_k − r̄]× (A, 3, 3), positions ``lever`` (A, 3) m."""
        a = self._per_sample_scale(angjerk_std, "angjerk_std", "rad/s³")
        lev = torch.as_tensor(np.asarray(lever, dtype=np.float64) if not torch.is_tensor(lever) else lever,
                              dtype=self.dtype, device=self.device)
        if lev.shape != (self.A, 3) or not bool(torch.isfinite(lev).all()):
            raise UserError(f"lever: expected finite positions of shape (A, 3) = ({self.A}, 3) m, got "
                            f"{tuple(lev.shape)}")
        self.angjerk_std, self.lever = a, lev
        self.loading_rot = centred_ages(self.age) * a[:, None]
        # rotational_loadings of a unit age on every triad: the per-triad 3×3 block [r_k − r̄]×
        self._cross = rotational_loadings(torch.ones(1, self.A, dtype=self.dtype, device=self.device),
                                          lev).view(self.A, 3, 3)

    def _set_general(self, rate, instant_std):
        """The whitened loading W_t = Λ^½[s_t D_t, angular jerk block, per-triad blocks]
        (T, 3A, R) of the general path (module docstring, "Angular jerk", "Instant error", "Unknown
        ages"), formed only where its Gram path needs it (per-triad blocks, more than
        ``_MAX_AGE_PAIRS`` pairs of triads); the per-triad blocks (columns that each live on one
        triad's rows) are kept as ``_blocks`` = (triad of each column (C,), λ^½-whitened values (C, 3, T))."""
        self._blocks = None
        if rate is not None:
            rate = torch.as_tensor(rate, dtype=self.dtype, device=self.device)
            if rate.shape != (self.T, self.A, 3) or not bool(torch.isfinite(rate).all()):
                raise UserError(f"rate: expected finite output rates of shape (T, A, 3) = ({self.T}, {self.A}, 3) "
                                f"m/s³, got {tuple(rate.shape)}")
            e = instant_std if torch.is_tensor(instant_std) else torch.as_tensor(instant_std, dtype=self.dtype)
            e = e.to(self.dtype)
            if e.dim() > 1 or (e.dim() == 1 and len(e) != self.A) or not bool(torch.isfinite(e).all()) \
                    or bool((e < 0).any()):
                raise UserError(f"instant_std: expected a finite std >= 0 (s), scalar or ({self.A},)")
            self.rate, self.instant_std = rate, e
        cols, tri, vals = self._loading_columns()
        if tri or self.A * (self.A + 1) // 2 > _MAX_AGE_PAIRS:
            self.W = torch.cat(cols, -1) * self._sqrt_lam[None, :, None]  # (T, 3A, R)
        if tri:
            k = torch.cat(tri)
            sl = self._sqrt_lam.view(self.A, 3)
            self._blocks = (k, (torch.cat(vals, 1) * sl[k]).permute(1, 2, 0).contiguous())
            self._blocks_identity = len(k) == self.A and bool((k == torch.arange(self.A, device=k.device)).all())

    def _loading_columns(self):
        """The per-sample covariance's loading Ũ_t as column blocks (unwhitened, in the order the
        general path stacks them): ([(T, 3A, ·) blocks], [triad of each per-triad column], [their
        values (T, ·, 3)]) — the jerk, the angular jerk, the instant errors, the unknown ages."""
        cols = [loadings(self.loading)]
        tri, vals = [], []
        if self.loading_rot is not None:
            cols.append(rotational_loadings(self.loading_rot, self.lever))
        if self.rate is not None:
            cols.append(instant_error_loadings(self.rate, self.instant_std))
            tri.append(torch.arange(self.A, device=self.device))
            vals.append(self.rate * self.instant_std.expand(self.A)[:, None])
        if self.age_var is not None:
            k, v = age_prior_blocks(self.age_var, self.jerk_std, self.angjerk_std, self.lever, self.age_rate)
            dense = torch.zeros(self.T, self.A, 3, len(k), dtype=self.dtype, device=self.device)
            dense.permute(1, 3, 0, 2)[k, torch.arange(len(k))] = v.transpose(0, 1)  # column j on triad k[j]
            cols.append(dense.reshape(self.T, 3 * self.A, len(k)))
            tri.append(k.to(self.device))
            vals.append(v)
        return cols, tri, vals

    def loading_matrix(self) -> torch.Tensor:
        """Ũ (T, 3A, R): every column of the per-sample covariance Ũ_tŨ_tᵀ (units of the outputs per
        unit-variance state), unwhitened; the jerk alone on the closed-form path.  With it the
        sample's covariance is Q + Ũ_tŨ_tᵀ (+ HFHᵀ under a proper φ prior), which
        :mod:`.acc_block_marginal` inverts densely."""
        return torch.cat(self._loading_columns()[0], -1)

    # ------------------------------------------------------------------ per-θ terms
    def _percov_terms(self, r: torch.Tensor) -> dict:
        """The flat projection at r (B, A, 3) plus ``V`` (B, 3, 7, T): rows i of [V_t, v_t] =
        L_t⁻¹[Ũ_tᵀSG, Ũ_tᵀSr̄_t] stored component-first for the per-draw sums, and ``logdetN``
        (B, T) (module docstring; zero where the sample has no loading)."""
        if self.general:
            return self._percov_terms_general(r)
        proj = self._projection_hot(r, extras=True)
        B, A, T = r.shape[0], self.A, self.T
        idx = self.active
        full = len(idx) == T
        u_t, diag, usl, sum3 = self._theta_free
        Ta = u_t.shape[1]
        sl = self._sqrt_lam.view(A, 3, 1)
        # Without autograd the (B, ·, T) temporaries live in reused buffers, as in the flat
        # projection (fresh MB-sized allocations cost page faults comparable to the arithmetic).
        reuse = not (torch.is_grad_enabled() and (r.requires_grad or self.loading.requires_grad))
        ws = self._workspace if reuse else (lambda name, shape: None)
        # Layouts keep the sample index last (contiguous), so every per-sample step below is an
        # elementwise op over T or a reduction over an outer dimension.
        # HᵀΛŨ_t as (B, 6, 3, Ta): one (18 × A)(A × Ta) product per θ
        Hs = (proj["Hw"].view(B, A, 3, 6) * sl).permute(0, 3, 2, 1).reshape(B, 18, A)
        Y = torch.matmul(Hs, u_t, out=ws("pc_Y", (B, 18, Ta))).view(B, 6, 3 * Ta)
        Yh = torch.linalg.solve_triangular(proj["L"], Y, upper=False, out=ws("pc_Yh", (B, 6, 3 * Ta)))
        Yh = Yh.view(B, 6, 3, Ta)  # (M + F⁻¹)^(-½) HᵀΛŨ_t
        # N_t = I + ŨᵀΛŨ − (HᵀΛŨ)ᵀ(M + F⁻¹)⁻¹(HᵀΛŨ) = I + Ũ_tᵀSŨ_t: its 6 distinct entries
        tmp = ws("pc_tmp", (B, 6, Ta))
        P = [torch.mul(Yh[:, :, j], Yh[:, :, k], out=tmp).sum(1) for j, k in _PAIRS]
        n00, n11, n22 = diag[0] - P[0], diag[1] - P[1], diag[2] - P[2]
        n10, n20, n21 = P[3].neg(), P[4].neg(), P[5].neg()
        # 3×3 Cholesky and forward substitution in closed form over all samples at once (N_t ⪰ I:
        # the square roots are of numbers ≥ 1 up to rounding)
        l00 = n00.sqrt()
        l10, l20 = n10 / l00, n20 / l00
        l11 = (n11 - l10 * l10).sqrt()
        l21 = (n21 - l20 * l10) / l11
        l22 = (n22 - l20 * l20 - l21 * l21).sqrt()
        e_w = proj["e_w"] if full else proj["e_w"][:, idx]
        a = torch.matmul(torch.mul(e_w, usl, out=ws("pc_eu", (B, Ta, 3 * A))), sum3)  # Ũ_tᵀ Λ e_t = Ũ_tᵀ S r̄_t
        Gs = (proj["Gt"].view(B, A, 3, 6) * sl).permute(0, 2, 3, 1).reshape(B, 18, A)
        Ea = torch.cat((torch.matmul(Gs, u_t, out=ws("pc_E", (B, 18, Ta))).view(B, 3, 6, Ta),
                        a.transpose(1, 2)[:, :, None]), 2, out=ws("pc_Ea", (B, 3, 7, Ta)))  # [Ũ_tᵀSG, Ũ_tᵀSr̄_t]
        Xb = ws("pc_X", (B, 3, 7, Ta))
        o = (lambda i: None) if Xb is None else (lambda i: Xb[:, i])
        x0 = torch.div(Ea[:, 0], l00[:, None], out=o(0))
        x1 = torch.addcmul(Ea[:, 1], l10[:, None], x0, value=-1, out=o(1))
        x1 = torch.div(x1, l11[:, None], out=o(1))
        x2 = torch.addcmul(Ea[:, 2], l20[:, None], x0, value=-1, out=o(2))
        x2 = torch.addcmul(x2, l21[:, None], x1, value=-1, out=o(2))
        x2 = torch.div(x2, l22[:, None], out=o(2))
        X = Xb if Xb is not None else torch.stack((x0, x1, x2), 1)  # (B, 3, 7, Ta)
        logdetN = 2 * (l00.log() + l11.log() + l22.log())
        if not bool(torch.isfinite(logdetN).all()):
            raise UserError("age: the per-sample covariance is not positive definite (non-finite loading?)")
        if full:
            V = X
        else:
            V = torch.zeros(B, 3, 7, T, dtype=self.dtype, device=self.device)
            V[..., idx] = X
            logdetN = torch.zeros(B, T, dtype=self.dtype, device=self.device).index_copy(1, idx, logdetN)
        proj.update(V=V, logdetN=logdetN)
        return proj

    def _percov_terms_general(self, r: torch.Tensor) -> dict:
        """:meth:`_percov_terms` with the angular jerk and/or the instant errors (module docstring, "Cost of
        the general path"): ``LN`` L_N's columns and inverse pivots (:func:`_cholesky_over_samples`),
        N_t = L_N L_Nᵀ, and ``logdetN``; no ``V``: the draws' W_tᵀS(r̄_t − Gδ) come from
        :meth:`_w_residual`.  The instant errors' columns (column k on triad k's rows) enter N_t by the Gram."""
        proj = self._projection_hot(r, extras=True)
        B, A, T = r.shape[0], self.A, self.T
        d_t, d_rows, cs, P, wk, wtw, pairs = self._theta_free
        J = P.shape[-1]
        R = J + (0 if wk is None else wk.shape[0])
        # Without autograd every (·, T) temporary lives in a reused buffer (fresh MB-sized
        # allocations cost page faults comparable to the arithmetic) and the Cholesky runs in place.
        reuse = not (torch.is_grad_enabled() and (r.requires_grad or cs.requires_grad
                                                  or (wk is not None and wk.requires_grad)))
        ws = self._workspace if reuse else (lambda name, shape: None)
        # L⁻¹H_wᵀ first (6 × 3A per θ), so no triangular solve runs over the samples
        Kh = torch.linalg.solve_triangular(proj["L"], proj["Hw"].transpose(-1, -2), upper=False)
        if pairs is not None:
            N = self._n_from_age_pairs(Kh, P, pairs, ws("pc_N", (J * J * B, T)))
        else:
            # L⁻¹H_wᵀW_t (6, R, B, T): the age-loaded columns by one (6·J·B × A)(A × T) product, the
            # sample index last so every per-sample step is an elementwise op over the samples
            lhs = torch.einsum("bfki,kir->frbk", Kh.view(B, 6, A, 3), P).reshape(6 * J * B, A)
            Yh = (lhs @ d_t).view(6, J, B, T) * cs[:, None]
            if wk is not None:
                Kk = Kh.view(B, 6, A, 3).permute(0, 2, 1, 3)  # (B, A, 6, 3)
                if not self._blocks_identity:  # column j on triad k[j]'s rows
                    Kk = Kk[:, self._blocks[0]]
                Yk = torch.matmul(Kk, wk).permute(2, 1, 0, 3)  # (6, C, B, T)
                Yh = torch.cat((Yh, Yk), 1)
            # N_t = I + W_tᵀW_t − Σ_f (L⁻¹H_wᵀW_t)_f (L⁻¹H_wᵀW_t)_fᵀ: one rank-1 update per φ component
            N = torch.addcmul(wtw[:, :, None], Yh[0, :, None], Yh[0, None], value=-1, out=ws("pc_N", (R, R, B, T)))
            for f in range(1, 6):
                N = N.addcmul_(Yh[f, :, None], Yh[f, None], value=-1)
        piv, cols, inv = _cholesky_over_samples(N, inplace=reuse)
        logdetN = 2 * piv.log().sum(0)  # not finite where a pivot is not positive and finite
        if not bool(torch.isfinite(logdetN).all()):
            raise UserError("rate: the per-sample covariance is not positive definite (non-finite loading?)")
        proj.update(logdetN=logdetN, LN=(cols, inv))
        return proj

    def _w_residual(self, p: dict, d: torch.Tensor, t0: int, t1: int, ws=None) -> torch.Tensor:
        """u = W_tᵀ(Ẽ_w δ − Λ^½e_t) (B, R, τ, N) at the samples t0:t1 of the general path (module docstring),
        δ = ``d`` (6, τ, N) or (B, 6, τ, N), ``p`` its projection (Ẽ_w = ``Gt``, Λ^½e = ``e_w``); ``ws`` a
        workspace (no autograd: temporaries reused, updated in place)."""
        inplace = ws is not None
        buf = ws if inplace else (lambda name, shape: None)
        _, d_rows, cs, P, wk, _, _ = self._theta_free
        Gt, ew = p["Gt"], p["e_w"]
        B, n = Gt.shape[0], Gt.shape[1]
        tau, N = d.shape[-2], d.shape[-1]
        J = P.shape[-1]
        g = torch.matmul(Gt, d.reshape(*d.shape[:-3], 6, tau * N), out=buf("pc_g", (B, n, tau * N))).view(B, n, tau, N)
        e = ew[:, t0:t1, :, None].transpose(1, 2)
        g = g.sub_(e) if inplace else g - e  # Ẽ_w δ − Λ^½e_t (B, 3A, τ, N)
        gd = torch.mul(g, d_rows[t0:t1].T[None, :, :, None], out=buf("pc_gd", (B, n, tau, N)))
        u = torch.matmul(P.reshape(n, J).T, gd.view(B, n, tau * N), out=buf("pc_u", (B, J, tau * N)))
        u = u.view(B, J, tau, N)
        u = u.mul_(cs[:, t0:t1, None]) if inplace else u * cs[:, t0:t1, None]
        if wk is not None:
            gk = g.view(B, self.A, 3, tau, N)
            gk = gk if self._blocks_identity else gk[:, self._blocks[0]]  # column j on triad k[j]'s rows
            uk = (gk * wk[:, :, t0:t1, None]).sum(2)  # (B, C, τ, N)
            u = torch.cat((u, uk), 1)
        return u

    @staticmethod
    def _n_from_age_pairs(Kh, P, pairs, out=None):
        """N_t (J, J, B, T) when W_t's rows of triad k are d_kt P_k diag(c_t): N_t − I = diag(c_t) Σ_k,l
        d_kt d_lt C_kl diag(c_t), C_kl = δ_kl P_kᵀP_k − (L⁻¹H_w,kᵀP_k)ᵀ(L⁻¹H_w,lᵀP_l) (J × J per θ): one
        (J²B × A(A+1)/2)(A(A+1)/2 × T) product (the Gram costs ≈ 2.5× more at A = 8).  ``Kh`` L⁻¹H_wᵀ
        (B, 6, 3A), ``P`` (A, 3, J), ``pairs`` (k, l, d_kd_l (½ on k = l), 2δ_kl P_kᵀP_k, c_ic_j)."""
        kk, ll, F, ptp2, sc = pairs
        B, A, J = Kh.shape[0], P.shape[0], P.shape[-1]
        Zk = torch.einsum("bfki,kir->bkfr", Kh.view(B, 6, A, 3), P)  # (B, A, 6, J): L⁻¹H_w,kᵀP_k
        X = torch.einsum("bkfi,blfj->bklij", Zk, Zk)  # (B, A, A, J, J)
        coef = ptp2 - X[:, kk, ll] - X[:, ll, kk]  # (B, pairs, J, J): C_kl + C_lk (k < l), 2C_kk
        G = torch.mm(coef.permute(2, 3, 0, 1).reshape(J * J * B, -1), F, out=out).view(J, J, B, -1)
        N = torch.mul(G, sc[:, :, None], out=G if out is not None else None)
        N.diagonal(0, 0, 1).add_(1.0)
        return N

    @property
    def _theta_free(self):
        """Cached θ-free tensors.  Closed-form path (jerk only), of the loaded samples: uᵀ (A, Ta);
        diag(ŨᵀΛŨ) + 1 (3, Ta); u_kt λ_k^½ (Ta, 3A); the (3A, 3) triad-sum matrix.  General path: the
        centred ages dᵀ (A, T) and per row (T, 3A); the J = 3 or 6 age-loaded columns' scales (J, T) (s_t,
        a_t) and blocks Λ_k^½[I₃, [r_k − r̄]×] (A, 3, J); the per-triad block columns' λ^½-whitened values
        (C, 3, T) (instant errors, unknown ages); I + W_tᵀW_t (R, R, T) for the Gram; the age pairs of :meth:`_n_from_age_pairs` (each None where unused)."""
        if getattr(self, "_tf_cache", None) is None and self.general:
            wk = None if self._blocks is None else self._blocks[1]
            sl = self._sqrt_lam.view(self.A, 3)
            P = torch.diag_embed(sl)  # (A, 3, 3): Λ_k^½ I₃
            cs = self.jerk_std.expand(3, self.T)
            if self.loading_rot is not None:
                P = torch.cat((P, self._cross * sl[..., None]), -1)
                cs = torch.cat((cs, self.angjerk_std.expand(3, self.T)), 0)
            d_t = centred_ages(self.age).T.contiguous()
            pairs, wtw = None, None
            if self.W is None:
                kk, ll = torch.triu_indices(self.A, self.A, device=self.device)
                F = d_t[kk] * d_t[ll] * torch.where(kk == ll, 0.5, 1.0).to(self.dtype)[:, None]
                ptp2 = 2 * (P.transpose(-1, -2) @ P)[kk] * (kk == ll).to(self.dtype)[:, None, None]
                pairs = (kk, ll, F.contiguous(), ptp2, cs[:, None] * cs[None])
            else:  # the Gram's θ-free part
                eye = torch.eye(self.W.shape[-1], dtype=self.dtype, device=self.device)
                wtw = self.W.transpose(-1, -2) @ self.W + eye
                wtw = wtw.permute(1, 2, 0).contiguous()
            d_rows = d_t.T.repeat_interleave(3, 1)  # (T, 3A)
            self._tf_cache = (d_t, d_rows, cs, P, wk, wtw, pairs)
        if getattr(self, "_tf_cache", None) is None:
            u = self.loading[self.active]  # (Ta, A)
            lam = self.lam.view(self.A, 3)
            usl = (u[..., None] * self._sqrt_lam.view(self.A, 3)).reshape(len(u), 3 * self.A)
            sum3 = torch.eye(3, dtype=self.dtype, device=self.device).repeat(self.A, 1)
            self._tf_cache = (u.T.contiguous(), (1.0 + (u * u) @ lam).T.contiguous(), usl, sum3)
        return self._tf_cache

    def _kernel(self, q: torch.Tensor) -> torch.Tensor:
        """Per-draw log weight from q̃ (any shape): −½ q̃ (Gaussian) or the scale mixture's
        closed form (module docstring)."""
        if self.nu is None:
            return -0.5 * q
        a = 0.5 * torch.as_tensor(self.nu, dtype=q.dtype, device=q.device)
        n = 3 * self.A - (0 if self.phi_prior_prec is not None else 6)
        const = torch.lgamma(a + n / 2) - torch.lgamma(a) - n / 2 * torch.log(a)
        return const - (a + n / 2) * torch.log1p(q.clamp_min(0) / (2 * a))

    # ------------------------------------------------------------------ estimators
    def log_lik_given_omega(self, positions: torch.Tensor, omega: torch.Tensor) -> torch.Tensor:
        """log p(y^a | ω_{1:T}, θ) with φ_t, m_t (and λ_t) integrated out (module docstring), up to
        the base class's dropped constants.  positions (..., A, 3) m; omega (T, 3) or (..., T, 3)
        rad/s broadcasting against the positions' batch.  Returns (...); differentiable."""
        return self.log_lik_per_sample(positions, omega).sum(-1) + self._block_term(positions)

    def log_lik_per_sample(self, positions: torch.Tensor, omega: torch.Tensor) -> torch.Tensor:
        """The terms log p(y_t^a | ω_t, θ) (..., T) nats of :meth:`log_lik_given_omega`, each with
        its share −½ log|M(θ)| of the common determinant: differentiated per sample they are the
        scores a sandwich needs (the samples are independent given ω and θ)."""
        r = self._positions(positions)
        batch = r.shape[:-2]
        B = int(np.prod(batch)) if len(batch) else 1
        omega = torch.as_tensor(omega, dtype=self.dtype, device=self.device)
        delta = (u_of_omega(omega) - u_of_omega(self.omega.mean)).expand(*batch, self.T, 6).reshape(B, self.T, 6)
        p = self._percov_terms(r.reshape(B, self.A, 3))
        if "LN" in p:  # the general path: u = W_tᵀS(r̄_t − Gδ_t), then L_N⁻¹u
            u = self._w_residual(p, delta.transpose(1, 2)[..., None], 0, self.T)
            corr = _forward_solve_sq(u, *p["LN"], lambda x: x[..., None], inplace=False)[..., 0]
        else:
            V = p["V"]  # (B, 3, 7, T)
            corr = (torch.einsum("bijt,btj->bit", V[:, :, :6], delta) - V[:, :, 6]).square().sum(1)
        q = p["c"] - 2 * (p["b"] * delta).sum(-1) + ((delta @ p["C"]) * delta).sum(-1) - corr
        out = self._kernel(q) - 0.5 * p["logdetM"][:, None] - 0.5 * p["logdetN"]
        return out.reshape(*batch, self.T)

    def log_phat(self, positions, generator=None, z=None, num_draws=None, independent_draws: bool = False):
        """log p̂(y^a | y^g, θ) with the per-sample covariance (module docstring); the arguments and
        the draws are :meth:`RaoBlackwellLikelihood.log_phat`'s (same z → the same ω draws).
        Without any loaded sample and with ``nu=None`` it is the flat estimator itself."""
        if len(self.active) == 0 and self.nu is None:
            return super().log_phat(positions, generator=generator, z=z, num_draws=num_draws,
                                    independent_draws=independent_draws)
        r = self._positions(positions)
        batch = r.shape[:-2]
        z = self._draws(batch, z, num_draws, generator, independent_draws)
        N = z.shape[-2]
        B = int(np.prod(batch)) if len(batch) else 1
        p = self._percov_terms(r.reshape(B, self.A, 3))
        zt = z.transpose(-1, -2)
        if len(zt.shape[:-3]):
            zt = zt.expand(*batch, *zt.shape[-3:]).reshape(B, self.T, 3, N)
        Rc, w, floor = self._factor_any(p["c"], p["b"], p["C"])
        V = p.get("V")  # (B, 3, 7, T) on the jerk's closed-form path
        # without autograd the per-draw temporaries live in reused buffers, updated in place
        grad = torch.is_grad_enabled() and (p["logdetN"].requires_grad or zt.requires_grad)
        ws = (lambda name, shape: None) if grad else self._workspace

        def logw(s, d, t0, t1):
            # d (…, 6, τ, N): q̃ = s + floor − ‖V_t δ − v_t‖², the 3×6 product as six fused multiply-adds
            # over (B, 3, τ, N) (a batched matmul of 3×6 blocks is slower); the general path: ‖L_N⁻¹u‖²
            if "LN" in p:
                u = self._w_residual(p, d, t0, t1, None if grad else self._workspace)
                corr = _forward_solve_sq(u, *p["LN"], lambda x: x[..., t0:t1, None], inplace=not grad)
                return self._kernel(corr.neg_().add_(s).add_(floor[:, t0:t1, None]))
            Vc = V[..., t0:t1, None]  # (B, 3, 7, τ, 1)
            dd = d if d.dim() == 3 else d[:, None]  # (6, τ, N) or (B, 1, 6, τ, N)
            acc = torch.mul(Vc[:, :, 0], dd[..., 0, :, :], out=ws("pc_acc", (B, 3, t1 - t0, N)))
            for j in range(1, 6):
                acc = acc.addcmul_(Vc[:, :, j], dd[..., j, :, :])
            corr = torch.mul(acc.sub_(Vc[:, :, 6]), acc, out=None if grad else acc).sum(1)  # (B, τ, N)
            return self._kernel(corr.neg_().add_(s).add_(floor[:, t0:t1, None]))

        inplace = not (torch.is_grad_enabled() and (Rc.requires_grad or zt.requires_grad))
        lse = self._lse_direct(zt, Rc, w, inplace, logw=logw)  # (B, T)
        out = lse.sum(-1) - self.T * math.log(N) - 0.5 * self.T * p["logdetM"] - 0.5 * p["logdetN"].sum(-1)
        return out.reshape(batch) + self._block_term(positions)

    def _factor_any(self, c, b, C):
        """(R_C, w, floor) with q = ‖R_C δ + w_t‖² + floor_t: :meth:`_factor` where it applies,
        else (C singular, A ≤ 4 rounding) a square root of C from its eigendecomposition and the
        pseudo-inverse (b_t lies in C's range, both being Ẽ_wᵀ times a vector); ``floor`` is then
        only c − ‖w‖², which the max-shifted log-sum-exp does not need to bound q."""
        fac = self._factor(c, b, C)
        if fac is not None:
            return fac
        ev, Vc = torch.linalg.eigh(C)
        tol = ev.amax(-1, keepdim=True) * 1e-12
        root = ev.clamp_min(0).sqrt()
        Rc = root[..., :, None] * Vc.transpose(-1, -2)  # C = RcᵀRc
        inv = torch.where(ev > tol, 1.0 / root.clamp_min(1e-300), torch.zeros_like(root))
        w = -(inv[..., :, None] * (Vc.transpose(-1, -2) @ b.transpose(-1, -2)))  # −Rc⁺ᵀ b (B, 6, T)
        return Rc, w, c - (w * w).sum(-2)


def _cholesky_over_samples(N, inplace: bool = False):
    """(diagonal of L (R, …), columns L[j+1:, j] for j < R, 1/L[j, j]) of N = L Lᵀ, ``N`` (R, R, …) symmetric
    (lower part read), one per trailing index (the samples).  Right-looking, each step one elementwise op
    over all samples (a batched LAPACK call per R × R costs more than the arithmetic).  ``inplace``: N is
    scratch, overwritten by L (the columns returned are views of it); not with autograd."""
    R = N.shape[0]
    out = (lambda v: v) if inplace else (lambda v: None)  # noqa: E731
    piv, cols, inv = [], [], []
    for j in range(R):
        p = torch.sqrt(N[0, 0], out=out(N[0, 0]))
        piv.append(p)
        inv.append(p.reciprocal())
        if j + 1 < R:
            col = torch.mul(N[1:, 0], inv[-1], out=out(N[1:, 0]))  # L[j+1:, j]
            cols.append(col)
            N = torch.addcmul(N[1:, 1:], col[:, None], col[None], value=-1, out=out(N[1:, 1:]))
    return torch.stack(piv), cols, inv


def _forward_solve_sq(u, cols, inv, sl, inplace: bool):
    """‖L⁻¹u‖² over dim 1 of ``u`` (B, R, …), L's ``cols``, ``inv`` from :func:`_cholesky_over_samples`;
    ``sl`` maps their (…, B, T) to u's trailing shape.  ``inplace``: u is scratch (no autograd)."""
    R = u.shape[1]
    if inplace:
        for j in range(R):
            x = u[:, j].mul_(sl(inv[j]))
            if j + 1 < R:
                u[:, j + 1:].addcmul_(sl(cols[j]).movedim(0, 1), x[:, None], value=-1)
        return u.mul_(u).sum(1)
    xs, rest = [], u
    for j in range(R):
        xs.append(rest[:, 0] * sl(inv[j]))
        if j + 1 < R:
            rest = torch.addcmul(rest[:, 1:], sl(cols[j]).movedim(0, 1), xs[-1][:, None], value=-1)
    return torch.stack(xs, 1).square().sum(1)
