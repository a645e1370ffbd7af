"""Export a calibration to the visual-inertial ecosystem: a Kalibr-style IMU chain YAML, and the
same file with OpenVINS' ``kalibr_imu_chain.yaml`` intrinsic fields.

Inputs: the recording (nominal orientations, stated noise, rate), its ``positions.json`` (DESIGN
§7.3), optionally ``intrinsics.json`` (:mod:`accel_bayes.prep.intrinsics`) and a mismatch report
(§7.2) for the gyro couplings and time offsets.  One entry ``imu<k>`` per IMU label k.

Frames and conventions (also written into the file's comments)
----------------------------------------------------------------
* **T_i_b** (4×4, m) takes a point from the body frame — the reference IMU's sensor frame — to
  IMU i's sensor frame: p_i = T_i_b · p_b, the Kalibr IMU-chain meaning.  With R_k = R(q_k) the
  array → sensor rotation of IMU k (§7.0; q_k from positions.json where estimated, otherwise the
  recording's nominal one) and r_i IMU i's position relative to the reference (array frame,
  positions.json ``mean``)::

      T_i_b = [[R_i R_refᵀ, −R_i r_i], [0, 0, 0, 1]]

  (a point p_b is at R_refᵀ p_b in the array frame, origin at the reference IMU; IMU i sees it
  at R_i (R_refᵀ p_b − r_i)).  The reference's T_i_b is the identity.
* **Noise**: ``*_noise_density`` = σ / √rate (σ the recording's stated per-axis white-noise std,
  rate its median sample rate), in m s-2/√Hz and rad s-1/√Hz.  ``*_random_walk`` only where the
  recording carries one (CSV import from a description or sensor.yaml); otherwise left out and
  said so.
* **time_offset** (s) only where a mismatch report estimated a ``time_offset`` for that IMU:
  the package's convention, positive = IMU i sampled late — its sample stamped t holds the
  output at t + time_offset.
* **Accelerometer intrinsics** (OpenVINS): OpenVINS reads a raw accelerometer sample as
  a_m = Ta · R_IMUtoACC · a_I + b_a + n and corrects it with
  a_I = R_IMUtoACCᵀ · Ta⁻¹ · (a_m − b_a).  The package's model (:mod:`accel_bayes.prep.intrinsics`) is
  a_true = T (a_raw − b) with T lower-triangular in the sensor frame.  So the exported
  **Ta = T⁻¹** (lower-triangular too: the inverse of a lower-triangular matrix is), **R_IMUtoACC
  = I** (the corrected x axis is the sensor's x axis, the xy plane its xy plane: the gauge that
  fixes T's triangular form) and b_a = b (written as ``accelerometer_bias``; OpenVINS estimates
  its biases online, the value is for its initial state).  OpenVINS' ``kalibr`` IMU model keeps
  Da = Ta⁻¹ lower-triangular with R_ACCtoIMU fixed — exactly this form — so ``model: kalibr`` is
  written; its ``rpng`` model (upper-triangular Da, estimated R_ACCtoIMU) is a different gauge
  and is not emitted.
* **Gyroscope intrinsics** (OpenVINS: w_m = Tw · R_IMUtoGYRO · w_I + Tg · a_I + b_g): from a
  mismatch report only — ``gyro_scale`` findings give the relative scale/misalignment matrix M
  (M[a, a] = scale, M[a, b] = coupling of a ``from_axis`` b finding) and ``gyro_g_sensitivity``
  the diagonal Tg; Tw · R_IMUtoGYRO = I + M is split into a lower-triangular Tw (positive
  diagonal) times a rotation (the kalibr model's gauge).  Without a report Tw = R_IMUtoGYRO = I
  and Tg = 0, and the file says they were not estimated.
* **Uncertainty** (extra keys, ignored by Kalibr and OpenVINS): ``T_i_b_translation_cov``
  (3×3, m², IMU i's frame: R_i Σ_i R_iᵀ of the positions.json covariance; orientation uncertainty
  not included), ``accelerometer_intrinsics_cov`` (9×9, the package's parameters in the order of
  :data:`accel_bayes.prep.intrinsics.ACC_PARAMS`), ``Ta_cov`` (6×6, Ta's lower-triangular entries
  column by column — Ta00, Ta10, Ta20, Ta11, Ta21, Ta22 — linearised: dTa = −Ta dT Ta),
  ``gyroscope_bias`` / ``gyroscope_bias_cov``.

The ``kalibr`` format is plain YAML (PyYAML reads it); the ``openvins`` format is the same text
behind OpenCV's ``%YAML:1.0`` first line, with the intrinsic fields always present (identity
where not estimated), as OpenVINS reads it through ``cv::FileStorage``.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from ..errors import UserError
from ..physics.geometry import quat_to_matrix
from .recording import Recording

__all__ = ["FORMATS", "imu_chain", "t_i_b", "openvins_acc_intrinsics", "gyro_intrinsics_from_report",
           "export_imu_chain"]

FORMATS = ("kalibr", "openvins")
AXES = ("x", "y", "z")


def _R(q) -> np.ndarray:
    return quat_to_matrix(torch.as_tensor(np.asarray(q, dtype=np.float64))).numpy()


def t_i_b(q_i, q_ref, r_i) -> np.ndarray:
    """T_i_b (4×4) of the module docstring: reference-IMU frame → IMU i frame.  ``q_i``, ``q_ref``:
    array → sensor quaternions (w, x, y, z), §7.0; ``r_i``: IMU i's position relative to the
    reference, array frame, m."""
    Ri, Rref = _R(q_i), _R(q_ref)
    T = np.eye(4)
    T[:3, :3] = Ri @ Rref.T
    T[:3, 3] = -Ri @ np.asarray(r_i, dtype=np.float64)
    return T


def openvins_acc_intrinsics(T: np.ndarray, acc_cov: np.ndarray | None = None):
    """(Ta, R_IMUtoACC, Ta_cov) for the package's lower-triangular T (a_true = T (a_raw − b)).

    Ta = T⁻¹ (lower-triangular), R_IMUtoACC = I; Ta_cov (6×6) over Ta's lower-triangular entries
    column by column, from the 9×9 ``acc_cov`` of ``ACC_PARAMS`` (None if not given)."""
    from ..prep.intrinsics import _T_INDEX

    T = np.asarray(T, dtype=np.float64)
    Ta = np.linalg.inv(T)
    Ta = np.tril(Ta)  # exactly zero above the diagonal (the inverse is lower-triangular)
    cov = None
    if acc_cov is not None and np.isfinite(acc_cov).all():
        order = [(0, 0), (1, 0), (2, 0), (1, 1), (2, 1), (2, 2)]
        J = np.zeros((6, 6))
        for j, (a, b) in enumerate(_T_INDEX):
            E = np.zeros((3, 3))
            E[a, b] = 1.0
            dTa = -Ta @ E @ Ta
            J[:, j] = [dTa[i, k] for i, k in order]
        cov = J @ np.asarray(acc_cov)[3:, 3:] @ J.T
    return Ta, np.eye(3), cov


def _lower_times_rotation(A: np.ndarray):
    """A = L · Q with L lower-triangular (positive diagonal) and Q a rotation (A with det > 0)."""
    Qt, U = np.linalg.qr(A.T)  # Aᵀ = Qt U  ⇒  A = Uᵀ Qtᵀ
    s = np.sign(np.diag(U))
    s[s == 0] = 1.0
    U, Qt = s[:, None] * U, Qt * s[None, :]
    return U.T, Qt.T


def gyro_intrinsics_from_report(report: dict, K: int):
    """Per IMU (Tw, R_IMUtoGYRO, Tg, time_offset or None, notes) from a mismatch report (§7.2).

    ``gyro_scale`` findings fill M (relative scale on the diagonal, ``from_axis`` couplings off
    it; a block finding with axis null and a 3 × 3 ``scale``, the detector's gyro linear stage, adds
    the whole matrix), ``gyro_g_sensitivity`` the diagonal of Tg (rad s-1 per m s-2), ``time_offset`` the
    offset (s, positive = late).  Tw · R_IMUtoGYRO = I + M, Tw lower-triangular."""
    from ..mismatch.report import validate_report

    validate_report(report)
    M = np.zeros((K, 3, 3))
    Tg = np.zeros((K, 3, 3))
    dt = [None] * K
    notes = [[] for _ in range(K)]
    for f in report["findings"]:
        k, name, p = f["imu"], f["effect"], f["parameters"]
        if k is None or not 0 <= k < K:
            continue
        try:
            if name == "gyro_scale" and f["axis"] is None:  # a gyro linear block: the whole 3 × 3 (and offset)
                M[k] += np.asarray(p["scale"], dtype=np.float64).reshape(3, 3)
                notes[k].append("gyro_scale 3x3 block (its offset, bias, is not part of Tw/R_IMUtoGYRO)")
            elif name == "gyro_scale":
                a = AXES.index(f["axis"])
                b = AXES.index(p.get("from_axis") or f["axis"])
                M[k, a, b] += float(p["scale"])
                notes[k].append(f"gyro_scale {f['axis']}" + (f" from {AXES[b]}" if b != a else ""))
            elif name == "gyro_g_sensitivity":
                Tg[k] += np.diag(np.asarray(p["sensitivity"], dtype=np.float64).reshape(3))
                notes[k].append("gyro_g_sensitivity")
            elif name == "time_offset":
                dt[k] = float(p["offset"])
                notes[k].append("time_offset")
        except (KeyError, TypeError, ValueError):
            raise UserError(f"mismatch report: finding {name!r} of IMU {k}: parameters {p!r} do not match "
                            "DESIGN §7.2") from None
    out = []
    for k in range(K):
        Tw, Rg = _lower_times_rotation(np.eye(3) + M[k])
        out.append((Tw, Rg, Tg[k], dt[k], notes[k]))
    return out


# ------------------------------------------------------------------------------ YAML text
def _num(x: float) -> str:
    x = float(x)
    if not math.isfinite(x):
        raise UserError(f"export: a value to write is not finite ({x}); expected finite numbers")
    s = repr(x + 0.0)  # repr: the shortest text that reads back to the same double; +0.0 drops −0
    mant, e, exp = s.partition("e")
    # YAML 1.1 (PyYAML, so Kalibr) reads "4e-08" as a string: a float needs a point in its mantissa.
    return f"{mant}.0e{exp}" if e and "." not in mant else s


def _matrix(name: str, A, indent: str = "  ", comment: str = "") -> list[str]:
    A = np.asarray(A, dtype=np.float64)
    lines = [f"{indent}{name}:" + (f"  # {comment}" if comment else "")]
    for row in A:
        lines.append(f"{indent}  - [{', '.join(_num(v) for v in row)}]")
    return lines


def imu_chain(recording: Recording, positions: dict, intrinsics=None, report: dict | None = None, *,
              fmt: str = "kalibr", input_names: dict | None = None) -> str:
    """The IMU chain YAML text (module docstring).

    recording : the recording the calibration was made from (orientations, noise, rate).
    positions : a positions document (:func:`accel_bayes.data.positions.read_positions` output).
    intrinsics : an :class:`accel_bayes.prep.intrinsics.Intrinsics` or None.
    report : a mismatch report dict (§7.2) or None.
    fmt : "kalibr" (plain YAML) or "openvins" (``%YAML:1.0`` header, intrinsic fields always).
    input_names : {"recording": …, "positions": …, …} file names for the provenance comment.
    """
    if fmt not in FORMATS:
        raise UserError(f"--format: expected one of {FORMATS}, got {fmt!r}")
    K = recording.K
    if "means" not in positions:
        from .positions import read_positions

        positions = read_positions(positions)
    means, covs, ori = positions["means"], positions["covs"], positions["orientations"]
    if means.shape[0] != K:
        raise UserError(f"positions: {means.shape[0]} IMUs, the recording has {K}; expected the calibration of "
                        "this recording")
    ref = int(positions["reference_imu"])
    if ref != int(recording.reference_imu):
        raise UserError(f"positions.reference_imu: {ref}, the recording's is {recording.reference_imu}; expected the same")
    if intrinsics is not None and intrinsics.K != K:
        raise UserError(f"intrinsics: estimated for {intrinsics.K} IMUs, the recording has {K}")
    rate = recording.sample_rate
    if not (rate > 0 and math.isfinite(rate)):
        raise UserError("recording.time: expected at least two samples to give a sample rate")
    gyro_ix = gyro_intrinsics_from_report(report, K) if report is not None else None

    nominal = np.asarray(recording.nominal_orientation, dtype=np.float64)
    est_q = np.isfinite(ori).all(-1)
    q = np.where(est_q[:, None], ori, nominal)
    est_r = np.isfinite(means).all(-1)
    # IMUs without an estimated position (no accelerometer): their nominal offset from the reference.
    nom_rel = np.asarray(recording.nominal_position) - np.asarray(recording.nominal_position)[ref]
    r = np.where(est_r[:, None], means, nom_rel)
    has_gyro = recording.has_gyro
    labels = recording.attrs.get("imu_labels")
    rw = {kind: recording.attrs.get(f"{kind}_random_walk") for kind in ("acc", "gyro")}
    write_ix = fmt == "openvins" or intrinsics is not None or report is not None

    names = input_names or {}
    out = []
    if fmt == "openvins":
        out.append("%YAML:1.0 # OpenCV FileStorage header: OpenVINS reads this file with cv::FileStorage")
    out += [
        "# IMU chain exported by accel_bayes (accel-bayes export).",
        f"# from: recording {names.get('recording', '?')}, positions {names.get('positions', '?')} "
        f"(method {positions.get('method', '?')})"
        + (f", intrinsics {names['intrinsics']}" if names.get("intrinsics") else "")
        + (f", mismatch report {names['report']}" if names.get("report") else ""),
        f"# imu<k> is the recording's IMU label k; body frame b = the reference IMU imu{ref}'s sensor frame.",
        "# T_i_b (m): p_i = T_i_b p_b takes a point from the body frame to IMU i's sensor frame,",
        "#   T_i_b = [[R_i R_ref^T, -R_i r_i], [0 0 0 1]], R_k = R(q_k) array->sensor (DESIGN 7.0),",
        "#   r_i = position relative to the reference in the array frame (positions.json mean).",
        "# noise densities = sigma / sqrt(update_rate): m/s^2/sqrt(Hz), rad/s/sqrt(Hz); random walks",
        "#   m/s^3/sqrt(Hz), rad/s^2/sqrt(Hz), only where known. time_offset (s) only where estimated:",
        "#   positive = sampled late (sample stamped t holds the output at t + time_offset).",
    ]
    if write_ix:
        out += [
            "# Intrinsics (OpenVINS): raw a_m = Ta R_IMUtoACC a_I + b_a, corrected a_I = R_IMUtoACC^T Ta^-1 (a_m - b_a);",
            "#   Ta = T^-1 of accel_bayes' a = T (a_raw - b), lower-triangular, R_IMUtoACC = I (model kalibr:",
            "#   Da = Ta^-1 lower-triangular). Gyro: w_m = Tw R_IMUtoGYRO w_I + Tg a_I + b_g.",
            "# Extra keys (ignored by Kalibr and OpenVINS): T_i_b_translation_cov (m^2, IMU i frame),",
            "#   accelerometer_bias (m/s^2), accelerometer_intrinsics_cov (9x9, b_x b_y b_z t_xx t_yy t_zz t_yx t_zx t_zy),",
            "#   Ta_cov (6x6: Ta00 Ta10 Ta20 Ta11 Ta21 Ta22), gyroscope_bias (rad/s), gyroscope_bias_cov.",
        ]
    else:
        out.append("# Extra key (ignored by Kalibr and OpenVINS): T_i_b_translation_cov (m^2, IMU i frame).")
    out.append("")
    for k in range(K):
        Ri = _R(q[k])
        # The body frame is the reference's frame by definition: exactly the identity, not R Rᵀ rounded.
        T = np.eye(4) if k == ref else t_i_b(q[k], q[ref], r[k])
        out.append(f"imu{k}:")
        src = []
        src.append("orientation from positions.json" if est_q[k] else "orientation nominal (not estimated)")
        if not est_r[k]:
            src.append("position nominal (not estimated: no accelerometer)")
        out += _matrix("T_i_b", T, comment="; ".join(src))
        out += _matrix("T_i_b_translation_cov", Ri @ covs[k] @ Ri.T, comment=f"m^2, IMU {k}'s frame")
        sa = float(recording.acc_noise_std[k])
        if recording.has_acc[k] and math.isfinite(sa):
            out.append(f"  accelerometer_noise_density: {_num(sa / math.sqrt(rate))}  "
                       f"# m/s^2/sqrt(Hz), sigma {sa:.6g} m/s^2")
        r_a = (rw["acc"] or [None] * K)[k]
        out.append(f"  accelerometer_random_walk: {_num(r_a)}  # m/s^3/sqrt(Hz)" if r_a is not None
                   else "  # accelerometer_random_walk: not known (not in the recording)")
        sg = float(recording.gyro_noise_std[k])
        if has_gyro[k] and math.isfinite(sg):
            out.append(f"  gyroscope_noise_density: {_num(sg / math.sqrt(rate))}  # rad/s/sqrt(Hz), sigma {sg:.6g} rad/s")
            r_g = (rw["gyro"] or [None] * K)[k]
            out.append(f"  gyroscope_random_walk: {_num(r_g)}  # rad/s^2/sqrt(Hz)" if r_g is not None
                       else "  # gyroscope_random_walk: not known (not in the recording)")
        else:
            out.append("  # no gyroscope on this IMU: gyroscope_noise_density and random walk left out")
        topic = f"/{labels[k]}" if isinstance(labels, list) and len(labels) == K else f"/imu{k}"
        out.append(f'  rostopic: "{topic}"')
        dtk = gyro_ix[k][3] if gyro_ix is not None else None
        out.append(f"  time_offset: {_num(dtk)}  # s, estimated (mismatch report)" if dtk is not None
                   else "  # time_offset: not estimated")
        out.append(f"  update_rate: {_num(rate)}  # Hz, median of the recording")
        if not write_ix:
            out.append('  model: "calibrated"  # no intrinsics given: outputs taken as they are')
            out.append("")
            continue
        out.append('  model: "kalibr"  # OpenVINS: lower-triangular Da = Ta^-1, R_ACCtoIMU fixed')
        if gyro_ix is not None:
            Tw, Rg, Tg, _, notes = gyro_ix[k]
            what = ", ".join(notes) if notes else "no gyro finding for this IMU: identity"
            gnote = f"from the mismatch report ({what})"
        else:
            Tw, Rg, Tg = np.eye(3), np.eye(3), np.zeros((3, 3))
            gnote = "not estimated: identity"
        out += _matrix("Tw", Tw, comment=gnote)
        out += _matrix("R_IMUtoGYRO", Rg, comment=gnote)
        acc_ok = intrinsics is not None and np.isfinite(intrinsics.acc_matrix[k]).all() \
            and np.isfinite(intrinsics.acc_bias[k]).all()
        if acc_ok:
            Ta, Racc, Ta_cov = openvins_acc_intrinsics(intrinsics.acc_matrix[k], intrinsics.acc_cov[k])
            out += _matrix("Ta", Ta, comment="T^-1 of intrinsics.json acc_matrix, lower-triangular")
            out += _matrix("R_IMUtoACC", Racc, comment="identity: the triangular gauge of T")
        else:
            out += _matrix("Ta", np.eye(3), comment="not estimated: identity")
            out += _matrix("R_IMUtoACC", np.eye(3), comment="not estimated: identity")
        out += _matrix("Tg", Tg, comment=gnote.replace("identity", "zero") + "; rad/s per m/s^2")
        if acc_ok:
            out.append(f"  accelerometer_bias: [{', '.join(_num(v) for v in intrinsics.acc_bias[k])}]  # m/s^2, b_a")
            if np.isfinite(intrinsics.acc_cov[k]).all():
                out += _matrix("accelerometer_intrinsics_cov", intrinsics.acc_cov[k])
            if Ta_cov is not None:
                out += _matrix("Ta_cov", Ta_cov)
        if intrinsics is not None and np.isfinite(intrinsics.gyro_bias[k]).all():
            out.append(f"  gyroscope_bias: [{', '.join(_num(v) for v in intrinsics.gyro_bias[k])}]  # rad/s, b_g")
            if np.isfinite(intrinsics.gyro_bias_cov[k]).all():
                out += _matrix("gyroscope_bias_cov", intrinsics.gyro_bias_cov[k])
        out.append("")
    return "\n".join(out)


def export_imu_chain(recording, positions, output, *, intrinsics=None, report=None, fmt: str = "kalibr",
                     overwrite: bool = False) -> Path:
    """Read the inputs (paths or objects), build :func:`imu_chain` and write it to ``output``
    atomically.  ``recording``: a path (read with :func:`accel_bayes.data.io.load_recording`) or a
    :class:`Recording`; ``positions``: path or document; ``intrinsics``: path,
    :class:`~accel_bayes.prep.intrinsics.Intrinsics` or None; ``report``: path, dict or None."""
    from ..prep.intrinsics import Intrinsics
    from .io import load_recording
    from .positions import read_positions

    names = {}
    loaded = load_recording(recording)
    if loaded.path is not None:
        names["recording"] = Path(loaded.path).name
    recording = loaded.recording
    if not isinstance(positions, dict):
        names["positions"] = Path(positions).name
    positions = read_positions(positions)
    if intrinsics is not None and not isinstance(intrinsics, Intrinsics):
        names["intrinsics"] = Path(intrinsics).name
        intrinsics = Intrinsics.from_json(intrinsics)
    if report is not None and not isinstance(report, dict):
        p = Path(report)
        if not p.is_file():
            raise FileNotFoundError(f"{p}: no such mismatch report")
        names["report"] = p.name
        try:
            report = json.loads(p.read_text(encoding="utf-8"))
        except ValueError as exc:
            raise UserError(f"{p}: not valid JSON ({exc})") from None
    text = imu_chain(recording, positions, intrinsics, report, fmt=fmt, input_names=names)
    from .outputs import write_text

    return write_text(output, text, overwrite=overwrite)
