"""Fit the rig model (:mod:`.model`) to a recording with the package's structured LM, and its
Laplace posterior with an identifiability check (:class:`RigResult`)."""
from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.ndimage import gaussian_filter1d

from ...data.validation import sample_present
from ...errors import UserError
from ...physics.geometry import boxminus, matrix_to_quat, quat_to_matrix
from ..lm import ChainResidual, GlobalResidual, LevenbergMarquardt, Problem, Variable
from ..lm.linear import NotPositiveDefinite, SchurComplementSolver
from .initial import align_gyros, interp_rows
from .robust import DEFAULT_SCORE_BLOCK, block_scores, robust_summary, robust_warning
from .model import (LINEAR_BLOCKS, BiasGrid, bucket_samples, mean_biases, measurement_jacobian, measurement_residual,
                    process_jacobian, process_matrices, process_residual, stamp_jitter_std,
                    timing_noise_directions, walk_residual, symmetric)

__all__ = ["RigSettings", "RigResult", "fit_rig", "rig_samples", "unexcited_axes", "blind_lever_axes",
           "DEFAULT_KNOT_SPACING", "bias_walks", "bias_knot_spacing", "DEFAULT_RANDOM_WALK", "MIN_BIAS_SPACING"]

#: per-parameter scales of "a confident number": a direction of the Laplace posterior whose std
#: exceeds its scale (scaled Fisher information eigenvalue < 1) is reported unidentified
IDENT_SCALE = {"q": math.radians(1.0), "r": 0.01, "o": 2e-3, "d": 1e-3, "oa": 2e-3}

#: bias random-walk densities assumed where neither the rests nor the recording give them (gyro
#: rad/s/√s, acc m/s²/√s): EuRoC's ADIS16448 sensor.yaml figures, the values VIO users start from
#: and an upper end for MEMS IMUs (a walk assumed too large widens the clock std, one too small
#: makes it overconfident: ``experiments/rig_offset_decomposition.md``)
DEFAULT_RANDOM_WALK = {"gyro": 1.9393e-5, "acc": 3.0e-3}

#: s, the motion knots' spacing h unless ``RigSettings.knot_spacing`` says otherwise.  Why fixed and
#: not finer at higher rates (until issue #28's fifth round h was 2.5 / the rate of sampling
#: instants, 5–10 ms): the motion knots are nuisances fitted jointly with the clocks, and the finer
#: they are the more of each IMU's noise at its own instants they absorb, which the joint MAP then
#: reads as timing (errors in variables: the Laplace std does not see it).  On concealed rig seed
#: 29 (4 IMUs, 200/125/100/100 Hz, white noise only) the offsets' z went −1.4/−3.4/−1.4 at 5 ms,
#: −4.5/−6.3/−11.5 at 2.5 ms and −0.8/−0.8/+0.7 at 10 ms, the std there at the bound
#: (``experiments/rig_knot_spacing.md``).  10 ms still holds the hand motion: a cubic between knots
#: misses a 7 Hz sinusoid by ~1e-4 of its amplitude (noise-free fits: errors ≤ 0.08 of their std);
#: faster motion (vibration, impacts above ~25 Hz) is what the setting is for.
DEFAULT_KNOT_SPACING = 0.01

#: s, the finest bias-knot spacing (:func:`bias_knot_spacing`): one knot per ≥ 1 s of samples is
#: determined by the data, not by the walk prior (the 10 ms motion knots' walking biases were not:
#: LM crawled along their thousands of prior-dominated directions, ``experiments/rig_mimu_pairs.md``)
MIN_BIAS_SPACING = 1.0


@dataclass(frozen=True)
class RigSettings:
    """Options of :func:`fit_rig`.

    knot_spacing : s, or None: :data:`DEFAULT_KNOT_SPACING`.
    orientation_prior_deg : std (°) of the nominal-orientation prior (IMUs whose nominal is not the
        identity, which format v1 cannot tell from "not stated").
    contradiction_sigma : a fitted orientation further than this many prior std from its nominal
        draws a warning.
    max_iter : LM step attempts per pass (a second pass, after re-bucketing the samples at the first
        pass's clock estimates, runs only where some sample moved by more than h/4).  40 stopped 6 of
        exp_1's 28 MIMU pair fits short of convergence (``experiments/rig_mimu_pairs.md``); fits that
        converge stop earlier.
    hessian : "exact" (default) or "gauss_newton" information for the Laplace posterior.  The
        Gauss–Newton JᵀJ evaluates ∂r/∂o = R ω̇ at the *estimated* motion, whose noise adds to its
        square (errors in variables): on concealed rigs it made the clock std 25–40 % too small;
        the exact Hessian's local–global cross terms remove that (about as long as the fit itself).
    lever_prior_std : m, std of the (effectively flat) lever-arm prior about the nominal positions.
    stamp_jitter : model each IMU's stamping error as per-sample timing noise, its std estimated from
        the stamps (:func:`~.model.stamp_jitter_std`; only where the IMUs carry their own stamps).
    random_walk : {"gyro": rad/s/√s, "acc": m/s²/√s} for every IMU, or None: per IMU from
        :func:`bias_walks` (rests, then the recording, then :data:`DEFAULT_RANDOM_WALK` with a warning).
        The walks live on a coarse grid of bias knots of their own (:func:`bias_knot_spacing`).
    prior_scale : multiplies the white-jerk intensities q_c estimated from the reference (> 1: weaker).
    ftol : LM's relative cost-change stop (1e-8 of a cost of order the number of residuals is far
        below the 0.5 that a 1-std move of one parameter makes).
    linear_errors : sensor kinds ("gyro", "acc") whose readings get a linear error per non-reference
        IMU relative to the reference, y = (I + M) R v with M symmetric (scale factors and
        non-orthogonality: Kalibr's scale-misalignment model less its rotation, which R holds),
        marginalised like the biases.  Off by default; on the MIMU4444 the gyros' relative M
        reaches 2 % (``experiments/rig_mimu_diagnose.md``).
    linear_error_std : std of each entry of M's Gaussian prior about 0 (dimensionless; 3 %: the
        scale tolerance of consumer MEMS gyros, weak against what 10 s of hand motion determines).
    acc_delay : give each non-reference IMU's accelerometer a time offset δ_k of its own against its
        gyro (relative to the reference's, which f absorbs): its acc readings are taken at t + δ_k.
        Off by default.  On the MIMU4444 the offsets timed by the gyros alone and by both sensors
        differ by up to 0.3 ms; the delay moves them by up to 0.14 ms
        (``experiments/rig_mimu_diagnose.md``).
    acc_delay_std : s, std of δ_k's Gaussian prior about 0 (2 ms: the sampling-clock ages' range).
    score_block : s, the block length of the misspecification-robust sandwich covariance
        (:mod:`.robust`, 3 s); None: no sandwich (Laplace only).
    """

    knot_spacing: float | None = None
    orientation_prior_deg: float = 5.0
    contradiction_sigma: float = 3.0
    max_iter: int = 100
    ftol: float = 1e-8
    prior_scale: float = 1.0
    hessian: str = "exact"
    lever_prior_std: float = 1.0
    stamp_jitter: bool = True
    random_walk: dict | None = None
    linear_errors: tuple = ()
    linear_error_std: float = 0.03
    acc_delay: bool = False
    acc_delay_std: float = 2e-3
    score_block: float | None = DEFAULT_SCORE_BLOCK

    def __post_init__(self):
        bad = set(self.linear_errors) - set(LINEAR_BLOCKS)
        if bad or isinstance(self.linear_errors, str):
            raise UserError(f"linear_errors: expected a tuple of 'gyro' and/or 'acc', got {self.linear_errors!r}")
        if not (math.isfinite(self.linear_error_std) and self.linear_error_std > 0):
            raise UserError(f"linear_error_std: expected a finite std > 0, got {self.linear_error_std!r}")
        if not isinstance(self.acc_delay, bool):
            raise UserError(f"acc_delay: expected true or false, got {self.acc_delay!r}")
        if not (math.isfinite(self.acc_delay_std) and self.acc_delay_std > 0):
            raise UserError(f"acc_delay_std: expected a finite std > 0 (s), got {self.acc_delay_std!r}")
        # the walk prior's precision is 1/density² per knot step: a zero or missing density would make
        # the initial cost infinite deep inside LM, so it is refused here, naming the option
        if self.random_walk is None:
            return
        rw = self.random_walk
        if not isinstance(rw, dict) or set(rw) != {"gyro", "acc"}:
            raise UserError('random_walk: expected {"gyro": rad/s/√s, "acc": m/s²/√s} or None')
        for kind in ("gyro", "acc"):
            v = rw[kind]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise UserError(f"random_walk: {kind} must be a finite density > 0 (got {v!r}); the rig model has "
                                "no constant-bias mode, a very small density is the closest")


@dataclass
class RigResult:
    """A rig posterior (Laplace at the MAP), per IMU in label order.

    orientation (K, 4) quaternions (DESIGN §7.0); orientation_cov (K, 3, 3) rad², sensor frame;
    position (K, 3) m, array frame, relative to the reference; position_cov (K, 3, 3) m²;
    time_offset, time_offset_std (K,) s; clock_drift, clock_drift_std (K,) (NaN where the IMU has no
    own stamps); gyro_bias, acc_bias (K, 3): time means of the walking biases relative to the
    reference's (rad/s, m/s²); random_walk (K, 2): the [gyro, acc] walk densities used (rad/s/√s,
    m/s²/√s); bias_knot_spacing (2,): the [gyro, acc] bias grids' spacing (s); own_stamps (K,) bool; stamp_jitter_std (K,) s (0 where
    not modelled); linear_error: {"gyro"/"acc": (K, 3, 3) M} for the kinds in
    ``RigSettings.linear_errors`` (0 for the reference); acc_delay, acc_delay_std (K,) s: each acc's
    delay δ against its gyro relative to the reference's (0 without ``RigSettings.acc_delay``, NaN std
    where unidentified); chi2_per_imu (K, 2): [gyro, acc] mean squared
    whitened residual per reading of each IMU; unidentified: list of
    (imu label, parameter name) pairs; warnings: one line each; converged, reason, n_iter,
    chi2_per_dof, seconds.
    """

    reference_imu: int
    orientation: np.ndarray
    orientation_cov: np.ndarray
    position: np.ndarray
    position_cov: np.ndarray
    time_offset: np.ndarray
    time_offset_std: np.ndarray
    clock_drift: np.ndarray
    clock_drift_std: np.ndarray
    gyro_bias: np.ndarray
    acc_bias: np.ndarray
    own_stamps: np.ndarray
    unidentified: list
    warnings: list
    converged: bool
    reason: str
    n_iter: int
    chi2_per_dof: float
    seconds: float
    info_eigs: np.ndarray = field(default=None, repr=False)
    hessian: str = "exact"
    lever_prior_std: float = 1.0
    stamp_jitter_std: np.ndarray = None
    #: joint posterior covariance of the free parameters (NaN rows where unidentified) and their
    #: labels (imu label, block name, component) — the cross terms the per-block fields leave out
    free_cov: np.ndarray = field(default=None, repr=False)
    free_labels: list = field(default=None, repr=False)
    random_walk: np.ndarray = None
    bias_knot_spacing: np.ndarray = None
    linear_error: dict = None
    chi2_per_imu: np.ndarray = None
    acc_delay: np.ndarray = None
    acc_delay_std: np.ndarray = None
    #: s, the motion knots' spacing h the fit used
    knot_spacing: float = None
    #: the sandwich's per-block influences on the free parameters (:mod:`.robust`; None without)
    block_scores: object = field(default=None, repr=False)


def bias_walks(rec, samples, order, settings) -> tuple[np.ndarray, list]:
    """(K, 2) [gyro, acc] bias random-walk densities (rad/s/√s, m/s²/√s) in internal order, and
    warnings: ``settings.random_walk`` if given, else per IMU from its rests (Allan deviation) or the
    recording's ``gyro_random_walk`` / ``acc_random_walk`` (:func:`accel_bayes.data.export.random_walks`),
    else :data:`DEFAULT_RANDOM_WALK` with a one-line warning naming the key."""
    from ...data.export import random_walks  # the exports' resolution: one way for both
    K = len(order)
    if settings.random_walk is not None:
        return np.tile([settings.random_walk["gyro"], settings.random_walk["acc"]], (K, 1)).astype(float), []
    rates = np.ones(rec.K)
    for i, k in enumerate(order):
        rates[k] = 1.0 / float(np.median(np.diff(samples[i]["ds"])))
    known = random_walks(rec, rates, required=[])
    out, missing = np.zeros((K, 2)), set()
    for i, k in enumerate(order):
        for c, kind in enumerate(("gyro", "acc")):
            if (k, kind) in known:
                out[i, c] = known[k, kind][0]
            else:
                out[i, c] = DEFAULT_RANDOM_WALK[kind]
                missing.add(kind)
    if not missing:
        return out, []
    said = ", ".join(f"{kind}_random_walk {DEFAULT_RANDOM_WALK[kind]:g}" for kind in sorted(missing))
    return out, [f"{'/'.join(f'{m}_random_walk' for m in sorted(missing))}: unknown for some IMUs (no long rests, "
                 f"not in the recording); assumed {said} (EuRoC ADIS16448) — state them in the array "
                 "description for a clock std that fits the sensors"]


def rig_samples(rec, ref: int):
    """Per-IMU sample dicts in internal order (reference first), the order, t₀ and own-stamp flags.

    Stamps are ``time`` plus ``imu_time_offset`` where given (the IMU's own clock); clipped or
    flagged samples keep their slot with zero weight.
    """
    time = np.asarray(rec.time, dtype=float)
    t0 = float(time[0])
    K = rec.K
    if rec.gyro is None or np.isnan(np.asarray(rec.gyro)).all(axis=(0, 2)).any():
        raise UserError("gyro: the rig model needs a gyroscope on every IMU")
    present = sample_present(rec)
    order = [ref] + [k for k in range(K) if k != ref]
    off = None if rec.imu_time_offset is None else np.asarray(rec.imu_time_offset, dtype=float)
    out, own = [], np.zeros(K, bool)
    for k in order:
        rows = np.flatnonzero(present[:, k])
        s = time[rows].copy()
        if off is not None and np.isfinite(off[rows, k]).any():
            s = s + np.nan_to_num(off[rows, k])
            own[k] = True
        if not np.array_equal(present[:, k], present[:, ref]):
            own[k] = True
        keep_a = np.ones(len(rows), bool)
        keep_g = np.ones(len(rows), bool)
        for name, keep in (("acc_clipped", keep_a), ("acc_flagged", keep_a), ("gyro_clipped", keep_g),
                           ("gyro_flagged", keep_g)):
            m = getattr(rec, name)
            if m is not None:
                keep &= ~np.asarray(m)[rows, k]
        out.append({"ds": s - t0, "yg": np.asarray(rec.gyro)[rows, k], "ya": np.asarray(rec.acc)[rows, k],
                    "wg": keep_g / float(np.asarray(rec.gyro_noise_std)[k]),
                    "wa": keep_a / float(np.asarray(rec.acc_noise_std)[k])})
    own[ref] = False
    return out, order, t0, own


def _initial_knots(smp0, R0, tau):
    """[ω, ω̇, f, ḟ] at the knots from the reference IMU alone (interpolated, lightly smoothed)."""
    h = tau[1] - tau[0]
    w = interp_rows(tau, smp0["ds"], smp0["yg"]) @ R0
    f = interp_rows(tau, smp0["ds"], smp0["ya"]) @ R0
    ws, fs = gaussian_filter1d(w, 1.5, axis=0), gaussian_filter1d(f, 1.5, axis=0)
    wd, fd = np.gradient(ws, h, axis=0), np.gradient(fs, h, axis=0)
    wdd, fdd = np.gradient(gaussian_filter1d(wd, 1.5, axis=0), h, axis=0), np.gradient(
        gaussian_filter1d(fd, 1.5, axis=0), h, axis=0)
    # prior intensity: the mean squared ω̈ (f̈) over 1 s — a generous (weak) white-jerk prior
    qc_w = max(float((wdd ** 2).mean()), 1e-6)
    qc_f = max(float((fdd ** 2).mean()), 1e-6)
    return np.concatenate((ws, wd, fs, fd), 1), qc_w, qc_f


def bias_knot_spacing(sigma, walk, span: float) -> float:
    """Spacing H (s) of one sensor kind's bias knots: the largest at which the linear interpolant
    of a walk of density K between knots misses it by at most a quarter of a sample's white noise σ
    (the Brownian bridge's std, K√H/2 at mid-interval, ≤ σ/4: the unmodelled part adds ≤ 1/16 to
    a sample's variance), for every IMU (sigma, walk: per non-reference IMU, σ per sample and
    the relative walk density in the same unit per √s); at least :data:`MIN_BIAS_SPACING`, at most
    the span (s) of the recording (then one interval: a walk between two end knots).  :func:`fit_rig`
    makes it whole intervals over the span, rounding up unless that breaks the 1 s floor."""
    sigma, walk = np.asarray(sigma, dtype=float), np.asarray(walk, dtype=float)
    H = float(np.min((sigma / (2.0 * walk)) ** 2))
    return float(min(max(H, MIN_BIAS_SPACING), span))


def unexcited_axes(smp0, R0, sigma_g: float, width_s: float = 0.02, factor: float = 100.0) -> list:
    """Array-frame axes (unit 3-vectors) the rig never turns about: eigen-directions of the mean
    ω ωᵀ of the reference gyro (Gaussian-smoothed over ``width_s``) below ``factor`` × the smoothed
    noise variance σ_g²/(2√π·n), n the smoothing width in samples."""
    dt = float(np.median(np.diff(smp0["ds"])))
    n = max(width_s / dt, 1.0)
    w = gaussian_filter1d(smp0["yg"] @ R0, n, axis=0)
    lam, V = np.linalg.eigh(w.T @ w / len(w))
    floor = sigma_g ** 2 / (2 * math.sqrt(math.pi) * n)
    return [V[:, i] for i in range(3) if lam[i] < factor * floor]


def blind_lever_axes(unexcited: list) -> list:
    """Lever-arm directions no acc sees: with rotation about one axis only (two unexcited axes) the
    lever arm along that axis; with no rotation, every direction; else none (ω in a plane still
    sees r ⊥ the plane through −|ω|² r)."""
    if len(unexcited) == 3:
        return [np.eye(3)[i] for i in range(3)]
    if len(unexcited) == 2:
        return [np.cross(unexcited[0], unexcited[1])]
    return []


def fit_rig(rec, settings: RigSettings = RigSettings()) -> RigResult:
    """MAP and Laplace posterior of a rig's orientations, lever arms, clock offsets and drifts.

    rec : a format-v1 :class:`~accel_bayes.data.recording.Recording` with gyros on every IMU
    (≥ 2 IMUs; multi-rate NaN-union recordings as DESIGN §7.1).  Units: s, m, rad.
    """
    t_start = _time.perf_counter()
    ref = int(rec.reference_imu)
    K = rec.K
    if K < 2:
        raise UserError("acc: a rig needs at least 2 IMUs")
    smp, order, t0, own_lab = rig_samples(rec, ref)
    own = own_lab[order]
    q_nom = np.asarray(rec.nominal_orientation, dtype=float)[order]
    R0 = quat_to_matrix(torch.as_tensor(q_nom[0])).numpy()
    h = settings.knot_spacing or DEFAULT_KNOT_SPACING

    # starting values: gyro alignment against the reference (Kabsch + lag search)
    R_init, o_init = [], [0.0]
    w_ref_arr = smp[0]["yg"] @ R0   # reference readings in the array frame
    for k in range(1, K):
        Rk, ok = align_gyros(smp[0]["ds"], w_ref_arr, smp[k]["ds"], smp[k]["yg"])
        R_init.append(Rk), o_init.append(ok)
    o_init = np.asarray(o_init)
    d_init = np.zeros(K)
    lo = min(s["ds"].min() for s in smp) - 0.03
    hi = max(s["ds"].max() for s in smp) + 0.03
    n_knots = int(math.ceil((hi - lo) / h)) + 1
    tau = lo + h * np.arange(n_knots)
    x0, qc_w, qc_f = _initial_knots(smp[0], R0, tau)
    # each IMU's bias relative to the reference's walks with both walks' variances (the
    # reference's own walk is absorbed in ω and f)
    walk, warnings = bias_walks(rec, smp, order, settings)
    walk_rel = np.sqrt(walk[1:] ** 2 + walk[0] ** 2)
    AB = process_matrices(h, qc_w * settings.prior_scale, qc_f * settings.prior_scale)
    R0t = torch.as_tensor(R0)
    span = tau[-1] - tau[0]
    grids = []
    for c, key in enumerate(("wg", "wa")):
        sigma = [1.0 / float(np.max(s[key])) if np.max(s[key]) > 0 else np.inf for s in smp[1:]]
        H = bias_knot_spacing(sigma, walk_rel[:, c], span)
        # whole intervals over the span: rounded up to keep the bridge bound, down to keep the 1 s floor
        n_int = min(int(math.ceil(span / H - 1e-9)), int(math.floor(span / MIN_BIAS_SPACING + 1e-9)))
        n_b = max(n_int, 1) + 1
        grids.append(BiasGrid(t0=float(tau[0]), H=span / (n_b - 1), n=n_b))

    nom_pos = np.asarray(rec.nominal_position, dtype=float)[order]
    tt = lambda a: torch.as_tensor(np.asarray(a, dtype=float))  # noqa: E731
    q0 = matrix_to_quat(tt(np.stack(R_init)))
    values = {"q": q0, "r": tt(nom_pos[1:] - nom_pos[0]), "o": tt(o_init[1:]), "d": tt(d_init[1:]),
              "bg": torch.zeros(K - 1, grids[0].n, 3, dtype=torch.float64),
              "ba": torch.zeros(K - 1, grids[1].n, 3, dtype=torch.float64)}
    lin = [LINEAR_BLOCKS[kind] for kind in ("gyro", "acc") if kind in settings.linear_errors]
    priors_lin = []
    if settings.acc_delay:
        values["oa"] = torch.zeros(K - 1, dtype=torch.float64)
        eye_a = torch.eye(K - 1, dtype=torch.float64) / settings.acc_delay_std
        priors_lin.append(GlobalResidual(lambda g: g["oa"] / settings.acc_delay_std, jac=lambda g: {"oa": eye_a},
                                         name="acc_delay_prior"))
    for name in lin:
        values[name] = torch.zeros(K - 1, 6, dtype=torch.float64)
        eye = torch.eye(6 * (K - 1), dtype=torch.float64) / settings.linear_error_std
        priors_lin.append(GlobalResidual(lambda g, name=name: g[name].reshape(-1) / settings.linear_error_std,
                                         jac=lambda g, name=name, eye=eye: {name: eye}, name=f"{name}_prior"))
    fixed_d = torch.as_tensor(~own[1:])
    # nominal orientations other than the identity are stated ones (format v1 writes identity when absent)
    stated = ~np.all(np.isclose(q_nom[1:], [1.0, 0, 0, 0]) | np.isclose(q_nom[1:], [-1.0, 0, 0, 0]), axis=1)
    sig_q = math.radians(settings.orientation_prior_deg)
    qn_t = tt(q_nom[1:])
    # a proper but effectively flat lever-arm prior (1 m std about the nominal): it changes nothing
    # the data identify (stds of tens of µm) and keeps LM from wandering along an unexcited
    # direction (the lever arm along the only rotation axis) to metres
    r_nom = tt(nom_pos[1:] - nom_pos[0])
    priors = [GlobalResidual(lambda g: ((g["r"] - r_nom) / settings.lever_prior_std).reshape(-1),
                             jac=lambda g: {"r": torch.eye(3 * (K - 1), dtype=torch.float64) / settings.lever_prior_std},
                             name="lever_arm_prior")]
    for c, name in enumerate(("bg", "ba")):
        fn, Jw = walk_residual(grids[c], walk_rel[:, c])
        priors.append(GlobalResidual(lambda g, fn=fn, name=name: fn(g[name]),
                                     jac=lambda g, Jw=Jw, name=name: {name: Jw}, name=f"{name}_walk"))
    priors += priors_lin
    if stated.any():
        sel = torch.as_tensor(stated)
        priors.append(GlobalResidual(lambda g: (boxminus(g["q"][sel], qn_t[sel]) / sig_q).reshape(-1),
                                     name="orientation_prior"))

    # stamping errors are timing noise of each sample; a shared stamp column (one clock) moves
    # every IMU alike and is left out (see the package docstring)
    sep = bool(own_lab.any()) and settings.stamp_jitter
    sig_j = np.array([stamp_jitter_std(s["ds"]) if sep else 0.0 for s in smp])

    x = tt(x0)
    log_all, res = [], None
    o_used = d_used = None
    for _ in range(2):
        o_full = np.r_[0.0, values["o"].numpy()]
        d_full = np.r_[0.0, values["d"].numpy()]
        if o_used is not None:
            span = max(float(s["ds"].max()) for s in smp)
            moved = np.abs(o_full - o_used) + span * np.abs(d_full - d_used)
            if moved.max() < h / 4:  # every sample still in (or a cubic's short reach from) its interval
                break
        o_used, d_used = o_full, d_full
        data = bucket_samples(smp, o_full, d_full, lo, h, n_knots, grids)
        if sig_j.any():  # the weights of this pass, from its starting motion and clocks
            data.u = timing_noise_directions(values, x[:-1], x[1:], data, R0t, sig_j)
        meas = ChainResidual(lambda g, xp, xn, dd: measurement_residual(g, xp, xn, dd, R0t), data=data,
                             jac=lambda g, xp, xn, dd: measurement_jacobian(g, xp, xn, dd, R0t), name="rig")
        proc = ChainResidual(lambda g, xp, xn, dd: process_residual(xp, xn, dd), data=AB,
                             jac=lambda g, xp, xn, dd: process_jacobian(xp, dd), name="motion_prior")
        prob = Problem({"q": Variable(values["q"], "quaternion"), "r": Variable(values["r"]),
                        "o": Variable(values["o"]), "d": Variable(values["d"], fixed=fixed_d),
                        "bg": Variable(values["bg"]), "ba": Variable(values["ba"]),
                        **{name: Variable(values[name]) for name in lin + (["oa"] if settings.acc_delay else [])}},
                       x, [meas, proc] + priors)
        res = LevenbergMarquardt(max_iter=settings.max_iter, ftol=settings.ftol, xtol=1e-12, gtol=1e-9).solve(prob)
        values, x = res.values, res.locals
        log_all += res.log

    # Laplace posterior of the free globals (motion knots marginalised by the LM's Schur complement,
    # the bias knots by :func:`_marginal_information`)
    all_labels = res.free_labels()
    keep = np.array([name in IDENT_SCALE for name, _ in all_labels])
    labels = [lab for lab, k in zip(all_labels, keep) if k]
    scale = np.array([IDENT_SCALE[name] for name, _ in labels])
    hess_used = settings.hessian
    prob = res.problem
    info_blocks = lambda how: (prob.exact_hessian(values, x) if how == "exact"  # noqa: E731
                               else prob.linearize(values, x, step=False))
    reduce = lambda L: SchurComplementSolver(prob.local_structure).reduce(L.U, L.W, L.V, L.V_off).numpy()  # noqa: E731
    try:
        lin_h = info_blocks(settings.hessian)
        S = _marginal_information(reduce(lin_h), keep)
        indefinite = np.linalg.eigvalsh(S * scale[:, None] * scale[None, :]).min() < 0
    except (NotPositiveDefinite, np.linalg.LinAlgError):
        indefinite = True
    if indefinite:
        # not at a minimum (LM stopped on a ridge along an unexcited direction): the PSD
        # Gauss–Newton information; its errors-in-variables optimism is why the excitation rule
        # below checks the lever arm independently
        lin_h = info_blocks("gauss_newton")
        S = _marginal_information(reduce(lin_h), keep)
        hess_used = "gauss_newton (exact Hessian indefinite)"
    # Directions whose std would exceed IDENT_SCALE (scaled eigenvalue < 1, negative included: at
    # an unexcited direction LM stops on a ridge, not at a minimum) are unidentified.  The
    # covariance is the inverse on the identified subspace (conditional on the unidentified
    # directions), and the parameters that load on an unidentified direction get NaN (no number).
    Ss = S * scale[:, None] * scale[None, :]
    lam, V = np.linalg.eigh(0.5 * (Ss + Ss.T))
    ok = lam >= 1.0
    cov = (V[:, ok] / lam[ok]) @ V[:, ok].T * scale[:, None] * scale[None, :]
    # the data's own spread per time block, for the robust std (before the NaN rows below)
    scores = block_scores(prob, values, x, lin_h, keep, cov, settings.score_block) if settings.score_block else None
    unident = set()
    flagged = np.zeros(len(labels), bool)
    for i in np.flatnonzero(~ok):
        for j in np.flatnonzero(np.abs(V[:, i]) > 0.3):
            flagged[j] = True
            name, idx = labels[j]
            unident.add((order[idx[0] + 1], name))
    # the lever arm along an axis the board never turns about is seen by nothing (ω̇×r and
    # ω×(ω×r) vanish for r ∥ ω), whatever a noise-fitted motion suggests to the information matrix
    for axis in blind_lever_axes(unexcited_axes(smp[0], R0, float(np.asarray(rec.gyro_noise_std)[ref]))):
        for j, (name, idx) in enumerate(labels):
            if name == "r" and abs(axis[idx[1]]) > 0.3:
                flagged[j] = True
                unident.add((order[idx[0] + 1], "r"))
    cov[flagged, :] = np.nan
    cov[:, flagged] = np.nan

    n_res = int((data.wg > 0).sum() * 3 + (data.wa > 0).sum() * 3)
    r_meas = measurement_residual(values, x[:-1], x[1:], data, R0t)
    chi2 = float((r_meas ** 2).sum()) / max(n_res - len(all_labels), 1)
    r2 = (r_meas.reshape(*data.imu.shape, 6) ** 2).numpy()
    chi2_imu = np.zeros((K, 2))
    for c, (key, cols) in enumerate((("wg", slice(0, 3)), ("wa", slice(3, 6)))):
        used = (getattr(data, key) > 0).numpy()
        for ki in range(K):
            sel = used & (data.imu.numpy() == ki)
            chi2_imu[order[ki], c] = r2[sel][:, cols].mean() if sel.any() else np.nan

    # back to label order, covariances per block
    pos_idx = {lab: i for i, lab in enumerate(labels)}

    def block(name, k_int, n):
        ii = [pos_idx.get((name, (k_int - 1,) + ((c,) if n > 1 else ()))) for c in range(n)]
        C = np.zeros((n, n))
        for a, ia in enumerate(ii):
            for b, ib in enumerate(ii):
                if ia is not None and ib is not None:
                    C[a, b] = cov[ia, ib]
        return C

    ori = np.zeros((K, 4)); ori_cov = np.zeros((K, 3, 3)); pos = np.zeros((K, 3)); pos_cov = np.zeros((K, 3, 3))
    to = np.zeros(K); to_s = np.zeros(K); dr = np.full(K, np.nan); dr_s = np.full(K, np.nan)
    bgo = np.zeros((K, 3)); bao = np.zeros((K, 3)); sjo = np.zeros(K); oa = np.zeros(K); oa_s = np.zeros(K)
    sjo[order] = sig_j
    ori[ref] = q_nom[0]
    dr[ref], dr_s[ref] = 0.0, 0.0
    qv = values["q"].numpy()
    b_mean = np.concatenate((np.zeros((1, 6)), np.concatenate((mean_biases(values["bg"]), mean_biases(values["ba"])), 1)))
    wko = np.zeros((K, 2)); wko[order] = walk
    for ki in range(1, K):
        lab = order[ki]
        ori[lab] = qv[ki - 1] * np.sign(qv[ki - 1][0] or 1.0)
        Rk = quat_to_matrix(values["q"][ki - 1]).numpy()
        # tangent δ acts in the array frame (R Exp(δ)); the contract reports the sensor frame (R δ)
        ori_cov[lab] = Rk @ block("q", ki, 3) @ Rk.T
        pos[lab] = values["r"][ki - 1].numpy()
        pos_cov[lab] = block("r", ki, 3)
        to[lab] = float(values["o"][ki - 1]); to_s[lab] = math.sqrt(max(block("o", ki, 1)[0, 0], 0.0))
        if settings.acc_delay:
            oa[lab] = float(values["oa"][ki - 1]); oa_s[lab] = math.sqrt(max(block("oa", ki, 1)[0, 0], 0.0))
        if own[ki]:
            dr[lab] = float(values["d"][ki - 1]); dr_s[lab] = math.sqrt(max(block("d", ki, 1)[0, 0], 0.0))
        bgo[lab], bao[lab] = b_mean[ki, :3], b_mean[ki, 3:]
        if stated[ki - 1]:
            ang = float(boxminus(values["q"][ki - 1], qn_t[ki - 1]).norm())
            if ang > settings.contradiction_sigma * sig_q:
                warnings.append(f"nominal_orientation: IMU {lab} is {math.degrees(ang):.1f}° from its nominal "
                                f"orientation (> {settings.contradiction_sigma:g} × {settings.orientation_prior_deg:g}° "
                                "prior std); the data contradict it")
    out = RigResult(reference_imu=ref, orientation=ori, orientation_cov=ori_cov, position=pos, position_cov=pos_cov,
                     time_offset=to, time_offset_std=to_s, clock_drift=dr, clock_drift_std=dr_s, gyro_bias=bgo,
                     acc_bias=bao, own_stamps=own_lab, unidentified=sorted(unident), warnings=warnings,
                     converged=bool(res.converged), reason=res.reason, n_iter=len(log_all), chi2_per_dof=chi2,
                     seconds=time_elapsed(t_start), info_eigs=lam, hessian=hess_used,
                     stamp_jitter_std=sjo, free_cov=cov, random_walk=wko,
                     bias_knot_spacing=np.array([grids[0].H, grids[1].H]), knot_spacing=float(h), chi2_per_imu=chi2_imu,
                     acc_delay=oa, acc_delay_std=oa_s,
                     linear_error={kind: _label_order(symmetric(torch.cat((values[LINEAR_BLOCKS[kind]].new_zeros(1, 6),
                                                                           values[LINEAR_BLOCKS[kind]]))).numpy(), order)
                                   for kind in settings.linear_errors},
                     free_labels=[(order[idx[0] + 1], name, idx[1] if len(idx) > 1 else 0) for name, idx in labels],
                     block_scores=scores)
    line = robust_warning(robust_summary(out))
    if line:
        out.warnings.append(line)
    return out


def _label_order(a: np.ndarray, order: list) -> np.ndarray:
    """Rows of a (internal order, reference first) put in label order."""
    out = np.empty_like(a)
    out[order] = a
    return out


def _marginal_information(S: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Information of the ``keep`` coordinates with the others (the bias knots) marginalised: the
    Schur complement S_kk − S_kb S_bb⁻¹ S_bk (Cholesky: raises LinAlgError where S_bb is not
    positive definite)."""
    b = ~keep
    if not b.any():
        return S
    Skk, Skb, Sbb = S[np.ix_(keep, keep)], S[np.ix_(keep, b)], S[np.ix_(b, b)]
    L = np.linalg.cholesky(0.5 * (Sbb + Sbb.T))
    Y = np.linalg.solve(L, Skb.T)
    out = Skk - Y.T @ Y
    return 0.5 * (out + out.T)


def time_elapsed(t_start: float) -> float:
    return float(_time.perf_counter() - t_start)
