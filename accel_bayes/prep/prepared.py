"""One recording turned into fit inputs (issue #26 item 1): :func:`prepare_recording` makes the
frozen :class:`PreparedRecording` — which IMUs, which samples, the array-frame outputs and their
noise — with the checks every fit needs, once.

Today :meth:`accel_bayes.model.likelihood.RaoBlackwellLikelihood.from_recording` takes it; the MAP
(``inference/map.py``), self-calibration (``pipelines/selfcal.py``), motion estimation
(``inference/motion.py``) and the mismatch fits (``mismatch/prepared.py``) still make their own
inputs and are to follow.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from ..errors import UserError
from .selection import DEFAULT_MIN_ROTATION, Selection, select_samples

__all__ = ["PreparedRecording", "prepare_recording"]


@dataclass(frozen=True, eq=False)  # eq=False: tensors have no single truth value
class PreparedRecording:
    """The selected samples of a recording in the array frame (DESIGN §7.0), ready for a fit.

    acc : (T, A, 3) m/s², the accelerometer triads of ``imu_labels`` (ascending), kept samples.
    gyro : (T, G, 3) rad/s, the gyroscopes of ``gyro_labels`` (ascending), kept samples.
    acc_noise_std : (A,) m/s²; gyro_noise_std : (G,) rad/s — the recording's stated white noise.
    imu_labels, gyro_labels : recording IMU indices of the rows of ``acc`` and of ``gyro``.
    reference : row of ``acc`` of the recording's reference IMU (the origin of the positions).
    nominal_positions : (A, 3) m, the design positions of the rows.
    sample_index : (T,) int, the kept samples' indices into the recording; ``selection`` the
        :class:`~accel_bayes.prep.selection.Selection` they came from.
    provenance : plain values saying where it came from (source, description, counts).
    """

    acc: torch.Tensor
    gyro: torch.Tensor
    acc_noise_std: np.ndarray
    gyro_noise_std: torch.Tensor
    imu_labels: tuple
    gyro_labels: tuple
    reference: int
    nominal_positions: torch.Tensor
    sample_index: np.ndarray
    selection: Selection
    provenance: dict = field(default_factory=dict)

    @property
    def T(self) -> int:
        return int(self.acc.shape[0])

    @property
    def A(self) -> int:
        return int(self.acc.shape[1])


def prepare_recording(rec, *, selection: Selection | None = None, select=None, min_rotation: float | None = None,
                      drop_clipped: bool = False, acc_imus=None, gyro_imus=None, dtype=torch.float64,
                      device=None) -> PreparedRecording:
    """The :class:`PreparedRecording` of ``rec`` (a :class:`~accel_bayes.data.recording.Recording`).

    IMUs: those with accelerometer data (or ``acc_imus``; at least 3, the reference among them)
    and those with a gyroscope (or ``gyro_imus``; at least 1).  Samples: ``selection`` as it is
    (then ``select``, ``min_rotation`` and ``drop_clipped`` must be left at their defaults), else
    :func:`~accel_bayes.prep.selection.select_samples` on those IMUs, rests kept:
    ``select=None`` every sample with a finite gyro reading, a (T,) bool mask or indices those,
    ``"rotation"`` the samples with |ω̄_t| ≥ ``min_rotation`` rad/s (default
    :data:`~accel_bayes.constants.DEFAULT_MIN_ROTATION`); ``drop_clipped`` also drops samples at
    an accelerometer's or gyroscope's range.  Bad input → one-line :class:`UserError` naming the
    field."""
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
    return PreparedRecording(
        acc=acc, gyro=gyro, acc_noise_std=np.asarray(rec.acc_noise_std)[labels], gyro_noise_std=gstd,
        imu_labels=tuple(int(k) for k in labels), gyro_labels=tuple(int(k) for k in glabels),
        reference=int(np.flatnonzero(labels == ref_label)[0]),
        nominal_positions=torch.as_tensor(np.asarray(rec.nominal_position)[labels], dtype=dtype, device=acc.device),
        sample_index=idx, selection=selection,
        provenance={"source": rec.source, "description": rec.description, "samples": int(T), "kept": int(len(idx))})
