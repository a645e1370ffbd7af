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
* ``events``: the window's moves one at a time (the jackknife blocks whose board-mean RMS |ω̇|
  exceeds :data:`EVENT_WDOT`, each cut out with its neighbours' half blocks): the eight-IMU rig and
  the pairs of :data:`PAIRS` on each, the pairs study's z per move, and how far the eight-IMU offsets
  of the moves differ (a constant offset says: within their stds).
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
import itertools  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
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
from experiments._stamp import run_stamp  # noqa: E402

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


def _block_motion(sub):
    """Per jackknife block: RMS |ω| (rad/s) and RMS |ω̇| (rad/s², finite differences) of the board's
    mean gyro — where the timing information is."""
    w = np.nanmean(np.asarray(sub.gyro, dtype=float), axis=1)
    wd = np.gradient(w, np.asarray(sub.time, dtype=float), axis=0)
    edges = np.linspace(0, len(w), N_BLOCKS + 1).astype(int)
    return [{"t0": float(sub.time[a]), "rms_w": float(np.sqrt((w[a:b] ** 2).sum(1).mean())),
             "rms_wdot": float(np.sqrt((wd[a:b] ** 2).sum(1).mean()))} for a, b in zip(edges[:-1], edges[1:])]


#: rad/s², board-mean RMS |ω̇| of a jackknife block that holds a move (exp_1's rest blocks: 0.12)
EVENT_WDOT = 1.0


def _slice(sub, a: int, b: int):
    """``sub`` cut to its rows a:b."""
    out = sub.copy()
    for name in ("time", "acc", "gyro", "acc_clipped", "gyro_clipped", "acc_flagged", "gyro_flagged", "segment",
                 "imu_time_offset"):
        v = getattr(out, name)
        if v is not None:
            setattr(out, name, np.asarray(v)[a:b].copy())
    return out


def step_events(sub, variant):
    settings = _settings(variant)
    blocks = _block_motion(sub)
    n = len(sub.time)
    edges = np.linspace(0, n, N_BLOCKS + 1).astype(int)
    half = (edges[1] - edges[0]) // 2
    out = {"variant": variant, "events": []}
    for b, blk in enumerate(blocks):
        if blk["rms_wdot"] < EVENT_WDOT:
            continue
        a, e = max(edges[b] - half, 0), min(edges[b + 1] + half, n)
        cut = _slice(sub, a, e)
        r = fit_rig(cut, settings)
        ev = {"block": b, "t0": float(cut.time[0]), "t1": float(cut.time[-1]), "reason": r.reason,
              "seconds": r.seconds, "chi2_per_dof": r.chi2_per_dof, "time_offset": r.time_offset.tolist(),
              "diff": {f"{i}-{j}": offset_difference(r, i, j) for i, j in itertools.combinations(range(sub.K), 2)},
              "pairs": [_pair(cut, i, j, settings) for i, j in PAIRS]}
        out["events"].append(ev)
        print({k: ev[k] for k in ("block", "reason", "seconds")}, flush=True)
    outputs.write_json(CACHE / f"events_{variant}.json", out)


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
             "Regenerate (each `PYTHONPATH=. python3 experiments/rig_mimu_diagnose.py …`): `--step map`; `--step fits "
             "--variant V` for V in none, gyro, gyro_timing, acc_delay; `--step jackknife --variant none`; `--step events "
             "--variant none`; `--step swap --variant none`; then `--step report`; about 35 min of fits in all "
             f"({run_stamp()}).  exp_1, the pairs study's 30 s window.", ""]
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
        lines += ["## Refits with the rig model's optional terms (`--step fits`)", "",
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
                  "| variant | pair | offset (ms) | Laplace std (ms) | jackknife std (ms) | ratio | offset without block "
                  "b (ms), b = 0…9 |", "|---|---|---|---|---|---|---|"]
        for v, d in jks.items():
            for p in d["pairs"]:
                loo = " ".join(f"{1e3 * x:+.3f}" for x in p["loo"])
                lines.append(f"| {v} | {p['i']}–{p['j']} | {1e3 * p['offset']:+.4f} | {1e3 * p['std']:.4f} | "
                             f"{1e3 * p['jk_std']:.4f} | {p['jk_std'] / p['std']:.1f} | {loo} |")
        bl = CACHE / "blocks.json"
        if bl.exists():
            lines += ["", "Motion per block (board mean gyro, `--step map`): " + "; ".join(
                f"{b}: |ω| {r['rms_w']:.3f} rad/s, |ω̇| {r['rms_wdot']:.2f} rad/s²"
                for b, r in enumerate(json.loads(bl.read_text()))) + "."]
        lines.append("")
    evp = CACHE / "events_none.json"
    if evp.exists():
        evs = json.loads(evp.read_text())["events"]
        lines += ["## One move at a time (`--step events`)", "",
                  "The window's timing information sits in its moves: " + "; ".join(
                      f"block {e['block']} ({e['t0']:.1f}–{e['t1']:.1f} s, eight-IMU LM {e['reason']}, "
                      f"χ²/dof {e['chi2_per_dof']:.2f})" for e in evs) + ".  Per move, the pairs study's z and the "
                  "eight-IMU o_j − o_i; last column: the two moves' eight-IMU values apart in their combined std.", "",
                  "| pair | " + " | ".join(f"z (block {e['block']})" for e in evs) + " | " +
                  " | ".join(f"eight-IMU (block {e['block']}, ms)" for e in evs) + " | moves apart (std) |",
                  "|---|" + "---|" * (2 * len(evs) + 1)]
        zs_ev = {e["block"]: [] for e in evs}
        apart = []
        for a, (i, j) in enumerate(PAIRS):
            cz, co, vals = [], [], []
            for e in evs:
                z, d8, s8 = _z(e["pairs"][a], e)
                zs_ev[e["block"]].append(z)
                cz.append(f"{z:+.2f}")
                co.append(f"{1e3 * d8:+.4f} ± {1e3 * s8:.4f}")
                vals.append((d8, s8))
            sep = ((vals[0][0] - vals[-1][0]) / math.hypot(vals[0][1], vals[-1][1])) if len(vals) > 1 else float("nan")
            apart.append(sep)
            lines.append(f"| {i}–{j} | " + " | ".join(cz) + " | " + " | ".join(co) + f" | {sep:+.1f} |")
        lines += ["", "z RMS per move: " + ", ".join(
            f"block {b} {math.sqrt(np.nanmean(np.square(v))):.2f}" for b, v in zs_ev.items()) +
            f"; the moves' eight-IMU offsets apart by RMS {math.sqrt(np.nanmean(np.square(apart))):.1f} combined std.", ""]
        if "none" in fits and len(evs) == 2:
            # Δ = pair − eight-IMU on each move: two disjoint estimates per pair; their half squared
            # difference estimates Var(Δ) of one move without the model's stds, and the whole window's Δ
            # (both moves) has about half that variance
            dd = []
            for a, p in enumerate(PAIRS):
                d_e = [e["pairs"][a]["offset"] - e["diff"][f"{p[0]}-{p[1]}"][0] for e in evs]
                dd.append((d_e[0] - d_e[1]) ** 2 / 2)
            s_move = math.sqrt(float(np.mean(dd)))
            full_d = np.array([fits["none"]["pairs"][a]["offset"] - fits["none"]["full"]["diff"][f"{i}-{j}"][0]
                               for a, (i, j) in enumerate(PAIRS)])
            z_ind = full_d / (s_move / math.sqrt(2))
            lines += [f"An estimate of Var(Δ) that does not use the model's stds: over these {len(PAIRS)} pairs the "
                      f"spread of Δ between the two moves gives a per-move std of Δ of {1e3 * s_move:.3f} ms, so "
                      f"{1e3 * s_move / math.sqrt(2):.3f} ms for the whole window's Δ (against √(s_pair² − s_8²) of "
                      "0.007–0.02 ms); on that scale the whole window's Δ (variant none) has RMS "
                      f"{math.sqrt(float(np.mean(z_ind ** 2))):.2f} (max |·| {np.abs(z_ind).max():.2f}).", ""]
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
    ap.add_argument("--step", choices=("map", "fits", "swap", "events", "jackknife", "report"), required=True)
    ap.add_argument("--variant", choices=VARIANTS, default="none")
    args = ap.parse_args(argv)
    if args.step == "report":
        return report()
    torch.set_num_threads(1)
    sub = window(import_mimu(DATA / "exp_1" / "data.bin.gz"), 30.0)
    if args.step == "map":
        outputs.write_json(CACHE / "map.json", _map_rows(sub))
        outputs.write_json(CACHE / "blocks.json", _block_motion(sub))
    elif args.step == "fits":
        step_fits(_variant_data(sub, args.variant), args.variant)
    elif args.step == "events":
        step_events(_variant_data(sub, args.variant), args.variant)
    elif args.step == "swap":
        step_swap(_variant_data(sub, args.variant), args.variant)
    else:
        step_jackknife(_variant_data(sub, args.variant), args.variant)


if __name__ == "__main__":
    main()
