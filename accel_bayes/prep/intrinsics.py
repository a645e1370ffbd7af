"""Intrinsic calibration of each IMU from the rests of a recording (DESIGN §2, "preprocess").

[C21] §IV-B calibrates every accelerometer triad with a first-order model from stationary
conditions before estimating the geometry (their ref. [18]); this module does that step.

Accelerometer model (per IMU k, sensor frame)
---------------------------------------------
    a_true = T_k (a_raw − b_k),        |a_true| = g   in every rest

* b_k (3,) m/s² — offset (bias).
* T_k (3, 3) — **lower-triangular**: diagonal = scale factors (t_xx, t_yy, t_zz), below the
  diagonal = non-orthogonality (t_yx, t_zx, t_zy).  At rest only |a_true| is known, so any
  rotation of the corrected frame fits equally well (3 of a general T's 9 entries are not
  estimable from gravity).  The triangular form removes exactly that freedom: the corrected x
  axis is the sensor's x axis, the corrected xy plane is the sensor's xy plane.  It is the
  inverse of [S16] eq. 21–22's model z = Sᵀ f + o with S upper-triangular (Sᵀ lower-triangular,
  and so is its inverse) and the usual convention of multi-position calibration.  How the
  corrected frame sits on the board (the triad's orientation) is a separate question — answered
  by the array-level calibration, not here.  Positive diagonal entries fix the sign.
  In the terms of the effects library (one definition per sensor error): the raw output is
  a_raw = T⁻¹ a_true + b, a general gain and bias (``acc_scale``, ``acc_misalignment``,
  ``acc_bias``; :meth:`Intrinsics.acc_effects`) restricted to the triangular gauge gain = L·Q
  with Q = I (:func:`accel_bayes.physics.effects.triangular_gauge`).
* The 9 parameters per IMU, in this order (``ACC_PARAMS``):
  ``[b_x, b_y, b_z, t_xx, t_yy, t_zz, t_yx, t_zx, t_zy]``.

Estimation: for each rest s the mean raw output m_ks (unclipped samples only) gives one residual
r_ks = |T_k (m_ks − b_k)| − g with weight n_ks / σ_k² (n_ks samples, σ_k the pooled within-rest
std of that IMU: the white-noise variance of the rest mean).  The package's batched
Levenberg–Marquardt (:class:`accel_bayes.inference.lm.BatchedLevenbergMarquardt`, all IMUs at
once) minimises Σ_s w r² (9 unknowns per IMU).  Needs at least 9 rests in
9 distinct orientations (more for an uncertainty).

Uncertainty: the Laplace (Gauss–Newton) covariance (JᵀWJ)⁻¹, multiplied by the reduced χ²
(χ²/(S − 9)) when that exceeds 1.  On real sensors it does by far: the residuals are set by
model error (non-linearity, temperature drift, the fit's 9-parameter form), not by white noise,
so the covariance is scaled to the observed misfit (the convention of weighted least squares
with an estimated variance factor).  ``chi2_per_dof`` is reported so the user can see which
case applies.

Gyroscopes: only the offset is estimable at rest ([C21] §IV-B).  b_g,k is the mean over the
rests of each rest's mean (unclipped samples); its covariance is the sample covariance of the
rest means divided by the number of rests, so it includes what varies between rests (Earth's
rotation, ~7·10⁻⁵ rad/s, seen differently in each orientation; g-sensitivity; drift) besides the
white noise.

Gravity: ``g`` defaults to the standard 9.80665 m/s² (the constant the MIMU importer's scaling
uses).  The rests cannot tell g: the fit is invariant under (T, g) → (c T, c g), so g only sets
the overall scale of the corrected outputs (and the residuals scale with it).  Use the local
value when it is known; never tune it per recording.

What the uncertainty covers: the noise and misfit of the rests of *this* recording.  On the
six MIMU4444 recordings (``experiments/mimu_intrinsics.py``) the self-calibrated rests agree with
|a| = g to ≤ 0.014 m/s², scale and non-orthogonality repeat across experiments to about their
reported std, but the accelerometer offsets differ between experiments by ~0.02 m/s²
(~25× their within-recording std) and the gyro offsets by ~0.06 °/s: turn-on offsets.
Estimate the intrinsics from rests of the same power-up as the data they correct.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..constants import ACC_PARAMS, ACC_T_INDEX, G0
from ..errors import UserError
from ..inference.lm.damping import NielsenDamping
from ..inference.lm import BatchedLevenbergMarquardt, StoppingRule
from ..data.recording import Recording
from ..data.segments import cluster_orientations, detect_static, mask_from_labels, static_segments

__all__ = [
    "SCHEMA",
    "ACC_PARAMS",
    "Intrinsics",
    "estimate_intrinsics",
    "static_acc_errors",
    "rest_segments",
    "masked_segment_means",
    "triangular_matrix",
]

SCHEMA = "accel_bayes.intrinsics/1"
_MIN_REST_SAMPLES = 10


def triangular_matrix(t: torch.Tensor) -> torch.Tensor:
    """Lower-triangular T from its six entries ``(t_xx, t_yy, t_zz, t_yx, t_zx, t_zy)``:
    (..., 6) → (..., 3, 3)."""
    txx, tyy, tzz, tyx, tzx, tzy = t.unbind(-1)
    o = torch.zeros_like(txx)
    return torch.stack((torch.stack((txx, o, o), -1), torch.stack((tyx, tyy, o), -1),
                        torch.stack((tzx, tzy, tzz), -1)), -2)


# --------------------------------------------------------------------------------- rests
def rest_segments(recording: Recording, segments=None) -> list[tuple[int, int]]:
    """The static ``(start, stop)`` index pairs to use.

    ``segments``: None (the recording's ``segment`` labels when present, else
    :func:`accel_bayes.data.segments.detect_static`), a (T,) bool mask, or a list of pairs.
    """
    T = recording.T
    if segments is None:
        if recording.segment is not None:
            mask = mask_from_labels(recording.segment)
        else:
            mask = detect_static(recording.acc, recording.gyro, recording.time)
        return static_segments(mask)
    arr = np.asarray(segments)
    if arr.dtype == bool:
        if arr.shape != (T,):
            raise UserError(f"segments: a bool mask must have shape ({T},), got {arr.shape}")
        return static_segments(arr)
    try:
        pairs = np.asarray(segments, dtype=np.int64).reshape(-1, 2)
    except (TypeError, ValueError):
        raise UserError("segments: expected a (T,) bool mask or a list of (start, stop) index pairs") from None
    if pairs.size and (pairs.min() < 0 or pairs.max() > T or np.any(pairs[:, 1] <= pairs[:, 0])):
        raise UserError(f"segments: expected 0 <= start < stop <= {T} for every (start, stop) pair")
    return [(int(a), int(b)) for a, b in pairs]


def masked_segment_means(x: np.ndarray, segments, valid: np.ndarray | None = None):
    """Per-segment means of (T, K, 3) outputs over the samples where ``valid`` (T, K) holds
    (and the values are finite).  Returns (means (S, K, 3), counts (S, K)); NaN means where a
    segment has no valid sample of an IMU."""
    x = np.asarray(x, dtype=np.float64)
    ok = np.isfinite(x).all(-1)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool)
    segs = np.asarray(segments, dtype=np.int64).reshape(-1, 2)
    xs = np.where(ok[..., None], x, 0.0)
    c = np.concatenate((np.zeros((1,) + xs.shape[1:]), np.cumsum(xs, axis=0)), axis=0)
    n = np.concatenate((np.zeros((1, ok.shape[1])), np.cumsum(ok, axis=0)), axis=0)
    sums = c[segs[:, 1]] - c[segs[:, 0]]
    counts = n[segs[:, 1]] - n[segs[:, 0]]
    with np.errstate(invalid="ignore", divide="ignore"):
        means = sums / counts[..., None]
    means[counts == 0] = np.nan
    return means, counts.astype(np.int64)


def _pooled_std(x, segments, valid, means):
    """(K,) pooled within-rest white-noise std (RMS over axes), unclipped samples only."""
    K = x.shape[1]
    ss = np.zeros(K)
    n = np.zeros(K)
    for i, (a, b) in enumerate(segments):  # one pass per rest (tens), vectorised inside
        v = valid[a:b] & np.isfinite(x[a:b]).all(-1)
        d = np.where(v[..., None], x[a:b] - means[i], 0.0)
        ss += (d * d).sum((0, 2))
        n += np.maximum(v.sum(0) - 1, 0) * 3
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(ss / n)


# --------------------------------------------------------------------------------- result
@dataclass
class Intrinsics:
    """Per-IMU intrinsic calibration (accelerometer bias/scale/non-orthogonality, gyro bias).

    Attributes (K IMUs; NaN rows for IMUs without that triad)
    ----------
    acc_bias : (K, 3) m/s² — b_k of a_true = T_k (a_raw − b_k), sensor frame.
    acc_matrix : (K, 3, 3) — T_k, lower-triangular (module docstring), dimensionless.
    acc_cov : (K, 9, 9) — covariance of ``ACC_PARAMS`` (Laplace, scaled by max(1, χ²/dof)).
    gyro_bias : (K, 3) rad/s — subtract from the gyro output.
    gyro_bias_cov : (K, 3, 3) (rad/s)² — standard error of the bias (between-rest spread / S).
    residual_rms : (K,) m/s² — RMS of |T(m − b)| − g over the rests used.
    chi2_per_dof : (K,) — weighted misfit per degree of freedom (≈ 1 if only white noise).
    acc_noise_std : (K,) m/s² — the pooled within-rest noise std used for the weights.
    n_rests : (K,) int — rests used per IMU;  n_orientations : distinct orientations among them.
    g : float m/s² — the gravity magnitude the model was fitted to.
    source : str — provenance (what was estimated from, how).
    """

    acc_bias: np.ndarray
    acc_matrix: np.ndarray
    acc_cov: np.ndarray
    gyro_bias: np.ndarray
    gyro_bias_cov: np.ndarray
    residual_rms: np.ndarray
    chi2_per_dof: np.ndarray
    acc_noise_std: np.ndarray
    n_rests: np.ndarray
    n_orientations: int
    g: float
    source: str = ""
    extra: dict = field(default_factory=dict)

    # ------------------------------------------------------------ derived
    @property
    def K(self) -> int:
        return int(np.asarray(self.acc_bias).shape[0])

    @property
    def acc_scale(self) -> np.ndarray:
        """(K, 3) diagonal of T (scale-factor corrections; 1 = none)."""
        return np.diagonal(self.acc_matrix, axis1=-2, axis2=-1).copy()

    @property
    def acc_misalignment(self) -> np.ndarray:
        """(K, 3) off-diagonal entries (t_yx, t_zx, t_zy) of T (non-orthogonality, dimensionless
        ≈ rad for small angles)."""
        T = np.asarray(self.acc_matrix)
        return np.stack((T[:, 1, 0], T[:, 2, 0], T[:, 2, 1]), -1)

    @property
    def acc_std(self) -> np.ndarray:
        """(K, 9) standard deviations of ``ACC_PARAMS``."""
        return np.sqrt(np.diagonal(self.acc_cov, axis1=-2, axis2=-1))

    @property
    def acc_bias_std(self) -> np.ndarray:
        return self.acc_std[:, :3]

    @property
    def gyro_bias_std(self) -> np.ndarray:
        return np.sqrt(np.diagonal(self.gyro_bias_cov, axis1=-2, axis2=-1))

    def acc_params(self) -> np.ndarray:
        """(K, 9) the parameter vectors in ``ACC_PARAMS`` order."""
        T = np.asarray(self.acc_matrix)
        t = np.stack([T[:, i, j] for i, j in ACC_T_INDEX], -1)
        return np.concatenate((np.asarray(self.acc_bias), t), -1)

    # ------------------------------------------------------------ use
    def correct_acc(self, acc: np.ndarray) -> np.ndarray:
        """T_k (a_raw − b_k) for (..., K, 3) raw outputs (sensor frame), m/s²."""
        a = np.asarray(acc, dtype=np.float64) - self.acc_bias
        return np.einsum("kij,...kj->...ki", np.asarray(self.acc_matrix), a)

    def acc_effects(self) -> list:
        """The accelerometer errors as effects of the physics library (``acc_scale``,
        ``acc_misalignment``, ``acc_bias`` per IMU; :func:`accel_bayes.physics.effects.
        acc_gain_effects`): raw outputs a_raw = T⁻¹ a_true + b, i.e. gain T⁻¹ and bias b, sensor
        frame.  T⁻¹ is lower-triangular, so this is the triangular gauge (module docstring):
        :func:`~accel_bayes.physics.effects.gain_to_intrinsics` recovers (T, b) from the effects
        with an identity rotation.  IMUs without an estimate (NaN) get none."""
        from ..physics.effects import acc_gain_effects, intrinsics_gain

        out = []
        for k in range(self.K):
            if np.isfinite(self.acc_bias[k]).all() and np.isfinite(self.acc_matrix[k]).all():
                out += acc_gain_effects(*intrinsics_gain(self.acc_matrix[k], self.acc_bias[k]), imu=k)
        return out

    def correct_gyro(self, gyro: np.ndarray) -> np.ndarray:
        """gyro − b_g for (..., K, 3), rad/s."""
        return np.asarray(gyro, dtype=np.float64) - self.gyro_bias

    def apply(self, recording: Recording) -> Recording:
        """A NEW recording with corrected outputs (sensor frame); the input is not modified.

        acc ← T(acc − b), gyro ← gyro − b_g; IMUs without estimates (NaN) keep their outputs.
        Clipping flags, segments, geometry and attributes are carried over; the stated acc noise
        std becomes σ·sqrt(tr(T Tᵀ)/3) (isotropic white noise through T, RMS over axes);
        ``source`` gets a provenance note appended.
        """
        if not isinstance(recording, Recording):
            raise UserError(f"recording: expected a Recording, got {type(recording).__name__}")
        if recording.K != self.K:
            raise UserError(f"intrinsics: estimated for {self.K} IMUs, the recording has {recording.K}")
        out = recording.copy()
        acc_ok = np.isfinite(self.acc_bias).all(-1) & np.isfinite(self.acc_matrix).all((-1, -2))
        if acc_ok.any():
            corr = self.correct_acc(out.acc)
            out.acc = np.where(acc_ok[None, :, None], corr, out.acc)
            T = np.asarray(self.acc_matrix)
            f = np.sqrt(np.einsum("kij,kij->k", T, T) / 3.0)
            out.acc_noise_std = np.where(acc_ok, out.acc_noise_std * np.where(acc_ok, f, 1.0), out.acc_noise_std)
        gyro_ok = np.isfinite(self.gyro_bias).all(-1)
        if out.gyro is not None and gyro_ok.any():
            out.gyro = np.where(gyro_ok[None, :, None], self.correct_gyro(out.gyro), out.gyro)
        note = (f"intrinsic calibration applied by accel_bayes.prep.intrinsics ({SCHEMA}: acc a = T(a_raw - b), "
                f"T lower-triangular, g = {self.g:.6g} m/s2, {int(np.max(self.n_rests, initial=0))} rests; "
                f"gyro bias removed: {bool(gyro_ok.any() and out.gyro is not None)}; intrinsics from: "
                f"{self.source or 'unknown'})")
        out.source = f"{recording.source}; {note}" if recording.source else note
        out.attrs = dict(recording.attrs)
        out.attrs["intrinsics_applied"] = SCHEMA
        return out

    # ------------------------------------------------------------ files
    def to_dict(self) -> dict:
        """JSON-ready dict, schema ``accel_bayes.intrinsics/1`` (NaN → null)."""
        from .. import __version__

        def L(x):
            a = np.asarray(x, dtype=np.float64)
            return None if not np.isfinite(a).all() else a.tolist()

        imus = []
        for k in range(self.K):
            imus.append({
                "imu": k,
                "acc_bias": L(self.acc_bias[k]),
                "acc_matrix": L(self.acc_matrix[k]),
                "acc_cov": L(self.acc_cov[k]),
                "acc_bias_std": L(self.acc_bias_std[k]),
                "acc_scale": L(self.acc_scale[k]),
                "acc_misalignment": L(self.acc_misalignment[k]),
                "gyro_bias": L(self.gyro_bias[k]),
                "gyro_bias_cov": L(self.gyro_bias_cov[k]),
                "gyro_bias_std": L(self.gyro_bias_std[k]),
                "residual_rms": L(self.residual_rms[k]),
                "chi2_per_dof": L(self.chi2_per_dof[k]),
                "acc_noise_std": L(self.acc_noise_std[k]),
                "n_rests": int(self.n_rests[k]),
            })
        return {
            "schema": SCHEMA,
            "model": "a_true = T (a_raw - b), T lower-triangular (scale on the diagonal, non-orthogonality "
                     "below it), |a_true| = g at rest; gyro_true = gyro_raw - gyro_bias; sensor frame, SI units",
            "acc_params": list(ACC_PARAMS),
            "g": float(self.g),
            "n_orientations": int(self.n_orientations),
            "imus": imus,
            "provenance": {"version": __version__, "source": self.source, **self.extra},
        }

    def to_json(self, path=None, *, overwrite: bool = True) -> str:
        """The JSON text; with ``path`` also written there atomically."""
        text = json.dumps(self.to_dict(), indent=1) + "\n"
        if path is not None:
            from ..data.outputs import write_text

            write_text(path, text, overwrite=overwrite)
        return text

    @classmethod
    def from_dict(cls, d: dict) -> "Intrinsics":
        """Inverse of :meth:`to_dict`; raises :class:`UserError` naming the bad field."""
        if not isinstance(d, dict):
            raise UserError(f"intrinsics: expected a JSON object, got {type(d).__name__}")
        if d.get("schema") != SCHEMA:
            raise UserError(f"intrinsics.schema: expected {SCHEMA!r}, got {d.get('schema')!r}")
        imus = d.get("imus")
        if not isinstance(imus, list) or not imus:
            raise UserError("intrinsics.imus: expected a non-empty list")
        K = len(imus)
        try:
            g = float(d["g"])
        except (KeyError, TypeError, ValueError):
            raise UserError("intrinsics.g: expected a number (m/s2)") from None
        if not (g > 0 and math.isfinite(g)):
            raise UserError(f"intrinsics.g: expected a positive number, got {d.get('g')!r}")

        def get(i, e, key, shape):
            v = e.get(key)
            if v is None:
                return np.full(shape, np.nan)
            try:
                a = np.asarray(v, dtype=np.float64)
            except (TypeError, ValueError):
                a = None
            if a is None or a.shape != shape:
                raise UserError(f"intrinsics.imus[{i}].{key}: expected shape {shape}")
            return a

        fields = {"acc_bias": (3,), "acc_matrix": (3, 3), "acc_cov": (9, 9), "gyro_bias": (3,),
                  "gyro_bias_cov": (3, 3), "residual_rms": (), "chi2_per_dof": (), "acc_noise_std": ()}
        out = {k: np.full((K,) + s, np.nan) for k, s in fields.items()}
        n_rests = np.zeros(K, dtype=np.int64)
        for i, e in enumerate(imus):
            if not isinstance(e, dict) or e.get("imu") != i:
                raise UserError(f"intrinsics.imus[{i}].imu: expected {i} (IMUs listed in label order)")
            for k, s in fields.items():
                out[k][i] = get(i, e, k, s)
            n_rests[i] = int(e.get("n_rests", 0))
            T = out["acc_matrix"][i]
            if np.isfinite(T).all() and (np.abs(np.triu(T, 1)).max() > 0 or np.any(np.diag(T) <= 0)):
                raise UserError(f"intrinsics.imus[{i}].acc_matrix: expected lower-triangular with a positive diagonal")
        prov = dict(d.get("provenance") or {})
        src = str(prov.pop("source", ""))
        prov.pop("version", None)
        return cls(n_rests=n_rests, n_orientations=int(d.get("n_orientations", 0)), g=g, source=src,
                   extra=prov, **out)

    @classmethod
    def from_json(cls, src) -> "Intrinsics":
        """Load from a path, JSON text or an already parsed dict."""
        if isinstance(src, dict):
            return cls.from_dict(src)
        if isinstance(src, str) and src.lstrip().startswith("{"):
            text, where = src, "intrinsics"
        else:
            p = Path(src)
            if not p.exists():
                raise FileNotFoundError(f"{p}: no such intrinsics file")
            text, where = p.read_text(encoding="utf-8"), str(p)
        try:
            d = json.loads(text)
        except ValueError as exc:
            raise UserError(f"{where}: not valid JSON ({exc})") from None
        try:
            return cls.from_dict(d)
        except UserError as exc:
            raise UserError(f"{where}: {exc}") from None


# --------------------------------------------------------------------------------- estimation
def _residuals(p, m, g):
    """r (K, S), J (K, S, 9) of |T(m − b)| − g; p (K, 9), m (K, S, 3)."""
    b, t = p[:, :3], p[:, 3:]
    T = triangular_matrix(t)  # (K, 3, 3)
    d = m - b[:, None, :]  # (K, S, 3)
    v = torch.einsum("kij,ksj->ksi", T, d)
    nv = v.norm(dim=-1)
    u = v / nv[..., None]
    r = nv - g
    Jb = -torch.einsum("ksi,kij->ksj", u, T)
    Jt = torch.stack([u[..., i] * d[..., j] for i, j in ACC_T_INDEX], -1)
    return r, torch.cat((Jb, Jt), -1)


def _lm(p, m, w, g, max_iter=200, tol=1e-13):
    """Fit the rest model of every IMU at once with the package's batched Levenberg–Marquardt
    (:class:`~accel_bayes.inference.lm.BatchedLevenbergMarquardt`: Nielsen damping with Marquardt
    scaling, one λ and one stopping reason per IMU).  p (K, 9) start, m (K, S, 3) rest means,
    w (K, S) weights.  Returns (p, r, J at p, all converged)."""
    def linearize(p_, idx):
        r, J = _residuals(p_, m[idx], g)
        wi = w[idx]
        b = -torch.einsum("ksi,ks,ks->ki", J, wi, r)
        H = torch.einsum("ksi,ks,ksj->kij", J, wi, J)
        return 0.5 * (wi * r * r).sum(-1), b, H

    stop = StoppingRule(max_iter, ftol=1e-15, xtol=tol, gtol=0.0)
    res = BatchedLevenbergMarquardt(NielsenDamping(tau=1e-3), stop).solve(linearize, p, subset=True)
    r, J = _residuals(res.x, m, g)
    return res.x, r, J, bool(res.converged.all())


def estimate_intrinsics(recording: Recording, segments=None, g: float = G0, *,
                        min_orientations: int = 9, orientation_tol_deg: float = 2.0) -> Intrinsics:
    """Estimate accelerometer bias/scale/non-orthogonality and gyro bias per IMU from rests.

    Parameters
    ----------
    recording : raw outputs (sensor frame).
    segments : None (the recording's ``segment`` labels, else :func:`detect_static`), a (T,)
        bool mask or a list of ``(start, stop)`` pairs of static samples.
    g : gravity magnitude, m/s² (default standard gravity 9.80665).
    min_orientations : refuse fewer distinct rest orientations (9 unknowns per IMU).
    orientation_tol_deg : rests within this angle count as one orientation (for that check).

    Saturated samples (``acc_clipped`` / ``gyro_clipped``) and samples an importer marked
    implausible (``acc_flagged`` / ``gyro_flagged``) are excluded from the rest means;
    a rest keeps an IMU only with at least 10 valid samples.  Returns :class:`Intrinsics`.
    """
    if not isinstance(recording, Recording):
        raise UserError(f"recording: expected a Recording, got {type(recording).__name__}")
    try:
        g = float(g)
    except (TypeError, ValueError):
        raise UserError(f"g: expected a number in m/s2, got {g!r}") from None
    if not (g > 0 and math.isfinite(g)):
        raise UserError(f"g: expected a positive gravity magnitude in m/s2, got {g!r}")
    segs = rest_segments(recording, segments)
    K = recording.K
    if not segs:
        raise UserError("segments: no static segment found; intrinsic calibration needs rests in "
                        f"at least {min_orientations} orientations")
    acc = np.asarray(recording.acc, dtype=np.float64)
    valid_a = _valid(recording, "acc")
    means, counts = masked_segment_means(acc, segs, valid_a)  # (S, K, 3), (S, K)
    use = (counts >= _MIN_REST_SAMPLES) & np.isfinite(means).all(-1)  # (S, K)
    has = recording.has_acc & use.any(0)

    # Distinct orientations, judged per IMU in its own sensor frame (directions of the rest means).
    n_orient = np.zeros(K, dtype=np.int64)
    for k in np.flatnonzero(has):
        mk = means[use[:, k], k]
        n_orient[k] = int(cluster_orientations(mk / np.linalg.norm(mk, axis=-1, keepdims=True), orientation_tol_deg).max() + 1)
    bad = np.flatnonzero(has & (n_orient < min_orientations))
    if bad.size:
        raise UserError(f"segments: IMU {int(bad[0])} has rests in only {int(n_orient[bad[0]])} distinct orientations; "
                        f"the accelerometer model has 9 unknowns and needs at least {min_orientations}")

    sigma = _pooled_std(acc, segs, valid_a, means)  # (K,)
    acc_bias = np.full((K, 3), np.nan)
    acc_matrix = np.full((K, 3, 3), np.nan)
    acc_cov = np.full((K, 9, 9), np.nan)
    rms = np.full(K, np.nan)
    chi2 = np.full(K, np.nan)
    n_rests = use.sum(0).astype(np.int64) * has
    idx = np.flatnonzero(has)
    converged = True
    if idx.size:
        m = torch.as_tensor(np.where(use[:, idx, None], means[:, idx], 0.0).transpose(1, 0, 2))  # (k, S, 3)
        sig = np.where(np.isfinite(sigma[idx]) & (sigma[idx] > 0), sigma[idx], 1.0)
        w = torch.as_tensor(np.where(use[:, idx], counts[:, idx], 0).T / sig[:, None] ** 2)  # (k, S)
        norm = m.norm(dim=-1)
        scale0 = g / (torch.where(w > 0, norm, 0).sum(-1) / (w > 0).sum(-1))
        p0 = torch.zeros(idx.size, 9, dtype=torch.float64)
        p0[:, 3:6] = scale0[:, None]
        p, r, J, converged = _lm(p0, m, w, g)
        A = torch.einsum("ksi,ks,ksj->kij", J, w, J)
        evals = torch.linalg.eigvalsh(A)
        if bool((evals[:, 0] <= 1e-12 * evals[:, -1]).any()):
            k = int(idx[int(torch.argmin(evals[:, 0] / evals[:, -1]))])
            raise UserError(f"segments: the rests of IMU {k} do not determine its 9 accelerometer parameters "
                            "(orientations too few or too alike)")
        n_used = (w > 0).sum(-1).to(torch.float64)
        dof = (n_used - 9).clamp_min(0)
        c2 = (w * r * r).sum(-1)
        red = torch.where(dof > 0, c2 / dof.clamp_min(1), torch.full_like(c2, float("nan")))
        factor = torch.where(torch.isfinite(red), red.clamp_min(1.0), torch.ones_like(red))
        cov = torch.linalg.inv(A) * factor[:, None, None]
        pn = p.numpy()
        acc_bias[idx] = pn[:, :3]
        acc_matrix[idx] = triangular_matrix(p[:, 3:]).numpy()
        acc_cov[idx] = cov.numpy()
        rms[idx] = torch.sqrt((torch.where(w > 0, r, 0) ** 2).sum(-1) / n_used).numpy()
        chi2[idx] = red.numpy()

    # Gyro bias: mean of the rest means; standard error from their spread.
    gyro_bias = np.full((K, 3), np.nan)
    gyro_cov = np.full((K, 3, 3), np.nan)
    if recording.gyro is not None:
        valid_g = _valid(recording, "gyro")
        gm, gc = masked_segment_means(recording.gyro, segs, valid_g)
        guse = (gc >= _MIN_REST_SAMPLES) & np.isfinite(gm).all(-1)
        for k in np.flatnonzero(recording.has_gyro & guse.any(0)):  # K iterations over IMUs
            x = gm[guse[:, k], k]
            gyro_bias[k] = x.mean(0)
            if x.shape[0] > 1:
                gyro_cov[k] = np.cov(x, rowvar=False).reshape(3, 3) / x.shape[0]

    desc = recording.description or "recording"
    n_orient_all = int(n_orient[has].min()) if has.any() else 0
    src = (f"estimated by accel_bayes.prep.intrinsics from {len(segs)} static segments of '{desc}' "
           f"(g = {g:.6g} m/s2, rest means of unclipped samples, LM fit of |T(m - b)| = g"
           f"{'' if converged else ', LM NOT converged for every IMU'})")
    return Intrinsics(acc_bias=acc_bias, acc_matrix=acc_matrix, acc_cov=acc_cov, gyro_bias=gyro_bias,
                      gyro_bias_cov=gyro_cov, residual_rms=rms, chi2_per_dof=chi2, acc_noise_std=sigma,
                      n_rests=n_rests, n_orientations=n_orient_all, g=g, source=src,
                      extra={"segments": len(segs), "converged": bool(converged)})


def _valid(recording: Recording, sensor: str) -> np.ndarray:
    """(T, K) bool: samples of ``sensor`` ("acc"/"gyro") neither clipped nor marked implausible."""
    ok = np.ones((recording.T, recording.K), dtype=bool)
    for m in (getattr(recording, f"{sensor}_clipped"), getattr(recording, f"{sensor}_flagged")):
        if m is not None:
            ok &= ~np.asarray(m, bool)
    return ok


def static_acc_errors(recording: Recording, g: float = G0, segments=None) -> np.ndarray:
    """(S, K) |mean acc| − g per static segment and IMU, m/s² (unclipped samples; NaN where an
    IMU has no valid sample in a segment).  Segments as in :func:`estimate_intrinsics`."""
    segs = rest_segments(recording, segments)
    means, _ = masked_segment_means(recording.acc, segs, _valid(recording, "acc"))
    return np.linalg.norm(means, axis=-1) - float(g)
