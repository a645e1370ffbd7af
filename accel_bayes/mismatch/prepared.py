"""A recording prepared for mismatch analysis (:func:`prepare`): THE calibration's preparation
(:func:`accel_bayes.prep.preprocess.preprocess` — intrinsics from the rests, the one sample
selection), made into the package's one fit input
(:func:`accel_bayes.prep.prepared.prepare_recording`, where the IMU, geometry and noise checks
live), then converted to the tensors the augmented-model fits use (:class:`Prepared`,
:func:`from_prepared`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from ..errors import UserError
from ..physics.effects import CandidateLayout
from ..prep.prepared import PreparedRecording, prepare_recording
from ..prep.preprocess import Preprocessed, preprocess
from ..prep.selection import DEFAULT_MIN_ROTATION, Selection

__all__ = ["Prepared", "prepare", "from_prepared"]


@dataclass
class Prepared:
    """A recording in the form the fits use (torch, float64, sensor frame).

    y_acc, y_gyro (T, K, 3) outputs with NaN → 0; m_acc, m_gyro (T, K, 3) 1.0 where observed;
    sigma_acc, sigma_gyro (K,) stated noise; q (K, 4) nominal orientations; nominal (K, 3)
    design positions relative to the reference IMU ``ref``; has_acc/has_gyro (K,) bool;
    acc_rate/gyro_rate (T, K, 3) d/dt of the fitted nominal outputs (set after the baseline fit,
    used by time_offset).  ``rec`` is the recording actually fitted: intrinsics applied when
    they were, only the selected samples.  selection : the
    :class:`~accel_bayes.prep.selection.Selection` of ``rec``'s source recording that gave it
    (its ``runs``/``gaps`` say where the kept samples are not consecutive); preparation : the
    JSON-ready account of both steps (``report.json`` ``details.recording.preparation``).
    n_dropped_clipped : samples dropped as clipped.  source : the whole prepared recording
    (every sample, intrinsics applied when they were), of which ``rec`` is the selection.
    prepared : the :class:`~accel_bayes.prep.prepared.PreparedRecording` it was made from (the
    IMUs, reference, samples and checks are its).
    """

    rec: object
    time: torch.Tensor
    y_acc: torch.Tensor
    y_gyro: torch.Tensor
    m_acc: torch.Tensor
    m_gyro: torch.Tensor
    sigma_acc: torch.Tensor
    sigma_gyro: torch.Tensor
    q: torch.Tensor
    nominal: torch.Tensor
    ref: int
    has_acc: np.ndarray
    has_gyro: np.ndarray
    acc_rate: torch.Tensor | None = None
    gyro_rate: torch.Tensor | None = None
    n_dropped_clipped: int = 0
    selection: Selection | None = field(default=None, repr=False)
    source: object = field(default=None, repr=False)
    preparation: dict = field(default_factory=dict)
    prepared: PreparedRecording | None = field(default=None, repr=False)

    @property
    def T(self) -> int:
        return int(self.y_acc.shape[0])

    @property
    def K(self) -> int:
        return int(self.y_acc.shape[1])

    @property
    def layout(self) -> CandidateLayout:
        return CandidateLayout(self.K, self.has_acc, self.has_gyro, self.ref)

    @property
    def free_imus(self) -> list[int]:
        """IMUs whose position is estimated: accelerometer IMUs except the reference."""
        return [k for k in range(self.K) if self.has_acc[k] and k != self.ref]

    @property
    def n_obs(self) -> int:
        return int(self.m_acc.sum() + self.m_gyro.sum())


def prepare(rec, *, intrinsics="auto", drop_static: bool = True, drop_clipped: bool = True,
            min_rotation: float | None = DEFAULT_MIN_ROTATION, segments=None) -> Prepared:
    """Prepare a recording for mismatch analysis exactly as the calibration prepares it, and
    convert it to the fits' form.

    rec : a :class:`~accel_bayes.data.recording.Recording`, the
        :class:`~accel_bayes.prep.preprocess.Preprocessed` of one, or a
        :class:`~accel_bayes.prep.prepared.PreparedRecording` (both used as they are).
    intrinsics, drop_static, drop_clipped, min_rotation, segments : passed to
        :func:`accel_bayes.prep.preprocess.preprocess`; the defaults are
        :func:`accel_bayes.pipelines.calibrate.calibrate`'s (intrinsics from the recording's own rests when
        it has them in ≥ 9 orientations; rests, clipped samples and samples rotating slower than
        0.5 rad/s dropped), so ``mismatch`` and ``calibrate`` fit the same corrected samples of a
        recording.  ``min_rotation=0`` and ``intrinsics="none"`` give the raw recording minus its
        rests and clipped samples.

    Why clipped samples go (``drop_clipped``): a flagged output sits at the range while the true
    one is beyond it: its Gaussian residual would be a censored quantity treated as a
    measurement, the per-sample motion fitted to it is biased (every IMU sees the same ω, so all
    gyros clip together and ω is pulled to the range), and the resulting structured residuals get
    absorbed by whichever candidate effect fits them best.  Clipping the recording does *not* flag
    (an unstated range) stays in and is what the ``saturation`` effect explains.

    The kept recording is ``Prepared.rec``; what was done is ``Prepared.preparation`` and
    ``Prepared.selection``.
    """
    if isinstance(rec, PreparedRecording):
        return from_prepared(rec)
    if isinstance(rec, Preprocessed):
        pre = rec
    else:
        if rec.gyro is None or not np.asarray(rec.has_gyro).any():
            raise UserError("gyro: mismatch detection needs gyroscope data (the motion is estimated from the gyros)")
        pre = preprocess(rec, intrinsics=intrinsics, drop_static=drop_static, drop_clipped=drop_clipped,
                         min_rotation=min_rotation, segments=segments)
    sel = pre.selection
    if sel.n_kept < 10:  # 9 motion states per sample are profiled: a handful of samples says nothing
        raise UserError(f"mismatch: too few samples remain for mismatch detection ({sel.summary()}); "
                        "relax the selection (min_rotation, drop_static, drop_clipped)")
    it = pre.summary["intrinsics"]
    preparation = {
        "by": "accel_bayes.prep.preprocess (the calibration's preparation)",
        "intrinsics": {k: it[k] for k in ("applied", "how", "why", "rests", "orientations", "rest_error_max_before",
                                          "rest_error_max_after", "source") if k in it},
        "selection": sel.to_dict(),
        "notes": list(pre.notes),
    }
    return from_prepared(prepare_recording(pre.recording, selection=sel, provenance={"preparation": preparation}))


def from_prepared(prepared: PreparedRecording) -> Prepared:
    """The mismatch fits' form of a :class:`~accel_bayes.prep.prepared.PreparedRecording` (its IMU,
    reference, geometry and noise checks already done there): every IMU of the recording, sensor
    frame, NaN outputs masked, only the kept samples.  ``preparation`` is the record's
    ``provenance["preparation"]`` when :func:`prepare` made it, else the selection alone."""
    sel = prepared.selection
    if sel.n_kept < 10:
        raise UserError(f"mismatch: too few samples remain for mismatch detection ({sel.summary()}); "
                        "relax the selection (min_rotation, drop_static, drop_clipped)")
    if not prepared.gyro_labels:
        raise UserError("gyro: mismatch detection needs gyroscope data (the motion is estimated from the gyros)")
    preparation = prepared.provenance.get("preparation") or {"by": "accel_bayes.prep.prepared.prepare_recording",
                                                             "selection": sel.to_dict()}
    rec = prepared.kept_recording()
    has_acc = np.asarray(rec.has_acc, bool)
    has_gyro = np.asarray(rec.has_gyro, bool)
    ref = prepared.imu_labels[prepared.reference]
    f = lambda x: torch.as_tensor(np.asarray(x, dtype=np.float64))  # noqa: E731
    acc, gyro = f(rec.acc), f(rec.gyro)
    m_acc = torch.isfinite(acc).double() * f(has_acc)[None, :, None]
    m_gyro = torch.isfinite(gyro).double() * f(has_gyro)[None, :, None]
    nominal = f(rec.nominal_position)
    nominal = nominal - nominal[ref]
    sa, sg = f(rec.acc_noise_std), f(rec.gyro_noise_std)
    # IMUs without the sensor have no stated noise; any positive value does (their mask is 0)
    sa = torch.where(sa > 0, sa, torch.ones_like(sa))
    sg = torch.where(sg > 0, sg, torch.ones_like(sg))
    return Prepared(rec=rec, time=f(rec.time), y_acc=torch.nan_to_num(acc), y_gyro=torch.nan_to_num(gyro),
                    m_acc=m_acc, m_gyro=m_gyro, sigma_acc=sa, sigma_gyro=sg, q=f(rec.nominal_orientation),
                    nominal=nominal, ref=ref, has_acc=has_acc, has_gyro=has_gyro,
                    n_dropped_clipped=int(sel.dropped["clipped"]), selection=sel, preparation=preparation,
                    source=prepared.recording, prepared=prepared)
