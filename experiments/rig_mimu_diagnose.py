"""Why exp_1's two-IMU rigs disagree with the eight-IMU rig (issue #28, the MIMU pair must-show,
``experiments/rig_mimu_pairs.md``: z RMS 5.64) → ``experiments/rig_mimu_diagnose.md``.

    PYTHONPATH=. python3 experiments/rig_mimu_diagnose.py --step map
    PYTHONPATH=. python3 experiments/rig_mimu_diagnose.py --step fits --variant none      (and gyro, gyro+acc)
    PYTHONPATH=. python3 experiments/rig_mimu_diagnose.py --step jackknife --variant none (and gyro)
    PYTHONPATH=. python3 experiments/rig_mimu_diagnose.py --step report

Same window as the pairs study (:func:`experiments.rig_mimu_pairs.window`, 30 s).  Steps:

* ``map``: each IMU's gyro (acc) readings against IMU 0's, the RMS left by the best rotation and by
  the best 3×3 linear map (plus a constant), and the largest entry of the map's symmetric part
  minus I (polar decomposition: scale and non-orthogonality relative to IMU 0) — a look at cause
  (a)/(b) without any fit.  The acc comparison ignores the lever arms (mm on this board).
* ``fits``: the eight-IMU rig and the worst pairs of the pairs study refitted with the rig's
  ``linear_errors`` option (``none``, ``gyro``, ``gyro+acc``), or with the accs' stated noise
  multiplied by :data:`ACC_MUTE` (``gyro_timing``: the clocks timed by the gyros alone), or with
  the ``acc_delay`` option (each acc its own delay against its gyro; ``acc_delay+gyro`` with the
  gyro linear errors too): offsets,
  z as the pairs study computes it, and χ² per reading per IMU (cause (c): stated against fitted
  noise).
* ``swap``: the pairs of :data:`JK_PAIRS` with the other IMU as the reference (the rig model is not
  symmetric: the reference has no biases, linear errors or delay of its own), o_i − o_j against
  o_j − o_i.
* ``jackknife``: the pair offset's delete-one-block jackknife std (10 blocks of 3 s, a block's
  samples weighted 0) against the pair's Laplace std — an estimate of Var that does not rest on the
  model being right (cause (d)).

Each step caches its records in ``experiments/results/rig_mimu_diagnose/``; ``report`` writes the
document from them.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import datetime  # noqa: E402
import itertools  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from accel_bayes.data import outputs  # noqa: E402
from accel_bayes.data.mimu import import_mimu  # noqa: E402
from accel_bayes.inference.rig import RigSettings, fit_rig  # noqa: E402
from accel_bayes.inference.rig.initial import kabsch  # noqa: E402
from experiments.rig_mimu_pairs import DATA, imus, offset_difference, window  # noqa: E402

CACHE = REPO / "experiments" / "results" / "rig_mimu_diagnose"
#: the pairs with the largest |z| in rig_mimu_pairs.md (13:29 run) and two near zero as controls
PAIRS = [(4, 5), (2, 6), (2, 5), (3, 6), (0, 5), (0, 6), (1, 6), (0, 2), (5, 6)]
JK_PAIRS = [(4, 5), (2, 6), (0, 5)]
N_BLOCKS = 10


VARIANTS = ("none", "gyro", "gyro+acc", "gyro_timing", "acc_delay", "acc_delay+gyro")
#: ``gyro_timing``: the accs' stated noise times this, so that the clocks are timed by the gyros alone
ACC_MUTE = 100.0


def _settings(variant: str) -> RigSettings:
    parts = variant.split("+")
    lin = tuple(p for p in parts if p in ("gyro", "acc"))
    return RigSettings(knot_spacing=0.01, linear_errors=lin, acc_delay="acc_delay" in parts)


def _variant_data(sub, variant: str):
    if variant != "gyro_timing":
        return sub
    out = sub.copy()
    out.acc_noise_std = np.asarray(sub.acc_noise_std, dtype=float) * ACC_MUTE
    return out


def _map_rows(sub):
    rows = []
    for kind in ("gyro", "acc"):
        y = np.asarray(getattr(sub, kind), dtype=float)
        for k in range(1, sub.K):
            a, b = y[:, 0], y[:, k]
            R, _ = kabsch(a - a.mean(0), b - b.mean(0))
            rot = b - b.mean(0) - (a - a.mean(0)) @ R.T
            X = np.c_[a, np.ones(len(a))]
            B, *_ = np.linalg.lstsq(X, b, rcond=None)
            lin = b - X @ B
            U, s, _ = np.linalg.svd(B[:3].T)
            P = U @ np.diag(s) @ U.T - np.eye(3)
            rows.append({"kind": kind, "imu": k, "rms_rot": float(np.sqrt((rot ** 2).mean())),
                         "rms_lin": float(np.sqrt((lin ** 2).mean())), "max_sym": float(np.abs(P).max()),
                         "noise": float(math.hypot(getattr(sub, f"{kind}_noise_std")[0],
                                                   getattr(sub, f"{kind}_noise_std")[k]))})
    return rows


def _pair(sub, i, j, settings):
    r = fit_rig(imus(sub, [i, j]), settings)
    return {"i": i, "j": j, "offset": float(r.time_offset[1]), "std": float(r.time_offset_std[1]),
            "reason": r.reason, "n_iter": r.n_iter, "seconds": r.seconds, "chi2_per_imu": r.chi2_per_imu.tolist(),
            "linear_error": {k: v[1].tolist() for k, v in (r.linear_error or {}).items()}}


def step_fits(sub, variant):
    settings = _settings(variant)
    r = fit_rig(sub, settings)
    full = {"reason": r.reason, "n_iter": r.n_iter, "seconds": r.seconds, "chi2_per_dof": r.chi2_per_dof,
            "chi2_per_imu": r.chi2_per_imu.tolist(), "unidentified": [[int(k), n] for k, n in r.unidentified],
            "diff": {f"{i}-{j}": offset_difference(r, i, j) for i, j in itertools.combinations(range(sub.K), 2)},
            "linear_error": {k: v.tolist() for k, v in (r.linear_error or {}).items()}}
    out = {"variant": variant, "full": full, "pairs": []}
    for i, j in PAIRS:
        out["pairs"].append(_pair(sub, i, j, settings))
        print(out["pairs"][-1], flush=True)
    outputs.write_json(CACHE / f"fits_{variant}.json", out)


def step_jackknife(sub, variant):
    settings = _settings(variant)
    n = len(sub.time)
    edges = np.linspace(0, n, N_BLOCKS + 1).astype(int)
    out = {"variant": variant, "blocks": N_BLOCKS, "pairs": []}
    for i, j in JK_PAIRS:
        full = _pair(sub, i, j, settings)
        loo = []
        for b in range(N_BLOCKS):
            cut = sub.copy()
            flag = np.zeros((n, sub.K), bool)
            flag[edges[b]:edges[b + 1]] = True
            cut.acc_flagged, cut.gyro_flagged = flag, flag.copy()
            loo.append(_pair(cut, i, j, settings)["offset"])
        m = float(np.mean(loo))
        jk = math.sqrt((N_BLOCKS - 1) / N_BLOCKS * float(np.sum((np.asarray(loo) - m) ** 2)))
        out["pairs"].append({"i": i, "j": j, "offset": full["offset"], "std": full["std"], "loo": loo, "jk_std": jk})
        print(out["pairs"][-1], flush=True)
    outputs.write_json(CACHE / f"jackknife_{variant}.json", out)


def step_swap(sub, variant):
    settings = _settings(variant)
    out = {"variant": variant, "pairs": []}
    for i, j in JK_PAIRS:
        fwd, back = _pair(sub, i, j, settings), _pair(sub, j, i, settings)
        out["pairs"].append({"i": i, "j": j, "forward": fwd, "back": back})
        print(out["pairs"][-1], flush=True)
    outputs.write_json(CACHE / f"swap_{variant}.json", out)


def _z(p, full):
    d8, s8 = full["diff"][f"{p['i']}-{p['j']}"]
    var = p["std"] ** 2 - s8 ** 2
    return (p["offset"] - d8) / math.sqrt(var) if var > 0 else float("nan"), d8, s8


def report():
    lines = ["# Why exp_1's two-IMU rigs disagree with the eight-IMU rig (issue #28)", "",
             "Regenerate: `PYTHONPATH=. python3 experiments/rig_mimu_diagnose.py --step STEP [--variant V]` for the "
             "steps and variants below, then `--step report` "
             f"({datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, {platform.machine()} "
             f"{platform.system()}, 2-core CPU shared with other jobs).  exp_1, the pairs study's 30 s window.", ""]
    mp = CACHE / "map.json"
    if mp.exists():
        rows = json.loads(mp.read_text())
        lines += ["## (a), (b) without a fit: each IMU against IMU 0 (`--step map`)", "",
                  "RMS of IMU k's readings minus IMU 0's mapped by the best rotation, and by the best 3×3 linear "
                  "map; √(σ_0² + σ_k²) from the stated noise; the largest |entry| of the map's symmetric part − I "
                  "(relative scale and non-orthogonality).", "",
                  "| sensor | IMU | RMS rotation | RMS linear | stated noise | max sym. error |", "|---|---|---|---|---|---|"]
        for r in rows:
            sym = f"{100 * r['max_sym']:.2f} %" if r["kind"] == "gyro" else "— (gravity-dominated)"
            lines.append(f"| {r['kind']} | {r['imu']} | {r['rms_rot']:.5f} | {r['rms_lin']:.5f} | {r['noise']:.5f} | "
                         f"{sym} |")
        lines += ["", "(rad/s for the gyros, m/s² for the accs.  The acc map is not a scale estimate: in this gentle "
                  "window the specific force is mostly gravity along one axis, which leaves the map's other "
                  "directions to the noise.)", ""]
    fits = {v: json.loads((CACHE / f"fits_{v}.json").read_text()) for v in VARIANTS
            if (CACHE / f"fits_{v}.json").exists()}
    if fits:
        lines += ["## Refits with the rig's `linear_errors` option (`--step fits`)", "",
                  "z = Δ/√(s_pair² − s_8²) as in the pairs study, both fits with the same option.", "",
                  "| pair | " + " | ".join(f"z ({v})" for v in fits) + " | " +
                  " | ".join(f"pair offset ({v}, ms)" for v in fits) + " |",
                  "|---|" + "---|" * (2 * len(fits))]
        zs = {v: [] for v in fits}
        for a, (i, j) in enumerate(PAIRS):
            cells_z, cells_o = [], []
            for v, d in fits.items():
                p = d["pairs"][a]
                z, d8, s8 = _z(p, d["full"])
                zs[v].append(z)
                cells_z.append(f"{z:+.2f}")
                cells_o.append(f"{1e3 * p['offset']:+.4f} ± {1e3 * p['std']:.4f} (8: {1e3 * d8:+.4f} ± {1e3 * s8:.4f})")
            lines.append(f"| {i}–{j} | " + " | ".join(cells_z) + " | " + " | ".join(cells_o) + " |")
        lines += ["", "z RMS over these pairs: " + ", ".join(
            f"{v} {math.sqrt(np.nanmean(np.square(zs[v]))):.2f}" for v in fits) + ".", ""]
        lines += ["Eight-IMU fits: " + "; ".join(
            f"{v}: LM {d['full']['reason']} ({d['full']['n_iter']} steps, {d['full']['seconds']:.0f} s), χ²/dof "
            f"{d['full']['chi2_per_dof']:.3f}" for v, d in fits.items()) + ".", "",
                  "χ² per reading per IMU of the eight-IMU fits [gyro, acc] (cause (c): 1 where the stated noise is "
                  "right):", "", "| IMU | " + " | ".join(fits) + " |", "|---|" + "---|" * len(fits)]
        for k in range(8):
            lines.append(f"| {k} | " + " | ".join(
                "{:.2f}, {:.2f}".format(*d["full"]["chi2_per_imu"][k]) for d in fits.values()) + " |")
        lin = {v: d["full"]["linear_error"] for v, d in fits.items() if d["full"]["linear_error"]}
        for v, le in lin.items():
            for kind, M in le.items():
                M = np.asarray(M)
                lines += ["", f"Fitted relative {kind} linear error M (eight-IMU, variant {v}): largest |entry| per "
                          "IMU " + ", ".join(f"{k}: {100 * np.abs(M[k]).max():.2f} %" for k in range(1, len(M))) + "."]
        lines.append("")
    jks = {v: json.loads((CACHE / f"jackknife_{v}.json").read_text()) for v in VARIANTS
           if (CACHE / f"jackknife_{v}.json").exists()}
    if jks:
        lines += ["## (d) Is the pair's std honest? Delete-one-block jackknife (`--step jackknife`)", "",
                  f"{N_BLOCKS} blocks of 3 s, each left out once (its samples weighted 0); jackknife std of the pair "
                  "offset against its Laplace std.", "",
                  "| variant | pair | offset (ms) | Laplace std (ms) | jackknife std (ms) | ratio |", "|---|---|---|---|---|---|"]
        for v, d in jks.items():
            for p in d["pairs"]:
                lines.append(f"| {v} | {p['i']}–{p['j']} | {1e3 * p['offset']:+.4f} | {1e3 * p['std']:.4f} | "
                             f"{1e3 * p['jk_std']:.4f} | {p['jk_std'] / p['std']:.2f} |")
        lines.append("")
    sw = CACHE / "swap_none.json"
    if sw.exists():
        lines += ["## The reference's role: each pair with the other IMU as reference (`--step swap`)", "",
                  "| pair | o_j − o_i, i reference (ms) | −(o_i − o_j), j reference (ms) | difference / pair std |",
                  "|---|---|---|---|"]
        for p in json.loads(sw.read_text())["pairs"]:
            f, b = p["forward"], p["back"]
            lines.append(f"| {p['i']}–{p['j']} | {1e3 * f['offset']:+.4f} ± {1e3 * f['std']:.4f} | "
                         f"{-1e3 * b['offset']:+.4f} ± {1e3 * b['std']:.4f} | "
                         f"{(f['offset'] + b['offset']) / max(f['std'], b['std']):+.2f} |")
        lines.append("")
    lines += ["## Reading", "", "READING", ""]
    doc = REPO / "experiments" / "rig_mimu_diagnose.md"
    old = doc.read_text() if doc.exists() else ""
    if "## Reading" in old:  # the reading is written by hand from the tables; keep it across regenerations
        lines = lines[:-4] + [old[old.index("## Reading"):].rstrip("\n"), ""]
    outputs.write_text(doc, "\n".join(lines) + "\n")
    print("\n".join(lines))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--step", choices=("map", "fits", "swap", "jackknife", "report"), required=True)
    ap.add_argument("--variant", choices=VARIANTS, default="none")
    args = ap.parse_args(argv)
    if args.step == "report":
        return report()
    torch.set_num_threads(1)
    sub = window(import_mimu(DATA / "exp_1" / "data.bin.gz"), 30.0)
    if args.step == "map":
        outputs.write_json(CACHE / "map.json", _map_rows(sub))
    elif args.step == "fits":
        step_fits(_variant_data(sub, args.variant), args.variant)
    elif args.step == "swap":
        step_swap(_variant_data(sub, args.variant), args.variant)
    else:
        step_jackknife(_variant_data(sub, args.variant), args.variant)


if __name__ == "__main__":
    main()
