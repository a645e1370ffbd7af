#!/usr/bin/env python3
"""Probe (issue #30, angjerk_cal): does the board's unresolved ANGULAR jerk, loaded on each triad by
its centred data age times its lever arm (rows d_kt [r_k − r̄]×,
:func:`accel_bayes.model.unresolved_cov.rotational_loadings`), gain likelihood beside the linear jerk?

Per case, ``calibrate(rec, model=report.json)`` is run up to its per-sample-covariance step (the
noise step, the MAP and the model's gyro posterior exactly as ``calibrate --model`` makes them);
there, on the same likelihood at the MAP positions and ω̄, the scales are fitted by type-II ML
(:func:`accel_bayes.model.unresolved_fit.fit_unresolved_scales`) twice: the jerk alone (today's
model), and the jerk with the angular jerk (rank-6 loading, separate scale per |ω| band, the lever
arms the recording's nominal positions).  Reported: the gain in nats per sample, the fitted
scales (physical units: times the noise model's per-sample scale, median per band), and for the
concealed cases the generator's truth: the RMS per axis of ω̈ of the vibration and impacts (the
motion's ω̈ less the hand motion's, at the samples used, per band), which the outputs do not resolve.

    PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/angjerk_probe.py --cases 15,20,3,6 --exps 1

Writes ``experiments/angjerk_probe.md`` and ``experiments/out/angjerk_probe/summary.json``.
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent
DOC = ROOT / "angjerk_probe.md"


def probe(rec, report, truth_omega_ddot=None) -> dict:
    """The two type-II fits at calibrate's per-sample-covariance step (module docstring)."""
    from accel_bayes.model.likelihood import RaoBlackwellLikelihood
    from accel_bayes.model.unresolved_fit import fit_unresolved_scales

    out = {}

    def step(_build, lik, terms, omega_norm, sample_scale, map_res, nominal_acc, prior_std, **_):
        base = RaoBlackwellLikelihood(lik.acc, lik.omega, lik.acc_noise_std, 1, reference=lik.reference,
                                      phi_prior=lik.phi_prior, prepared=lik.prepared)
        p = terms.parameters
        band = torch.bucketize(torch.as_tensor(omega_norm, dtype=torch.float64),
                               torch.as_tensor(p["omega_edges"], dtype=torch.float64), right=True)
        pos0 = torch.as_tensor(map_res.positions, dtype=torch.float64)
        s_t = torch.as_tensor(np.asarray(sample_scale, dtype=np.float64))
        t0 = time.perf_counter()
        fit = fit_unresolved_scales(base, terms.age_acc, band, pos0, lever=nominal_acc)
        nb = len(fit.jerk_rms)
        phys = lambda v: [float((v[b] * s_t[band == b]).median()) if bool((band == b).any()) else None  # noqa: E731
                          for b in range(nb)]
        out.update(T=int(base.T), A=int(base.A), fit_seconds=time.perf_counter() - t0,
                   band_samples=[int((band == b).sum()) for b in range(nb)],
                   omega_edges=[float(e) for e in p["omega_edges"]],
                   loglik_jerk=fit.loglik_no_angjerk, loglik_both=fit.loglik, loglik_flat=fit.loglik_flat,
                   gain_nats_per_sample=fit.gain_angjerk / base.T,
                   gain_jerk_nats_per_sample=(fit.loglik_no_angjerk - fit.loglik_flat) / base.T,
                   angjerk_rms_fitted=phys(fit.angjerk_rms), jerk_rms_fitted_both=phys(fit.jerk_rms),
                   lever_rms_m=float((nominal_acc - nominal_acc.mean(0)).norm(dim=-1).square().mean().sqrt()),
                   age_rms_s=float((terms.age_acc - terms.age_acc.mean(-1, keepdim=True)).square().mean().sqrt()))
        if truth_omega_ddot is not None:
            wdd = truth_omega_ddot(terms.time.numpy())  # (T, 3)
            out["truth_angjerk_rms_per_axis"] = [float(np.sqrt((wdd[(band == b).numpy()] ** 2).mean()))
                                                 if bool((band == b).any()) else None for b in range(nb)]

    from experiments._percov_step import at_percov_step

    at_percov_step(rec, report, step)
    return out


def vibration_omega_ddot(truth):
    """t (N,) s → ω̈ (N, 3) rad/s³ (body frame) of the vibration and impacts: the motion's ω̈ less
    that of the same motion without them, by central differences of ω̇ (h = 10 µs)."""
    from experiments.clockgen.cases import motion_of

    full = motion_of(truth)
    hand = motion_of(truth)
    hand.rot_vib = hand.rot_imp = hand.pos_vib = hand.pos_imp = None
    h = 1e-5

    def wdd(m, t):
        return (m.at(t + h)["dw"] - m.at(t - h)["dw"]) / (2 * h)

    return lambda t: wdd(full, t) - wdd(hand, t)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default="15,20,3,6", help="concealed clock seeds (percov_conceal's cache)")
    ap.add_argument("--exps", default="1", help="MIMU experiments (reports in --reports)")
    ap.add_argument("--conceal", type=Path, default=ROOT / "out" / "percov_conceal")
    ap.add_argument("--reports", type=Path, default=ROOT / "out" / "mimu_mismatch")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "angjerk_probe")
    args = ap.parse_args(argv)
    from accel_bayes.data.outputs import write_json, write_text
    from experiments.percov_conceal import case_recording

    args.out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    rows = []
    for seed in [int(s) for s in args.cases.split(",") if s]:
        f = args.out / f"clock-{seed:03d}.json"
        if not f.exists():
            case = json.loads((args.conceal / f"clock-{seed:03d}" / "case.json").read_text())
            rec, truth, _ = case_recording(seed, case["duration"], case["mount_std_m"], case["acc_intrinsics"])
            r = probe(rec, args.conceal / f"clock-{seed:03d}" / "report.json", vibration_omega_ddot(truth))
            write_json(f, {"case": f"clock-{seed:03d}", "board": case["board"], "rate_hz": case["f_host"], **r})
        rows.append(json.loads(f.read_text()))
    for exp in [int(s) for s in args.exps.split(",") if s]:
        f = args.out / f"exp_{exp}.json"
        if not f.exists():
            from accel_bayes.data.mimu import import_mimu
            from experiments._data import data_dir
            rec = import_mimu(Path(data_dir()) / f"exp_{exp}" / "data.bin.gz")
            r = probe(rec, args.reports / f"exp_{exp}" / "report.json")
            write_json(f, {"case": f"exp_{exp}", "board": "mimu4444 (real)", "rate_hz": None, **r})
        rows.append(json.loads(f.read_text()))
    write_json(args.out / "summary.json", rows)
    from experiments._reading import READING_MARKER, kept_reading

    write_text(DOC, document(rows, time.perf_counter() - t_start) + "\n" + READING_MARKER + kept_reading(DOC))
    print(f"wrote {DOC}")
    return 0


def _fmt(v, f="{:.3g}"):
    return "—" if v is None else f.format(v)


def document(rows, seconds) -> str:
    now = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    L = ["# angjerk_probe — the board's unresolved angular jerk beside the linear jerk (issue #30, angjerk_cal)", "",
         f"Regenerate: `PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/angjerk_probe.py --cases 15,20,3,6 "
         f"--exps 1` ({now}, {platform.machine()} {platform.system()}, shared 2-core CPU, nice 5; cached per case in "
         f"`experiments/out/angjerk_probe/`; this invocation {seconds:.0f} s).", "",
         "What runs (the script's docstring): `calibrate(rec, model=report.json)` up to its per-sample-covariance "
         "step; there, at the MAP positions and ω̄, the scales by type-II ML with the jerk alone and with the jerk "
         "and the angular jerk (rank 6, own scale per |ω| band, lever arms = nominal positions). Gain = "
         "(log-likelihood with both − with the jerk alone) / T. Truth (concealed cases): RMS per axis of the "
         "vibration's and impacts' ω̈ at the samples used, per band.", "",
         "| case | board | rate Hz | T | A | jerk gain over flat (nats/sample) | **angular-jerk gain (nats/sample)** "
         "| ω̈ scale fitted per band (rad/s³) | ω̈ truth RMS per axis per band (rad/s³) | jerk fitted with it (m/s³) "
         "| fit s |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        L.append(f"| {r['case']} | {r['board']} | {_fmt(r['rate_hz'])} | {r['T']} | {r['A']} | "
                 f"{r['gain_jerk_nats_per_sample']:.3f} | **{r['gain_nats_per_sample']:.3f}** | "
                 f"{', '.join(_fmt(v) for v in r['angjerk_rms_fitted'])} | "
                 f"{', '.join(_fmt(v) for v in r.get('truth_angjerk_rms_per_axis') or [None])} | "
                 f"{', '.join(_fmt(v) for v in r['jerk_rms_fitted_both'])} | {r['fit_seconds']:.0f} |")
    L += ["", "Band samples per case: " + "; ".join(f"{r['case']} {r['band_samples']}" for r in rows) + ".", ""]
    return "\n".join(L) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
