"""The :class:`Recording` type: one array recording in memory (format v1, DESIGN §7.1).

Arrays are numpy (what the file holds); :meth:`Recording.acc_tensor` and friends give torch
views for the numerical code.  Reading/writing and validation live in :mod:`accel_bayes.data.io`.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch

from ..physics.arrays import SensorArray
from ..physics.models import to_array_frame

__all__ = ["Recording", "stamp_rate"]


def stamp_rate(stamps_s) -> float:
    """An IMU's output rate (Hz) from its own stamps (s, increasing): the reciprocal of the mean of
    its regular steps (those within 0.5–1.5 × the median step, so that a dropped sample does not
    lower it), rounded to 6 significant figures.  The mean, not the median: EuRoC's 200 Hz stamps
    step 4 999 936, 4 999 936, 5 000 128 ns, whose median reads 200.00256 Hz and turns a stated
    density of 2.0e-3 into 0.0019999872, while their mean is 5 ms.  NaN for fewer than 2 stamps."""
    s = np.asarray(stamps_s, dtype=np.float64)
    if s.size < 2:
        return float("nan")
    d = np.diff(s)
    med = float(np.median(d))
    d = d[(d > 0.5 * med) & (d < 1.5 * med)]
    return float(f"{1.0 / float(d.mean()):.6g}") if d.size and med > 0 else float("nan")


@dataclass
class Recording:
    """An inertial-sensor-array recording (DESIGN §7.1, format v1).

    Attributes
    ----------
    time : (T,) float64, s — strictly increasing sample times.
    acc : (T, K, 3) float64, m/s² — accelerometer outputs, sensor frame.
    gyro : (T, K, 3) float64 or None, rad/s — gyroscope outputs, sensor frame; NaN rows for IMUs
        without a gyroscope.
    nominal_position : (K, 3) float64, m — design positions, array frame.
    nominal_orientation : (K, 4) float64 — array → sensor quaternions (w, x, y, z), §7.0.
    acc_noise_std : (K,) float64, m/s²;  gyro_noise_std : (K,) float64, rad/s.
    acc_clipped, gyro_clipped : (T, K) bool or None — samples known to be at the sensor range.
    acc_flagged, gyro_flagged : (T, K) bool or None — samples an importer's plausibility check
        distrusts (a value the rigid board contradicts); fits leave them out like clipped ones.
    segment : (T,) str array ("static"/"dynamic") or None.
    imu_time_offset : (T, K) float64 or None, s — an IMU's own time stamp minus ``time``, where
        the IMUs were stamped separately and an importer put them on one time base.
    reference_imu : int — origin of the geometry (default 0).
    acc_range, gyro_range : float or None — full scale, m/s² and rad/s.
    description, source : str — free text; ``source`` records provenance.
    attrs : dict — further global attributes, kept on round trips.
    """

    time: np.ndarray
    acc: np.ndarray
    nominal_position: np.ndarray
    acc_noise_std: np.ndarray
    gyro_noise_std: np.ndarray
    gyro: np.ndarray | None = None
    nominal_orientation: np.ndarray | None = None
    acc_clipped: np.ndarray | None = None
    gyro_clipped: np.ndarray | None = None
    acc_flagged: np.ndarray | None = None
    gyro_flagged: np.ndarray | None = None
    segment: np.ndarray | None = None
    imu_time_offset: np.ndarray | None = None
    reference_imu: int = 0
    acc_range: float | None = None
    gyro_range: float | None = None
    description: str = ""
    source: str = ""
    attrs: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.nominal_orientation is None:
            K = np.asarray(self.nominal_position).shape[0]
            q = np.zeros((K, 4))
            q[:, 0] = 1.0
            self.nominal_orientation = q

    # ------------------------------------------------------------------ sizes
    @property
    def T(self) -> int:
        """Number of samples."""
        return int(self.acc.shape[0])

    @property
    def K(self) -> int:
        """Number of IMUs."""
        return int(self.acc.shape[1])

    @property
    def has_gyro(self) -> np.ndarray:
        """(K,) bool — IMUs whose gyro output is present (not all NaN)."""
        if self.gyro is None:
            return np.zeros(self.K, dtype=bool)
        return ~np.all(np.isnan(self.gyro), axis=(0, 2))

    @property
    def has_acc(self) -> np.ndarray:
        """(K,) bool — IMUs whose accelerometer output is present (not all NaN)."""
        return ~np.all(np.isnan(self.acc), axis=(0, 2))

    @property
    def sample_rate(self) -> float:
        """Median sample rate, Hz."""
        if self.T < 2:
            return float("nan")
        return float(1.0 / np.median(np.diff(self.time)))

    # ------------------------------------------------------------------ torch views
    def acc_tensor(self, frame: str = "sensor", dtype=torch.float64, device=None) -> torch.Tensor:
        """Accelerometer outputs as a (T, K, 3) tensor, in the ``"sensor"`` or ``"array"`` frame
        (array frame: rotated by R(q)ᵀ of the nominal orientation)."""
        return self._tensor(self.acc, frame, dtype, device)

    def gyro_tensor(self, frame: str = "sensor", dtype=torch.float64, device=None) -> torch.Tensor:
        """Gyroscope outputs as a (T, K, 3) tensor (NaN for IMUs without one)."""
        if self.gyro is None:
            raise ValueError("gyro: this recording has no gyroscope data")
        return self._tensor(self.gyro, frame, dtype, device)

    def _tensor(self, x, frame, dtype, device):
        t = torch.as_tensor(np.asarray(x), dtype=dtype, device=device)
        if frame == "sensor":
            return t
        if frame == "array":
            q = torch.as_tensor(self.nominal_orientation, dtype=dtype, device=device)
            return to_array_frame(t, q)
        raise ValueError(f"frame: expected 'sensor' or 'array', got {frame!r}")

    def sensor_array(self, dtype=torch.float64, device=None) -> SensorArray:
        """The :class:`SensorArray` this recording describes (nominal design, stated noise)."""
        f = lambda x: torch.as_tensor(np.asarray(x), dtype=dtype, device=device)  # noqa: E731
        return SensorArray(
            positions=f(self.nominal_position),
            orientations=f(self.nominal_orientation),
            has_acc=torch.as_tensor(self.has_acc, device=device),
            has_gyro=torch.as_tensor(self.has_gyro, device=device),
            acc_noise_std=f(self.acc_noise_std),
            gyro_noise_std=f(self.gyro_noise_std),
            acc_range=self.acc_range,
            gyro_range=self.gyro_range,
            reference_imu=int(self.reference_imu),
            name=self.description or "recording",
        )

    def select(self, index) -> "Recording":
        """A new recording holding only the samples ``index`` (bool mask or integer indices)."""
        idx = np.asarray(index)
        take = lambda x: None if x is None else np.asarray(x)[idx]  # noqa: E731
        return replace(self, time=take(self.time), acc=take(self.acc), gyro=take(self.gyro),
                       acc_clipped=take(self.acc_clipped), gyro_clipped=take(self.gyro_clipped),
                       acc_flagged=take(self.acc_flagged), gyro_flagged=take(self.gyro_flagged),
                       segment=take(self.segment), imu_time_offset=take(self.imu_time_offset),
                       attrs=dict(self.attrs))

    def copy(self) -> "Recording":
        """Deep copy."""
        c = lambda x: None if x is None else np.array(x, copy=True)  # noqa: E731
        return replace(self, time=c(self.time), acc=c(self.acc), gyro=c(self.gyro),
                       nominal_position=c(self.nominal_position), nominal_orientation=c(self.nominal_orientation),
                       acc_noise_std=c(self.acc_noise_std), gyro_noise_std=c(self.gyro_noise_std),
                       acc_clipped=c(self.acc_clipped), gyro_clipped=c(self.gyro_clipped),
                       acc_flagged=c(self.acc_flagged), gyro_flagged=c(self.gyro_flagged),
                       segment=c(self.segment), imu_time_offset=c(self.imu_time_offset),
                       attrs=dict(self.attrs))
