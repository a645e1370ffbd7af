"""Export a calibration to the visual-inertial ecosystem: a Kalibr-style IMU chain YAML, the
same file with OpenVINS' ``kalibr_imu_chain.yaml`` intrinsic fields, and Kalibr's per-IMU input
YAMLs.

Inputs: the recording (nominal orientations, stated noise, rate, rests), its ``positions.json``
(DESIGN §7.3), optionally ``intrinsics.json`` (:mod:`accel_bayes.prep.intrinsics`) and a
mismatch report (§7.2) for the gyro couplings and time offsets.

Order: the reference IMU is always ``imu0``, the others follow in the recording's order (Kalibr
takes its first IMU as the reference, IccSensors.py; OpenVINS reads only ``imu0``,
VioManagerOptions.h).  The file's comments map every ``imu<j>`` to the recording's IMU.

Files a consumer would refuse are not written: Kalibr's ConfigReader needs both noise densities
and both random walks > 0 for every IMU, OpenVINS those of ``imu0`` (a missing node exits).
Random walks come from the rests (:mod:`accel_bayes.data.allan`, when the static stretches give
them to ±25 % from a rest of at least 20 crossover times), else from the recording (the array description's ``acc_random_walk`` /
``gyro_random_walk`` or sensor.yaml's, stored at import); else the export is refused naming the
key.  Noise densities and ``update_rate`` use each IMU's own rate (:func:`nominal_rate`): the
stated one, else that of its own stamps — a multi-rate rig's IMUs each get theirs.

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
* **Noise**: ``*_noise_density`` = σ / √rate (σ the recording's per-axis white-noise std, rate
  :func:`nominal_rate`), in m s-2/√Hz and rad s-1/√Hz; ``*_random_walk`` in m s-3/√Hz and
  rad s-2/√Hz (above), with ``*_random_walk_std`` where estimated.
* **time_offset** (s, relative to imu0) only where estimated: positions.json ``time_offset``
  (§7.3; with ``time_offset_std`` and, as extra keys, ``clock_drift``; the std is the rig's
  ``std_reported`` where positions.json has one — the block sandwich where its misspecification
  test fired — else the Laplace ``std``, and the YAML comment says which), else a mismatch report's
  ``time_offset`` findings.  Positive = IMU i sampled late — its sample stamped t holds the
  output at t + time_offset — which is Kalibr's meaning (IccSensors.py: an IMU measurement is
  placed at ``stamp + timeOffset``).
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
  (3×3, m², IMU i's frame: R_i Σ_i R_iᵀ of the positions.json covariance), ``T_i_b_rotation_cov``
  (3×3 rad², positions.json ``orientation_cov`` / ``orientation_std`` where estimated), ``accelerometer_intrinsics_cov`` (9×9, the package's parameters in the order of
  :data:`accel_bayes.constants.ACC_PARAMS`), ``Ta_cov`` (6×6, Ta's lower-triangular entries
  column by column — Ta00, Ta10, Ta20, Ta11, Ta21, Ta22 — linearised: dTa = −Ta dT Ta),
  ``gyroscope_bias`` / ``gyroscope_bias_cov``.

The ``kalibr`` format is plain YAML (PyYAML reads it); the ``openvins`` format is the same text
behind OpenCV's ``%YAML:1.0`` first line, with the intrinsic fields always present (identity
where not estimated), as OpenVINS reads it through ``cv::FileStorage``.  ``kalibr-imu`` writes
one plain-YAML file per IMU, ``imu0.yaml`` (the reference), ``imu1.yaml``, … into a directory:
``rostopic`` (the array description's, else ``/imu<j>``), ``update_rate``, densities, random
walks, ``time_offset`` where estimated.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from ..constants import ACC_T_INDEX
from ..errors import UserError
from ..physics.geometry import quat_to_matrix
from .allan import RELATIVE_SE_MAX, allan_random_walk, static_runs
from .mismatch_report import validate_report
from .recording import Recording, stamp_rate
from .validation import is_multirate, sample_present

__all__ = ["FORMATS", "imu_chain", "kalibr_imu_files", "t_i_b", "openvins_acc_intrinsics",
           "gyro_intrinsics_from_report", "export_order", "nominal_rate", "imu_stamps", "random_walks"]

FORMATS = ("kalibr", "openvins", "kalibr-imu")
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
    T = np.asarray(T, dtype=np.float64)
    Ta = np.linalg.inv(T)
    Ta = np.tril(Ta)  # exactly zero above the diagonal (the inverse is lower-triangular)
    cov = None
    if acc_cov is not None and np.isfinite(acc_cov).all():
        order = [(0, 0), (1, 0), (2, 0), (1, 1), (2, 1), (2, 2)]
        J = np.zeros((6, 6))
        for j, (a, b) in enumerate(ACC_T_INDEX):
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


# ------------------------------------------------------------------------------ what every format holds
def export_order(K: int, ref: int) -> list[int]:
    """Recording IMU indices in export order: the reference first (Kalibr takes its first IMU as
    the reference, IccSensors.py; OpenVINS reads only ``imu0``), then the others in file order."""
    return [ref] + [k for k in range(K) if k != ref]


def imu_stamps(recording: Recording, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, stamps s) of IMU k's own samples: the rows where it has one (DESIGN §7.1: a
    multi-rate recording is NaN elsewhere) and ``time`` plus its ``imu_time_offset`` there."""
    rows = np.flatnonzero(sample_present(recording)[:, k])
    s = np.asarray(recording.time, dtype=np.float64)[rows]
    if recording.imu_time_offset is not None:
        s = s + np.nan_to_num(np.asarray(recording.imu_time_offset, dtype=np.float64)[rows, k])
    return rows, s


def nominal_rate(recording: Recording, k: int | None = None) -> tuple[float, str]:
    """(rate, Hz; how it was obtained) of IMU ``k`` (default the reference IMU): its stated rate
    where the recording carries one (``imu_rate_hz[k]``, or ``rate_hz`` for an IMU of a single-rate
    recording — sensor.yaml's, at import), else the rate of its own stamps
    (:func:`~accel_bayes.data.recording.stamp_rate`).  Each IMU of a multi-rate rig has its own."""
    k = int(recording.reference_imu) if k is None else int(k)
    per = recording.attrs.get("imu_rate_hz")
    stated = per[k] if isinstance(per, list) and len(per) == recording.K else None
    if stated is None and not is_multirate(recording):
        stated = recording.attrs.get("rate_hz")
    if isinstance(stated, (int, float)) and not isinstance(stated, bool) and math.isfinite(stated) and stated > 0:
        return float(stated), "stated (sensor.yaml rate_hz)"
    rate = stamp_rate(imu_stamps(recording, k)[1])
    if not (rate > 0 and math.isfinite(rate)):
        raise UserError(f"recording.time: IMU {k} has fewer than two samples; expected its stamps to give a sample rate")
    return rate, "mean rate of its own stamps"


_RW_KEYS = {"acc": ("accelerometer_random_walk", "m/s^3/sqrt(Hz)"), "gyro": ("gyroscope_random_walk", "rad/s^2/sqrt(Hz)")}


def random_walks(recording: Recording, rate, imus=None, required=None) -> dict:
    """Bias random walk per IMU and sensor: ``{(k, "acc"|"gyro"): (K, std or None, source)}``.
    ``rate``: Hz, one for all IMUs or one per IMU (each IMU's rests are read on its own stamps).

    From the rests (:func:`accel_bayes.data.allan.allan_random_walk`) where the recording's
    static stretches give K̂ to within :data:`~accel_bayes.data.allan.RELATIVE_SE_MAX`; else from
    the recording's ``acc_random_walk`` / ``gyro_random_walk`` attributes (stored at import from
    the array description or sensor.yaml); else :class:`UserError` naming the key.  ``imus``:
    the recording indices to resolve (default all with that sensor); ``required``: those whose
    unknown random walk is refused (default all of ``imus``; the others are left out)."""
    K = recording.K
    imus = list(range(K) if imus is None else imus)
    required = set(imus if required is None else required)
    rates = np.broadcast_to(np.asarray(rate, dtype=np.float64), (K,))

    def rests(k):
        """(rows of IMU k's own samples, static runs in them): each IMU on its own stamps."""
        rows, s = imu_stamps(recording, k)
        if recording.segment is None:
            return rows, []
        seg = np.asarray(recording.segment)[rows]
        # A stretch must be evenly sampled: split it where a stamp gap exceeds 1.5 periods.
        gap = np.flatnonzero(np.diff(s) > 1.5 / rates[k]) + 1
        runs = []
        for a, b in static_runs(seg):
            cuts = [a] + [int(g) for g in gap if a < g < b] + [b]
            runs += [(c0, c1) for c0, c1 in zip(cuts[:-1], cuts[1:]) if c1 - c0 >= 6]
        return rows, runs

    labels = recording.attrs.get("imu_labels")
    out = {}
    for k in imus:
        rows, runs = rests(k)
        rate = float(rates[k])
        for kind in ("acc", "gyro"):
            data = recording.acc if kind == "acc" else recording.gyro
            if data is None or not np.isfinite(np.asarray(data)[:, k]).any():
                continue
            est = allan_random_walk(np.asarray(data, dtype=np.float64)[rows, k], runs, rate) if runs else None
            if est is not None and est.accepted:
                out[k, kind] = (est.k, est.k_se, f"rests, Allan deviation: {est.static_s:.0f} s static, longest "
                                                 f"{est.longest_s:.0f} s")
                continue
            stated = (recording.attrs.get(f"{kind}_random_walk") or [None] * K)
            v = stated[k] if isinstance(stated, list) and len(stated) == K else None
            if isinstance(v, (int, float)) and math.isfinite(v) and v > 0:
                out[k, kind] = (float(v), None, "stated (array description or sensor.yaml, at import)")
                continue
            if k not in required:
                continue
            name = f"{labels[k]!r}" if isinstance(labels, list) and len(labels) == K else str(k)
            why = ("the recording has no rests" if not runs else
                   f"its rests ({sum(b - a for a, b in runs) / rate:.0f} s static, longest "
                   f"{max(b - a for a, b in runs) / rate:.0f} s) do not give it to ±{RELATIVE_SE_MAX:.0%} "
                   "(an Allan-deviation estimate needs one rest of at least 20 crossover times √3·N/K, minutes to an hour)")
            raise UserError(f"imu[{k}].{kind}_random_walk: IMU {name}'s {_RW_KEYS[kind][0]} is unknown — {why}; "
                            f"expected {kind}_random_walk ({_RW_KEYS[kind][1]}) in its [[imu]] table of the array "
                            "description (or sensor.yaml), given at import; Kalibr and OpenVINS refuse a file "
                            "without it")
    return out


def _reported_std(entry: dict):
    """(std s or None, how) of a positions.json ``time_offset``/``clock_drift`` entry: the rig's
    ``std_reported`` where it has one (the block sandwich where its misspecification test fired,
    DESIGN §7.3's added keys; what ``calibrate-rig`` prints), else §7.3's Laplace ``std``."""
    if entry.get("std_reported") is not None:
        how = "block sandwich: the Laplace std failed its test" if entry.get("robust_used") else "Laplace"
        return float(entry["std_reported"]), how
    return (None, None) if entry.get("std") is None else (float(entry["std"]), "Laplace")


def _time_offsets(positions: dict, report_ix, order, ref: int):
    """Per recording IMU (offset s relative to the reference, std or None, drift dict or None,
    source) or None: positions.json ``time_offset`` (§7.3) first, else a mismatch report's."""
    K = len(order)
    imus = {int(e.get("imu", i)): e for i, e in enumerate(positions.get("imus", []))}
    out = [None] * K
    if any(isinstance(e.get("time_offset"), dict) for e in imus.values()):
        o_ref = float(imus.get(ref, {}).get("time_offset", {}).get("mean", 0.0))
        for k in range(K):
            e = imus.get(k, {})
            to = e.get("time_offset")
            if isinstance(to, dict) and to.get("mean") is not None:
                out[k] = (float(to["mean"]) - o_ref, _reported_std(to), e.get("clock_drift"), "positions.json")
            elif k == ref:
                out[k] = (0.0, None, None, "reference")
        return out
    if report_ix is not None and any(r[3] is not None for r in report_ix):
        o_ref = report_ix[ref][3] or 0.0
        for k in range(K):
            if report_ix[k][3] is not None or k == ref:
                out[k] = ((report_ix[k][3] or 0.0) - o_ref, None, None, "mismatch report")
    return out


# ------------------------------------------------------------------------------ YAML text
def _num(x: float, digits: int | None = None) -> str:
    x = float(x)
    if not math.isfinite(x):
        raise UserError(f"export: a value to write is not finite ({x}); expected finite numbers")
    # repr: the shortest text that reads back to the same double; +0.0 drops −0.  ``digits``
    # only for standard errors, whose own precision is a few per cent.
    s = repr(x + 0.0) if digits is None else repr(float(f"{x:.{digits}g}") + 0.0)
    mant, e, exp = s.partition("e")
    # YAML 1.1 (PyYAML, so Kalibr) reads "4e-08" as a string: a float needs a point in its mantissa.
    return f"{mant}.0e{exp}" if e and "." not in mant else s


def _matrix(name: str, A, indent: str = "  ", comment: str = "") -> list[str]:
    A = np.asarray(A, dtype=np.float64)
    lines = [f"{indent}{name}:" + (f"  # {comment}" if comment else "")]
    for row in A:
        lines.append(f"{indent}  - [{', '.join(_num(v) for v in row)}]")
    return lines


def _prepare(recording: Recording, positions: dict, intrinsics, report, fmt: str):
    """Checks, then everything the formats share (one dict)."""
    if fmt not in FORMATS:
        raise UserError(f"--format: expected one of {FORMATS}, got {fmt!r}")
    K = recording.K
    if "means" not in positions:
        from .positions import read_positions

        positions = read_positions(positions)
    means, ori = positions["means"], positions["orientations"]
    if means.shape[0] != K:
        raise UserError(f"positions: {means.shape[0]} IMUs, the recording has {K}; expected the calibration of "
                        "this recording")
    ref = int(positions["reference_imu"])
    if ref != int(recording.reference_imu):
        raise UserError(f"positions.reference_imu: {ref}, the recording's is {recording.reference_imu}; expected the same")
    if intrinsics is not None and intrinsics.K != K:
        raise UserError(f"intrinsics: estimated for {intrinsics.K} IMUs, the recording has {K}")
    order = export_order(K, ref)
    # Kalibr reads both densities of every IMU it is given; OpenVINS those of imu0 only.
    need = order if fmt != "openvins" else [ref]
    for k in need:
        for kind, has, sig in (("acc", recording.has_acc, recording.acc_noise_std),
                               ("gyro", recording.has_gyro, recording.gyro_noise_std)):
            if not has[k] or not math.isfinite(float(sig[k])):
                tool = "OpenVINS reads imu0's" if fmt == "openvins" else "Kalibr reads every IMU's"
                raise UserError(f"imu[{k}].sensors: IMU {k} has no {kind} data or noise std; {tool} "
                                f"{'accelerometer' if kind == 'acc' else 'gyroscope'}_noise_density, expected both "
                                "sensors with a stated or estimated noise")
    # Each IMU's own rate (a multi-rate rig's differ): update_rate and densities per IMU.
    rates = [nominal_rate(recording, k) for k in range(K)]
    rate, rate_how = np.array([r[0] for r in rates]), [r[1] for r in rates]
    rw = random_walks(recording, rate, imus=[k for k in order if recording.has_gyro[k] or recording.has_acc[k]],
                      required=need)
    report_ix = gyro_intrinsics_from_report(report, K) if report is not None else None
    nominal = np.asarray(recording.nominal_orientation, dtype=np.float64)
    est_q = np.isfinite(ori).all(-1)
    est_r = np.isfinite(means).all(-1)
    # IMUs without an estimated position (no accelerometer): their nominal offset from the reference.
    nom_rel = np.asarray(recording.nominal_position) - np.asarray(recording.nominal_position)[ref]
    topics = recording.attrs.get("imu_rostopics")
    return {
        "K": K, "ref": ref, "order": order, "positions": positions, "rate": rate, "rate_how": rate_how, "rw": rw,
        "report_ix": report_ix, "q": np.where(est_q[:, None], ori, nominal), "est_q": est_q, "est_r": est_r,
        "r": np.where(est_r[:, None], means, nom_rel), "covs": positions["covs"],
        "dt": _time_offsets(positions, report_ix, order, ref),
        "labels": recording.attrs.get("imu_labels") if isinstance(recording.attrs.get("imu_labels"), list) else None,
        "topics": topics if isinstance(topics, list) and len(topics) == K else None,
    }


def _imu_lines(recording: Recording, P: dict, j: int, *, with_pose: bool) -> list[str]:
    """The keys every format shares for export slot ``j`` (two-space indented)."""
    k = P["order"][j]
    out = []
    if with_pose:
        src = ["orientation from positions.json" if P["est_q"][k] else "orientation nominal (not estimated)"]
        if not P["est_r"][k]:
            src.append("position nominal (not estimated: no accelerometer)")
        # The body frame is the reference's frame by definition: exactly the identity, not R Rᵀ rounded.
        T = np.eye(4) if k == P["ref"] else t_i_b(P["q"][k], P["q"][P["ref"]], P["r"][k])
        Ri = _R(P["q"][k])
        out += _matrix("T_i_b", T, comment="; ".join(src))
        out += _matrix("T_i_b_translation_cov", Ri @ P["covs"][k] @ Ri.T, comment=f"m^2, IMU {j}'s frame")
        e = next((e for e in P["positions"].get("imus", []) if int(e.get("imu", -1)) == k), {})
        ocov = e.get("orientation_cov")
        if ocov is None and e.get("orientation_std") is not None:
            ocov = np.diag(np.square(np.asarray(e["orientation_std"], dtype=np.float64).reshape(3)))
        if ocov is not None:
            out += _matrix("T_i_b_rotation_cov", ocov, comment="rad^2, rotation vector in IMU's frame (positions.json)")
    rate = float(P["rate"][k])
    for kind, sig, has in (("acc", recording.acc_noise_std, recording.has_acc),
                           ("gyro", recording.gyro_noise_std, recording.has_gyro)):
        word = "accelerometer" if kind == "acc" else "gyroscope"
        unit = "m/s^2" if kind == "acc" else "rad/s"
        s = float(sig[k])
        if has[k] and math.isfinite(s):
            out.append(f"  {word}_noise_density: {_num(s / math.sqrt(rate))}  # {unit}/sqrt(Hz), sigma {s:.6g} {unit}")
        else:
            out.append(f"  # no {word} on this IMU: {word}_noise_density and random walk left out")
            continue
        if (k, kind) in P["rw"]:
            v, se, src = P["rw"][k, kind]
            out.append(f"  {word}_random_walk: {_num(v)}  # {_RW_KEYS[kind][1]}, {src}")
            if se is not None:
                out.append(f"  {word}_random_walk_std: {_num(se, 4)}  # standard error of the Allan estimate")
        else:  # only where the format does not read it (OpenVINS: IMUs after imu0)
            out.append(f"  # {word}_random_walk: not known (not read by this format for this IMU)")
    topic = P["topics"][k] if P["topics"] else f"/imu{j}"
    out.append(f'  rostopic: "{topic}"')
    dt = P["dt"][k]
    if dt is not None:
        out.append(f"  time_offset: {_num(dt[0])}  # s, relative to imu0, {dt[3]}: positive = sampled late "
                   "(Kalibr: sample stamped t is at t + time_offset)")
        if dt[1] is not None and dt[1][0] is not None:
            out.append(f"  time_offset_std: {_num(dt[1][0])}  # s, {dt[1][1]}")
        if isinstance(dt[2], dict) and dt[2].get("mean") is not None:
            out.append(f"  clock_drift: {_num(dt[2]['mean'])}  # dimensionless, DESIGN 7.3 (not read by Kalibr/OpenVINS)")
            sd, how = _reported_std(dt[2])
            if sd is not None:
                out.append(f"  clock_drift_std: {_num(sd)}  # {how}")
    else:
        out.append("  # time_offset: not estimated")
    out.append(f"  update_rate: {_num(rate)}  # Hz, {P['rate_how'][k]}")
    return out


def _header(P: dict, fmt: str, positions: dict, names: dict) -> list[str]:
    out = ["# exported by accel_bayes (accel-bayes export).",
           f"# from: recording {names.get('recording', '?')}, positions {names.get('positions', '?')} "
           f"(method {positions.get('method', '?')})"
           + (f", intrinsics {names['intrinsics']}" if names.get("intrinsics") else "")
           + (f", mismatch report {names['report']}" if names.get("report") else "")]
    lab = P["labels"]
    out.append("# imu<j> = recording IMU " + ", ".join(
        f"imu{j} <- {k}" + (f" ({lab[k]})" if lab else "") for j, k in enumerate(P["order"]))
        + f"; the reference IMU {P['ref']} is imu0 (Kalibr's first IMU is its reference, OpenVINS reads imu0).")
    return out


def imu_chain(recording: Recording, positions: dict, intrinsics=None, report: dict | None = None, *,
              fmt: str = "kalibr", input_names: dict | None = None) -> str:
    """The IMU chain YAML text (module docstring).

    recording : the recording the calibration was made from (orientations, noise, rate).
    positions : a positions document (:func:`accel_bayes.data.positions.read_positions` output).
    intrinsics : an :class:`accel_bayes.prep.intrinsics.Intrinsics` or None.
    report : a mismatch report dict (§7.2) or None.
    fmt : "kalibr" (plain YAML) or "openvins" (``%YAML:1.0`` header, intrinsic fields always).
    input_names : {"recording": …, "positions": …, …} file names for the provenance comment.
    Raises :class:`UserError` where a consumer would refuse the file (a random walk or noise
    unknown: the key is named).
    """
    if fmt == "kalibr-imu":
        raise UserError("--format kalibr-imu writes one file per IMU: use kalibr_imu_files")
    P = _prepare(recording, positions, intrinsics, report, fmt)
    positions = P["positions"]
    ref, K = P["ref"], P["K"]
    gyro_ix = P["report_ix"]
    write_ix = fmt == "openvins" or intrinsics is not None or report is not None

    out = []
    if fmt == "openvins":
        out.append("%YAML:1.0 # OpenCV FileStorage header: OpenVINS reads this file with cv::FileStorage")
    out += _header(P, fmt, positions, input_names or {})
    out += [
        "# IMU chain. Body frame b = the reference IMU's sensor frame (imu0).",
        "# T_i_b (m): p_i = T_i_b p_b takes a point from the body frame to IMU i's sensor frame,",
        "#   T_i_b = [[R_i R_ref^T, -R_i r_i], [0 0 0 1]], R_k = R(q_k) array->sensor (DESIGN 7.0),",
        "#   r_i = position relative to the reference in the array frame (positions.json mean).",
        "# noise densities = sigma / sqrt(update_rate): m/s^2/sqrt(Hz), rad/s/sqrt(Hz); random walks",
        "#   m/s^3/sqrt(Hz), rad/s^2/sqrt(Hz), from the rests (Allan deviation) or stated at import.",
        "# time_offset (s) only where estimated: positive = sampled late (sample stamped t holds the",
        "#   output at t + time_offset).",
    ]
    if write_ix:
        out += [
            "# Intrinsics (OpenVINS): raw a_m = Ta R_IMUtoACC a_I + b_a, corrected a_I = R_IMUtoACC^T Ta^-1 (a_m - b_a);",
            "#   Ta = T^-1 of accel_bayes' a = T (a_raw - b), lower-triangular, R_IMUtoACC = I (model kalibr:",
            "#   Da = Ta^-1 lower-triangular). Gyro: w_m = Tw R_IMUtoGYRO w_I + Tg a_I + b_g.",
            "# Extra keys (ignored by Kalibr and OpenVINS): T_i_b_translation_cov (m^2, IMU i frame),",
            "#   T_i_b_rotation_cov, *_random_walk_std, time_offset_std, clock_drift,",
            "#   accelerometer_bias (m/s^2), accelerometer_intrinsics_cov (9x9, b_x b_y b_z t_xx t_yy t_zz t_yx t_zx t_zy),",
            "#   Ta_cov (6x6: Ta00 Ta10 Ta20 Ta11 Ta21 Ta22), gyroscope_bias (rad/s), gyroscope_bias_cov.",
        ]
    else:
        out.append("# Extra keys (ignored by Kalibr and OpenVINS): T_i_b_translation_cov (m^2, IMU i frame),"
                   " T_i_b_rotation_cov, *_random_walk_std, time_offset_std, clock_drift.")
    out.append("")
    for j, k in enumerate(P["order"]):
        out.append(f"imu{j}:")
        out += _imu_lines(recording, P, j, with_pose=True)
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


def kalibr_imu_files(recording: Recording, positions: dict, report: dict | None = None, *,
                     input_names: dict | None = None) -> dict:
    """Kalibr's per-IMU input YAMLs (``kalibr_calibrate_imu_camera --imu imu0.yaml imu1.yaml …``):
    ``{"imu0.yaml": text, …}`` in export order, the reference first (Kalibr's reference IMU).
    Each holds what ConfigReader.ImuParameters reads — ``rostopic``, ``update_rate``, both noise
    densities and random walks, all > 0 — plus ``time_offset`` where estimated; the calibrated
    pose is in a comment (Kalibr estimates it; it takes no prior from this file)."""
    P = _prepare(recording, positions, None, report, "kalibr-imu")
    names = input_names or {}
    files = {}
    for j, k in enumerate(P["order"]):
        T = np.eye(4) if k == P["ref"] else t_i_b(P["q"][k], P["q"][P["ref"]], P["r"][k])
        lines = _header(P, "kalibr-imu", P["positions"], names)
        lines += [f"# Kalibr IMU input file {j + 1} of {len(P['order'])}: pass them in this order, "
                  "--imu " + " ".join(f"imu{i}.yaml" for i in range(len(P["order"]))) + ".",
                  "# calibrated T_i_b (p_i = T_i_b p_b, body = imu0's frame; for comparison with Kalibr's result):"]
        lines += [f"#   [{', '.join(f'{v:.9g}' for v in row)}]" for row in T]
        lines.append("")
        lines += [ln[2:] for ln in _imu_lines(recording, P, j, with_pose=False)]
        files[f"imu{j}.yaml"] = "\n".join(lines) + "\n"
    return files
