"""What a mismatch report found, put into the calibration's likelihood (issue #11 item 5).

``accel-bayes calibrate REC --model report.json`` (:func:`accel_bayes.pipelines.calibrate.calibrate`
with ``model=``) reads a DESIGN §7.2 report (:func:`load_model`), checks that it belongs to the
recording (:meth:`CalibrationModel.check_recording`) and uses its findings as follows.

Random gyroscope effects → the per-sample gyro posterior
--------------------------------------------------------
For ``timing_wander`` on IMU k's gyroscope (and the gyro half of ``sampling_jitter`` on IMU k) the
gyro's error at sample t is, to first order in the instant error δ_t (std σ_δ = width/√12, the
effect's own parametrisation, :class:`~accel_bayes.physics.effects.jitter.TimingWander`),
ω̇_t δ_t plus white noise; its moment-matched per-sample covariance is

    C_t,k = σ_k² I₃ + (width²/12) ω̇_t ω̇_tᵀ + excess_noise_var · I₃         (rad/s)²,

σ_k the recording's stated gyro noise, ω̇_t (rad/s²) the rate of change of the motion
(:func:`~accel_bayes.physics.effects.output_rates`, second-order differences within each run of
contiguous samples — the rates the detector uses — of the inverse-variance gyro mean).  Gyros
without a finding keep C_t,k = σ_k² I₃.  The posterior of ω_t given the G gyros (flat prior,
precision-weighted fusion, the generalised least-squares estimate)

    P_t = (Σ_k C_t,k⁻¹)⁻¹,      ω̄_t = P_t Σ_k C_t,k⁻¹ y_t,k,

replaces :func:`~accel_bayes.model.gyro_posterior.gyro_posterior`'s "calibrated" one (which it equals when
the report has no such finding): a wandering gyro counts less where ω̇ is large, and ω's
posterior covariance grows there.

What a per-sample covariance cannot carry: the AR(1) correlation of the instant error from one
sample to the next (``correlation`` ≈ 0.7–0.87 on the MIMU data).  The likelihood treats the
samples as independent given θ; what that leaves is what the sandwich covariance measures
(:func:`accel_bayes.inference.noise_fit.sandwich_inflation`, Newey–West lags), and ``calibrate`` records it.

Gyro linear blocks → the gyro outputs corrected
-----------------------------------------------
A ``gyro_scale`` finding with a 3 × 3 ``scale`` and a ``bias`` (the detector's gyro linear stage,
:class:`~accel_bayes.physics.effects.GyroLinear`: y_k = (I + M_k) g_k + b_k, sensor frame) is
inverted on IMU k's gyro outputs before anything else, y_k ← (I + M_k)⁻¹(y_k − b_k) — what the
detector did to the recording before it named the other effects.  The rates ω̇ of the timing
effects are then read from the corrected gyros.

The accelerometer blocks (``acc_scale`` with a 3 × 3 ``scale`` and a ``bias``: the detector's opt-in
accelerometer linear stage, :class:`~accel_bayes.physics.effects.AccLinear`) are inverted the same
way on the accelerometer outputs, y_k ← (I + M_k)⁻¹(y_k − b_k), before the clocks' mean correction —
where the calibration's own preparation did not calibrate the triads from the rests (the detector
runs the stage only then; on outputs ``prep`` transformed the blocks would not apply, and
``calibrate`` lists them as skipped with that reason).

Sampling clocks and unresolved motion → mean effect corrected, random effect as covariance
-------------------------------------------------------------------------------------------
With an ``unresolved_motion`` finding (issue #30 Deliver 2; :mod:`accel_bayes.pipelines.calibrate_model`):

* :func:`unresolved_terms` reads each ``sampling_clock`` finding's data age at the samples (a
  sawtooth; the accelerometer's plus the acc − gyro filter delay, an unidentified delay, written
  null, taken as 0) and the ``unresolved_motion`` finding's band edges and scales;
* an IMU without a ``sampling_clock`` finding (the detector found no beat, or rejected it) samples on
  its own clock all the same: its age is not 0 but unknown, uniform over the register hold [0, 1/f)
  (f the clocked IMUs' mean internal rate, else the vocabulary's 1 kHz), plus the same acc − gyro
  filter delay.  It is given the expected age (the clocked IMUs' mean age, and their mean filter
  delay on the accelerometer) and the age's variance (1/f)²/12, which loads the unresolved motion as
  a random age (``age_var_acc`` / ``age_var_gyro``), together with the part of the motion the outputs
  resolve (the mean correction takes off only the expected age times the rate): the per-triad
  columns of :func:`~accel_bayes.model.unresolved_cov.age_prior_blocks`, a per-gyro covariance in the
  posterior of ω; ``unclocked`` lists those IMUs and why (``experiments/unclocked_probe.md``);
* the clocks' mean effect is taken off the outputs, y ← y + age·ẏ (:func:`clock_corrected`);
* the unresolved angular acceleration, loaded on each gyro by its centred age, enters the fused
  posterior of ω (:func:`fused_gyro_posterior` with ``age``);
* the unresolved jerk, loaded on each accelerometer triad by its centred age, is projected out per
  sample with φ_t (:class:`~accel_bayes.model.likelihood_percov.PerSampleCovLikelihood`), its scale
  per report band fitted by type-II ML on the calibration's own likelihood; no tempering;
* beside it each triad's own instant error (the part of its sampling instant no clock gives, the
  finding's ``age_error_rms_s``), times the rate of that triad's output: a per-triad covariance
  e² ρ_kt ρ_ktᵀ per sample, e by type-II ML from the report's value (option ``instant_error``);
* with option ``angular_jerk``, the board's unresolved angular jerk loaded on each triad by its
  centred age times its lever arm about the nominal positions' centroid, its own scale per band by
  type-II ML (the report has no scale for it: ``unresolved_motion`` carries the jerk's and the
  angular acceleration's only).

Without an ``unresolved_motion`` finding the clocks are listed as skipped (an age alone loads nothing).

Everything else → recorded as skipped, with the reason
------------------------------------------------------
* ``unexplained``: carries no model;
* random effects on accelerometers (``timing_wander`` with sensor ``acc``, the acc half of
  ``sampling_jitter``): listed as skipped; with an ``unresolved_motion`` finding their physics (an
  instant error times the triad's output rate) is carried by the one fitted instant error e of every
  triad (above), not per IMU from the finding's width; without one the likelihood has one noise level
  per triad, constant over the samples, and the type-II ML level absorbs it;
* other mean, clip and noise-level effects: not applied by this version; a warning says so.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch

from ..data.mismatch_report import read_report
from ..constants import ACC_OUTPUTS
from ..errors import UserError
from .gyro_posterior import GyroPosterior

__all__ = ["CalibrationModel", "load_model", "fused_gyro_posterior", "corrected_array", "clock_corrected",
           "UnresolvedTerms",
           "unresolved_terms"]

# effects whose gyroscope part is a per-sample timing error (the moment-matched covariance above)
_TIMING = ("timing_wander", "sampling_jitter")
# effects that enter together as the per-sample unresolved-motion covariance (the section above)
_UNRESOLVED = ("sampling_clock", "unresolved_motion")


@dataclass
class CalibrationModel:
    """A mismatch report read for the calibration (module docstring).

    source : the file path, or None for an in-memory report.
    sha256 : SHA-256 of the file's bytes (of its canonical JSON for a dict).
    recording : the report's ``details.recording`` block ({} if absent): T, K, T_given, ….
    gyro_effects : [(finding index, IMU label, effect)] — the random gyro effects used.
    gyro_linear : [(finding index, IMU label, GyroLinear)] — the gyro linear blocks used.
    acc_linear : [(finding index, IMU label, AccLinear)] — the accelerometer linear blocks used.
    acc_outputs : the outputs those blocks were estimated on (``details.acc_linear_stage.outputs``, one of
        :data:`accel_bayes.constants.ACC_OUTPUTS`; the first, "as recorded", where the report does not say).
    used, skipped : [{"finding", "effect", "imu", "sensor", "how"/"why"}] per finding.
    report : the report's document as read (what :func:`unresolved_terms` reads again at the samples).
    unresolved : the report has an ``unresolved_motion`` finding: the per-sample covariance is used.
    unexplained : the report has an ``unexplained`` finding (a misfit none of its effects explains):
        calibrate's noise "auto" then estimates the levels (``CalibrateOptions.noise_mode``).
    """

    source: str | None
    sha256: str
    recording: dict
    gyro_effects: list = field(default_factory=list)
    gyro_linear: list = field(default_factory=list)
    acc_linear: list = field(default_factory=list)
    acc_outputs: str = ACC_OUTPUTS[0]
    used: list = field(default_factory=list)
    skipped: list = field(default_factory=list)
    report: dict = field(default_factory=dict, repr=False)
    unresolved: bool = False
    unexplained: bool = False

    def check_recording(self, rec) -> None:
        """Refuse (one-line :class:`UserError` naming the field) a report that was not made on
        ``rec`` (the recording as loaded, before any selection): its IMU count K and its number
        of samples (``details.recording.T_given``, what ``detect`` was given: a report made on a
        cut recording is refused for the whole one) must match, and every IMU a used finding
        names must have a gyroscope (an accelerometer, for an accelerometer block).  A report without ``details.recording`` is not checked."""
        r = self.recording
        if "K" in r and int(r["K"]) != int(rec.K):
            raise UserError(f"model: details.recording.K: the report is for {r['K']} IMUs, the recording has {rec.K}")
        if "T_given" in r and int(r["T_given"]) != int(rec.T):
            raise UserError(f"model: details.recording.T_given: the report was made on {r['T_given']} samples, the "
                            f"recording has {rec.T}")
        has_gyro = np.asarray(rec.has_gyro, dtype=bool)
        for i, k, _ in self.gyro_effects + self.gyro_linear:
            if not (0 <= k < len(has_gyro)) or not has_gyro[k]:
                raise UserError(f"model: findings[{i}].imu: IMU {k} has no gyroscope in the recording")
        has_acc = np.asarray(rec.has_acc, dtype=bool)
        for i, k, _ in self.acc_linear:
            if not (0 <= k < len(has_acc)) or not has_acc[k]:
                raise UserError(f"model: findings[{i}].imu: IMU {k} has no accelerometer in the recording")

    def match_acc_outputs(self, rest_calibrated: bool) -> None:
        """Keep the accelerometer blocks only where the calibration's preparation gives the outputs they
        were estimated on (``acc_outputs``): rest-calibrated blocks after the rests' intrinsics, blocks on
        the outputs as recorded without them; else :meth:`drop_acc_linear` with the reason."""
        if not self.acc_linear or self.acc_outputs == ACC_OUTPUTS[bool(rest_calibrated)]:
            return
        self.drop_acc_linear("accelerometer linear block: estimated on the outputs " + self.acc_outputs
                             + ", while this calibration's preparation " + ("calibrated the triads from the rests"
                             if rest_calibrated else "did not calibrate the triads (no rests that determine them)"))

    def drop_acc_linear(self, why: str) -> None:
        """Move the accelerometer blocks from ``used`` to ``skipped`` with the reason ``why`` (the
        calibration's preparation transformed the outputs the blocks were estimated on)."""
        idx = {i for i, _, _ in self.acc_linear}
        for row in [r for r in self.used if r["finding"] in idx]:
            self.used.remove(row)
            self.skipped.append({k: v for k, v in row.items() if k not in ("how", "parameters")} | {"why": why})
        self.acc_linear = []

    def describe(self) -> dict:
        """The provenance record (``settings["model"]``, positions.json)."""
        return {"source": self.source, "sha256": self.sha256,
                "recording": {k: self.recording.get(k) for k in ("T", "K", "T_given") if k in self.recording},
                "used": list(self.used), "skipped": list(self.skipped),
                "gyro_covariance": "C_tk = sigma_k^2 I + sum over findings on gyro k of (width^2/12) wdot_t wdot_t^T "
                                   "+ excess_noise_var I; omega posterior by precision-weighted fusion per sample; "
                                   "AR(1) correlation not carried (left to the sandwich)"}


def load_model(model) -> CalibrationModel:
    """Read and check a mismatch report (path, dict or :class:`~accel_bayes.mismatch.report.MismatchReport`)
    and sort its findings into used and skipped (module docstring).  Bad input → one-line
    :class:`UserError` naming the field."""
    from ..physics.effects import make_effect

    doc, source, sha = read_report(model, "model")
    details = doc.get("details") or {}
    if not isinstance(details, dict):
        raise UserError("model: details: expected an object")
    rec_info = details.get("recording") or {}
    if not isinstance(rec_info, dict):
        raise UserError("model: details.recording: expected an object")
    for key in ("K", "T_given", "T"):
        v = rec_info.get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
            raise UserError(f"model: details.recording.{key}: expected a positive integer, got {v!r}")
    out = CalibrationModel(source=source, sha256=sha, recording=dict(rec_info), report=doc)
    stage = details.get("acc_linear_stage") or {}
    outputs = stage.get("outputs", ACC_OUTPUTS[0]) if isinstance(stage, dict) else ACC_OUTPUTS[0]
    if outputs not in ACC_OUTPUTS:
        raise UserError("model: details.acc_linear_stage.outputs: expected one of "
                        f"{', '.join(map(repr, ACC_OUTPUTS))}, got {outputs!r}")
    out.acc_outputs = outputs
    unresolved = []
    for i, f in enumerate(doc["findings"]):
        name, imu = f["effect"], f.get("imu")
        params = dict(f.get("parameters") or {})
        sensor = f.get("sensor") or params.get("sensor")
        row = {"finding": i, "effect": name, "imu": imu, "sensor": sensor}
        if name == "unexplained":
            out.unexplained = True
            out.skipped.append({**row, "why": "no model: an unexplained excess names no physics to put in the "
                                              "likelihood (the type-II ML noise level and the sandwich cover it)"})
            continue
        if name in _UNRESOLVED:  # sorted below, once it is known whether the report has the motion's scales
            unresolved.append(row)
            continue
        if name == "timing_wander" and "sensor" in f and "sensor" not in params:
            params["sensor"] = f["sensor"]
        try:
            e = make_effect(name, imu=imu, axis=f.get("axis"), parameters=params)
        except UserError as exc:
            raise UserError(f"model: findings[{i}]: {exc}") from None
        if e.name == "acc_linear":
            out.acc_linear.append((i, int(e.imu), e))
            out.used.append({**row, "sensor": "acc", "how": "accelerometer outputs corrected: y <- (I + scale)^-1 "
                                                           "(y - bias), sensor frame",
                             "parameters": {"scale": e.params["matrix"].tolist(), "bias": e.params["bias"].tolist()}})
            continue
        if e.name == "gyro_linear" and e.imu is not None:
            out.gyro_linear.append((i, int(e.imu), e))
            out.used.append({**row, "sensor": "gyro", "how": "gyro outputs corrected: y <- (I + scale)^-1 (y - bias), "
                                                            "sensor frame",
                             "parameters": {"scale": e.params["matrix"].tolist(), "bias": e.params["bias"].tolist()}})
            continue
        if e.kind != "random":
            out.skipped.append({**row, "why": f"{e.kind} effect: not applied by calibrate --model in this version "
                                              "(only random gyroscope effects are)"})
            warnings.warn(f"model: findings[{i}] ({e.label()}): {e.kind} effects are not applied; skipped",
                          RuntimeWarning, stacklevel=2)
            continue
        if name not in _TIMING:  # pragma: no cover - no other random effect in the catalogue today
            out.skipped.append({**row, "why": "random effect without a per-sample gyro covariance"})
            continue
        which = getattr(e, "which", "both")
        for p in e.parameters:
            v = float(e.params[p.name])
            if not (math.isfinite(v) and v >= 0):
                raise UserError(f"model: findings[{i}].parameters.{p.name}: expected a finite value >= 0, got {v!r}")
        if which == "acc":
            out.skipped.append({**row, "why": "accelerometer random effect: the likelihood has one noise level per "
                                              "triad, constant over samples; the type-II ML level absorbs it"})
            continue
        out.gyro_effects.append((i, int(e.imu), e))
        how = ("gyro covariance += (width^2/12) wdot wdot^T" +
               (" + excess_noise_var I" if name == "timing_wander" else ""))
        out.used.append({**row, "sensor": "gyro", "how": how,
                         "parameters": {p.name: float(e.params[p.name]) for p in e.parameters}})
        if which == "both":
            out.skipped.append({**row, "sensor": "acc", "why": "accelerometer half of sampling_jitter: the likelihood "
                                                               "has one noise level per triad, constant over samples"})
    out.unresolved = any(r["effect"] == "unresolved_motion" for r in unresolved)
    for row in unresolved:
        if not out.unresolved:
            out.skipped.append({**row, "why": "no unresolved_motion finding in the report: a data age alone loads "
                                              "nothing (the per-sample covariance needs the motion's scales)"})
        elif row["effect"] == "sampling_clock":
            out.used.append({**row, "sensor": "acc+gyro", "how": "mean effect taken off (y <- y + age dy/dt, the acc "
                                                                 "age with the acc - gyro filter delay); the centred "
                                                                 "age loads the unresolved motion per sample"})
        else:
            out.used.append({**row, "sensor": "acc+gyro", "how": "per-sample covariance: jerk on the accelerometer "
                                                                 "rows (projected out with phi_t, scale per |omega| "
                                                                 "band by type-II ML on the calibration's own "
                                                                 "likelihood), angular acceleration in the gyro "
                                                                 "posterior of omega (the report's scales)"})
    return out


def corrected_array(gyro, orientations, gyro_labels, blocks):
    """Invert linear blocks on array-frame outputs (module docstring): the gyro blocks on the gyros,
    and the same for the accelerometer blocks on the accelerometers.

    gyro : (T, G, 3) array-frame outputs (rad/s, or m/s² for accelerometer blocks); orientations : (G, 4)
    the sensors' nominal quaternions (array → sensor); gyro_labels : the G IMU labels; blocks :
    [(IMU label, GyroLinear or AccLinear)].  Returns a new tensor: y_a ← R_kᵀ (I + M_k)⁻¹ (R_k y_a − b_k)
    for each block's sensor, unchanged elsewhere."""
    from ..physics.geometry import quat_to_matrix

    y = torch.as_tensor(gyro, dtype=torch.float64).clone()
    labels = [int(k) for k in gyro_labels]
    R = quat_to_matrix(torch.as_tensor(np.asarray(orientations, dtype=np.float64)))
    for k, e in blocks:
        g = labels.index(int(k))
        y[:, g] = e.invert(y[:, g] @ R[g].T) @ R[g]  # to the sensor frame, inverted, back
    return y


def fused_gyro_posterior(gyro, gyro_std, gyro_labels, time, effects, age=None, angular_acc_std=None, age_var=None):
    """The gyro posterior of ω_t with the report's random gyro effects (module docstring).

    gyro : (T, G, 3) rad/s, array frame, the selected samples.  gyro_std : (G,) rad/s stated noise.
    gyro_labels : the G IMU labels of the gyros.  time : (T,) s of those samples (gaps allowed).
    effects : [(IMU label, effect)] with ``params`` width (s) and, for ``timing_wander``,
    excess_noise_var ((rad/s)²).
    age (T, G) s, angular_acc_std (T,) rad/s² (both or neither): the unresolved angular
    acceleration α_t ~ N(0, s_t² I₃) loaded on gyro k by its centred data age d_kt, common to the
    gyros of a sample, so the stacked covariance is blockdiag(C_t,k) + s_t² (d_t d_tᵀ) ⊗ I₃; the GLS
    posterior through Woodbury with P_k = C_t,k⁻¹: precision Σ_k P_k − s² b (I + s² c)⁻¹ b,
    b = Σ_k d_k P_k, c = Σ_k d_k² P_k (with C_t,k = σ_k² I it is
    :func:`~accel_bayes.model.gyro_posterior.gyro_posterior_timing`).
    age_var (G,) s² (with ``age``): the variance of the age of gyros without a clock, whose random part
    reads the unresolved angular acceleration and the resolved rate ω̇_t late, adding
    age_var_k (s_t² I₃ + ω̇_t ω̇_tᵀ) to C_t,k (module docstring; ``age`` then holds their expected age).
    Returns (:class:`~accel_bayes.model.gyro_posterior.GyroPosterior` with method "model", ω̇ (T, 3) rad/s²).
    """
    from ..physics.effects import output_rates

    y = torch.as_tensor(gyro, dtype=torch.float64)
    T, G, _ = y.shape
    s = torch.as_tensor(np.asarray(gyro_std, dtype=np.float64))
    labels = [int(k) for k in gyro_labels]
    w = s.pow(-2)
    mean0 = (y * w[:, None]).sum(1) / w.sum()  # the "calibrated" mean: where ω̇ is read from
    wdot = output_rates(torch.as_tensor(time, dtype=torch.float64), mean0[:, None], mean0[:, None])[1][:, 0]
    eye = torch.eye(3, dtype=torch.float64)
    outer = wdot[:, :, None] * wdot[:, None, :]  # (T, 3, 3)
    C = (s**2)[None, :, None, None] * eye.expand(T, G, 3, 3).clone()
    for k, e in effects:
        g = labels.index(int(k))
        width = float(e.params["width"])
        C[:, g] += (width * width / 12.0) * outer
        if "excess_noise_var" in e.params:
            C[:, g] += float(e.params["excess_noise_var"]) * eye
    if age_var is not None and angular_acc_std is not None:
        s2a = torch.as_tensor(angular_acc_std, dtype=torch.float64).expand(T).square()
        v = torch.as_tensor(np.asarray(age_var, dtype=np.float64))
        C = C + v[None, :, None, None] * (s2a[:, None, None, None] * eye + outer[:, None])
    Pk = torch.linalg.inv(C)  # (T, G, 3, 3) per-gyro precisions
    prec = Pk.sum(1)
    Py = Pk @ y.unsqueeze(-1)  # (T, G, 3, 1)
    rhs = Py.sum(1)
    if (age is None) != (angular_acc_std is None):
        raise UserError("age, angular_acc_std: give both (the unresolved angular acceleration) or neither")
    if age is not None:
        d = torch.as_tensor(age, dtype=torch.float64)
        if d.shape != (T, G) or not bool(torch.isfinite(d).all()):
            raise UserError(f"age: expected finite data ages of shape (T, G) = ({T}, {G}) s, got {tuple(d.shape)}")
        d = d - d.mean(-1, keepdim=True)
        s2 = torch.as_tensor(angular_acc_std, dtype=torch.float64).expand(T).square()[:, None, None]
        b = (d[:, :, None, None] * Pk).sum(1)
        c = (d.square()[:, :, None, None] * Pk).sum(1)
        Minv_b = torch.linalg.solve(eye + s2 * c, b)  # (I + s² c)⁻¹ b
        prec = prec - s2 * b @ Minv_b
        rhs = rhs - s2 * Minv_b.transpose(-1, -2) @ (d[:, :, None, None] * Py).sum(1)
    cov = torch.linalg.inv(prec)
    cov = 0.5 * (cov + cov.transpose(-1, -2))
    mean = (cov @ rhs).squeeze(-1)
    return GyroPosterior(mean, cov, "model"), wdot


def clock_corrected(acc, gyro, time, age_acc, age_gyro):
    """The sampling clocks' mean effect taken off (DESIGN §7.2 vocabulary 1.2, ``sampling_clock``):
    an output read ``age`` late is y(t − age) ≈ y(t) − age·ẏ(t), so y ← y + age·ẏ, ẏ by second-order
    differences of the outputs themselves within each run of contiguous samples
    (:func:`~accel_bayes.physics.effects.output_rates`, the rates the detector's clock effect uses).
    acc (T, A, 3) m/s², gyro (T, G, 3) rad/s (any one frame); time (T,) s; age_acc (T, A) s (with the
    acc − gyro filter delay), age_gyro (T, G) s.  Returns (acc, gyro) corrected, float64."""
    from ..physics.effects import output_rates

    acc = torch.as_tensor(acc, dtype=torch.float64)
    gyro = torch.as_tensor(gyro, dtype=torch.float64)
    acc_rate, gyro_rate = output_rates(torch.as_tensor(time, dtype=torch.float64), acc, gyro)
    return (acc + torch.as_tensor(age_acc, dtype=torch.float64)[..., None] * acc_rate,
            gyro + torch.as_tensor(age_gyro, dtype=torch.float64)[..., None] * gyro_rate)


@dataclass
class UnresolvedTerms:
    """A report's unresolved motion at a calibration's samples (module docstring).

    age_acc (T, A) s, age_gyro (T, G) s : the data ages of the accelerometer rows and the gyros;
    jerk_std (T,) m/s³, angular_acc_std (T,) rad/s² : the per-axis scales at each sample's |ω| band;
    used : [{"finding", "effect", "imu", "how"}] the findings read; parameters : the
    ``unresolved_motion`` finding's parameters (``omega_edges`` rad/s, ``jerk_rms`` m/s³, …);
    time (T,) s the samples' read times (the output rates of the triads' instant error are taken on it);
    age_var_acc (A,), age_var_gyro (G,) s²: the variance of the data age of the rows without a clock
    (0 for the clocked), their expected age being in ``age_acc`` / ``age_gyro``; unclocked: one record
    per IMU without a clock (its label, the expected ages, the age's std, why)."""

    age_acc: torch.Tensor
    age_gyro: torch.Tensor
    jerk_std: torch.Tensor
    angular_acc_std: torch.Tensor
    used: list
    parameters: dict = field(default_factory=dict)
    time: torch.Tensor | None = None
    age_var_acc: torch.Tensor | None = None
    age_var_gyro: torch.Tensor | None = None
    unclocked: list = field(default_factory=list)


def _unclocked_age_prior(time, clocks) -> dict:
    """The age prior of an IMU without a clock (module docstring): expected age (s) of the gyro and
    of the accelerometer (with the clocked IMUs' mean acc − gyro filter delay), the variance (s²)
    of the uniform hold (1/f)²/12 and f (Hz)."""
    from ..physics.effects.clock import SamplingClock

    f_null = next(p.null for p in SamplingClock.parameters if p.name == "internal_rate_hz")
    if not clocks:  # nothing to borrow: the hold's own mean, no filter delay known
        f = float(f_null)
        return {"gyro": 0.5 / f, "acc": 0.5 / f, "var": 1.0 / (12 * f * f), "rate_hz": f}
    t = torch.as_tensor(np.asarray(time, dtype=np.float64))
    f = float(np.mean([float(c.params["internal_rate_hz"]) for c in clocks.values()]))
    gyro = float(torch.stack([c.physical_age(t) for c in clocks.values()]).mean())
    delay = float(np.mean([float(c.params["filter_delay_acc_minus_gyro_s"]) for c in clocks.values()]))
    return {"gyro": gyro, "acc": gyro + delay, "var": 1.0 / (12 * f * f), "rate_hz": f}


def unresolved_terms(model, time, acc_labels, gyro_labels, omega_norm) -> "UnresolvedTerms | None":
    """The per-sample covariance's inputs from a mismatch report (path, dict or report object):
    ``time`` (T,) s of the calibration's samples on the recording's time axis, ``acc_labels`` /
    ``gyro_labels`` the IMU labels of the accelerometer rows and gyros, ``omega_norm`` (T,) rad/s
    (|ω̄_t|, for the bands).  None when the report has no ``unresolved_motion`` finding (without
    its scales there is no term); IMUs without a ``sampling_clock`` finding get the age prior of
    the module docstring (expected age and its variance).  Bad
    findings → one-line :class:`UserError` naming ``findings[i]`` and the field."""
    from ..physics.effects import make_effect
    from .likelihood_percov import ages_from_clocks, band_scale

    doc, _, _ = read_report(model, "model")
    clocks, used, um = {}, [], None
    for i, f in enumerate(doc["findings"]):
        if f["effect"] == "sampling_clock":
            if f.get("imu") is None:
                raise UserError(f"model: findings[{i}].imu: a sampling_clock finding names its IMU")
            # a filter delay the detector could not identify is written null: no acc - gyro difference taken
            params = {k: (0.0 if v is None and k == "filter_delay_acc_minus_gyro_s" else v)
                      for k, v in dict(f["parameters"]).items()}
            try:
                clocks[int(f["imu"])] = make_effect("sampling_clock", imu=f["imu"], axis=None, parameters=params)
            except UserError as exc:
                raise UserError(f"model: findings[{i}]: {exc}") from None
            used.append({"finding": i, "effect": "sampling_clock", "imu": int(f["imu"]),
                         "how": "data age (sawtooth) loading the unresolved motion; acc + filter delay"})
        elif f["effect"] == "unresolved_motion":
            if um is not None:
                raise UserError(f"model: findings[{i}]: a second unresolved_motion finding (expected one per report)")
            um = (i, f["parameters"])
    if um is None:
        return None
    i, p = um
    for key in ("omega_edges", "jerk_rms", "angular_acc_rms"):
        if key not in p:
            raise UserError(f"model: findings[{i}].parameters.{key}: missing (unresolved_motion, vocabulary 1.2)")
    try:
        jerk = band_scale(omega_norm, p["omega_edges"], p["jerk_rms"], "jerk_rms")
        alpha = band_scale(omega_norm, p["omega_edges"], p["angular_acc_rms"], "angular_acc_rms")
    except UserError as exc:
        raise UserError(f"model: findings[{i}].parameters.{exc}") from None
    used.append({"finding": i, "effect": "unresolved_motion", "imu": None,
                 "how": "per-sample covariance: jerk on the accelerometers, angular acceleration on the gyros, "
                        "loaded by the centred data ages, scales per |omega| band"})
    ages = {"acc": ages_from_clocks(time, clocks, acc_labels, "acc"),
            "gyro": ages_from_clocks(time, clocks, gyro_labels, "gyro")}
    var = {"acc": torch.zeros(len(acc_labels), dtype=torch.float64),
           "gyro": torch.zeros(len(gyro_labels), dtype=torch.float64)}
    missing = sorted({int(k) for k in list(acc_labels) + list(gyro_labels)} - set(clocks))
    unclocked = []
    if missing:
        prior = _unclocked_age_prior(time, clocks)
        for sensor, labels in (("acc", acc_labels), ("gyro", gyro_labels)):
            for j, k in enumerate(labels):
                if int(k) in missing:
                    ages[sensor][:, j] = prior[sensor]
                    var[sensor][j] = prior["var"]
        why = ("no sampling_clock finding in the report: the IMU samples on its own clock all the same, its data "
               "age unknown, uniform over the register hold [0, 1/f)")
        unclocked = [{"imu": k, "why": why, "age_acc_s": prior["acc"], "age_gyro_s": prior["gyro"],
                      "age_std_s": math.sqrt(prior["var"]), "internal_rate_hz": prior["rate_hz"]} for k in missing]
        used.append({"finding": None, "effect": "sampling_clock", "imu": missing,
                     "how": "no clock in the report: expected age (the clocked IMUs' mean, + their mean filter delay "
                            "on acc) and a random age of variance (1/f)^2/12 loading the unresolved motion"})
    return UnresolvedTerms(ages["acc"], ages["gyro"], jerk, alpha, used, dict(p),
                           torch.as_tensor(np.asarray(time, dtype=np.float64)), var["acc"], var["gyro"], unclocked)
