"""Real-data preprocessing before the geometry calibration (DESIGN §2 "preprocess"; issue #6 item 2).

:func:`preprocess` turns an imported recording into what the [C21] likelihood should see:

1. **Intrinsic calibration** from the recording's own rests
   (:func:`accel_bayes.prep.intrinsics.estimate_intrinsics`: accelerometer bias, scale factor and
   non-orthogonality per IMU, gyro bias), applied to every sample
   (:meth:`~accel_bayes.prep.intrinsics.Intrinsics.apply`).  [C21] §IV-B calibrates the triads at
   rest before estimating the geometry, and the model ([C21] eq. 4) assumes calibrated sensors.
   The intrinsics of one power-up do not transfer to another (turn-on offsets differ by
   ~25× their std across the MIMU experiments, ``experiments/mimu_intrinsics.py``), so they
   are estimated from the same recording.  ``intrinsics="auto"`` skips the step, with a note,
   on a recording that has no rests in at least 9 distinct orientations (e.g. simulated
   twisting) or whose intrinsics were already applied.
2. **Sample selection** (each switchable; every drop is counted by reason, in this order):

   * ``drop_static`` — samples inside the rests (they carry no information on the positions:
     ω = 0 there, [C21] §IV-C; they were used for step 1);
   * ``drop_clipped`` — samples where any accelerometer or gyroscope axis sits at its range
     (``acc_clipped``/``gyro_clipped``): the model cannot explain them;
   * ``min_rotation`` — samples with |ω̄_t| < ``min_rotation`` rad/s, ω̄_t the inverse-variance-
     weighted mean of the (bias-corrected) gyros in the array frame (default 0.5 rad/s ≈ 29 °/s,
     :data:`accel_bayes.prep.selection.DEFAULT_MIN_ROTATION`): the centripetal term ω×(ω×r) that
     carries the positions is then < 0.25 % of g at 20 mm ([C21] §IV-C), and the rotational
     ω̇×r term is integrated out with φ.  0 keeps every sample.

The selection is THE one of :func:`accel_bayes.prep.selection.select_samples` (samples with no
finite gyro reading are dropped as ``non_finite``; a caller's own mask or indices, ``select``, is
the ``user`` reason).

Returns a :class:`Preprocessed` (corrected recording, the :class:`Selection`, the intrinsics and a
JSON-ready ``summary``) that :func:`accel_bayes.pipelines.calibrate.calibrate` records in the
``positions.json`` provenance and prints.

:func:`draw_intrinsics` draws intrinsics from their reported uncertainty (Laplace covariance of
the rest fit, scaled to its misfit) — used to measure how much the intrinsic-calibration
uncertainty moves the geometry (``experiments/mimu_repeatability.py``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..constants import G0, RAD_TO_DEG
from ..errors import UserError
from .intrinsics import ACC_PARAMS, Intrinsics, estimate_intrinsics, rest_segments, static_acc_errors, \
    triangular_matrix
from .selection import DEFAULT_MIN_ROTATION, Selection, check_min_rotation, clipped_mask, rotation_rate, \
    select_samples
from ..data.recording import Recording

__all__ = ["Preprocessed", "preprocess", "draw_intrinsics", "INTRINSICS_MODES", "MIN_REST_ORIENTATIONS"]

INTRINSICS_MODES = ("auto", "estimate", "none")
MIN_REST_ORIENTATIONS = 9  # the accelerometer model has 9 unknowns per IMU


@dataclass
class Preprocessed:
    """What :func:`preprocess` did.

    recording : the recording to calibrate (intrinsics applied when they were), ALL samples.
    selection : the :class:`~accel_bayes.prep.selection.Selection` of the samples to use
        (``keep`` is its (T,) mask).
    intrinsics : the :class:`~accel_bayes.prep.intrinsics.Intrinsics` applied, or None.
    has_rests : whether the recording has rests (static segments) at all.
    summary : JSON-ready dict: ``intrinsics`` (what was estimated/applied, or why not) and
        ``samples`` (counts: recording, static, clipped (dropped), non_finite, slow, kept, clipped_kept (clipped
        samples among the kept ones, > 0 only with ``drop_clipped=False``); the thresholds used).
    notes : human-readable lines (also in ``summary["notes"]``).
    """

    recording: Recording
    selection: Selection
    intrinsics: Intrinsics | None
    has_rests: bool
    summary: dict
    notes: list = field(default_factory=list)

    @property
    def keep(self) -> np.ndarray:
        """(T,) bool: the samples to use (``selection.keep``)."""
        return self.selection.keep

    @property
    def n_kept(self) -> int:
        return self.selection.n_kept

    def lines(self) -> list[str]:
        """Short human report (what ``accel-bayes calibrate`` prints before the table)."""
        s = self.summary["samples"]
        out = []
        it = self.summary["intrinsics"]
        if it["applied"]:
            out.append(f"intrinsics: {it['how']}; worst rest | |a| - g | {it['rest_error_max_before']:.4f} -> "
                       f"{it['rest_error_max_after']:.4f} m/s2; acc bias up to {it['acc_bias_max']:.3f} m/s2, "
                       f"scale {it['acc_scale_min']:.4f}-{it['acc_scale_max']:.4f}, gyro bias up to "
                       f"{it['gyro_bias_max_dps']:.2f} deg/s")
        else:
            out.append(f"intrinsics: not applied ({it['why']})")
        out.append(f"samples: {s['recording']} in the recording; dropped {s['static']} static, {s['clipped']} clipped "
                   f"(acc or gyro at range), {s.get('flagged', 0)} flagged implausible by the importer, {s.get('non_finite', 0)} without a finite gyro, {s['slow']} with |w| < {s['min_rotation']:g} rad/s; kept {s['kept']}")
        out.extend(f"note: {n}" for n in self.notes)
        return out


def _load_intrinsics(spec):
    if isinstance(spec, Intrinsics):
        return spec
    if isinstance(spec, (str, Path)) and str(spec) not in INTRINSICS_MODES:
        if isinstance(spec, str) and spec.lstrip().startswith("{"):
            return Intrinsics.from_json(spec)
        if not Path(spec).is_file():
            raise UserError(f"intrinsics: expected one of {INTRINSICS_MODES}, an Intrinsics or an intrinsics JSON "
                            f"file, got {str(spec)!r} (no such file)")
        return Intrinsics.from_json(spec)
    return None


def _intrinsics_summary(intr: Intrinsics, before: np.ndarray, after: np.ndarray, how: str) -> dict:
    ok = np.isfinite(intr.acc_bias).all(-1)
    gb = np.abs(intr.gyro_bias) * RAD_TO_DEG
    return {
        "applied": True,
        "how": how,
        "rests": int(intr.extra.get("segments", int(np.max(intr.n_rests, initial=0)))),
        "orientations": int(intr.n_orientations),
        "rest_error_max_before": float(np.nanmax(np.abs(before))) if before.size else float("nan"),
        "rest_error_max_after": float(np.nanmax(np.abs(after))) if after.size else float("nan"),
        "acc_bias_max": float(np.nanmax(np.linalg.norm(intr.acc_bias[ok], axis=-1))) if ok.any() else float("nan"),
        "acc_scale_min": float(np.nanmin(intr.acc_scale[ok])) if ok.any() else float("nan"),
        "acc_scale_max": float(np.nanmax(intr.acc_scale[ok])) if ok.any() else float("nan"),
        "acc_misalignment_max": float(np.nanmax(np.abs(intr.acc_misalignment[ok]))) if ok.any() else float("nan"),
        "gyro_bias_max_dps": float(np.nanmax(gb)) if np.isfinite(gb).any() else float("nan"),
        "chi2_per_dof": [None if not np.isfinite(v) else float(v) for v in intr.chi2_per_dof],
        "residual_rms": [None if not np.isfinite(v) else float(v) for v in intr.residual_rms],
        "acc_bias": [[float(x) for x in row] for row in np.asarray(intr.acc_bias)],
        "acc_scale": [[float(x) for x in row] for row in intr.acc_scale],
        "gyro_bias_dps": [[float(x) for x in row] for row in np.asarray(intr.gyro_bias) * RAD_TO_DEG],
        "source": intr.source,
    }


def preprocess(recording: Recording, *, intrinsics="auto", g: float = G0, drop_static: bool = True,
               drop_clipped: bool = True, min_rotation: float | None = DEFAULT_MIN_ROTATION,
               segments=None, select=None) -> Preprocessed:
    """Intrinsic calibration from the recording's rests, then selection of informative samples.

    recording : a :class:`~accel_bayes.data.recording.Recording` (sensor frame, raw or calibrated).
    intrinsics : "auto" (default) — estimate from the recording's rests and apply, or skip with a
        note when there are no rests in ≥ 9 distinct orientations or the recording says
        intrinsics were already applied; "estimate" — the same but an error instead of the
        skip; "none" (or False) — skip; an :class:`~accel_bayes.prep.intrinsics.Intrinsics` or the
        path of an intrinsics JSON (``accel-bayes intrinsics``) — apply those.
    g : gravity magnitude for the rest fit, m/s² (standard gravity by default).
    drop_static : drop the samples of the rests.
    drop_clipped : drop samples where any accelerometer or gyroscope is flagged as clipped.
    min_rotation : drop samples with |ω̄_t| below this, rad/s (None or 0: keep them).
    segments : the rests — None (the recording's ``segment`` labels, else
        :func:`accel_bayes.data.segments.detect_static`), a (T,) bool mask or (start, stop) pairs.
    select : further selection ANDed with the above (the ``user`` reason): a (T,) bool mask or
        sample indices; "rotation" (compatibility) raises the threshold to the default 0.5 rad/s
        when ``min_rotation`` is 0, its drops then counted as ``user``.

    Returns a :class:`Preprocessed`.  The input recording is not modified.
    """
    if not isinstance(recording, Recording):
        raise UserError(f"recording: expected a Recording, got {type(recording).__name__}")
    if intrinsics is False or intrinsics is None:
        intrinsics = "none"
    if intrinsics is True:
        intrinsics = "estimate"
    given = _load_intrinsics(intrinsics)
    if given is None and intrinsics not in INTRINSICS_MODES:
        raise UserError(f"intrinsics: expected one of {INTRINSICS_MODES}, an Intrinsics or a JSON path, "
                        f"got {intrinsics!r}")
    min_rotation = check_min_rotation(min_rotation)  # before the intrinsics fit: fail fast

    T = recording.T
    segs = rest_segments(recording, segments)
    static = np.zeros(T, dtype=bool)
    for a, b in segs:  # one slice per rest (tens)
        static[a:b] = True
    has_rests = bool(segs)
    notes: list[str] = []

    # ---- 1. intrinsics
    rec = recording
    intr = None
    already = "intrinsics_applied" in (recording.attrs or {})
    if given is not None:
        intr = given
        how = f"given ({intr.source or 'file'})"
    elif intrinsics == "none":
        why = "switched off (intrinsics='none')"
    elif already:
        why = f"the recording says intrinsics were already applied ({recording.attrs['intrinsics_applied']})"
        if intrinsics == "estimate":
            raise UserError(f"intrinsics: {why}; pass intrinsics='none' to use the recording as it is")
    elif not has_rests:
        why = "no static segments in the recording (nothing to estimate intrinsics from)"
        if intrinsics == "estimate":
            raise UserError(f"intrinsics: {why}")
    else:
        try:
            intr = estimate_intrinsics(recording, segments=segs, g=g, min_orientations=MIN_REST_ORIENTATIONS)
            how = f"estimated from {len(segs)} rests of this recording"
        except UserError as exc:
            if intrinsics == "estimate":
                raise
            why = f"rests do not determine them ({exc})"
    if intr is not None:
        if intr.K != recording.K:
            raise UserError(f"intrinsics: estimated for {intr.K} IMUs, the recording has {recording.K}")
        rec = intr.apply(recording)
        before = static_acc_errors(recording, g, segs) if has_rests else np.zeros(0)
        after = static_acc_errors(rec, g, segs) if has_rests else np.zeros(0)
        it_summary = _intrinsics_summary(intr, before, after, how)
    else:
        it_summary = {"applied": False, "why": why}
        notes.append(f"intrinsic calibration skipped: {why}")

    # ---- 2. selection: THE one (accel_bayes.prep.selection), on the corrected gyros
    user = select
    if isinstance(select, str):
        if select != "rotation":
            raise UserError(f"select: expected None, a mask, indices or 'rotation', got {select!r}")
        # compatibility: "rotation" means the rotation test even when min_rotation is 0
        user = None if min_rotation > 0 else ~(rotation_rate(rec) < DEFAULT_MIN_ROTATION)
    sel = select_samples(rec, static=static if has_rests else None, drop_static=drop_static,
                         drop_clipped=drop_clipped, min_rotation=min_rotation, user=user)
    keep = sel.keep
    if not keep.any():
        if select is not None and sel.dropped["user"]:
            raise UserError("select: no samples left after selection")
        raise UserError("preprocess: no samples left after dropping static, clipped and slow samples "
                        f"(min_rotation = {min_rotation:g} rad/s); relax the selection")
    clip = clipped_mask(rec)
    w = sel.rotation_rate if sel.rotation_rate is not None else np.full(T, np.inf)
    d = sel.dropped
    samples = {"recording": int(T), "static": d["static"], "clipped": d["clipped"], "flagged": d["flagged"], "non_finite": d["non_finite"],
               "slow": d["slow"], "kept": sel.n_kept, "clipped_kept": int((keep & clip).sum()),
               "drop_static": bool(drop_static), "drop_clipped": bool(drop_clipped), "min_rotation": min_rotation,
               "rests": len(segs), "kept_runs": sel.kept_runs,
               "rotation_rate_kept_median": float(np.median(w[keep])) if np.isfinite(w).all() else None}
    if select is not None:
        samples["user_select_dropped"] = d["user"]
    summary = {"intrinsics": it_summary, "samples": samples, "notes": list(notes)}
    return Preprocessed(recording=rec, selection=sel, intrinsics=intr, has_rests=has_rests, summary=summary, notes=notes)


def draw_intrinsics(intr: Intrinsics, generator: torch.Generator | int = 0) -> Intrinsics:
    """Intrinsics drawn from N(estimate, reported covariance) per IMU: the 9 accelerometer
    parameters (``ACC_PARAMS``, ``acc_cov``) and the gyro bias (``gyro_bias_cov``).  IMUs with
    no estimate stay NaN.  ``generator``: a torch.Generator or an int seed."""
    g = generator if isinstance(generator, torch.Generator) else torch.Generator().manual_seed(int(generator))
    K = intr.K
    def sqrtm(cov):  # PSD square root (handles zero / rank-deficient covariances)
        c = torch.as_tensor(np.nan_to_num(np.asarray(cov, dtype=np.float64)))
        lam, V = torch.linalg.eigh(0.5 * (c + c.transpose(-1, -2)))
        return V * lam.clamp_min(0).sqrt().unsqueeze(-2)

    p = torch.as_tensor(intr.acc_params())  # (K, 9)
    e = torch.randn(K, 9, generator=g, dtype=torch.float64)
    pd = p + (sqrtm(intr.acc_cov) @ e.unsqueeze(-1)).squeeze(-1)
    eg = torch.randn(K, 3, generator=g, dtype=torch.float64)
    gbd = torch.as_tensor(intr.gyro_bias) + (sqrtm(intr.gyro_bias_cov) @ eg.unsqueeze(-1)).squeeze(-1)
    acc_matrix = triangular_matrix(pd[:, 3:]).numpy()
    acc_matrix = np.where(np.isfinite(intr.acc_matrix), acc_matrix, np.nan)
    return Intrinsics(acc_bias=np.where(np.isfinite(intr.acc_bias), pd[:, :3].numpy(), np.nan), acc_matrix=acc_matrix,
                      acc_cov=np.asarray(intr.acc_cov).copy(), gyro_bias=gbd.numpy(),
                      gyro_bias_cov=np.asarray(intr.gyro_bias_cov).copy(), residual_rms=np.asarray(intr.residual_rms).copy(),
                      chi2_per_dof=np.asarray(intr.chi2_per_dof).copy(), acc_noise_std=np.asarray(intr.acc_noise_std).copy(),
                      n_rests=np.asarray(intr.n_rests).copy(), n_orientations=intr.n_orientations, g=intr.g,
                      source=f"draw from the uncertainty of: {intr.source}", extra=dict(intr.extra))


assert ACC_PARAMS[:3] == ("b_x", "b_y", "b_z")  # draw_intrinsics relies on the bias-first order
