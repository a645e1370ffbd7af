"""Sensor arrays: which IMUs a board carries, where they sit and how they are turned.

A :class:`SensorArray` is the *design* of a board (nominal positions and orientations, which
IMUs carry accelerometer and gyroscope triads, noise levels and ranges).  Positions are in the
array frame, metres; orientations follow DESIGN §7.0 (``v_sensor = R(q) v_array``).

Presets:

* :func:`mimu4444_32` – the full 32-IMU MIMU4444 grid used in [C21] §IV-A (Fig. 1).
* :func:`mimu4444_8` – its 8 corner IMUs, the board of the shared real recordings.
* :func:`s16_plate` – the 5-triad aluminium plate of [S16] Table I.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import torch

from ..constants import DEG_TO_RAD, G0

__all__ = ["SensorArray", "mimu4444_32", "mimu4444_8", "s16_plate", "PRESETS", "preset", "check_triad_geometry"]

# MIMU bottom-side mounting (data README): C maps sensor → array, C = Cᵀ, so the array → sensor
# rotation of DESIGN §7.0 is C itself, quaternion (0, 1/√2, −1/√2, 0).
MIMU_BOTTOM_QUAT = (0.0, math.sqrt(0.5), -math.sqrt(0.5), 0.0)


@dataclass(frozen=True)
class SensorArray:
    """Design of an inertial sensor array.

    Attributes
    ----------
    positions : (K, 3) tensor, m — nominal triad positions, array frame.
    orientations : (K, 4) tensor — nominal array → sensor quaternions (w, x, y, z).
    has_acc, has_gyro : (K,) bool tensors — which IMUs carry which triad.
    acc_noise_std : (K,) tensor, m/s² — accelerometer white-noise std per axis.
    gyro_noise_std : (K,) tensor, rad/s — gyroscope white-noise std per axis.
    acc_range : float or None, m/s² — accelerometer full scale (outputs clip at ±range).
    gyro_range : float or None, rad/s — gyroscope full scale.
    reference_imu : int — the IMU whose accelerometer position defines the origin ([C21] r_1 ≡ 0).
    name : str — preset name or free text.
    package_size : float or None, m — side of the square IMU package (plots draw it).
    """

    positions: torch.Tensor
    orientations: torch.Tensor
    has_acc: torch.Tensor
    has_gyro: torch.Tensor
    acc_noise_std: torch.Tensor
    gyro_noise_std: torch.Tensor
    acc_range: float | None = None
    gyro_range: float | None = None
    reference_imu: int = 0
    name: str = "custom"
    package_size: float | None = None
    labels: tuple = field(default=())

    def __post_init__(self):
        K = self.positions.shape[0]
        if self.positions.shape != (K, 3):
            raise ValueError(f"positions: expected shape (K, 3), got {tuple(self.positions.shape)}")
        for nm, shp in (("orientations", (K, 4)), ("has_acc", (K,)), ("has_gyro", (K,)),
                        ("acc_noise_std", (K,)), ("gyro_noise_std", (K,))):
            got = tuple(getattr(self, nm).shape)
            if got != shp:
                raise ValueError(f"{nm}: expected shape {shp} for K={K} IMUs, got {got}")
        if not 0 <= self.reference_imu < K:
            raise ValueError(f"reference_imu: expected an IMU label in 0..{K - 1}, got {self.reference_imu}")
        if not bool(self.has_acc[self.reference_imu]):
            raise ValueError(f"reference_imu: IMU {self.reference_imu} has no accelerometer triad")
        if bool((self.acc_noise_std[self.has_acc] <= 0).any()):
            raise ValueError("acc_noise_std: expected > 0 for every IMU with an accelerometer")
        if bool((self.gyro_noise_std[self.has_gyro] <= 0).any()):
            raise ValueError("gyro_noise_std: expected > 0 for every IMU with a gyroscope")
        if not self.labels:
            object.__setattr__(self, "labels", tuple(range(K)))

    # ------------------------------------------------------------------ properties
    @property
    def K(self) -> int:
        """Number of IMUs."""
        return self.positions.shape[0]

    @property
    def acc_index(self) -> torch.Tensor:
        """Labels of the IMUs with an accelerometer triad (A of them), ascending."""
        return torch.nonzero(self.has_acc).flatten()

    @property
    def gyro_index(self) -> torch.Tensor:
        """Labels of the IMUs with a gyroscope triad (G of them), ascending."""
        return torch.nonzero(self.has_gyro).flatten()

    @property
    def dtype(self):
        return self.positions.dtype

    @property
    def device(self):
        return self.positions.device

    def relative_positions(self, positions: torch.Tensor | None = None) -> torch.Tensor:
        """Positions relative to the reference IMU (the [C21] parameterisation r_ref ≡ 0)."""
        p = self.positions if positions is None else positions
        return p - p[..., self.reference_imu : self.reference_imu + 1, :]

    def with_(self, **changes) -> "SensorArray":
        """A copy with some fields replaced (the dataclass is frozen)."""
        return replace(self, **changes)

    def to(self, dtype=None, device=None) -> "SensorArray":
        """The same array with its tensors moved/cast."""
        f = lambda t: t.to(dtype=dtype if t.is_floating_point() else None, device=device)  # noqa: E731
        return replace(self, positions=f(self.positions), orientations=f(self.orientations),
                       has_acc=f(self.has_acc), has_gyro=f(self.has_gyro),
                       acc_noise_std=f(self.acc_noise_std), gyro_noise_std=f(self.gyro_noise_std))

    def check(self) -> None:
        """Raise ValueError if the accelerometer geometry cannot be calibrated (see
        :func:`check_triad_geometry`)."""
        check_triad_geometry(self.positions[self.has_acc], labels=self.acc_index.tolist())


def check_triad_geometry(positions: torch.Tensor, labels=None, rel_tol: float = 1e-6) -> None:
    """Refuse accelerometer layouts whose geometry is unobservable.

    At least three accelerometer triads are needed, and they must not lie on one line: rotation
    about that line moves no triad relative to the others, so angular acceleration about it and
    the positions along it cannot be told apart ([S16] §II; [C21] needs H(θ) of full rank 6).
    """
    A = positions.shape[0]
    if A < 3:
        raise ValueError(f"accelerometer triads: at least 3 are needed for self-calibration, got {A}")
    d = positions - positions.mean(0, keepdim=True)
    sv = torch.linalg.svdvals(d)
    scale = float(sv[0]) if float(sv[0]) > 0 else 1.0
    if float(sv[1]) <= rel_tol * scale:
        lab = labels if labels is not None else list(range(A))
        raise ValueError(
            f"accelerometer triads {lab} are collinear: rotation about the line through them is "
            "unobservable, so their positions along it cannot be calibrated; add a triad off that line"
        )


def _tensor(x, dtype, device):
    return torch.as_tensor(x, dtype=dtype, device=device)


def _mimu_grid_positions(n_side: int = 4):
    """(x, y) of the MIMU4444 packages, in board-IMU order.

    The data README fixes the 8-corner order (IMU 1,2 at (−9.45, +9.45); 3,4 at (−9.45, −9.45);
    5,6 at (+9.45, +9.45); 7,8 at (+9.45, −9.45)).  We extend that order to the full grid: x
    ascending in the outer loop, y descending in the inner one, each package holding a top
    (odd board number) and a bottom (even) IMU.
    """
    vals = [-9.45e-3, -3.15e-3, 3.15e-3, 9.45e-3]
    xy = []
    for x in vals:
        for y in reversed(vals):
            xy.append((x, y))
    return xy


def _mimu(xy, dtype, device, name):
    pos, quat = [], []
    for x, y in xy:
        pos.append((x, y, 1e-3))  # top side: sensor axes = array axes
        quat.append((1.0, 0.0, 0.0, 0.0))
        pos.append((x, y, -1e-3))  # bottom side: rotated by C of the data README
        quat.append(MIMU_BOTTOM_QUAT)
    K = len(pos)
    return SensorArray(
        positions=_tensor(pos, dtype, device),
        orientations=_tensor(quat, dtype, device),
        has_acc=torch.ones(K, dtype=torch.bool, device=device),
        has_gyro=torch.ones(K, dtype=torch.bool, device=device),
        # [C21] §IV-A: σ_a = 0.04 m/s², σ_g = 0.06 °/s; MPU-9150 at ±16 g and ±2000 °/s.
        acc_noise_std=torch.full((K,), 0.04, dtype=dtype, device=device),
        gyro_noise_std=torch.full((K,), 0.06 * DEG_TO_RAD, dtype=dtype, device=device),
        acc_range=16 * G0,
        gyro_range=2000 * DEG_TO_RAD,
        reference_imu=0,
        name=name,
        package_size=4e-3,
    )


def mimu4444_32(dtype=torch.float64, device=None) -> SensorArray:
    """The 32-IMU MIMU4444 board: 4 × 4 packages, 6.3 mm pitch, IMUs on both PCB sides.

    Label k−1 is board IMU k (odd k top side, z = +1 mm; even k bottom side, z = −1 mm, rotated
    by the data README's C).  Noise levels are [C21] §IV-A's.
    """
    return _mimu(_mimu_grid_positions(), dtype, device, "mimu32")


def mimu4444_8(dtype=torch.float64, device=None) -> SensorArray:
    """The 8 corner IMUs of the MIMU4444 (the shared real recordings; ``IMU_positions.csv``)."""
    corners = [(-9.45e-3, 9.45e-3), (-9.45e-3, -9.45e-3), (9.45e-3, 9.45e-3), (9.45e-3, -9.45e-3)]
    return _mimu(corners, dtype, device, "mimu8")


def s16_plate(dtype=torch.float64, device=None) -> SensorArray:
    """The [S16] prototype: 5 accelerometer triads on an aluminium plate (Table I, cm → m).

    Triad 1 (label 0) sits on the mainboard at the centre and is the fixed reference; the
    prototype's single gyroscope triad (ITG-3200) is on the mainboard too, so label 0 also has a
    gyro.  Noise: [S16] §IV-B measured 4·10⁻⁴ (m/s²)² per axis (σ = 0.02 m/s²); the gyro noise is
    the ITG-3200 datasheet's 0.38 °/s rms.  The paper does not list nominal orientations; the
    preset uses the identity.  BMA180 range ±16 g is assumed (the paper does not state it).
    """
    pos_cm = [(0.07, -0.24, 3.87), (0.28, 11.89, 2.47), (11.93, -0.28, 2.50),
              (-0.27, -11.94, 2.51), (-11.94, 0.29, 2.51)]
    K = 5
    has_gyro = torch.zeros(K, dtype=torch.bool, device=device)
    has_gyro[0] = True
    return SensorArray(
        positions=_tensor(pos_cm, dtype, device) * 1e-2,
        orientations=_tensor([(1.0, 0.0, 0.0, 0.0)] * K, dtype, device),
        has_acc=torch.ones(K, dtype=torch.bool, device=device),
        has_gyro=has_gyro,
        acc_noise_std=torch.full((K,), 0.02, dtype=dtype, device=device),
        gyro_noise_std=torch.full((K,), 0.38 * DEG_TO_RAD, dtype=dtype, device=device),
        acc_range=16 * G0,
        gyro_range=2000 * DEG_TO_RAD,
        reference_imu=0,
        name="s16plate",
        package_size=None,
    )


PRESETS = {"mimu32": mimu4444_32, "mimu8": mimu4444_8, "s16plate": s16_plate}


def preset(name: str, dtype=torch.float64, device=None) -> SensorArray:
    """Look a preset up by its CLI name (``mimu32``, ``mimu8``, ``s16plate``)."""
    try:
        return PRESETS[name](dtype=dtype, device=device)
    except KeyError:
        raise ValueError(f"preset: expected one of {sorted(PRESETS)}, got {name!r}") from None
