"""One recording turned into fit inputs (issue #26 item 1): :func:`prepare_recording` makes the
frozen :class:`PreparedRecording` — which IMUs, which samples, the array-frame outputs and their
noise — with the checks every fit needs, once.

Every fit takes it: the likelihood (``RaoBlackwellLikelihood.from_recording``), the MAP
(``inference.map.fit_map_recording``), motion estimation (``inference.motion_estimate.estimate_motion``),
self-calibration (``pipelines.selfcal.prepare``) and the mismatch fits
(``mismatch.prepared.Prepared`` is made from one).  The fits no longer take ``select=``,
``min_rotation=`` or ``drop_clipped=``: the samples are chosen here (0.2.0);
:func:`refuse_removed_keywords` says so in a TypeError.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from ..data.recording import Recording
from ..errors import UserError
from ..physics.arrays import check_triad_geometry
from .selection import DEFAULT_MIN_ROTATION, Selection, select_samples

__all__ = ["PreparedRecording", "prepare_recording", "as_prepared", "refuse_removed_keywords", "GYRO_USES"]

GYRO_USES = ("required", "optional", "ignored")
# the sample-selection keywords the fits took before 0.2.0; they now belong to prepare_recording
REMOVED_KEYWORDS = ("select", "min_rotation", "drop_clipped", "selection", "acc_imus", "gyro_imus")


@dataclass(frozen=True, eq=False)  # eq=False: tensors have no single truth value
class PreparedRecording:
    """The selected samples of a recording in the array frame (DESIGN §7.0), ready for a fit.

    acc : (T, A, 3) m/s², the accelerometer triads of ``imu_labels`` (ascending), kept samples.
    gyro : (T, G, 3) rad/s, the gyroscopes of ``gyro_labels`` (ascending), kept samples.
    acc_noise_std : (A,) m/s²; gyro_noise_std : (G,) rad/s — the recording's stated white noise.
    imu_labels, gyro_labels : recording IMU indices of the rows of ``acc`` and of ``gyro``
        (``gyro`` and ``gyro_noise_std`` are None and ``gyro_labels`` empty for a fit that
        ignores the gyroscopes, ``gyro="ignored"``).
    reference : row of ``acc`` of the recording's reference IMU (the origin of the positions).
    nominal_positions : (A, 3) m, the design positions of the rows.
    sample_index : (T,) int, the kept samples' indices into the recording; ``selection`` the
        :class:`~accel_bayes.prep.selection.Selection` they came from.
    provenance : plain values saying where it came from (source, description, counts, and what
        the caller added, e.g. the intrinsics applied).
    recording : the :class:`~accel_bayes.data.recording.Recording` that ``sample_index`` indexes
        (all its samples, sensor frame): the fits that model each sensor axis themselves (motion
        estimation, self-calibration, the mismatch fits) read their raw outputs from it.
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
    recording: object = field(default=None, repr=False)

    @property
    def T(self) -> int:
        return int(self.acc.shape[0])

    @property
    def A(self) -> int:
        return int(self.acc.shape[1])

    @property
    def time(self) -> np.ndarray:
        """(T,) s, the kept samples' times."""
        return np.asarray(self.recording.time, dtype=np.float64)[self.sample_index]

    def kept_recording(self):
        """The recording restricted to the kept samples (itself when every sample is kept)."""
        if len(self.sample_index) == self.recording.T:
            return self.recording
        return self.recording.select(self.sample_index)

    def sensor_acc(self) -> np.ndarray:
        """(T, A, 3) m/s², the kept samples of the ``imu_labels`` triads in their sensor frames."""
        return np.asarray(self.recording.acc, dtype=np.float64)[self.sample_index][:, list(self.imu_labels)]


def refuse_removed_keywords(fit: str, keywords: dict) -> None:
    """TypeError for the sample-selection keywords the fits took before 0.2.0 (``select=``,
    ``min_rotation=``, ``drop_clipped=``, ``selection=``, ``acc_imus=``, ``gyro_imus=``): they are
    :func:`prepare_recording`'s now, so the message says where they went."""
    old = [k for k in REMOVED_KEYWORDS if k in keywords]
    if old:
        raise TypeError(f"{fit}: {', '.join(k + '=' for k in old)} removed in 0.2.0; choose the samples with "
                        f"accel_bayes.prep.prepared.prepare_recording(rec, {old[0]}=...) and pass its "
                        "PreparedRecording")


def as_prepared(source, fit: str, **options) -> PreparedRecording:
    """``source`` as a :class:`PreparedRecording`: itself, or :func:`prepare_recording` of a
    Recording with ``options`` (the fit's defaults: a fit given a plain recording uses every
    sample prepare_recording keeps by default).  Anything else: a TypeError naming ``fit``."""
    if isinstance(source, PreparedRecording):
        return source
    if isinstance(source, Recording):
        return prepare_recording(source, **options)
    raise TypeError(f"{fit}: expected a PreparedRecording (accel_bayes.prep.prepared.prepare_recording) or a "
                    f"Recording, got {type(source).__name__}")


def prepare_recording(rec, *, selection: Selection | None = None, select=None, min_rotation: float | None = None,
                      drop_clipped: bool = False, acc_imus=None, gyro_imus=None, reference: int | None = None,
                      reference_field: str = "reference_imu", gyro: str = "required", stated_noise: bool = True,
                      provenance: dict | None = None,
                      dtype=torch.float64, device=None) -> PreparedRecording:
    """The :class:`PreparedRecording` of ``rec`` (a :class:`~accel_bayes.data.recording.Recording`).

    IMUs: those with accelerometer data (or ``acc_imus``; at least 3, the reference among them,
    not on one line) and those with a gyroscope (or ``gyro_imus``; at least 1).  ``reference``:
    label of the origin IMU (default ``rec.reference_imu``; ``reference_field`` names it in an
    error, e.g. ``--fixed``).  ``gyro``: "required" (the [C21] likelihood and MAP, the mismatch
    fits), "optional" (used when the recording has them: motion estimation) or "ignored" ([S16]
    self-calibration: gyro flags and readings count for nothing).  ``stated_noise``: the
    recording's noise std must be > 0 for the IMUs used (False for a fit given its own noise, as
    motion estimation may be).

    Samples: ``selection`` as it is (then ``select``, ``min_rotation`` and ``drop_clipped`` must be
    left at their defaults), else :func:`~accel_bayes.prep.selection.select_samples` on those
    IMUs, rests kept: ``select=None`` every sample with a finite gyro reading and no importer
    flag, ``"all"`` every sample (for fits that weigh each sample themselves), a (T,) bool mask or
    indices those, ``"rotation"`` the samples with |ω̄_t| ≥ ``min_rotation`` rad/s (default
    :data:`~accel_bayes.constants.DEFAULT_MIN_ROTATION`); ``drop_clipped`` also drops samples at
    an accelerometer's or gyroscope's range.  ``provenance``: entries added to the record's.
    Bad input → one-line :class:`UserError` naming the field."""
    if gyro not in GYRO_USES:
        raise UserError(f"gyro: expected one of {GYRO_USES}, got {gyro!r}")
    has_acc = np.asarray(rec.has_acc)
    labels = np.flatnonzero(has_acc) if acc_imus is None else np.asarray(sorted(int(k) for k in acc_imus))
    if len(labels) < 3:
        raise UserError(f"acc_imus: at least 3 IMUs with accelerometer data are needed, got {labels.tolist()}")
    if not has_acc[labels].all():
        raise UserError(f"acc_imus: IMUs {labels[~has_acc[labels]].tolist()} have no accelerometer data")
    ref_label = int(rec.reference_imu if reference is None else reference)
    if ref_label not in labels:
        raise UserError(f"{reference_field}: IMU {ref_label} is not among the accelerometer IMUs used "
                        f"{labels.tolist()}")
    nominal = np.asarray(rec.nominal_position, dtype=np.float64)[labels]
    try:
        check_triad_geometry(torch.as_tensor(nominal), labels=labels.tolist())
    except ValueError as exc:
        raise UserError(f"nominal_position: {exc}") from None
    if stated_noise:
        _check_noise("acc_noise_std", rec.acc_noise_std, labels)
    has_gyro = np.zeros(rec.K, dtype=bool) if rec.gyro is None else np.asarray(rec.has_gyro, dtype=bool)
    use_gyro = gyro == "required" or (gyro == "optional" and has_gyro.any())
    if gyro == "required" and not has_gyro.any():
        raise UserError("gyro: this fit needs gyroscope data (the angular rate comes from the gyroscopes, "
                        "[C21] eq. 26b)")
    glabels = np.zeros(0, dtype=int)
    if use_gyro:
        glabels = np.flatnonzero(has_gyro) if gyro_imus is None else np.asarray(sorted(int(k) for k in gyro_imus))
        if len(glabels) == 0 or not has_gyro[glabels].all():
            raise UserError(f"gyro_imus: expected IMUs with gyroscope data, got {glabels.tolist()}")
        if stated_noise:
            _check_noise("gyro_noise_std", rec.gyro_noise_std, glabels)

    T = rec.T
    if selection is not None:
        if not isinstance(selection, Selection) or selection.T != T:
            raise UserError(f"selection: expected a Selection of this recording's {T} samples "
                            f"(accel_bayes.prep.selection.select_samples), got {type(selection).__name__}")
        if select is not None or min_rotation is not None or drop_clipped:
            raise UserError("selection: given together with select/min_rotation/drop_clipped; pass one or the other")
    else:
        if isinstance(select, str) and select not in ("rotation", "all"):
            raise UserError(f"select: expected None, 'all', a mask, indices or 'rotation', got {select!r}")
        rot = isinstance(select, str) and select == "rotation"
        every = isinstance(select, str) and select == "all"
        thr = (DEFAULT_MIN_ROTATION if min_rotation is None else float(min_rotation)) if rot else 0.0
        user = None if (select is None or isinstance(select, str)) else select
        selection = select_samples(rec, drop_static=False, drop_clipped=bool(drop_clipped), drop_flagged=not every,
                                   min_rotation=thr, user=user, acc_imus=labels,
                                   gyro_imus=glabels if use_gyro else None, use_gyro=use_gyro and not every)
    idx = np.array(selection.index)
    if len(idx) == 0:
        raise UserError("select: no samples left after selection")

    acc_all = rec.acc_tensor("array", dtype=dtype, device=device)
    acc = acc_all[torch.as_tensor(idx, device=acc_all.device)][:, torch.as_tensor(labels)]
    gyro_t = gstd = None
    if use_gyro:
        gyro_all = rec.gyro_tensor("array", dtype=dtype, device=device)
        gstd = torch.as_tensor(np.asarray(rec.gyro_noise_std)[glabels], dtype=dtype, device=device)
        gyro_t = gyro_all[torch.as_tensor(idx, device=gyro_all.device)][:, torch.as_tensor(glabels)]
    return PreparedRecording(
        acc=acc, gyro=gyro_t, acc_noise_std=np.asarray(rec.acc_noise_std)[labels], gyro_noise_std=gstd,
        imu_labels=tuple(int(k) for k in labels), gyro_labels=tuple(int(k) for k in glabels),
        reference=int(np.flatnonzero(labels == ref_label)[0]),
        nominal_positions=torch.as_tensor(nominal, dtype=dtype, device=acc.device),
        sample_index=idx, selection=selection,
        provenance={"source": rec.source, "description": rec.description, "samples": int(T), "kept": int(len(idx)),
                    **(provenance or {})},
        recording=rec)


def _check_noise(name: str, std, labels) -> None:
    """Stated noise std > 0 and finite for the IMUs used (Λ = σ⁻² otherwise has no meaning)."""
    s = np.asarray(std, dtype=np.float64)[labels]
    if not (np.isfinite(s).all() and (s > 0).all()):
        raise UserError(f"{name}: expected > 0 for every IMU used {list(map(int, labels))}, got {s.tolist()}")
