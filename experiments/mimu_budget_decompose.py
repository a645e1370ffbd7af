#!/usr/bin/env python3
"""Where the accelerometer excess of the six MIMU4444 recordings goes (issue #27, §7.2 budget).

Reads the detections cached by ``experiments/mimu_mismatch.py --stage detect`` (``OUT/exp_i/state.pt``:
the final prepared recording, the final fit and the accepted clocks) and decomposes what the final
mean model leaves over the stated noise, per sensor and per |ω| and |ω̇| band, into what each
variance model of the unresolved motion names (each fitted alone; the final model's own random
effects — 97e5674's timing wanders — shown beside them as the competing account):

* **bands**   — the term as 97e5674 fitted it: y_kt = d_kt m_t + e_kt, m_t ~ N(0, s²_b I₃) per |ω|
  band b, e_kt white per IMU *and band* (the white part is not named);
* **cells**   — the same with s² per |ω| × |ω̇| cell and one white variance per IMU;
* **cells + age error** — y_kt = (d_kt + ε_kt) m_t + e_kt, ε_kt ~ (0, e²) iid per IMU and sample:
  the part of each IMU's sampling instant its clock's sawtooth does not give.  Named: s²(d² + e²).

d_kt is IMU k's clock data age centred over the IMUs (s); y the leverage-corrected residual in the
array frame.  Each model's named variance is given as a share of the observed excess
Σ(y² − σ²) of the band (the residuals of the final mean model, so these shares are not the report's
b/a, whose a is the nominal model's).  Besides, per experiment: how bursty the excess is (share of
the power in the top 5 % of samples; lag-5 autocorrelation of the log per-sample power), how much
of a burst sample lies along the ages (the per-sample least-squares m̂_t, against the ages
permuted), the remainder's cross-IMU correlation after the cells + age-error model, the change of
the accelerometer excess with the datasheet's acc − gyro filter delay Δ = +0.2 ms applied to the
resolved motion (−Δ·ȧ), and how close the outputs come to the ±16 g range.

    python experiments/mimu_budget_decompose.py --out experiments/out/mimu_mismatch_97e5674 \\
        --doc experiments/mimu_budget_decompose.md
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent

DATASHEET_DELAY_S = 0.2e-3  # MPU-6050/9150 DLPF setting 2: acc 3.0 ms − gyro 2.8 ms


def _arrays(prep, fit, clocks, sensor):
    from accel_bayes.mismatch.clock import data_age
    from accel_bayes.mismatch.vibration import array_residuals

    a, ok = array_residuals(prep, fit, sensor)
    has = torch.zeros(prep.K, dtype=torch.bool)
    has[sorted({int(c.imu) for c in clocks})] = True
    w = (ok & has[None, :]).to(a.dtype)
    age = data_age(clocks, prep.time, prep.K)
    n = w.sum(1, keepdim=True).clamp_min(1)
    d = (age - (age * w).sum(1, keepdim=True) / n) * w
    sig2 = (prep.sigma_acc if sensor == "acc" else prep.sigma_gyro) ** 2
    return a[:, has], d[:, has], w[:, has], sig2[has]


def _bands(fit):
    from accel_bayes.mismatch.budget import band_edges

    x = fit.x.detach().numpy()
    out = []
    for v in (np.linalg.norm(x[:, 0:3], axis=1), np.linalg.norm(x[:, 3:6], axis=1)):
        out.append(torch.as_tensor(np.digitize(v, band_edges(v)), dtype=torch.long))
    return out


def decompose(state: dict) -> dict:
    """The decomposition of the module docstring for one cached detection."""
    from accel_bayes.mismatch.budget import predicted_extra_variance
    from accel_bayes.mismatch.unresolved import fit_grid, fit_scales

    prep, fit = state["prep"], state["refined"]
    clocks = [e for e in state["fixed"] if e.name == "sampling_clock"]
    lo, ld = _bands(fit)
    cell = lo * 5 + ld
    known = dict(zip(("acc", "gyro"), (v.mean(-1) for v in predicted_extra_variance(prep, fit))))
    has = torch.zeros(prep.K, dtype=torch.bool)
    has[sorted({int(c.imu) for c in clocks})] = True
    out = {"clock_imus": sorted(int(c.imu) for c in clocks), "random_effects": [e.label() for e in fit.effects
                                                                                  if e.kind == "random"]}
    for sensor in ("acc", "gyro"):
        a, d, w, sig2 = _arrays(prep, fit, clocks, sensor)
        exc = ((a ** 2).sum(-1) / 3 - sig2[None, :]) * w
        _, _, ls, _, _, _ = fit_scales(a, d, w, lo, 5, std=False)
        # the final model's own variance effects (noise factors, random timing: the competitors)
        named = {"own random effects": known[sensor][:, has] * w, "bands": torch.exp(ls)[lo][:, None] * d ** 2 * w}
        g = fit_grid(a, d, w, cell, 25, v_floor=sig2, std=False)
        named["cells"] = g.s2_no_age_error[cell][:, None] * d ** 2 * w
        named["cells + age error"] = g.s2[cell][:, None] * (d ** 2 + g.e2) * w

        def share(v, sel):
            return float(v[sel].sum() / exc[sel].sum())

        rows = []
        for name, lab in (("|omega|", lo), ("|omega_dot|", ld)):
            for b, (p0, p1) in enumerate(((0, 25), (25, 50), (50, 75), (75, 90), (90, 100))):
                sel = lab == b
                rows.append({"regime": f"{name} {p0}-{p1}%", "excess": float(exc[sel].sum() / w[sel].sum()),
                             **{k: share(v, sel) for k, v in named.items()}})
        allsel = torch.ones(len(lo), dtype=torch.bool)
        rows.insert(0, {"regime": "all", "excess": float(exc.sum() / w.sum()), **{k: share(v, allsel) for k, v in named.items()}})
        # bursts: the per-sample power's concentration and persistence
        Q = (a ** 2).sum((1, 2)).numpy()
        order = np.argsort(-Q)
        top = order[: max(len(Q) // 20, 1)]
        lq = np.log(Q + 1e-300) - np.log(Q + 1e-300).mean()
        # a burst sample's power along the ages (least-squares m̂_t), against the ages permuted
        dd = (d ** 2).sum(1).clamp_min(1e-30)

        def along(dv):
            m = torch.einsum("tk,tki->ti", dv, a) / (dv ** 2).sum(1).clamp_min(1e-30)[:, None]
            return ((m ** 2).sum(1) * (dv ** 2).sum(1)).numpy() / np.maximum(Q, 1e-300)

        perm = torch.as_tensor(np.random.default_rng(0).permutation(len(Q)))
        # the remainder after the cells + age-error model (its BLUP of m_t taken off): cross-IMU correlation
        s2 = g.s2[cell]
        v = g.v[None, :] + g.e2 * s2[:, None]
        inv = w / v
        c = (d ** 2 * inv).sum(1)
        m_hat = (s2 / (1 + s2 * c))[:, None] * torch.einsum("tk,tki->ti", d * inv, a)
        r = (a - d[..., None] * m_hat[:, None, :]).permute(0, 2, 1).reshape(-1, a.shape[1]).numpy()
        C = np.corrcoef(r.T)
        off = C[~np.eye(len(C), dtype=bool)]
        out[sensor] = {"rows": rows, "age_error_rms_s": float(np.sqrt(g.e2)), "white_var": g.v.tolist(),
                       "loglik": {"cells + age error": g.loglik, "cells": g.loglik_no_age_error},
                       "top5_power_share": float(Q[top].sum() / Q.sum()),
                       "log_power_autocorr_lag1": float((lq[1:] * lq[:-1]).mean() / lq.var()),
                       "log_power_autocorr_lag5": float((lq[5:] * lq[:-5]).mean() / lq.var()),
                       "top5_along_ages": float(along(d)[top].mean()), "top5_along_permuted": float(along(d[perm])[top].mean()),
                       "all_along_ages": float(along(d).mean()),
                       "remainder_corr_mean_abs": float(np.abs(off).mean()), "remainder_corr_range": [float(off.min()), float(off.max())]}
        del dd
    # the datasheet filter delay: −Δ·ȧ on the accelerometers (resolved motion), its effect on their power
    a, _, w, sig2 = _arrays(prep, fit, clocks, "acc")
    from accel_bayes.physics.geometry import quat_to_matrix

    R = quat_to_matrix(torch.as_tensor(prep.q, dtype=a.dtype))
    rate = torch.einsum("kji,tkj->tki", R, fit.ctx.acc_rate)[:, has] * w[..., None]
    p0 = float((a ** 2).sum())
    out["filter_delay"] = {"delta_s": DATASHEET_DELAY_S,
                           "power_change": float(((a + DATASHEET_DELAY_S * rate) ** 2).sum() / p0 - 1),
                           "rms_shift_m_s2": float((DATASHEET_DELAY_S * rate).pow(2).sum(-1).mean().sqrt())}
    yr = prep.rec.acc_range if getattr(prep.rec, "acc_range", None) else None
    ymax = prep.y_acc.abs().amax((1, 2)).numpy()
    out["range"] = {"acc_range_m_s2": yr, "max_abs_m_s2": float(ymax.max()),
                    "share_over_90pct_range": float((ymax > 0.9 * yr).mean()) if yr else None,
                    "dropped_clipped": int(prep.n_dropped_clipped)}
    return out


def markdown(res: dict, cmd: str, out_dir: Path) -> str:
    now = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    L = ["# Where the accelerometer excess goes: the unresolved motion's variance models on the six recordings "
         "(issue #27)\n",
         f"Generated {now} on {platform.machine()} {platform.system()} by `{cmd}`, from the detections cached in "
         f"`{out_dir}` (each experiment's final prepared recording, final fit and accepted clocks). "
         "Shares are of the excess over the stated noise that the final mean model leaves, per channel-sample; "
         "they are not the report's b/a, whose a is the nominal model's. The final model's own variance effects "
         "(noise factors, random timing) are a competing account of the same excess, shown beside the three "
         "models, each fitted alone. "
         "Module docstring of `experiments/mimu_budget_decompose.py`: the three models.\n"]
    for sensor in ("acc", "gyro"):
        L += [f"\n## {sensor}: share of the excess each model names\n",
              "| exp | regime | excess | final model's random effects | bands (97e5674's term) | cells | cells + age error |",
              "|---|---|---|---|---|---|---|"]
        for i, r in res.items():
            for row in r[sensor]["rows"]:
                L.append(f"| {i} | {row['regime'].replace('|', chr(92) + '|')} | {row['excess']:.4g} | {row['own random effects']:.2f} | {row['bands']:.2f} | "
                         f"{row['cells']:.2f} | "
                         f"{row['cells + age error']:.2f} |")
    L += ["\n## What the remainder looks like\n",
          "| exp | sensor | age error rms (ms) | Δlog L age error | top 5 % samples' share of the power | log-power autocorr. lag 1 / 5 "
          "| top 5 %: share along the ages (permuted) | all: along the ages | remainder cross-IMU corr. mean \\|r\\| (range) |",
          "|---|---|---|---|---|---|---|---|---|"]
    for i, r in res.items():
        for s in ("acc", "gyro"):
            x = r[s]
            L.append(f"| {i} | {s} | {x['age_error_rms_s'] * 1e3:.3f} | {x['loglik']['cells + age error'] - x['loglik']['cells']:.4g} | "
                     f"{x['top5_power_share']:.2f} | {x['log_power_autocorr_lag1']:.2f} / {x['log_power_autocorr_lag5']:.2f} | "
                     f"{x['top5_along_ages']:.2f} ({x['top5_along_permuted']:.2f}) | {x['all_along_ages']:.2f} | "
                     f"{x['remainder_corr_mean_abs']:.2f} ({x['remainder_corr_range'][0]:+.2f} to {x['remainder_corr_range'][1]:+.2f}) |")
    L += ["\n## Filter delay and range\n",
          "| exp | random effects in the final model | acc power change with −Δ·ȧ, Δ = +0.2 ms | rms of Δ·ȧ (m/s²) | max \\|acc\\| (m/s²) / range | share of samples over 90 % of the range | samples dropped as clipped |",
          "|---|---|---|---|---|---|---|"]
    for i, r in res.items():
        f, g = r["filter_delay"], r["range"]
        L.append(f"| {i} | {', '.join(r['random_effects']) or '–'} | {f['power_change']:+.4%} | {f['rms_shift_m_s2']:.3g} | "
                 f"{g['max_abs_m_s2']:.1f} / {g['acc_range_m_s2'] or float('nan'):.1f} | {g['share_over_90pct_range'] or 0:.4f} | {g['dropped_clipped']} |")
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=HERE / "out" / "mimu_mismatch")
    ap.add_argument("--experiments", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6])
    ap.add_argument("--doc", type=Path, default=None)
    args = ap.parse_args(argv)
    from accel_bayes.threads import torch_threads

    res = {}
    with torch_threads(1):
        for i in args.experiments:
            p = args.out / f"exp_{i}" / "state.pt"
            if not p.exists():
                print(f"exp_{i}: no cached detection ({p})")
                continue
            t0 = time.perf_counter()
            res[i] = decompose(torch.load(p, weights_only=False))
            print(f"exp_{i}: {time.perf_counter() - t0:.0f} s; acc all: " + ", ".join(
                f"{k} {v:.2f}" for k, v in res[i]["acc"]["rows"][0].items() if k not in ("regime", "excess")), flush=True)
    (args.out / "decompose.json").write_text(json.dumps(res, indent=1, default=float))
    if args.doc is not None:
        cmd = "python experiments/mimu_budget_decompose.py " + " ".join(argv if argv is not None else sys.argv[1:])
        args.doc.write_text(markdown(res, cmd, args.out.relative_to(HERE.parent) if args.out.is_relative_to(HERE.parent) else args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
