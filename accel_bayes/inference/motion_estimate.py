"""Using a calibration: per-sample motion of a calibrated array (ω, ω̇, s) with uncertainty.

Given a recording and a calibrated geometry (a DESIGN §7.3 ``positions.json``), every sample t
has 9 unknowns x_t = [ω_t, ω̇_t, s_t] and the measurements of [C21] eq. 4:

    accelerometer k:  R_k ᵀ y_k,t^a = f(r_k; ω_t, ω̇_t, s_t) + e      (models.specific_force)
    gyroscope k:      R_k ᵀ y_k,t^g = ω_t + e

R_k is the array → sensor rotation of IMU k (the calibration's ``orientation`` when given, else
the recording's nominal one); r_k the calibrated position, relative to the calibration's
reference IMU — so **s is the specific force at the reference IMU** (the origin of the
calibrated coordinates, [C21] r₁ ≡ 0), in the array frame.  Noise is white with the recording's
stated per-IMU std (or an override).

Solver
------
Weighted non-linear least squares per sample, all samples at once (no loop over samples): ω
starts at the weighted gyro mean, φ = [ω̇; s] at its linear least-squares value given ω ([C21]
eq. 5: y = G(θ)u(ω) + H(θ)φ), then a Levenberg–Marquardt loop on the batched 9×9 normal
equations (factored so that the batched work is matrix products, see
:class:`accel_bayes.physics.jacobians.AxisProjection`).
Residuals are per sensor axis with weight 1/σ_k²; in a triad flagged as clipped, an axis within
1 % of the sensor range gets weight 0 (the triad's other axes still count).  When the unclipped
gyro axes do not determine ω, the missing components come from the accelerometers — possible
because the centripetal term is quadratic in ω, which leaves the sign of ω undetermined: the
clipped gyro readings (right sign, magnitude at the range) start the solve on the right branch.
Such samples are flagged ``omega_needs_acc``; ``gyro_clipped`` flags any clipped gyro triad.

Uncertainty
-----------
* Noise part: the Laplace covariance at the optimum, (JᵀWJ)⁻¹ (Gauss–Newton Hessian).
* Geometry part: the calibration's position uncertainty N(mean_k, cov_k) (independent between
  IMUs: positions.json carries per-IMU 3×3 blocks only), propagated either by drawing ``draws``
  geometries (seeded) and re-solving every sample for each (``geometry="draws"``, default:
  ``draw_steps`` Gauss–Newton steps from the point estimate, which converge quadratically for
  perturbations this small; the sample covariance of the re-solved x over the draws), or by
  first-order propagation (``geometry="linear"``):
  dx/dr_k = −(JᵀWJ)⁻¹ Σ_{axes m of IMU k} w_m J_mᵀ ∂f_m/∂r_k with ∂f_k/∂r_k = R_k(Ω(ω)² + Ω(ω̇)),
  Cov = Σ_k (dx/dr_k) cov_k (dx/dr_k)ᵀ.  The two agree within the Monte Carlo error of the
  draws (tests/inference/test_motion_estimation.py); "linear" costs one solve instead of ``draws``.
* Total = noise part + geometry part (the two sources are independent).

Output: :class:`xarray.Dataset` (see :func:`estimate_motion`); :func:`write_motion` stores it as
NetCDF-4 (h5netcdf), atomically.

Limits.  The reported covariances assume the stated white noise and the rigid-body model with
calibrated triads; ``chi2``/``dof`` per sample says whether that holds.  On the real MIMU4444
recordings it does at rest (χ²/dof ≈ 1.1) but not in motion (median χ²/dof ≈ 2.6·10³ over the
dynamic samples of exp_2 with nominal positions): the gyros disagree with each other by ~1.4 %
of |ω| (uncalibrated gyro scale/misalignment, [C21] §IV-B) and the accelerometer residuals are
~1.5 m/s² RMS; pass larger ``acc_noise_std`` / ``gyro_noise_std`` there (as [C21] §IV-B does)
or calibrate the gyros.  Arrays without gyros start at ω = 0, where the accelerometers carry no
information on ω: such samples come out ``ill_posed``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..errors import UserError
from ..physics.geometry import quat_to_matrix
from .lm.damping import NielsenDamping
from .lm.linear import damped_step
from .lm import BatchedLevenbergMarquardt, StoppingRule
from ..physics.models import specific_force
from ..physics.jacobians import AxisProjection, axis_force, axis_force_jacobian, df_dr
from ..data.positions import POSITIONS_SCHEMA, read_positions

__all__ = [
    "MOTION_SCHEMA",
    "POSITIONS_SCHEMA",
    "PARAMS",
    "Calibration",
    "load_calibration",
    "solve_motion",
    "estimate_motion",
    "write_motion",
]

MOTION_SCHEMA = "accel_bayes.motion/1"
PARAMS = ("omega_x", "omega_y", "omega_z", "omega_dot_x", "omega_dot_y", "omega_dot_z", "s_x", "s_y", "s_z")
_CLIP_FRACTION = 0.99  # in a flagged triad, an axis within 1 % of the range counts as clipped (int16 codes
# sit a little inside the nominal range: 32767/16.4 = 1997.99 °/s of 2000)


# ------------------------------------------------------------------------------ calibration
@dataclass
class Calibration:
    """A calibrated geometry: positions (K, 3) m relative to ``reference_imu`` (NaN rows: no
    accelerometer triad), their covariances (K, 3, 3) m², optional orientations (K, 4) (NaN
    rows: use the nominal one), the method and where it came from."""

    positions: np.ndarray
    cov: np.ndarray
    orientations: np.ndarray | None
    reference_imu: int
    method: str = "unknown"
    source: str = ""

    @property
    def K(self) -> int:
        return int(self.positions.shape[0])


def _check_lever_arms(positions: np.ndarray, labels: list, rel_tol: float = 1e-6) -> None:
    """Refuse triad positions that cannot determine ω̇: it reaches the accelerometers only through
    the lever arms (f_k = (Ω(ω)² + Ω(ω̇)) p_k + s, [C21] eq. 4a), so triads at one point leave all
    of ω̇ undetermined and triads on one line leave its component along the line undetermined —
    every sample would come out ill-posed (NaN).  Positions in m."""
    d = positions - positions.mean(0)
    sv = np.linalg.svd(d, compute_uv=False) if len(positions) > 1 else np.zeros(1)
    if sv[0] <= 1e-9:  # 1 nm: coincident for any board
        raise UserError(f"calibration.imus: the calibrated accelerometer triads {labels} coincide (all at one "
                        "point): the geometry cannot determine the angular acceleration; expected distinct positions")
    if len(sv) < 2 or sv[1] <= rel_tol * sv[0]:
        raise UserError(f"calibration.imus: the calibrated accelerometer triads {labels} lie on one line: the "
                        "geometry cannot determine the angular acceleration about it; expected at least 3 triads "
                        "off one line")


def load_calibration(calibration, K: int | None = None) -> Calibration:
    """Read a calibration: a positions.json path, its parsed dict (DESIGN §7.3, schema
    ``accel_bayes.positions/1``), a (K, 3) positions array (no uncertainty), or a
    :class:`Calibration`.  Raises :class:`UserError` naming the offending field."""
    if isinstance(calibration, Calibration):
        cal = calibration
    elif isinstance(calibration, (str, Path, dict)):
        doc = read_positions(calibration)  # the one reader of the positions.json contract
        ori = doc["orientations"]
        cal = Calibration(positions=doc["means"], cov=doc["covs"],
                          orientations=ori if np.isfinite(ori).all(-1).any() else None,
                          reference_imu=doc.get("reference_imu", 0), method=str(doc.get("method", "unknown")),
                          source="positions dict")
        if not isinstance(calibration, dict):
            from ..data.io import recording_sha256

            cal.source = f"{calibration} (sha256 {recording_sha256(calibration)})"
    else:
        try:
            pos = np.asarray(calibration.detach().cpu() if torch.is_tensor(calibration) else calibration, dtype=np.float64)
        except (TypeError, ValueError):
            raise UserError(f"calibration: expected a positions.json path or dict, or a (K, 3) array, got "
                            f"{type(calibration).__name__}") from None
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise UserError(f"calibration: expected positions of shape (K, 3), got {pos.shape}")
        cal = Calibration(positions=pos.copy(), cov=np.zeros((pos.shape[0], 3, 3)), orientations=None,
                          reference_imu=0, method="given", source="positions array (no uncertainty)")
    if K is not None and cal.K != K:
        raise UserError(f"calibration.imus: lists {cal.K} IMUs, the recording has {K}")
    return cal


# ------------------------------------------------------------------------------ kernel
class _Data:
    """Per-sample measurements of one batch: sensor-frame acc y (N, M) with weights w (N, M)
    (1/σ², 0 for unused axes) and the gyro terms, reduced to the array frame:
    Γ = Σ_k R_kᵀ diag(w_g) R_k (N, 3, 3), ΓY = Σ_k R_kᵀ diag(w_g) y_g (N, 3), and the constant
    Σ y_gᵀ diag(w_g) y_g (N,)."""

    def __init__(self, y, w, Gam, GY, gconst):
        self.y, self.w, self.Gam, self.GY, self.gconst = y, w, Gam, GY, gconst

    def take(self, sl):
        return _Data(self.y[sl], self.w[sl], self.Gam[sl], self.GY[sl], self.gconst[sl])


def _cost_grad_hess(x, geo: AxisProjection, d: _Data):
    """cost (…, N), JᵀWe (…, N, 9), JᵀWJ (…, N, 9, 9) of the weighted least-squares objective
    Σ_m w_m (y_m − f_m)² + Σ_k (ȳ_k − ω)ᵀ Γ_k (ȳ_k − ω)  (factored form, see :class:`AxisProjection`)."""
    w = x[..., 0:3]
    f, al, be = axis_force(x, geo)  # (…, N, M) each
    e = d.y - f
    we = d.w * e
    wal = d.w * al
    wbe = d.w * be
    Gw = (d.Gam @ w.unsqueeze(-1)).squeeze(-1)
    cost = (we * e).sum(-1) + d.gconst - 2 * (w * d.GY).sum(-1) + (w * Gw).sum(-1)
    # ω block: Σ w a aᵀ with a = α r + β R + γ ω
    X = (wal * be) @ geo.rR
    Y = (wal * geo.gamma.unsqueeze(-2)) @ geo.rk + (wbe * geo.gamma.unsqueeze(-2)) @ geo.Rm
    Haa = ((wal * al) @ geo.rr + (wbe * be) @ geo.RR).unflatten(-1, (3, 3))
    X = X.unflatten(-1, (3, 3))
    wy = w.unsqueeze(-1) * Y.unsqueeze(-2)
    Haa = Haa + X + X.transpose(-1, -2) + wy + wy.transpose(-1, -2) \
        + (d.w @ geo.gamma2.unsqueeze(-1)).unsqueeze(-1) * (w.unsqueeze(-1) * w.unsqueeze(-2)) + d.Gam
    wg = d.w * geo.gamma.unsqueeze(-2)
    Hab = (wal @ geo.rC + wbe @ geo.RC).unflatten(-1, (3, 6)) + w.unsqueeze(-1) * (wg @ geo.C).unsqueeze(-2)
    Hbb = (d.w @ geo.CC).unflatten(-1, (6, 6))
    H = torch.cat((torch.cat((Haa, Hab), -1), torch.cat((Hab.transpose(-1, -2), Hbb), -1)), -2)
    ga = (we * al) @ geo.rk + (we * be) @ geo.Rm + w * (we @ geo.gamma.unsqueeze(-1)) + d.GY - Gw
    gb = we @ geo.C
    return cost, torch.cat((ga, gb), -1), H


def _initial(geo: AxisProjection, d: _Data, gyro_fallback):
    """ω from the (weighted) gyro mean, then φ = [ω̇; s] by linear least squares given ω."""
    N = d.Gam.shape[0]
    eye3 = torch.eye(3, dtype=d.Gam.dtype)
    ev = torch.linalg.eigvalsh(d.Gam)
    ok = ev[..., 0] > 1e-12 * ev[..., -1].clamp_min(1e-300)
    w = torch.linalg.solve(torch.where(ok[:, None, None], d.Gam, eye3), torch.where(ok[:, None], d.GY, 0))
    w = torch.where(ok[:, None], w, gyro_fallback)
    x = torch.cat((w, torch.zeros(N, 6, dtype=w.dtype)), -1)
    # f is linear in φ: the φ block of the normal equations at φ = 0 gives the exact LS solution.
    _, g, H = _cost_grad_hess(x, geo, d)
    Hp = H[:, 3:, 3:]
    evp = torch.linalg.eigvalsh(Hp)
    okp = evp[:, 0] > 1e-12 * evp[:, -1].clamp_min(1e-300)
    phi = torch.linalg.solve(torch.where(okp[:, None, None], Hp, torch.eye(6, dtype=Hp.dtype)), g[:, 3:].unsqueeze(-1)).squeeze(-1)
    x[:, 3:] = torch.where(okp[:, None], phi, 0)
    return x, ~ok


def solve_motion(geo: AxisProjection, d: _Data, x0, *, max_iter: int = 50, xtol: float = 1e-12):
    """x = [ω, ω̇, s] per sample by the package's batched Levenberg–Marquardt
    (:class:`~accel_bayes.inference.lm.BatchedLevenbergMarquardt`: Nielsen damping with Marquardt
    scaling, one λ and one stopping reason per sample; no loop over samples).  ``x0`` (*G, N, 9)
    with G the geometry's batch.  λ₀ = 10⁻⁸ (relative to diag H): the start (gyro mean, φ by
    linear least squares) is already close.  Converged: a step ≤ ``xtol``·‖x‖, or a relative
    cost change ≤ 10⁻¹⁴ (round-off level), accepted or not.
    Returns (x, cost, H = JᵀWJ at x, converged (*G, N) bool)."""
    if geo.rk.dim() == 2:  # one geometry: the solver evaluates only the samples still running
        def linearize(x, idx):
            cost, g, H = _cost_grad_hess(x, geo, d.take(idx))
            return 0.5 * cost, g, H  # the solver's ½‖r‖² convention; g = JᵀWe = −∇(cost/2)
    else:
        def linearize(x):
            cost, g, H = _cost_grad_hess(x, geo, d)
            return 0.5 * cost, g, H

    stop = StoppingRule(max_iter, ftol=1e-14, xtol=xtol, gtol=0.0, flat_rejected=True)
    lm = BatchedLevenbergMarquardt(NielsenDamping(tau=1e-8), stop)
    res = lm.solve(linearize, x0, subset=geo.rk.dim() == 2)
    return res.x, 2.0 * res.cost, res.H, res.converged


def gauss_newton_steps(geo: AxisProjection, d: _Data, x0, steps: int = 2):
    """``steps`` undamped Gauss–Newton steps from ``x0`` (*G, N, 9) — for re-solving under a
    slightly perturbed geometry, starting at the unperturbed optimum (quadratic convergence: a
    relative perturbation ε leaves an error of order ε^(2^steps)).  The linear solve is the
    batched LM's (:func:`~accel_bayes.inference.lm.linear.damped_step`, no damping).  Returns (x,
    the last step (*G, N, 9))."""
    x = x0.clone()
    step = torch.zeros_like(x)
    for _ in range(steps):
        _, g, H = _cost_grad_hess(x, geo, d)
        step, _ = damped_step(H, g)
        x = x + step
    return x, step


# ------------------------------------------------------------------------------ estimation
def _weights(y, clipped, rng, sigma, present):
    """Per-axis weights (T, K, 3) = 1/σ_k² on finite, unclipped axes; 0 elsewhere."""
    T, K, _ = y.shape
    finite = np.isfinite(y)
    w = np.broadcast_to((1.0 / sigma**2)[None, :, None], y.shape).copy()
    w[~finite] = 0
    w[:, ~present] = 0
    if clipped is not None:
        c = np.asarray(clipped, dtype=bool)
        if rng is not None and np.isfinite(rng):
            at = np.abs(np.where(finite, y, 0)) >= _CLIP_FRACTION * rng
            # A flagged triad loses the axes at the range; an unflagged one keeps everything.
            w[c[..., None] & at] = 0
            w[c & ~at.any(-1)] = 0  # flagged but no axis visibly at the range: drop the triad
        else:
            w[c] = 0
    return w


def _sigma(x, name, K):
    s = np.asarray(x, dtype=np.float64).reshape(-1)
    if s.size == 1:
        s = np.full(K, float(s[0]))
    if s.shape != (K,):
        raise UserError(f"{name}: expected a scalar or {K} values, got {s.size}")
    return s


def estimate_motion(prepared, calibration, *, draws: int = 200, seed: int = 0, geometry: str = "draws",
                    include_cov: bool = False, acc_noise_std=None, gyro_noise_std=None, max_iter: int = 50,
                    draw_steps: int = 2, chunk_systems: int = 100_000, **removed):
    """Estimate ω, ω̇ and s at every kept sample of a prepared recording from a calibrated array.

    Parameters
    ----------
    prepared : a :class:`~accel_bayes.prep.prepared.PreparedRecording` (its recording's
        sensor-frame outputs at its kept samples are used; intrinsics, when wanted, applied before
        preparing — :func:`accel_bayes.pipelines.motion.motion` does — and named in its
        ``provenance["intrinsics"]``), or a :class:`~accel_bayes.data.recording.Recording`,
        prepared here with every sample kept
        (``prepare_recording(rec, select="all", gyro="optional", stated_noise=False)``).
        Samples are not dropped for clipping: in a clipped triad only the axes at the range get
        weight 0 (module docstring), which is a per-axis weight, not a sample selection.
    calibration : positions.json path or dict (DESIGN §7.3), a (K, 3) array of positions relative
        to the reference IMU (no uncertainty), or a :class:`Calibration`.
    draws : number of geometry draws for ``geometry="draws"`` (0 → no geometry part).
    seed : seed of the geometry draws (same seed → same result).
    geometry : "draws" (re-solve per draw; default) or "linear" (first-order propagation).
    include_cov : also store the full 9×9 noise and geometry covariances per sample.
    acc_noise_std, gyro_noise_std : override the recording's stated noise (scalar or (K,)).
    max_iter : LM iterations of the point estimate.
    draw_steps : Gauss–Newton steps per geometry draw, started at the point estimate (the
        draws move positions by ~1 % of the baseline, so 2 steps converge to ~1e-8 relative;
        the largest last step, in noise stds, is reported as ``draws_last_step_max_in_noise_std``).
    chunk_systems : at most this many 9×9 systems per batch of the draws (memory bound).

    Returns an :class:`xarray.Dataset` with coords ``time``, ``axis`` (and ``param``/``param2``
    with ``include_cov``) and variables ``omega`` (rad s-1), ``omega_dot`` (rad s-2), ``s``
    (m s-2) — (time, axis), array frame, s at the reference IMU — their total std
    ``<name>_std`` and the parts ``<name>_std_noise``, ``<name>_std_geometry``; per-sample
    ``chi2`` (weighted residual sum of squares), ``dof``, and flags ``converged``,
    ``ill_posed`` (NaN estimates: the measurements left do not determine all 9 unknowns),
    ``gyro_clipped``, ``acc_clipped``, ``omega_needs_acc``.  Attributes hold units and
    provenance (schema ``accel_bayes.motion/1``).  ``intrinsics=`` and the sample-selection
    keywords (before 0.2.0) are a TypeError.
    """
    import time as _time

    import xarray as xr

    from ..prep.prepared import as_prepared, refuse_removed_keywords

    t_start = _time.perf_counter()
    refuse_removed_keywords("estimate_motion", removed)
    if "intrinsics" in removed:
        raise TypeError("estimate_motion: intrinsics= removed in 0.2.0; apply them to the recording before "
                        "prepare_recording (accel_bayes.pipelines.motion.motion does)")
    if removed:
        raise TypeError(f"estimate_motion: unexpected keyword(s) {sorted(removed)}")
    if geometry not in ("draws", "linear"):
        raise UserError(f"geometry: expected 'draws' or 'linear', got {geometry!r}")
    if isinstance(draws, bool) or not isinstance(draws, (int, np.integer)) or draws < 0 or draws == 1:
        raise UserError(f"draws: expected 0 or an integer >= 2, got {draws!r}")
    prepared = as_prepared(prepared, "estimate_motion", select="all", gyro="optional", stated_noise=False)
    recording = prepared.kept_recording()
    K = recording.K
    cal = load_calibration(calibration, K)
    intr_note = prepared.provenance.get("intrinsics", "none")
    sa = _sigma(recording.acc_noise_std if acc_noise_std is None else acc_noise_std, "acc_noise_std", K)
    sg = _sigma(recording.gyro_noise_std if gyro_noise_std is None else gyro_noise_std, "gyro_noise_std", K)

    has_acc = recording.has_acc & np.isfinite(cal.positions).all(-1)
    has_gyro = recording.has_gyro
    for name, s, present in (("acc_noise_std", sa, has_acc), ("gyro_noise_std", sg, has_gyro)):
        if present.any() and not (np.isfinite(s[present]).all() and (s[present] > 0).all()):
            raise UserError(f"{name}: expected positive finite noise std for every IMU in use, got {s[present].tolist()}")
    if not has_acc.any():
        raise UserError("calibration.imus: no IMU has both accelerometer data and a calibrated position")
    _check_lever_arms(cal.positions[has_acc], np.flatnonzero(has_acc).tolist())

    q = np.asarray(recording.nominal_orientation, dtype=np.float64).copy()
    if cal.orientations is not None:
        use_cal = np.isfinite(cal.orientations).all(-1)
        q[use_cal] = cal.orientations[use_cal]
    R = quat_to_matrix(torch.as_tensor(q))  # (K, 3, 3) array → sensor
    pos = torch.as_tensor(np.where(has_acc[:, None], cal.positions, 0.0))

    acc = np.asarray(recording.acc, dtype=np.float64)
    wa = _weights(acc, recording.acc_clipped, recording.acc_range, np.where(has_acc, sa, 1.0), has_acc)
    if recording.gyro is not None:
        gyro = np.asarray(recording.gyro, dtype=np.float64)
        wg = _weights(gyro, recording.gyro_clipped, recording.gyro_range, np.where(has_gyro, sg, 1.0), has_gyro)
    else:
        gyro = np.zeros_like(acc)
        wg = np.zeros_like(acc)
    M = 3 * K
    ya = torch.as_tensor(np.where(wa > 0, acc, 0.0)).reshape(-1, M)
    yg = torch.as_tensor(np.where(wg > 0, gyro, 0.0))
    wg_t = torch.as_tensor(wg)
    Lg = torch.einsum("kai,tka,kaj->tij", R, wg_t, R)  # Σ_k R_kᵀ diag(w_g) R_k
    GY = torch.einsum("kai,tka->ti", R, wg_t * yg)
    d = _Data(ya, torch.as_tensor(wa).reshape(-1, M), Lg, GY, (wg_t * yg * yg).sum((1, 2)))
    geo = AxisProjection(R, pos)

    # Fallback start for samples without a usable gyro axis: the clipped readings themselves
    # (right sign; magnitude at the range), averaged in the array frame.
    g_all = torch.as_tensor(np.where(np.isfinite(gyro), gyro, 0.0))
    n_g = max(int(has_gyro.sum()), 1)
    fallback = torch.einsum("kai,tka->tki", R, g_all)[:, has_gyro].sum(1) / n_g

    x0, acc_only = _initial(geo, d, fallback)
    x, _, H, conv = solve_motion(geo, d, x0, max_iter=max_iter)
    # The reported misfit comes from the package's one signal model (models.specific_force),
    # which the factored solver reproduces (tests pin the two together).
    f_s = torch.einsum("kab,tkb->tka", R, specific_force(pos, x[:, 0:3], x[:, 3:6], x[:, 6:9])).reshape(-1, M)
    g_s = torch.einsum("kab,tb->tka", R, x[:, 0:3])
    cost = (d.w * (d.y - f_s) ** 2).sum(-1) + (wg_t * (yg - g_s) ** 2).sum((1, 2))
    ev = torch.linalg.eigvalsh(H)
    ill = ~(ev[:, 0] > 1e-10 * ev[:, -1].clamp_min(1e-300)) | ~torch.isfinite(x).all(-1)
    Hs = torch.where(ill[:, None, None], torch.eye(9, dtype=H.dtype), H)
    cov_noise = torch.linalg.inv(Hs)
    cov_noise = 0.5 * (cov_noise + cov_noise.transpose(-1, -2))

    # ---- geometry part
    Tn = recording.T
    cov_r = torch.as_tensor(np.where(has_acc[:, None, None], cal.cov, 0.0))
    geo_used = bool((cov_r.abs().sum() > 0).item()) and (geometry == "linear" or draws >= 2)
    method = geometry if geo_used else "none"
    cov_geo = torch.zeros(Tn, 9, 9, dtype=torch.float64)
    draw_info = {}
    if geo_used and geometry == "linear":
        dfdr = df_dr(x[:, 0:3], x[:, 3:6])  # (T, 3, 3): ∂f_k/∂r_k, array frame, the same for every triad
        J = axis_force_jacobian(x, geo)  # (T, M, 9)
        Bm = geo.Rm @ dfdr  # (T, M, 3): ∂f_m/∂r_k(m)
        # dx/dr_k = −(JᵀWJ)⁻¹ Σ_{m in k} w_m J_mᵀ ∂f_m/∂r_k  (sign irrelevant for the covariance)
        P = (d.w[..., None, None] * J.unsqueeze(-1) * Bm.unsqueeze(-2)).unflatten(1, (K, 3)).sum(2)  # (T, K, 9, 3)
        A = cov_noise.unsqueeze(1) @ P
        cov_geo = (A @ cov_r @ A.transpose(-1, -2)).sum(1)
    elif geo_used:
        gen = torch.Generator().manual_seed(int(seed))
        ev_r, V = torch.linalg.eigh(cov_r)
        Lr = V * ev_r.clamp_min(0).sqrt().unsqueeze(-2)  # a square root of each PSD block
        z = torch.randn(draws, K, 3, generator=gen, dtype=torch.float64)
        r_d = pos + (Lr @ z.unsqueeze(-1)).squeeze(-1)  # (D, K, 3)
        r_d = torch.where(torch.as_tensor(has_acc)[None, :, None], r_d, 0.0)
        geo_d = AxisProjection(R, r_d)
        sd_noise0 = torch.sqrt(torch.diagonal(cov_noise, dim1=-2, dim2=-1).clamp_min(1e-300))
        chunk_t = max(1, int(chunk_systems) // draws)
        s1 = torch.zeros(Tn, 9, dtype=torch.float64)
        s2 = torch.zeros(Tn, 9, 9, dtype=torch.float64)
        worst = 0.0
        for a in range(0, Tn, chunk_t):  # chunks bound memory; each solves draws × chunk_t systems at once
            b = min(Tn, a + chunk_t)
            xd, last = gauss_newton_steps(geo_d, d.take(slice(a, b)), x[a:b].expand(draws, -1, -1), draw_steps)
            ok = ~ill[a:b]
            dev = torch.where(ok[:, None], xd - x[a:b], 0)  # about the point estimate; re-centred below
            s1[a:b] = dev.sum(0)
            s2[a:b] = torch.einsum("dti,dtj->tij", dev, dev)
            if bool(ok.any()):
                # Convergence of the draws, in units of the noise std of each unknown.
                worst = max(worst, float((last[:, ok].abs() / sd_noise0[a:b][ok]).max()))
        mean = s1 / draws
        cov_geo = (s2 - draws * mean.unsqueeze(-1) * mean.unsqueeze(-2)) / (draws - 1)
        draw_info = {"draws_last_step_max_in_noise_std": worst}
    cov_geo = 0.5 * (cov_geo + cov_geo.transpose(-1, -2))
    cov_tot = cov_noise + cov_geo

    # ---- flags and output
    nan = torch.tensor(float("nan"), dtype=torch.float64)
    x = torch.where(ill[:, None], nan, x)
    sd = lambda c: torch.sqrt(torch.diagonal(c, dim1=-2, dim2=-1).clamp_min(0))  # noqa: E731
    sd_tot, sd_noise, sd_geo = (torch.where(ill[:, None], nan, sd(c)) for c in (cov_tot, cov_noise, cov_geo))
    n_res = (wa > 0).sum((1, 2)) + (wg > 0).sum((1, 2))
    gclip = np.zeros(Tn, bool) if recording.gyro_clipped is None else np.asarray(recording.gyro_clipped, bool)[:, has_gyro].any(1)
    aclip = np.zeros(Tn, bool) if recording.acc_clipped is None else np.asarray(recording.acc_clipped, bool)[:, has_acc].any(1)
    from .. import __version__

    axis = ["x", "y", "z"]
    dv = {}
    for i, (name, unit, long) in enumerate((("omega", "rad s-1", "angular velocity"),
                                             ("omega_dot", "rad s-2", "angular acceleration"),
                                             ("s", "m s-2", "specific force at the reference IMU"))):
        sl = slice(3 * i, 3 * i + 3)
        dv[name] = (("time", "axis"), x[:, sl].numpy(), {"units": unit, "long_name": f"{long}, array frame"})
        dv[f"{name}_std"] = (("time", "axis"), sd_tot[:, sl].numpy(),
                             {"units": unit, "long_name": f"{long}: total std (noise + geometry)"})
        dv[f"{name}_std_noise"] = (("time", "axis"), sd_noise[:, sl].numpy(),
                                   {"units": unit, "long_name": f"{long}: std from measurement noise (Laplace)"})
        dv[f"{name}_std_geometry"] = (("time", "axis"), sd_geo[:, sl].numpy(),
                                      {"units": unit, "long_name": f"{long}: std from the calibration's position uncertainty"})
    dv["chi2"] = (("time",), torch.where(ill, nan, cost).numpy(),
                  {"long_name": "weighted residual sum of squares at the estimate (stated noise)"})
    dv["dof"] = (("time",), (n_res - 9).astype(np.int64), {"long_name": "residual degrees of freedom"})
    dv["converged"] = (("time",), conv.numpy(), {"long_name": "LM converged"})
    dv["ill_posed"] = (("time",), ill.numpy(), {"long_name": "unknowns not determined by the measurements left; NaN estimates"})
    dv["gyro_clipped"] = (("time",), gclip, {"long_name": "some gyroscope triad at its range"})
    dv["acc_clipped"] = (("time",), aclip, {"long_name": "some accelerometer triad at its range"})
    dv["omega_needs_acc"] = (("time",), acc_only.numpy(),
                             {"long_name": "the unclipped gyro axes do not determine omega: the missing components "
                                           "come from the accelerometers (start: the clipped gyro readings)"})
    coords = {"time": ("time", np.asarray(recording.time, dtype=np.float64), {"units": "s"}), "axis": axis}
    if include_cov:
        coords["param"] = list(PARAMS)
        coords["param2"] = list(PARAMS)
        dv["cov_noise"] = (("time", "param", "param2"), cov_noise.numpy(), {"long_name": "noise covariance of [omega, omega_dot, s]"})
        dv["cov_geometry"] = (("time", "param", "param2"), cov_geo.numpy(), {"long_name": "geometry covariance of [omega, omega_dot, s]"})
    attrs = {
        "schema": MOTION_SCHEMA,
        "frame": "array",
        "origin": f"position of the calibration's reference IMU {cal.reference_imu} (positions relative to it)",
        "reference_imu": int(cal.reference_imu),
        "geometry_method": method,
        "draws": int(draws) if method == "draws" else 0,
        "seed": int(seed),
        "calibration_method": cal.method,
        "calibration": cal.source,
        "orientations": "calibration" if cal.orientations is not None else "nominal (recording)",
        "intrinsics": intr_note,
        "acc_noise_std": json.dumps([float(v) for v in sa]),
        "gyro_noise_std": json.dumps([float(v) for v in sg]),
        "recording_source": recording.source,
        "recording_description": recording.description,
        "version": __version__,
        "seconds": float(_time.perf_counter() - t_start),
        "model": "R_k^T y_k^a = omega x (omega x r_k) + omega_dot x r_k + s + e; R_k^T y_k^g = omega + e ([C21] eq. 4)",
    }
    attrs.update({k: float(v) for k, v in draw_info.items()})
    return xr.Dataset(dv, coords=coords, attrs=attrs)


def write_motion(ds, path, *, overwrite: bool = False) -> Path:
    """Write a motion dataset to NetCDF-4 (h5netcdf), atomically
    (:func:`accel_bayes.data.outputs.write_netcdf`); an existing file is only replaced with ``overwrite``."""
    from ..data.io import ENGINE
    from ..data.outputs import write_netcdf

    enc = {name: {"_FillValue": None} for name, v in ds.variables.items() if v.dtype.kind == "f"}
    return write_netcdf(Path(path), ds, engine=ENGINE, encoding=enc, overwrite=overwrite)
