"""``accel-bayes info REC``: validate a recording file and summarise it."""
from __future__ import annotations

import json

import numpy as np

from ..constants import G0


def register(sub) -> None:
    p = sub.add_parser(
        "info",
        help="validate a recording file and print a summary",
        description="Read a format-v1 recording (validating it) and print its size, timing, IMUs, "
        "noise levels, ranges, clipping and static/dynamic split.  Exit status 2 if the file "
        "breaks the contract, with one line saying why.",
    )
    p.add_argument("recording", metavar="REC", help="recording file (.nc, format v1)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=_run)


def _fmt(x, unit="", digits=4) -> str:
    if x is None:
        return "not given"
    return f"{x:.{digits}g}{(' ' + unit) if unit else ''}"


def _us(x: float) -> str:
    return "< 0.001 µs" if x < 1e-9 else f"{x * 1e6:.3g} µs"


def _std_text(s: np.ndarray, has: np.ndarray, unit: str) -> str:
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
    has_a, has_g = rec.has_acc, rec.has_gyro
    out.update(imus_with_acc=int(has_a.sum()), imus_with_gyro=int(has_g.sum()), reference_imu=int(rec.reference_imu))
    out["acc_noise_std"] = np.asarray(rec.acc_noise_std, float).tolist()
    out["gyro_noise_std"] = np.asarray(rec.gyro_noise_std, float).tolist()
    out["acc_range"] = rec.acc_range
    out["gyro_range"] = rec.gyro_range
    out["acc_clipped"] = _clip_stats(rec.acc_clipped, has_a)
    out["gyro_clipped"] = _clip_stats(rec.gyro_clipped, has_g)
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


def _run(args) -> int:
    from ..data.io import read_recording

    rec = read_recording(args.recording)
    s = summarize(rec, args.recording)
    if args.json:
        print(json.dumps(s, indent=1))
        return 0
    has_a, has_g = rec.has_acc, rec.has_gyro
    lines = [f"file:            {s['file']}",
             f"samples T:       {s['samples']}",
             f"duration:        {s['duration_s']:.6g} s"]
    if "sample_rate_hz" in s:
        lines.append(f"sample rate:     {s['sample_rate_hz']:.6g} Hz (median step {s['dt_median_s'] * 1e3:.6g} ms; "
                     f"jitter std {_us(s['dt_jitter_std_s'])}, max |Δt − median| {_us(s['dt_max_dev_s'])})")
    lines.append(f"IMUs K:          {s['imus']} ({s['imus_with_acc']} with accelerometer, {s['imus_with_gyro']} with gyroscope)")
    lines.append(f"reference IMU:   {s['reference_imu']}")
    lines.append(f"acc noise std:   {_std_text(np.asarray(rec.acc_noise_std, float), has_a, 'm/s²')}")
    if has_g.any():
        lines.append(f"gyro noise std:  {_std_text(np.asarray(rec.gyro_noise_std, float), has_g, 'rad/s')}")
    lines.append(f"acc range:       {_fmt(rec.acc_range, 'm/s²')}"
                 + (f" ({rec.acc_range / G0:.3g} g)" if rec.acc_range else ""))
    if has_g.any():
        lines.append(f"gyro range:      {_fmt(rec.gyro_range, 'rad/s')}"
                     + (f" ({np.degrees(rec.gyro_range):.4g} °/s)" if rec.gyro_range else ""))
    for name in ("acc_clipped", "gyro_clipped"):
        c = s[name]
        if name == "gyro_clipped" and not has_g.any():
            continue
        label = name.replace("_", " ") + ":"
        if c is None:
            lines.append(f"{label:<17}no clipping mask")
        elif c["overall"] == 0:
            lines.append(f"{label:<17}none")
        else:
            lines.append(f"{label:<17}{100 * c['overall']:.3g} % of samples (worst IMU {c['worst_imu']}: "
                         f"{100 * c['worst']:.3g} %)")
    seg = s["segments"]
    if seg is None:
        lines.append("segments:        no segment labels")
    else:
        lines.append(f"segments:        static {seg['static']} samples ({100 * seg['static'] / s['samples']:.3g} %, "
                     f"{seg['static_runs']} runs), dynamic {seg['dynamic']} samples "
                     f"({100 * seg['dynamic'] / s['samples']:.3g} %, {seg['dynamic_runs']} runs)")
    lines.append(f"description:     {rec.description or '–'}")
    lines.append(f"source:          {rec.source or '–'}")
    for k, v in rec.attrs.items():
        text = v if isinstance(v, str) else json.dumps(v, default=str)
        if len(text) > 100:
            text = text[:97] + "..."
        lines.append(f"attr {k}: {text}")
    print("\n".join(lines))
    return 0
