"""[S16] self-calibration of one recording, as a library function (``accel-bayes selfcal``).

:func:`prepare` checks and extracts what the [S16] model needs (the samples of the IMUs with an
accelerometer triad — every sample, or those of a :class:`~accel_bayes.prep.selection.Selection` —
the fixed triad, the nominal poses); :func:`selfcal` runs
:func:`accel_bayes.inference.selfcal.self_calibrate` on it and, when it did not diverge, builds the
DESIGN §7.3 positions document (method "selfcal", relative to the fixed IMU, Laplace std/cov with
the motion marginalised, orientations), the ``poses.csv`` rows and the ``motion.csv`` table;
:func:`write_outputs` writes them and ``convergence.png``
(:func:`accel_bayes.diagnostics.plots.plot_convergence`).  Gyroscopes are ignored.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from ..data.io import load_recording
from ..errors import UserError
from .selfcal_options import SelfcalOptions

__all__ = ["SelfcalInput", "SelfcalOptions", "SelfcalRun", "prepare", "selfcal", "write_outputs", "POSES_HEADER",
           "MOTION_HEADER"]

POSES_HEADER = ("imu,x_mm,y_mm,z_mm,std_x_um,std_y_um,std_z_um,rotvec_x_deg,rotvec_y_deg,rotvec_z_deg,"
                "angle_vs_nominal_deg,angle_std_deg,fixed,has_acc")
MOTION_HEADER = ("time_s,a_lin_x_m_s2,a_lin_y_m_s2,a_lin_z_m_s2,omega_x_rad_s,omega_y_rad_s,omega_z_rad_s,"
                 "omega_dot_x_rad_s2,omega_dot_y_rad_s2,omega_dot_z_rad_s2")


@dataclass
class SelfcalInput:
    """What :func:`prepare` extracts from a recording for the [S16] model.

    recording : the recording; source : its :class:`~accel_bayes.data.io.LoadedRecording`.
    labels : IMU labels with an accelerometer triad (the triads fitted); fixed_label : the IMU
        held at its nominal pose; fixed : its row in ``labels``.
    acc : (T, A, 3) accelerometer outputs of those IMUs, m/s²; noise : (A,) their stated std, m/s².
    p_nom, q_nom : (K, 3) nominal positions (m) and (K, 4) orientations of every IMU.
    clipped : fraction of the fitted accelerometer samples flagged clipped (fitted as they are).
    selection : the :class:`~accel_bayes.prep.selection.Selection` the samples came from, or None
        (every sample); time : (T,) their times, s.
    prepared : the :class:`~accel_bayes.prep.prepared.PreparedRecording` all of it was taken from.
    """

    recording: object
    source: object
    labels: list
    fixed_label: int
    fixed: int
    acc: np.ndarray
    noise: np.ndarray
    p_nom: np.ndarray
    q_nom: np.ndarray
    has_acc: np.ndarray
    clipped: float
    time: np.ndarray
    selection: object = None
    prepared: object = field(default=None, repr=False)


@dataclass
class SelfcalRun:
    """What :func:`selfcal` returns.

    result : the :class:`~accel_bayes.inference.selfcal.SelfCalResult` (``ok`` False: diverged,
        then only ``result`` and the convergence log are meaningful).
    document : DESIGN §7.3 positions document (None when diverged).
    means : (K, 3) positions relative to the fixed IMU, m; pstd : (K, 3) their Laplace std, m.
    angle, angle_std : (K,) rotation from the nominal orientation and its RMS std, degrees.
    poses : rows of ``poses.csv``; motion : (T, 10) rows of ``motion.csv``.
    seconds : wall time of the self-calibration, s; warnings : why not trustworthy (LM limit,
        residuals that contradict the stated noise, scale not identified).
    check : the :class:`~accel_bayes.inference.selfcal.FitCheck` (None when diverged); the
        reported covariances are already multiplied by its ``inflation``.
    """

    input: SelfcalInput
    result: object
    seconds: float
    document: dict | None = None
    means: np.ndarray | None = None
    pstd: np.ndarray | None = None
    angle: np.ndarray | None = None
    angle_std: np.ndarray | None = None
    poses: list = field(default_factory=list)
    motion: np.ndarray | None = None
    warnings: list = field(default_factory=list)
    check: object = None

    @property
    def ok(self) -> bool:
        return bool(self.result.ok)

    @property
    def pstd_norm(self) -> np.ndarray:
        """(K,) norm of each IMU's position std, m (NaN where unknown)."""
        return np.array([np.linalg.norm(p) if np.isfinite(p).all() else np.nan for p in self.pstd])


def _options(options: SelfcalOptions | None, keywords: dict) -> SelfcalOptions:
    """``options`` (None: the defaults) with the fields given as keywords replaced (checked again)."""
    opts = options if options is not None else SelfcalOptions()
    return replace(opts, **keywords) if keywords else opts


def prepare(recording, options: SelfcalOptions | None = None, **keywords) -> SelfcalInput:
    """Check a recording for the [S16] model and extract its inputs (one-line :class:`UserError`
    naming the field otherwise), by the ``fixed``, ``selection`` and ``drop_clipped`` of
    ``options`` (:class:`~accel_bayes.pipelines.selfcal_options.SelfcalOptions`; keywords, kept
    for 0.2 only, replace its fields).  The IMUs, the samples and their checks are
    :func:`accel_bayes.prep.prepared.prepare_recording`'s (gyroscopes ignored).

    recording : a path, a Recording, a LoadedRecording, or a
        :class:`~accel_bayes.prep.prepared.PreparedRecording` (made with ``gyro="ignored"``; its
        reference IMU is the fixed one and its samples are fitted: give no ``fixed``,
        ``selection`` or ``drop_clipped`` then).
    fixed : label of the IMU held at its nominal pose (default the recording's reference IMU).
    selection : None (every sample, the [S16] setting) or a
        :class:`~accel_bayes.prep.selection.Selection` of this recording (the package's one sample
        selection, e.g. ``select_samples(rec, min_rotation=None)`` to leave out clipped samples).
        The process model links consecutive *kept* samples across each gap with the left-out
        samples' states integrated out exactly
        (:func:`~accel_bayes.inference.selfcal.bridged_process_whitening`).
    drop_clipped : without a ``selection``, leave out the samples where an accelerometer triad is
        flagged at its range (``select_samples(rec, drop_clipped=True, …)``, no other reason);
        default False: every sample, clipped ones fitted as they are ([S16]).
    """
    from ..prep.prepared import PreparedRecording, prepare_recording

    opts = _options(options, keywords)
    if isinstance(recording, PreparedRecording):
        if opts.fixed is not None or opts.selection is not None or opts.drop_clipped:
            raise UserError("recording: a PreparedRecording carries its fixed IMU and samples; give no fixed, "
                            "selection or drop_clipped with it")
        prepared = recording
        loaded = load_recording(prepared.recording)
        # every sample kept: the [S16] setting, fitted without gap bookkeeping (as no selection is)
        selection = None if prepared.selection.n_kept == prepared.recording.T else prepared.selection
    else:
        loaded = load_recording(recording)
        rec = loaded.recording
        fixed_label = int(rec.reference_imu if opts.fixed is None else opts.fixed)
        if not 0 <= fixed_label < rec.K:
            raise UserError(f"--fixed: expected an IMU label in 0..{rec.K - 1}, got {fixed_label}")
        asked = opts.selection is not None or opts.drop_clipped
        prepared = prepare_recording(rec, selection=opts.selection, select=None if asked else "all",
                                     drop_clipped=opts.drop_clipped, reference=fixed_label, reference_field="--fixed",
                                     gyro="ignored")
        selection = prepared.selection if asked else None
    rec = prepared.recording
    labels = list(prepared.imu_labels)
    index = prepared.sample_index
    if selection is not None and index.size < 3:  # without one, self_calibrate names the recording's length
        raise UserError(f"selection: keeps {index.size} samples; self-calibration needs at least 3")
    acc = prepared.sensor_acc()
    if not np.isfinite(acc).all():
        bad = sorted({labels[j] for j in np.nonzero(~np.isfinite(acc).all(axis=(0, 2)))[0]})
        raise UserError(f"acc: missing (NaN) samples for IMU(s) {bad}; self-calibration needs every sample "
                        "(the process model links consecutive samples), or a selection without them")
    clipped = 0.0
    if rec.acc_clipped is not None:
        clipped = float(np.asarray(rec.acc_clipped)[index][:, labels].mean())
    fixed_label = labels[prepared.reference]
    return SelfcalInput(recording=rec, source=loaded, labels=labels, fixed_label=fixed_label,
                        fixed=prepared.reference, acc=acc, noise=np.asarray(prepared.acc_noise_std, dtype=float),
                        p_nom=np.asarray(rec.nominal_position, dtype=float),
                        q_nom=np.asarray(rec.nominal_orientation, dtype=float), has_acc=np.asarray(rec.has_acc),
                        clipped=clipped, time=prepared.time, selection=selection, prepared=prepared)


def selfcal(recording, options: SelfcalOptions | None = None, *, progress: bool = False, **keywords) -> SelfcalRun:
    """[S16] self-calibration: poses of every accelerometer triad relative to the fixed one, jointly
    with the motion, from the accelerometers alone.

    recording : a path, a Recording, a LoadedRecording or the :class:`SelfcalInput` of :func:`prepare`
        (then its fixed IMU and samples are the ones fitted).
    options : a :class:`~accel_bayes.pipelines.selfcal_options.SelfcalOptions` (None: every
        default): the fixed IMU and the samples (:func:`prepare`), ``max_iter`` (LM iteration limit
        per stage), ``rerun`` (the [S16] §VI-A re-run from the estimate), ``seed`` (recorded in
        the provenance only: the self-calibration draws no random numbers), ``process_noise``
        ("estimate-snap", the default: the continuous-time motion model with white noise on the
        snap ω⃛ and on ä_lin — smooth ω̇ and a_lin, as in hand motion — its two intensities
        estimated from the recording, issue #12, experiments/s16_handlike.md; "estimate": white
        noise on the jerk, its board comes out up to 1 % small on hand-like motion,
        experiments/s16_handlike_jerk.md; "s16": the paper's fixed eq. 8 variances; see
        :func:`~accel_bayes.inference.selfcal.self_calibrate`) and ``marginal_scale`` (with an
        estimated process noise, move the estimate along the scale orbit to the maximum of the
        Laplace marginal likelihood, motion integrated out; "score": at the root of its
        approximate derivative instead, the earlier method; False: keep the joint MAP).
    progress : tqdm bars of the LM stages.
    keywords : (kept for 0.2 only; prefer ``options``) the options as keywords, e.g.
        ``selfcal(rec, max_iter=50)``: ``options`` with these fields replaced.
    """
    from .. import __version__
    from ..data.positions import positions_document
    from ..inference.selfcal import fit_check, self_calibrate
    from ..physics.geometry import boxminus

    opts = _options(options, keywords)
    inp = recording if isinstance(recording, SelfcalInput) else prepare(recording, opts)  # PreparedRecording too
    rec, labels, fixed_label, fixed = inp.recording, inp.labels, inp.fixed_label, inp.fixed
    K = rec.K
    p_nom, q_nom, noise = inp.p_nom, inp.q_nom, inp.noise
    t0 = time.perf_counter()
    time_s = inp.time
    steps = None if inp.selection is None else np.diff(np.asarray(inp.selection.index))
    res = self_calibrate(inp.acc, time_s, steps=steps, nominal_positions=p_nom[labels],
                         nominal_orientations=q_nom[labels], fixed=fixed, acc_noise_std=noise,
                         max_iter=opts.max_iter, progress=progress, rerun_from_estimate=opts.rerun,
                         process_noise=opts.process_noise, marginal_scale=opts.marginal_scale)
    run = SelfcalRun(input=inp, result=res, seconds=time.perf_counter() - t0)
    if not res.ok:
        return run

    # ---- positions.json: relative to the fixed IMU, array frame
    P = res.positions.detach().cpu().numpy()
    Q = res.orientations.detach().cpu().numpy()
    means = p_nom - p_nom[fixed_label]  # IMUs without accelerometer: nominal, unknown std
    covs = np.full((K, 3, 3), np.nan)
    oris = q_nom.copy()
    rel = P - P[fixed]
    pcov = res.position_cov.detach().cpu().numpy() if res.position_cov is not None else np.full((len(labels), 3, 3), np.nan)
    rcov = res.rotation_cov.detach().cpu().numpy() if res.rotation_cov is not None else np.full((len(labels), 3, 3), np.nan)
    for j, k in enumerate(labels):
        means[k] = rel[j]
        covs[k] = pcov[j]
        oris[k] = Q[j]
    covs[fixed_label] = 0.0
    # Residuals against the stated noise, scale identifiability (issue #12): a Laplace std that the
    # residuals contradict is inflated to match them, and the run is marked not trustworthy.
    check = fit_check(res, p_nom[labels])
    covs = covs * check.inflation
    rcov = rcov * check.inflation
    runs = [{k: v for k, v in r.items() if k not in ("positions", "orientations", "states")} for r in res.runs]
    settings = {**opts.to_settings(fixed_label=fixed_label),
                "process_noise": _process_noise_setting(res.process_noise), "imus_used": labels,
                "acc_noise_std": noise.tolist(), "warm_start_motion": True,
                "samples": int(len(time_s)), "selection": None if inp.selection is None else inp.selection.summary()}
    reasons = [] if res.converged else [f"LM stopped without converging ({res.lm_reason}); the estimate may be poor"]
    reasons += check.warnings()
    diagnostics = {"seconds": run.seconds, "F": res.cost, "F_per_constraint": res.cost / sum(res.n_constraints.values()),
                   "n_iter": int(sum(r["iterations"] for r in res.runs)), "converged": bool(res.converged),
                   "warnings": reasons,
                   "lm_reason": res.lm_reason, "runs": runs, "acc_clipped_fraction": inp.clipped,
                   "fit_check": check.to_dict()}
    run.document = positions_document(method="selfcal", reference_imu=fixed_label, means=means, covs=covs,
                                      orientations=oris, diagnostics=diagnostics,
                                      provenance={"version": __version__, "input_sha256": inp.source.sha256(),
                                                  "seed": opts.seed, "settings": settings})

    # ---- poses.csv
    dq = boxminus(torch.as_tensor(oris), torch.as_tensor(q_nom)).numpy()  # q = q_nom ∘ exp(δ)
    ang = np.degrees(np.linalg.norm(dq, axis=-1))
    pstd = np.sqrt(np.clip(np.diagonal(covs, axis1=1, axis2=2), 0, None))
    astd = np.full(K, np.nan)
    for j, k in enumerate(labels):
        astd[k] = np.degrees(np.sqrt(max(np.trace(rcov[j]), 0.0)))
    astd[fixed_label] = 0.0
    run.poses = [[k, *(means[k] * 1e3), *(pstd[k] * 1e6), *np.degrees(dq[k]), ang[k], astd[k],
                  int(k == fixed_label), int(inp.has_acc[k])] for k in range(K)]
    run.means, run.pstd, run.angle, run.angle_std = means, pstd, ang, astd
    # motion.csv keeps [a_lin, ω, ω̇]; the smoother model's extra derivatives (ω̈, ȧ_lin) stay in the result
    run.motion = np.column_stack([time_s, res.states[:, :9].detach().cpu().numpy()])
    run.warnings = reasons
    run.check = check
    return run


def _process_noise_setting(pn: dict) -> dict:
    """The process model of a run, for the provenance (JSON-ready)."""
    if pn.get("mode") == "s16":
        return {"mode": "s16", "variances": pn.get("variances")}
    model = ("white noise on snap (omega) and on d2 a_lin/dt2, exact discretisation" if pn.get("state_dim", 9) == 15
             else "white noise on jerk (omega) and on d a_lin/dt, exact discretisation")
    corr = pn.get("scale_correction")
    return {"mode": pn.get("mode"), "model": model,
            "intensities": pn.get("intensities"), "iterations": len(pn.get("history", [])),
            "scale_correction": None if corr is None else {"method": corr.get("method", "score"),
                                                            "factor": float(corr["factor"])}}


def write_convergence(run: SelfcalRun, out_dir, title: str = "") -> Path:
    """``convergence.png`` ([S16] Fig. 5) of a run, diverged or not."""
    from ..diagnostics.plots import plot_convergence

    path = Path(out_dir) / "convergence.png"
    plot_convergence(run.result.full_cost_log, run.result.n_constraints, path, title=title)
    return path


def write_outputs(run: SelfcalRun, out_dir, *, title: str = "") -> dict:
    """Write ``convergence.png`` and, unless the run diverged, ``positions.json``, ``poses.csv`` and
    ``motion.csv`` into ``out_dir`` (each file atomically); returns {name: path}."""
    from ..data.outputs import write_csv, write_text
    from ..data.positions import write_positions

    out = Path(out_dir)
    paths = {"convergence": write_convergence(run, out, title=title)}
    if not run.ok:
        return paths
    paths["positions"] = write_positions(run.document, out / "positions.json")
    paths["poses"] = write_text(out / "poses.csv", "".join(
        [POSES_HEADER + "\n"] + [",".join(str(int(v)) if i in (0, 12, 13) else ("nan" if not np.isfinite(v) else f"{v:.9g}")
                                          for i, v in enumerate(r)) + "\n" for r in run.poses]))
    paths["motion"] = write_csv(out / "motion.csv", run.motion, MOTION_HEADER)
    return paths
