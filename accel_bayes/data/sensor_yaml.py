"""An ASL/EuRoC ``sensor.yaml`` (EuRoC's, or OpenCV's with ``%YAML:1.0`` and ``!!opencv-matrix``)
and its ``T_BS`` pose against the array description.

The fields used: ``rate_hz`` (the stated rate of the export's densities), the noise densities
(σ = density·√rate where the noise is stated), the random walks (kept for
:mod:`accel_bayes.data.export`) and ``T_BS``, the IMU's pose in the body frame B, taken as the
array frame: the nominal pose where the description gives none, compared with it otherwise
(:func:`apply_t_bs`).  Other fields and unknown tags are ignored, not refused.
"""
from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import torch

from ..errors import UserError
from ..physics.geometry import matrix_to_quat
from .csv_description import ArraySpec, _num

__all__ = ["read_sensor_yaml", "apply_t_bs", "T_BS_TOLERANCE_M", "T_BS_TOLERANCE_DEG"]


def _yaml_loader():
    """PyYAML's safe loader that also reads OpenCV's ``!!opencv-matrix`` (rows, cols, data → an
    array) and skips any other unknown tag (None): fields this importer does not use must not
    fail the import."""
    import yaml

    class Loader(yaml.SafeLoader):
        pass

    def opencv_matrix(loader, node):
        m = loader.construct_mapping(node, deep=True)
        try:
            return np.asarray(m["data"], dtype=np.float64).reshape(int(m["rows"]), int(m["cols"]))
        except (KeyError, TypeError, ValueError):
            return None  # malformed: treated as absent, and refused only if it is a field we use

    Loader.add_constructor("tag:yaml.org,2002:opencv-matrix", opencv_matrix)
    Loader.add_multi_constructor("", lambda loader, suffix, node: None)
    return Loader


def _t_bs(v, path: Path) -> np.ndarray:
    """sensor.yaml's ``T_BS`` (EuRoC: {cols, rows, data}; OpenCV: !!opencv-matrix) as a checked 4×4."""
    if isinstance(v, dict):
        try:
            v = np.asarray(v["data"], dtype=np.float64).reshape(int(v["rows"]), int(v["cols"]))
        except (KeyError, TypeError, ValueError):
            v = None
    T = None if v is None else np.asarray(v, dtype=np.float64)
    what = "a 4x4 rigid transform (rows, cols, data) with a rotation block and last row [0, 0, 0, 1]"
    if T is None or T.shape != (4, 4) or not np.isfinite(T).all():
        raise UserError(f"{path}: T_BS: expected {what}")
    R = T[:3, :3]
    if (np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0
            or np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-12):
        raise UserError(f"{path}: T_BS: expected {what} (R Rᵀ = I within 1e-6)")
    return T


def read_sensor_yaml(path) -> dict:
    """The fields of an ASL/EuRoC ``sensor.yaml`` this importer uses, in SI units: ``rate_hz``,
    ``accelerometer_noise_density`` (m s-2/√Hz), ``gyroscope_noise_density`` (rad s-1/√Hz),
    ``accelerometer_random_walk``, ``gyroscope_random_walk`` and ``T_BS`` (4×4: p_B = T_BS p_S,
    the sensor's pose in the body frame) — those present.  OpenCV's ``%YAML:1.0`` first line, a
    byte-order mark, CRLF line ends, ``!!opencv-matrix`` tags and fields it does not use are
    accepted."""
    import yaml

    path = Path(path)
    text = path.read_text(encoding="utf-8-sig")
    text = re.sub(r"\A%YAML:1\.0[^\n]*\n", "", text)  # OpenCV's header, which PyYAML does not read
    try:
        doc = yaml.load(text, Loader=_yaml_loader())
    except yaml.YAMLError as exc:
        raise UserError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(doc, dict):
        raise UserError(f"{path}: expected a YAML mapping with rate_hz and noise densities")
    out = {}
    for key in ("rate_hz", "accelerometer_noise_density", "gyroscope_noise_density",
                "accelerometer_random_walk", "gyroscope_random_walk"):
        if key in doc:
            v = doc[key]
            if isinstance(v, str):  # YAML 1.1 reads "2e-3" (no point in the mantissa) as a string
                try:
                    v = float(v)
                except ValueError:
                    pass
            out[key] = _num(v, f"{path}: {key}", "a positive number", positive=True)
    if "T_BS" in doc:
        out["T_BS"] = _t_bs(doc["T_BS"], path)
    return out


# A sensor.yaml T_BS and a description's pose further apart than this give a warning.
T_BS_TOLERANCE_M, T_BS_TOLERANCE_DEG = 1e-3, 0.5


def apply_t_bs(spec: ArraySpec, streams) -> list[str]:
    """Nominal poses from sensor.yaml's T_BS where the description has none (array frame = B:
    position = T_BS translation, R(q) = R_BSᵀ since v_S = R_BSᵀ v_B); where it has one, compare
    and return a one-line warning per IMU beyond :data:`T_BS_TOLERANCE_M` / ``_DEG`` (the
    description wins: it is what was written for this rig).  Refuses a missing position that
    no T_BS supplies."""
    warnings = []
    for i, (s, st) in enumerate(zip(spec.imus, streams)):
        T = st.sensor_yaml.get("T_BS")
        if T is None:
            if not s.position_given:
                raise UserError(f"{spec.path}: imu[{i}].position: missing, and IMU {s.label!r} has no sensor.yaml "
                                "with T_BS; expected [x, y, z] in m (array frame)")
            continue
        q_bs = matrix_to_quat(torch.as_tensor(T[:3, :3].T.copy(), dtype=torch.float64)).numpy()
        if not s.position_given:
            s.position = T[:3, 3].copy()
        if not s.orientation_given:
            s.orientation = q_bs
        dp = float(np.linalg.norm(s.position - T[:3, 3]))
        dang = math.degrees(2.0 * math.acos(min(1.0, abs(float(np.dot(s.orientation, q_bs))))))
        if dp > T_BS_TOLERANCE_M or dang > T_BS_TOLERANCE_DEG:
            warnings.append(f"imu[{i}] ({s.label!r}): {st.file.parent / 'sensor.yaml'} T_BS differs from the array "
                            f"description by {dp * 1e3:.3g} mm and {dang:.3g}° (tolerance {T_BS_TOLERANCE_M * 1e3:g} mm, "
                            f"{T_BS_TOLERANCE_DEG:g}°); the description's pose is used")
    return warnings
