"""``accel-bayes info REC``: validate a recording file and summarise it."""
from __future__ import annotations

import json

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


def _run(args) -> int:
    from ..data.paths import require_file

    require_file(args.recording, "recording file")  # before torch is imported
    from ..data.io import load_recording
    from ..data.summary import gyro_range_deg_s, std_text, summarize

    rec = load_recording(args.recording).recording
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
    if "imu_sample_rate_hz" in s:
        lines.append(f"IMU rates:       {', '.join(f'{r:.6g}' for r in s['imu_sample_rate_hz'])} Hz (multi-rate: time is "
                     "the union of the IMUs' stamps, NaN where an IMU has none; the line above is the union's)")
    lines.append(f"IMUs K:          {s['imus']} ({s['imus_with_acc']} with accelerometer, {s['imus_with_gyro']} with gyroscope)")
    lines.append(f"reference IMU:   {s['reference_imu']}")
    lines.append(f"acc noise std:   {std_text(rec.acc_noise_std, has_a, 'm/s²')}")
    if has_g.any():
        lines.append(f"gyro noise std:  {std_text(rec.gyro_noise_std, has_g, 'rad/s')}")
    lines.append(f"acc range:       {_fmt(rec.acc_range, 'm/s²')}"
                 + (f" ({rec.acc_range / G0:.3g} g)" if rec.acc_range else ""))
    if has_g.any():
        lines.append(f"gyro range:      {_fmt(rec.gyro_range, 'rad/s')}"
                     + (f" ({gyro_range_deg_s(rec):.4g} °/s)" if rec.gyro_range else ""))
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
    for name in ("acc_flagged", "gyro_flagged"):
        if s[name] is not None:
            lines.append(f"{name.replace('_', ' ') + ':':<17}{s[name]} samples marked implausible by the importer")
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
