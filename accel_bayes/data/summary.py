"""A recording summarised: the numbers ``accel-bayes info`` prints (samples, rate, IMUs, noise,
ranges, clipping, static/dynamic split), as a JSON-ready dict."""
from __future__ import annotations

import numpy as np

from ..constants import RAD_TO_DEG
from .export import imu_stamps
from .recording import stamp_rate
from .validation import is_multirate

__all__ = ["summarize", "std_text", "gyro_range_deg_s"]


def std_text(s, has, unit: str) -> str:
    """Noise stds of the IMUs that have the sensor: one value "(all)", or the range and median."""
    s, has = np.asarray(s, float), np.asarray(has)
    v = s[has]
    if v.size == 0:
        return "–"
    if np.all(v == v[0]):
        return f"{v[0]:.4g} {unit} (all)"
    return f"{v.min():.4g}–{v.max():.4g} {unit} (per IMU, median {np.median(v):.4g})"


def _clip_stats(mask, has):
    if mask is None or not has.any():
        return None
    m = np.asarray(mask)[:, has]
    per = m.mean(0)
    labels = np.flatnonzero(has)
    w = int(np.argmax(per))
    return {"overall": float(m.mean()), "worst_imu": int(labels[w]), "worst": float(per[w])}


def summarize(rec, path=None) -> dict:
    """The numbers ``info`` prints, as a dict (JSON-ready)."""
    t = np.asarray(rec.time)
    T, K = rec.T, rec.K
    dt = np.diff(t)
    out = {"file": None if path is None else str(path), "samples": T, "imus": K}
    out["duration_s"] = float(t[-1] - t[0]) if T > 1 else 0.0
    if dt.size:
        med = float(np.median(dt))
        out["sample_rate_hz"] = 1.0 / med
        out["dt_median_s"] = med
        out["dt_jitter_std_s"] = float(np.std(dt))
        out["dt_max_dev_s"] = float(np.max(np.abs(dt - med)))
    if is_multirate(rec):
        # the union's steps say nothing of any one IMU's rate (DESIGN §7.1)
        out["imu_sample_rate_hz"] = [stamp_rate(imu_stamps(rec, k)[1]) for k in range(K)]
    has_a, has_g = rec.has_acc, rec.has_gyro
    out.update(imus_with_acc=int(has_a.sum()), imus_with_gyro=int(has_g.sum()), reference_imu=int(rec.reference_imu))
    out["acc_noise_std"] = np.asarray(rec.acc_noise_std, float).tolist()
    out["gyro_noise_std"] = np.asarray(rec.gyro_noise_std, float).tolist()
    out["acc_range"] = rec.acc_range
    out["gyro_range"] = rec.gyro_range
    out["acc_clipped"] = _clip_stats(rec.acc_clipped, has_a)
    out["gyro_clipped"] = _clip_stats(rec.gyro_clipped, has_g)
    for name, m in (("acc_flagged", rec.acc_flagged), ("gyro_flagged", rec.gyro_flagged)):
        # a count, not a fraction: marks are rare (a few per 10⁵) and each is worth seeing
        out[name] = None if m is None else int(np.asarray(m, bool).sum())
    if rec.segment is not None:
        seg = np.asarray(rec.segment).astype(str)
        st = seg == "static"
        runs = lambda m: int(np.sum(m & np.r_[True, ~m[:-1]]))  # noqa: E731
        out["segments"] = {"static": int(st.sum()), "dynamic": int((~st).sum()),
                           "static_runs": runs(st), "dynamic_runs": runs(~st)}
    else:
        out["segments"] = None
    out["description"] = rec.description
    out["source"] = rec.source
    return out


def gyro_range_deg_s(rec) -> float | None:
    """The recording's gyro range in °/s (None where not stated)."""
    return None if not rec.gyro_range else rec.gyro_range * RAD_TO_DEG
