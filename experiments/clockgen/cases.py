"""Boards, rigs and the seeded :func:`draw_case` API: (Recording, truth) for blind tests.

Kinds
-----
``clock``  an array whose IMUs sample on their own clocks, filter, hold and are read by the host;
``twin``   the same case (same seed: same motion, errors and noise streams) with every internal
           tick locked to the read instant, zero read skew, no jitter, identical filters;
``clean``  synchronised, no filter, no vibration or impacts, ideal sensors with white noise;
``rig``    2–4 separately clocked IMUs with their own stamps (DESIGN §7.3 convention), mixed rates.

Truth goes to the JSON sidecar only (:func:`write_case`), never into the recording.
"""
from __future__ import annotations

from io import BytesIO
from pathlib import Path

import numpy as np

from accel_bayes.data.recording import Recording

from .motion import G0, draw_motion, exp_so3
from .sensing import ACC_LSB, DLPF, DLPF2, GYRO_LSB, Clock, HostReader, SensorErrors, beat_frequency, quantise

F_INT = 1000.0          # Hz, nominal internal sampling rate (MPU-6050/9150 with DLPF on)
HOST_RATES = (62.5, 100.0, 125.0, 200.0, 250.0)
RIG_RATES = (100.0, 125.0, 200.0, 250.0, 400.0)
ACC_RANGE, GYRO_RANGE = 16 * G0, np.deg2rad(2000.0)
#: the :class:`~.motion.Motion` pieces ``draw_case(drop=...)`` can remove: rotational / translational
#: vibration, rotational / translational impacts
MOTION_PIECES = ("rot_vib", "pos_vib", "rot_imp", "pos_imp")
T_PRE = 0.2             # s of internal ticks before the first read: the filter settles at rest


def quat_to_matrix(q):
    """R(q) of DESIGN §7.0 (array → sensor) for q = (w, x, y, z)."""
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def matrix_to_quat(R):
    """The unit quaternion (w ≥ 0) with :func:`quat_to_matrix` = R (Shepperd's method)."""
    R = np.asarray(R, float)
    tr = np.trace(R)
    cands = [1 + tr, 1 + 2 * R[0, 0] - tr, 1 + 2 * R[1, 1] - tr, 1 + 2 * R[2, 2] - tr]
    i = int(np.argmax(cands))
    s = 2 * np.sqrt(cands[i])
    if i == 0:
        q = [s / 4, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif i == 1:
        q = [(R[2, 1] - R[1, 2]) / s, s / 4, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif i == 2:
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, s / 4, (R[1, 2] + R[2, 1]) / s]
    else:
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, s / 4]
    q = np.array(q)
    return q if q[0] >= 0 else -q


def board(name):
    """(positions (K,3) m, array→sensor rotations (K,3,3)) of a named board.

    ``mimu4444``: the 8 corner IMUs of the shared data's README (IMU_positions.csv; bottom-side
    IMUs rotated by C = [[0,−1,0],[−1,0,0],[0,0,−1]], which is its own inverse);
    ``plate4``: 4 IMUs at the corners of a 60 × 40 mm plate, yawed 0/90/180/270°;
    ``cube6``: 6 IMUs at the face centres of a 40 mm cube, each sensor's z along the outward normal.
    """
    if name == "mimu4444":
        x = 0.00945
        pos = np.array([[-x, x, 1e-3], [-x, x, -1e-3], [-x, -x, 1e-3], [-x, -x, -1e-3],
                        [x, x, 1e-3], [x, x, -1e-3], [x, -x, 1e-3], [x, -x, -1e-3]])
        C = np.array([[0.0, -1, 0], [-1, 0, 0], [0, 0, -1]])
        return pos, np.array([np.eye(3) if k % 2 == 0 else C.T for k in range(8)])
    if name == "plate4":
        pos = np.array([[0.03, 0.02, 0], [-0.03, 0.02, 0], [-0.03, -0.02, 0], [0.03, -0.02, 0]])
        return pos, np.array([exp_so3(np.array([0, 0, -k * np.pi / 2])) for k in range(4)])
    if name == "cube6":
        n = np.array([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
        Q = []
        for v in n:
            # the sensor's z is v: rotate array z onto v (any completion of the frame will do)
            axis = np.cross([0, 0, 1.0], v)
            ang = np.arccos(np.clip(v[2], -1, 1))
            ax = axis / np.linalg.norm(axis) * ang if np.linalg.norm(axis) > 0 else np.array([ang, 0, 0])
            Q.append(exp_so3(ax).T)   # sensor→array maps z to v; its transpose is array→sensor
        return 0.02 * n, np.array(Q)
    raise ValueError(f"board: {name!r} is not one of 'mimu4444', 'plate4', 'cube6'")


def _linear_errors(rng, K, gyro_linear, clean):
    """Per-IMU SensorErrors for acc and gyro; sizes in the docstring of :func:`draw_case`."""
    acc, gyro = [], []
    for _ in range(K):
        sa, sg = rng.uniform(0.02, 0.06), np.deg2rad(rng.uniform(0.02, 0.06) * 10)
        if clean:
            acc.append(SensorErrors(noise_std=sa))
            gyro.append(SensorErrors(noise_std=sg))
            continue
        Ma = np.eye(3) + rng.normal(0, rng.uniform(0.002, 0.01), (3, 3))
        acc.append(SensorErrors(Ma, rng.normal(0, 0.1, 3), sa))
        Mg = np.eye(3) + (rng.normal(0, rng.uniform(0.005, 0.03), (3, 3)) if gyro_linear else 0)
        gyro.append(SensorErrors(Mg, rng.normal(0, np.deg2rad(1.0), 3) if gyro_linear else None, sg))
    return acc, gyro


def draw_case(kind, seed, *, board_name=None, duration=20.0, f_host=None, gyro_linear=None,
              filtered=True, noise=True, quantised=True, vibration=True, errors=True, drift=None,
              read_jitter=None, n_imu=None, rot_axes=(0, 1, 2), read_jitter_max=None, drop=()):
    """A seeded blind-test case: returns (Recording, truth dict).

    ``clock`` / ``twin`` / ``clean`` on ``board_name`` (default: by seed among 'mimu4444',
    'plate4', 'cube6') read at ``f_host`` Hz (default: by seed from 62.5–250 Hz); ``rig`` with
    ``n_imu`` (2–4) IMUs.  Ranges drawn (clock): ε ~ U(±1 %) on 3 of 4 IMUs and ±(1–2 %) on the
    rest; tick phase U(0, 1); drift of the rate a ~ U(0, 1e-4) with a 100–400 s period on half
    the cases; read skew k·U(20, 80) µs; read jitter U(0, 30 µs) on half; acc−gyro extra filter
    delay U(±0.3 ms) on half; gyro 3×3 errors N(0, 0.5–3 %) and bias N(0, 1 °/s) when
    ``gyro_linear`` (default: even seeds); acc 3×3 errors N(0, 0.2–1 %), bias N(0, 0.1 m/s²);
    white noise acc 0.02–0.06 m/s², gyro 0.2–0.6 °/s at the register; int16 at ±16 g / ±2000 °/s.
    ``filtered``, ``noise``, ``quantised``, ``vibration``, ``errors`` (all linear errors) switch
    pieces off for validation; ``drift`` / ``read_jitter`` force the clock drift and the read
    jitter on or off (None: by seed); ``read_jitter_max`` (s) replaces the drawn upper end of the
    read latency where the jitter is on (a bus whose reads wait longer than 30 µs).  ``rot_axes`` (rigs): the array axes the rig rotates
    about — (2,) gives an under-excited rig (rotation about z only).  The exact motion is :func:`motion_of` (truth).
    ``drop``: motion pieces removed after the draw (a subset of :data:`MOTION_PIECES`), for ablations
    in which every other draw — hand motion, clocks, errors, noise — stays the same (``vibration=False``
    also skips the impacts' draws, which moves the hand motion's).
    """
    if kind == "rig":
        from .rig import draw_rig
        return draw_rig(seed, duration=duration, n_imu=n_imu, noise=noise, quantised=quantised,
                        rot_axes=rot_axes)
    if kind not in ("clock", "twin", "clean"):
        raise ValueError(f"kind: {kind!r} is not one of 'clock', 'twin', 'clean', 'rig'")
    rng = np.random.default_rng([seed, 27])
    board_name = board_name or ("mimu4444", "plate4", "cube6")[seed % 3]
    f_host = float(f_host or HOST_RATES[rng.integers(len(HOST_RATES))])
    gyro_linear = (seed % 2 == 0) if gyro_linear is None else bool(gyro_linear)
    pos, Q = board(board_name)
    K = len(pos)
    clean = kind == "clean"
    motion = motion_of({"seed": seed, "duration": duration, "vibration": vibration and not clean, "drop": list(drop)})
    acc_err, gyro_err = _linear_errors(np.random.default_rng([seed, 2]), K, gyro_linear, clean or not errors)
    if not noise:
        for e in acc_err + gyro_err:
            e.noise_std = 0.0
    # the clock draws happen for every kind so that a twin shares everything else with its case
    eps = np.where(rng.random(K) < 0.75, rng.uniform(-0.01, 0.01, K),
                   rng.choice([-1, 1], K) * rng.uniform(0.01, 0.02, K))
    phase = rng.random(K)
    drift_on = rng.random() < 0.5   # drawn even when forced, so that forcing changes nothing else
    drift_on = drift_on if drift is None else bool(drift)
    drift = rng.uniform(0, 1e-4, K) * drift_on
    drift_P, drift_psi = rng.uniform(100, 400, K), rng.uniform(0, 2 * np.pi, K)
    skew = np.arange(K) * rng.uniform(20e-6, 80e-6)
    jitter_on = rng.random() < 0.5
    jitter = rng.uniform(0, 30e-6) * (jitter_on if read_jitter is None else bool(read_jitter))
    if read_jitter_max is not None and jitter > 0:
        jitter = float(read_jitter_max)
    dgd = rng.uniform(-0.3e-3, 0.3e-3) * (rng.random() < 0.5)
    if kind == "clock":
        clocks = [Clock(F_INT, eps[k], phase[k], drift[k], drift_P[k], drift_psi[k]) for k in range(K)]
        reader = HostReader(f_host, skew, jitter)
    else:
        f_twin = f_host * round(F_INT / f_host)   # an internal rate with a tick on every read
        clocks = [Clock(f_twin) for _ in range(K)]
        reader = HostReader(f_host, np.zeros(K), 0.0)
        dgd = 0.0
    use_filter = filtered and not clean
    filt = {s: [DLPF(DLPF2[s][0] if use_filter else None, DLPF2[s][1] + (dgd if s == "acc" else 0.0),
                     c.f_int) for c in clocks] for s in ("acc", "gyro")}

    n_reads = int(np.floor(duration * f_host)) + 1
    r, stamps = reader.read_times(n_reads, np.random.default_rng([seed, 3]))
    out = {s: np.empty((n_reads, K, 3)) for s in ("acc", "gyro")}
    clip = {s: np.zeros((n_reads, K), bool) for s in ("acc", "gyro")}
    age, tick_idx = np.empty((n_reads, K)), np.empty((n_reads, K), np.int64)
    for k in range(K):
        ticks = clocks[k].ticks(-T_PRE, r[-1, k] + 0.01)
        f, w = motion.specific_force(ticks, pos[k:k + 1])
        true = {"acc": f[:, 0] @ Q[k].T, "gyro": w @ Q[k].T}
        idx, age[:, k] = HostReader.read(ticks, r[:, k])
        tick_idx[:, k] = idx
        for j, (s, err) in enumerate((("acc", acc_err[k]), ("gyro", gyro_err[k]))):
            nrng = np.random.default_rng([seed, 4, k, j])
            y = filt[s][k](err.apply(true[s], ticks, nrng, filt[s][k].noise_gain()))
            out[s][:, k], clip[s][:, k] = quantise(y[idx], ACC_LSB if s == "acc" else GYRO_LSB, quantised)

    st = motion.at(stamps)
    rec = Recording(time=stamps, acc=out["acc"], gyro=out["gyro"], nominal_position=pos,
                    nominal_orientation=np.array([matrix_to_quat(q) for q in Q]),
                    acc_noise_std=np.array([e.noise_std for e in acc_err]) if noise else np.full(K, 1e-3),
                    gyro_noise_std=np.array([e.noise_std for e in gyro_err]) if noise else np.full(K, 1e-4),
                    acc_clipped=clip["acc"], gyro_clipped=clip["gyro"], acc_range=ACC_RANGE,
                    gyro_range=GYRO_RANGE, description=f"clockgen {kind} case, seed {seed}",
                    source="experiments/clockgen (independent first-principles generator)")
    truth = {
        "generator": "experiments/clockgen", "kind": kind, "seed": int(seed), "board": board_name,
        "f_host": f_host, "duration": duration, "gyro_linear": gyro_linear,
        "vibration": vibration and not clean, "drop": list(drop),
        "clock": {"f_int_nominal": [c.f_int for c in clocks], "eps": [c.eps for c in clocks],
                  "phase": [c.phase for c in clocks], "drift_amp": [c.a for c in clocks],
                  "drift_period": [c.P for c in clocks], "drift_phase": [c.psi for c in clocks],
                  "beat_frequency": [float(beat_frequency(c.f_int, c.eps, f_host)) for c in clocks],
                  "read_skew": reader.skew.tolist(), "read_jitter_max": reader.jitter},
        "data_age": age, "read_time": r,
        "filter": {s: [f.params() for f in filt[s]] for s in filt}, "acc_minus_gyro_extra_delay": dgd,
        "errors": {"acc": [e.params() for e in acc_err], "gyro": [e.params() for e in gyro_err]},
        "pose": {"time": stamps, "phi": st["phi"], "p": st["p"], "frame": "R = Exp(phi): array -> world"},
        "rest": motion.rest_mask(stamps),
        "position": pos, "orientation": rec.nominal_orientation,
    }
    return rec, truth


def motion_of(truth):
    """The exact :class:`~.motion.Motion` of a case from its truth (seed, duration, vibration)."""
    vib = bool(truth.get("vibration", True))
    motion = draw_motion(np.random.default_rng([truth["seed"], 1]), truth["duration"], vibration=vib, impacts=vib,
                         rot_axes=tuple(truth.get("rot_axes", (0, 1, 2))))
    for piece in truth.get("drop", ()):
        if piece not in MOTION_PIECES:
            raise ValueError(f"drop: {piece!r} is not one of {MOTION_PIECES}")
        setattr(motion, piece, None)
    return motion


def write_case(rec, truth, path):
    """Write a case: format-v1 NetCDF + truth sidecar (multi-rate rigs too, DESIGN §7.1, since
    issue #28 item 1), or, where validation refuses the recording, per-IMU arrays to
    ``path.with_suffix('.npz')`` plus the sidecar with the refusal.  Returns the path written."""
    from accel_bayes.data import io, outputs
    from accel_bayes.errors import RecordingError
    path = Path(path)
    try:
        io.write_recording(rec, path, overwrite=True)
    except RecordingError as exc:
        path = path.with_suffix(".npz")
        arrays = {"time": rec.time, "acc": rec.acc, "gyro": rec.gyro, "nominal_position": rec.nominal_position,
                  "nominal_orientation": rec.nominal_orientation, "imu_time_offset": rec.imu_time_offset,
                  "acc_noise_std": rec.acc_noise_std, "gyro_noise_std": rec.gyro_noise_std}
        buf = BytesIO()
        np.savez(buf, **{k: v for k, v in arrays.items() if v is not None})
        outputs.write_bytes(path, buf.getvalue())
        truth = dict(truth, format_v1_refused=str(exc))
    io.write_truth(path, truth)
    return path
