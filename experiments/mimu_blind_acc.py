#!/usr/bin/env python3
"""The six real MIMU recordings calibrated blind to the accelerometers' errors (issue #30 item 4 on real data).

``percov_blind_acc.md`` tests the blind path (``detect --acc-linear``, then ``calibrate --model`` with the
accelerometer blocks integrated out) on concealed recordings.  Here the same path meets real sensors, with a
reference the blind path cannot see: each MIMU experiment's ~20 rests in different orientations let the
preparation calibrate every triad ([S16]-style intrinsics), so the whole recording's default calibration is
the reference.  The blind run gets only the recording's last ``--seconds`` (default 130 s: the last rest, one
orientation, and the ~100 s of hand rotation), where the preparation cannot calibrate the triads:

* ``reference`` — ``calibrate(whole recording)``, every default (intrinsics from the rests, the tempered
  default's std);
* ``blind`` — ``detect(crop, acc_linear=True)``, then ``calibrate(crop, model=report)`` with its defaults
  (``acc_blocks="fit"``: the triads' deviations integrated out, the part they share cut; untempered);
* ``blind_fixed`` — the same report, ``acc_blocks="fixed"`` (the blocks inverted as exact);
* ``rest_blocks`` — the crop with the whole recording's rest intrinsics applied to its outputs, then
  ``detect(acc_linear=True)`` on it (what linear error the rests leave, seen by the motion) and
  ``calibrate(model=report, intrinsics="none")``: the reference's intrinsics and the blind path's blocks;
* ``whole_blocks`` — the whole recording, ``detect(acc_linear=True)`` (since 2026-11-29 its accelerometer
  stage runs on the rest-calibrated outputs too) and ``calibrate(model=report)`` with every default: what a
  user gets from ``mismatch --acc-linear`` then ``calibrate --model`` on a recording with rests.

Scored per free coordinate: d = blind mean − reference mean and z = d / √(std_blind² + std_reference²).  The
two calibrations share the rotation's data, so z is a check of what the blind path adds (the accelerometers'
errors, estimated or integrated, against calibrated from the rests), not of the rotation's own noise: a
blind std that honestly carries the errors it cannot see gives |z| of order 1 or less.

The document also reads each chip's block from the ``whole_blocks`` reports, experiment by experiment
(:func:`chip_blocks`): its rotation about the board's normal in the array frame and whether it repeats
across the six experiments (the same chips every time) beyond the spread between them.

    PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/mimu_blind_acc.py
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from experiments._data import data_dir  # noqa: E402

DOC = HERE / "mimu_blind_acc.md"
OUT = HERE / "results" / "mimu_blind_acc"
REPORTS = HERE / "out" / "mimu_blind_acc"
VARIANTS = ("reference", "blind", "blind_fixed", "rest_blocks", "whole_blocks")
CALIB = {"chains": 2, "warmup": 300, "draws": 400, "seed": 0}


def crop(rec, seconds: float):
    """The recording's last ``seconds`` (s), times kept as recorded."""
    t = np.asarray(rec.time, dtype=np.float64)
    return rec.select(np.nonzero(t >= t[-1] - float(seconds))[0])


def run_one(exp: int, variant: str, seconds: float, out: Path = OUT, reports: Path = REPORTS) -> dict:
    """One calibration of experiment ``exp`` (cached in ``out/exp_N/{variant}.json``; the blind report in
    ``reports/exp_N/report.json``)."""
    from accel_bayes.data.mimu import import_mimu
    from accel_bayes.data.outputs import write_json
    from accel_bayes.mismatch import DetectOptions, detect
    from accel_bayes.pipelines.calibrate import calibrate

    f = out / f"exp_{exp}" / f"{variant}.json"
    if f.exists():
        return json.loads(f.read_text())
    rec = import_mimu(data_dir() / f"exp_{exp}" / "data.bin.gz")
    det_s, kw = 0.0, {}
    if variant != "reference":
        if variant == "rest_blocks":  # the rests' intrinsics (whole recording) applied to the crop's outputs
            from accel_bayes.prep.intrinsics import estimate_intrinsics

            rec = estimate_intrinsics(rec).apply(crop(rec, seconds))
            kw = {"intrinsics": "none"}
        elif variant != "whole_blocks":
            rec = crop(rec, seconds)
        rep = reports / f"exp_{exp}" / {"rest_blocks": "rest_report.json", "whole_blocks": "whole_report.json"}.get(
            variant, "report.json")
        if not rep.exists():
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                report = detect(rec, DetectOptions(seed=CALIB["seed"], acc_linear=True))
            det_s = time.perf_counter() - t0
            rep.parent.mkdir(parents=True, exist_ok=True)
            write_json(rep, report.to_dict())
        kw = {**kw, "model": str(rep), **({"acc_blocks": "fixed"} if variant == "blind_fixed" else {})}
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        res = calibrate(rec, progress=False, **CALIB, **kw)
    st = res.settings
    blocks = ((st.get("model") or {}).get("acc_blocks")) or {}
    doc = {"exp": exp, "variant": variant, "seconds_kept": None if variant in ("reference", "whole_blocks") else seconds,
           "T_used": st["T"], "intrinsics_applied": bool(st["preprocess"]["intrinsics"]["applied"]),
           "mean": [e["mean"] for e in res.positions["imus"]], "std": [e["std"] for e in res.positions["imus"]],
           "reference_imu": st["reference_imu"], "detect_seconds": det_s,
           "calibrate_seconds": time.perf_counter() - t0,
           "acc_blocks": {k: blocks.get(k) for k in ("tau_matrix", "tau_bias_m_s2", "report_blocks",
                                                    "common_shift_std_median_m", "laplace_std_ratio_median",
                                                    "mode_shift_m", "how")},
           "findings": [] if variant == "reference" else
           [{"effect": x["effect"], "imu": x.get("imu")}
            for x in json.loads(rep.read_text())["findings"]],
           "settings": CALIB}
    f.parent.mkdir(parents=True, exist_ok=True)
    write_json(f, doc)
    return doc


def compare(b: dict, r: dict) -> dict:
    """d (µm), z and the coordinates' names of blind ``b`` against reference ``r`` (free coordinates)."""
    ref = int(r["reference_imu"])
    mb, mr = np.asarray(b["mean"]), np.asarray(r["mean"])
    sb, sr = np.asarray(b["std"]), np.asarray(r["std"])
    keep = [k for k in range(len(mb)) if k != ref]
    d = (mb - mb[ref]) - (mr - mr[ref])
    s = np.sqrt(sb ** 2 + sr ** 2)
    names = [f"r[{k}, {a}]" for k in keep for a in "xyz"]
    return {"d_um": (1e6 * d[keep]).reshape(-1), "z": (d[keep] / s[keep]).reshape(-1), "names": names,
            "std_b_um": (1e6 * sb[keep]).reshape(-1), "std_r_um": (1e6 * sr[keep]).reshape(-1)}


def lower_layer(positions, ref: int) -> list[int]:
    """The IMUs more than 1 mm below the reference IMU ``ref`` (MIMU4444's underside), from ``positions``
    (K, 3) m: the one rule for the board's two layers here and in ``mimu_model_calibrate``."""
    p = np.asarray(positions, dtype=float)
    return [k for k in range(len(p)) if k != ref and p[k, 2] - p[ref, 2] < -1e-3]


def layer_shift(b: dict, r: dict) -> np.ndarray | None:
    """(x, y) µm: the mean d of the IMUs in the reference's lower layer (z more than 1 mm below the reference
    IMU: MIMU4444's IMUs on the board's underside) less that of the upper layer's (the reference IMU itself
    excluded); None on a one-layer board."""
    c = compare(b, r)
    ref = int(r["reference_imu"])
    lower = set(lower_layer(r["mean"], ref))
    low = np.array([k in lower for k in range(len(r["mean"])) if k != ref])
    if low.all() or not low.any():
        return None
    d = c["d_um"].reshape(-1, 3)
    return d[low, :2].mean(0) - d[~low, :2].mean(0)


def _rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def _shift(v) -> str:
    return "—" if v is None else f"({v[0]:+.0f}, {v[1]:+.0f})"


def markdown(rows: dict, cmd: str, seconds: float, kept: float) -> list[str]:
    from experiments._stamp import run_stamp

    L = ["# mimu_blind_acc — the six real MIMU recordings calibrated blind to the accelerometers' errors",
         "", f"Regenerate: `{cmd}` ({run_stamp()}; this invocation {seconds:.0f} s; per-experiment records in "
         "`experiments/results/mimu_blind_acc/`, the blind reports cached in `experiments/out/mimu_blind_acc/`).", "",
         "What runs: the script's docstring. **reference**: the whole recording, `calibrate` defaults (intrinsics "
         "from the ~20 rests). **blind**: the recording's last "
         f"{kept:g} s (one rest orientation and the rotation: the preparation cannot calibrate the triads), "
         "`detect(acc_linear=True)`, `calibrate(model=report)` defaults (`acc_blocks='fit'`, untempered). "
         "**blind, fixed**: the same with `acc_blocks='fixed'`. **rest + blocks**: the same crop with the whole "
         "recording's rest intrinsics applied, `detect(acc_linear=True)` on that (the linear errors the rests leave) and "
         "`calibrate(model=report, intrinsics='none')`. **whole + blocks**: the whole recording, `detect(acc_linear=True)` "
         "(its accelerometer stage on the rest-calibrated outputs) and `calibrate(model=report)` defaults. "
         f"Calibration {CALIB['chains']} chains × ({CALIB['warmup']} + {CALIB['draws']}), seed {CALIB['seed']}. "
         "z = (blind − reference) / √(std_blind² + std_reference²) per free coordinate; the two share the rotation's "
         "data, so |z| of order 1 or less is what an honest blind std gives.", ""]
    zb, zf, worst = [], [], []
    # the two runs with blocks on top of the rests' intrinsics: each against the reference, and the blind against it
    extra = {"rest": ([], []), "whole": ([], [])}
    L += ["| exp | intrinsics (ref / blind) | acc blocks | τ_M % / τ_b m/s² | z RMS blind / fixed | max \\|z\\| blind / fixed "
          "| RMS d µm blind / fixed | lower − upper layer d (x, y) µm blind / fixed | median std µm blind / fixed / reference "
          "| cut's spread median µm | seconds detect / calibrate "
          "| rest + blocks − reference: z RMS, layer d µm | blind − rest + blocks: z RMS, layer d µm "
          "| whole + blocks − reference: z RMS, layer d µm | blind − whole + blocks: z RMS, layer d µm |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    pair = lambda x, y, fmt: f"{x:{fmt}} / " + ("—" if y is None else f"{y:{fmt}}")  # noqa: E731
    for exp in sorted(rows):
        r, b, f, rb, wb = rows[exp]
        cb = compare(b, r)
        cf = compare(f, r) if f is not None else None
        zb.append(cb["z"])
        worst += [(abs(v), n, exp) for v, n in zip(cb["z"], cb["names"])]
        if cf is not None:
            zf.append(cf["z"])
        ab = b["acc_blocks"]
        cells = []
        for key, x in (("rest", rb), ("whole", wb)):
            for zs, (u, v) in zip(extra[key], ((x, r), (b, x))):
                if x is None:
                    cells.append("—")
                    continue
                c = compare(u, v)
                zs.append(c["z"])
                cells.append(f"{_rms(c['z']):.2f}, {_shift(layer_shift(u, v))}")
        L.append(f"| {exp} | {'yes' if r['intrinsics_applied'] else 'no'} / {'yes' if b['intrinsics_applied'] else 'no'} | "
                 f"{len(ab.get('report_blocks') or [])}/8 | "
                 + (f"{100 * ab['tau_matrix']:.2f} / {ab['tau_bias_m_s2']:.3f}" if ab.get("tau_matrix") else "—") + " | "
                 + pair(_rms(cb["z"]), None if cf is None else _rms(cf["z"]), ".2f") + " | "
                 + pair(np.abs(cb["z"]).max(), None if cf is None else np.abs(cf["z"]).max(), ".2f") + " | "
                 + pair(_rms(cb["d_um"]), None if cf is None else _rms(cf["d_um"]), ".0f") + " | "
                 + _shift(layer_shift(b, r)) + " / " + ("—" if f is None else _shift(layer_shift(f, r))) + " | "
                 + pair(np.median(cb["std_b_um"]), None if cf is None else np.median(cf["std_b_um"]), ".0f")
                 + f" / {np.median(cb['std_r_um']):.0f} | "
                 + ("—" if ab.get("common_shift_std_median_m") is None else f"{1e6 * ab['common_shift_std_median_m']:.0f}")
                 + f" | {b['detect_seconds']:.0f} / {b['calibrate_seconds']:.0f} | " + " | ".join(cells) + " |")
    if zb:
        z = np.concatenate(zb)
        L += ["", f"Pooled over {len(zb)} experiments ({len(z)} coordinates): blind z RMS {_rms(z):.2f}, max |z| "
              f"{np.abs(z).max():.2f}, beyond 3: {int((np.abs(z) > 3).sum())}"
              + ("" if not zf else f"; fixed z RMS {_rms(np.concatenate(zf)):.2f}, max |z| "
                 f"{np.abs(np.concatenate(zf)).max():.2f}, beyond 3: {int((np.abs(np.concatenate(zf)) > 3).sum())}") + "."]
        for key, name, it in (("rest", "Rest + blocks", "rest + blocks"), ("whole", "Whole recording + blocks", "it")):
            against, blind = extra[key]
            if against:
                L += ["", f"{name} against the reference: z RMS {_rms(np.concatenate(against)):.2f}; the blind against "
                      f"{it}: z RMS {_rms(np.concatenate(blind)):.2f}, max |z| {np.abs(np.concatenate(blind)).max():.2f} "
                      f"({len(against)} experiments)."]
        worst = sorted(worst, reverse=True)[:5]
        L += ["", "Largest |z| blind: " + ", ".join(f"exp {e} {n} {v:.2f}" for v, n, e in worst) + "."]
    return L


def chip_blocks(reports: dict, orientation=None) -> dict:
    """Each triad's accelerometer block from the whole recordings' reports (``reports``: experiment → report
    dict of ``detect(acc_linear=True)`` on the rest-calibrated outputs; the blocks are in each sensor's own
    frame): per IMU and experiment its rotation about the board's normal, ½(E_yx − E_xy) of the block in the
    array frame E = RᵀE_sR (``orientation`` (K, 3, 3) R the nominal array → sensor rotations; None: the sensor
    frame), mrad, with the std the report states, and its sensor-frame offsets x, y (m/s²); then the rotation
    less the experiment's mean over its triads (what the positions see: a rotation every triad shares moves no
    lever arm) and a one-way analysis of variance of those deviations across the experiments — the triads are
    the same chips in every experiment, so a chip's mounting shows as a between-IMU variance far above the
    within-IMU (experiment-to-experiment) one."""
    from scipy.stats import f as f_dist

    exps = sorted(reports)
    imus = sorted({int(f["imu"]) for e in exps for f in reports[e]["findings"] if f["effect"] == "acc_scale"})
    rot = np.full((len(exps), len(imus)), np.nan)
    rot_sd = np.full_like(rot, np.nan)
    gyro = np.full_like(rot, np.nan)  # the same chip's gyro block (gyro_scale), the same rotation
    off = np.full((len(exps), len(imus), 2), np.nan)
    for i, e in enumerate(exps):
        for f in reports[e]["findings"]:
            if f["effect"] not in ("acc_scale", "gyro_scale") or int(f["imu"]) not in imus:
                continue
            j = imus.index(int(f["imu"]))
            M = np.asarray(f["parameters"]["scale"], dtype=float)
            if orientation is not None:
                R = np.asarray(orientation, dtype=float)[int(f["imu"])]
                M = R.T @ M @ R
            if f["effect"] == "gyro_scale":
                gyro[i, j] = 1e3 * 0.5 * (M[1, 0] - M[0, 1])
                continue
            rot[i, j] = 1e3 * 0.5 * (M[1, 0] - M[0, 1])
            sd = np.asarray((f.get("std") or {}).get("matrix", np.full((3, 3), np.nan)), dtype=float)
            rot_sd[i, j] = 1e3 * 0.5 * np.hypot(sd[1, 0], sd[0, 1])
            off[i, j] = np.asarray(f["parameters"]["bias"], dtype=float)[:2]

    def anova(x):  # x (E, K) deviations, complete rows only
        x = x[~np.isnan(x).any(1)]
        E, K = x.shape
        if E < 2 or K < 2:
            return None
        msb = E * ((x.mean(0) - x.mean()) ** 2).sum() / (K - 1)
        msw = ((x - x.mean(0)) ** 2).sum() / (K * (E - 1))
        F = msb / msw
        return {"F": float(F), "df": [K - 1, K * (E - 1)], "log10_p": float(f_dist.logsf(F, K - 1, K * (E - 1)) / np.log(10)),
                "within_sd": float(np.sqrt(msw)), "experiments": int(E)}

    dev = rot - np.nanmean(rot, 1, keepdims=True)
    doff = off - np.nanmean(off, 1, keepdims=True)
    gdev = gyro - np.nanmean(gyro, 1, keepdims=True)
    ok = ~(np.isnan(dev) | np.isnan(gdev))
    corr = [float(np.corrcoef(dev[i, ok[i]], gdev[i, ok[i]])[0, 1]) if ok[i].sum() > 2 else None
            for i in range(len(exps))]
    return {"exps": exps, "imus": imus, "rot_mrad": rot.tolist(), "rot_sd_mrad": rot_sd.tolist(),
            "offset_m_s2": off.tolist(), "rot_dev_mrad": dev.tolist(), "anova_rot": anova(dev),
            "anova_offset": [anova(doff[..., a]) for a in range(2)], "gyro_rot_mrad": gyro.tolist(),
            "acc_gyro_corr": corr}


def chip_markdown(cb: dict, lower: set) -> list[str]:
    """The :func:`chip_blocks` table: per IMU its rotation per experiment, their mean ± sd, the stated std."""
    rot, sd, dev = (np.asarray(cb[k], dtype=float) for k in ("rot_mrad", "rot_sd_mrad", "rot_dev_mrad"))
    off = np.asarray(cb["offset_m_s2"], dtype=float)
    L = ["", "### Each chip's block, experiment by experiment (the whole recordings' reports)", "",
         "Rotation about the board's normal ½(E_yx − E_xy) of each triad's block (`mismatch --acc-linear` on the "
         "rest-calibrated outputs; in the array frame, E = RᵀE_sR with R the nominal orientation: an underside chip, "
         "flipped, reads its own rotation with the opposite sign), per experiment; then its mean ± sd over the "
         "experiments, the same less each experiment's mean over its triads (the part the positions see), the std "
         "the reports state, the same chip's gyro block's rotation (`gyro_scale`, the gyro stage's relative blocks), "
         "and the mean offsets x, y in the sensor's frame.", "",
         "| IMU | layer | " + " | ".join(f"exp {e} (mrad)" for e in cb["exps"])
         + " | mean ± sd (mrad) | less the triads' mean: mean ± sd (mrad) | stated std (mrad) | gyro: mean ± sd (mrad) "
           "| offset x, y (m/s²) |",
         "|---|---|" + "---|" * len(cb["exps"]) + "---|---|---|---|---|"]
    gy = np.asarray(cb.get("gyro_rot_mrad", np.full_like(rot, np.nan)), dtype=float)
    for j, k in enumerate(cb["imus"]):
        L.append(f"| {k} | {'under' if k in lower else 'upper'} | " + " | ".join(f"{v:+.1f}" for v in rot[:, j])
                 + f" | {np.nanmean(rot[:, j]):+.1f} ± {np.nanstd(rot[:, j], ddof=1):.1f} | "
                 f"{np.nanmean(dev[:, j]):+.1f} ± {np.nanstd(dev[:, j], ddof=1):.1f} | {np.nanmedian(sd[:, j]):.2f} | "
                 + ("—" if np.isnan(gy[:, j]).all() else f"{np.nanmean(gy[:, j]):+.2f} ± {np.nanstd(gy[:, j], ddof=1):.2f}")
                 + f" | {np.nanmean(off[:, j, 0]):+.3f}, {np.nanmean(off[:, j, 1]):+.3f} |")
    a = cb.get("anova_rot")
    if a:
        L += ["", f"One-way analysis of variance of the rotations less the triads' mean, IMU against experiment "
                  f"({a['experiments']} experiments): F = {a['F']:.1f} (df {a['df'][0]}, {a['df'][1]}), "
                  f"log10 p = {a['log10_p']:.1f}; within-IMU sd {a['within_sd']:.2f} mrad against a stated std of "
                  f"{np.nanmedian(sd):.2f} mrad (median)."
              + "".join(f" Offsets {ax}: F = {o['F']:.1f}, log10 p = {o['log10_p']:.1f}, within-IMU sd "
                        f"{o['within_sd']:.3f} m/s²." for ax, o in zip("xy", cb["anova_offset"]) if o)]
    c = [v for v in cb.get("acc_gyro_corr") or [] if v is not None]
    if c:
        L += ["", f"Correlation over the chips of the accelerometer's and the gyro's rotation (each less its "
                  f"experiment's mean), per experiment: {', '.join(f'{v:.2f}' for v in c)}."]
    return L


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--exps", default="1,2,3,4,5,6", help="comma-separated experiments (default all six)")
    ap.add_argument("--seconds", type=float, default=130.0, help="the blind run keeps the recording's last SECONDS (default 130)")
    ap.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated subset of " + ",".join(VARIANTS))
    ap.add_argument("--no-doc", action="store_true", help="run and cache only")
    args = ap.parse_args(argv)
    t0 = time.time()
    exps = [int(e) for e in args.exps.split(",") if e.strip()]
    variants = [v for v in args.variants.split(",") if v]
    if any(v not in VARIANTS for v in variants):
        ap.error(f"--variants: expected a subset of {','.join(VARIANTS)}, got {args.variants!r}")
    if not args.seconds > 0:
        ap.error("--seconds: expected a duration > 0 s")
    for e in exps:
        for v in variants:
            r = run_one(e, v, args.seconds)
            print(f"exp {e} {v}: T {r['T_used']}, intrinsics {r['intrinsics_applied']}, calibrate {r['calibrate_seconds']:.0f} s",
                  flush=True)
    if args.no_doc:
        return 0
    rows = {}
    for e in range(1, 7):
        fs = [OUT / f"exp_{e}" / f"{v}.json" for v in VARIANTS]
        if fs[0].exists() and fs[1].exists():
            rows[e] = tuple(json.loads(f.read_text()) if f.exists() else None for f in fs)
    from experiments._reading import write_with_reading

    cmd = "PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/mimu_blind_acc.py" + (
        "" if args.seconds == 130.0 else f" --seconds {args.seconds:g}")
    md = markdown(rows, cmd, time.time() - t0, args.seconds)
    reps = {e: json.loads((REPORTS / f"exp_{e}" / "whole_report.json").read_text()) for e in range(1, 7)
            if (REPORTS / f"exp_{e}" / "whole_report.json").exists()}
    if len(reps) >= 2:
        ref = next(r[0] for r in rows.values())
        from accel_bayes.data.mimu import import_mimu
        from accel_bayes.physics.geometry import quat_to_matrix
        import torch

        q = np.asarray(import_mimu(data_dir() / "exp_1" / "data.bin.gz").nominal_orientation, dtype=np.float64)
        R = quat_to_matrix(torch.as_tensor(q)).numpy()  # the same board in every experiment
        md += chip_markdown(chip_blocks(reps, R), set(lower_layer(ref["mean"], int(ref["reference_imu"]))))
    write_with_reading(DOC, md)
    print(f"wrote {DOC}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
