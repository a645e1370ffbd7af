#!/usr/bin/env python3
"""Why the untempered geometry flips on concealed clock recordings (issue #30 item 4): the generator's
pieces ablated one at a time, the noise step's MAPs compared, the misfit measured noise-free.

Cases: ``clock`` seeds of ``experiments/percov_conceal.py`` whose untempered geometry was reflected or
mis-sized (clock-001, -002, -009, -010, -019), built by its :func:`case_recording` (accelerometer
intrinsics known, nominal positions the truth moved by 0.5 mm).  Rows: the case as drawn; each
motion piece removed after the draw (``draw_case(drop=...)``: every other draw — hand motion,
clocks, errors, noise — unchanged); the DLPF off; the ``twin`` kind (every tick on the read
instant: no data ages, no read skew or jitter); the gyro linear errors off.

Per row, what ``calibrate``'s noise step does with estimated noise (``pipelines.calibrate_steps``):
the flat-φ MAP with the type-II ML noise levels (``fit_map_with_noise``), then the MAP under the
empirical φ prior started (a) from that flat MAP — the pipeline before this issue — and (b) from the
nominal design; the pipeline now keeps the higher of the two (``_prior_map``).  Scale =
Σ estimate·truth / Σ truth² over the free coordinates (1 right; < 0 reflected).

Noise-free misfit (``misfit``): the same row drawn without noise, quantisation and linear errors; per
sample the accelerometers (array frame) minus the centripetal prediction U(ω̄)θ at the TRUE positions
(ω̄ the gyros' mean), projected orthogonally to the span of H(θ) (the common ω̇ and specific force the
likelihood integrates out); RMS over samples with |ω̄| > 0.5 rad/s and coordinates, against the RMS
of the projected centripetal signal itself.  ρ = Σ‖P U θ‖² / (12 T σ̄²) with σ̄² the mean fitted noise
variance: along θ = cθ*, the flat likelihood's data term ½a(c − 1)² and the Occam term 3T·log|c|
(M's ω̇ block scales as c²) have a local mode near c = 1 only if a ≥ 12T, i.e. ρ ≥ 1.

    PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/vibgeom_probe.py --seeds 1,2,9,10,19
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
import warnings
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent
DOC = ROOT / "vibgeom_probe.md"
MOUNT_STD = 5e-4
ROWS = {
    "as drawn": {},
    "rot. vibration off": {"drop": ("rot_vib",)},
    "transl. vibration off": {"drop": ("pos_vib",)},
    "rot. impacts off": {"drop": ("rot_imp",)},
    "transl. impacts off": {"drop": ("pos_imp",)},
    "rot. vibration + impacts off": {"drop": ("rot_vib", "rot_imp")},
    "all vibration + impacts off": {"drop": ("rot_vib", "pos_vib", "rot_imp", "pos_imp")},
    "DLPF off": {"filtered": False},
    "twin (no ages, skew, jitter)": {"kind": "twin"},
    "gyro linear errors off": {"gyro_linear": False},
}


def _recording(seed, kw, duration=20.0, **extra):
    """The case as ``percov_conceal`` builds it (intrinsics known, mounted nominal), with ``kw``'s pieces."""
    from experiments.clockgen import draw_case
    from experiments.percov_conceal import known_acc_intrinsics, mounted

    kw = dict(kw, **extra)
    kind = kw.pop("kind", "clock")
    rec, truth = draw_case(kind, seed, duration=duration, **kw)
    rec = known_acc_intrinsics(rec, truth)
    rec, pos = mounted(rec, truth, MOUNT_STD, seed)
    return rec, truth, pos


def _scale(positions, pos, ref) -> float:
    est = np.delete(np.asarray(positions) - np.asarray(positions)[ref], ref, 0).ravel()
    tru = np.delete(pos - pos[ref], ref, 0).ravel()
    return float(est @ tru / (tru @ tru))


def noise_step_fits(rec, report=None) -> dict:
    """calibrate's noise step (estimated noise, its default φ prior) on ``rec``, the prior MAP fitted
    from both starts: the flat MAP, both refits, their log posteriors and the start the pipeline's
    rule (:data:`MODE_MARGIN_NATS`) keeps.  ``report``: a mismatch report whose fused gyro posterior
    replaces the calibrated one (the ``--model`` path)."""
    from accel_bayes.inference.map import fit_map
    from accel_bayes.inference.noise_fit import fit_map_with_noise
    from accel_bayes.model.likelihood import RaoBlackwellLikelihood
    from accel_bayes.model.noise import scale_samples
    from accel_bayes.pipelines.calibrate import _model_gyro_step
    from accel_bayes.pipelines.calibrate_options import CalibrateOptions
    from accel_bayes.pipelines.calibrate_steps import MODE_MARGIN_NATS, _model_option, _phi_prior_step, _prepare_step
    from accel_bayes.prep.prepared import prepare_recording

    opts = CalibrateOptions()
    pre = _prepare_step(rec, opts)
    lik = RaoBlackwellLikelihood.from_recording(prepare_recording(pre.recording, selection=pre.selection),
                                                num_draws=1, gyro_method="calibrated")
    if report is not None:
        lik, _, _ = _model_gyro_step(lik, pre.recording, _model_option(report))
    nom = torch.as_tensor(pre.recording.nominal_position, dtype=torch.float64)
    kw = dict(reference=lik.reference, prior_mean=nom, prior_std=opts.prior_std)
    flat, nm = fit_map_with_noise(lik.acc, lik.omega.mean, lik.omega.cov, lik.acc_noise_std, bins=opts.noise_bins, **kw)
    s_t = nm.sample_scale(lik.omega.mean.norm(dim=-1).cpu().numpy())
    acc_s, w_s, P_s = scale_samples(lik.acc, lik.omega.mean, lik.omega.cov, s_t)
    std = np.asarray(nm.std, dtype=np.float64)
    prior, _ = _phi_prior_step(acc_s, w_s, std, nom, opts.phi_prior)
    fits = {}
    for name, init, init_w in (("flat start", flat.positions, flat.omega), ("design start", nom, None)):
        fits[name] = fit_map(acc_s, w_s, P_s, std, init_positions=init, init_omega=init_w, on_divergence="ignore",
                             phi_prior=prior, **kw)
    lp = {k: float(v.log_posterior) for k, v in fits.items()}
    chosen = "design start" if lp["design start"] > lp["flat start"] + MODE_MARGIN_NATS else "flat start"
    return {"has_rests": bool(pre.has_rests), "T": int(lik.T), "noise_std": std.tolist(), "reference": lik.reference,
            "flat": flat, "fits": fits, "log_posterior": lp, "chosen": chosen}


def noise_step_maps(seed, kw) -> dict:
    """:func:`noise_step_fits` on a concealed case, the geometry scales against the generator's truth."""
    rec, _, pos = _recording(seed, kw)
    r = noise_step_fits(rec)
    ref = r.pop("reference")
    flat, fits = r.pop("flat"), r.pop("fits")
    return {**r, "flat_scale": _scale(flat.positions, pos, ref),
            "scale": {k: _scale(v.positions, pos, ref) for k, v in fits.items()}}


def _hat(v):
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1), np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def misfit(seed, kw, duration=20.0) -> dict:
    """Noise-free projected misfit and centripetal signal RMS (m/s²) at the true positions (docstring)."""
    from experiments.clockgen import quat_to_matrix

    rec, truth, _ = _recording(seed, kw, duration, noise=False, quantised=False, errors=False)
    pos = np.asarray(truth["position"], dtype=np.float64)
    K = len(pos)
    Q = np.array([quat_to_matrix(q) for q in truth["orientation"]])
    ya = np.einsum("kji,tkj->tki", Q, rec.acc)
    w = np.einsum("kji,tkj->tki", Q, rec.gyro).mean(1)
    sel = np.linalg.norm(w, axis=1) > 0.5
    ya, w = ya[sel], w[sel]
    th = pos - pos[0]
    H = np.concatenate([np.tile(np.eye(3), (K, 1))[None].repeat(len(w), 0),
                        -_hat(th).reshape(1, 3 * K, 3).repeat(len(w), 0)], 2)
    P = np.eye(3 * K) - H @ np.linalg.solve(np.swapaxes(H, 1, 2) @ H, np.swapaxes(H, 1, 2))
    U = _hat(w) @ _hat(w)
    sig = np.einsum("tij,kj->tki", U, th).reshape(len(w), 3 * K)
    sig = np.einsum("tij,tj->ti", P, sig)
    res = np.einsum("tij,tj->ti", P, ya.reshape(len(w), 3 * K)) - sig
    return {"misfit_rms": float(np.sqrt(np.mean(res ** 2))), "signal_rms": float(np.sqrt(np.mean(sig ** 2))),
            "signal_sq_sum": float(np.sum(sig ** 2)), "T": int(sel.sum())}


def mimu_start(exp: int, report: Path | None, out: Path) -> dict:
    """Which start the noise step keeps on MIMU experiment ``exp`` (:func:`noise_step_fits`; with
    ``report``, the ``--model`` path's fused gyro posterior): does the fix change real-data results?"""
    from accel_bayes.data.mimu import import_mimu
    from accel_bayes.data.outputs import write_json
    from experiments._data import data_dir

    f = out / f"mimu-exp_{exp}-{'with' if report else 'without'}.json"
    if f.exists():
        return json.loads(f.read_text())
    t0 = time.perf_counter()
    rec = import_mimu(data_dir() / f"exp_{exp}" / "data.bin.gz")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        r = noise_step_fits(rec, report)
    doc = {"exp": exp, "report": None if report is None else str(report), "T": r["T"], "chosen": r["chosen"],
           "log_posterior": r["log_posterior"], "seconds": time.perf_counter() - t0}
    out.mkdir(parents=True, exist_ok=True)
    write_json(f, doc)
    print(f"exp_{exp} {'with' if report else 'without'}: {doc['chosen']} {doc['log_posterior']}", flush=True)
    return doc


def sandwich_split(seed: int, out: Path) -> dict:
    """Class (2), the no-rest cases calibrated on the stated noise: the sandwich/Laplace std ratio of the
    plain untempered likelihood (flat φ prior, the stated σ; MAP from the design) clustered per channel,
    triad and sample, each without lags and with the Newey–West lags — heteroscedasticity, within-triad,
    cross-triad and time correlation — and the noise-free misfit RMS against the stated σ (m/s²)."""
    from accel_bayes.data.outputs import write_json
    from accel_bayes.inference.map import fit_map
    from accel_bayes.inference.noise_fit import sandwich_inflation
    from accel_bayes.model.likelihood import RaoBlackwellLikelihood
    from accel_bayes.pipelines.calibrate_options import CalibrateOptions
    from accel_bayes.pipelines.calibrate_steps import _prepare_step
    from accel_bayes.prep.prepared import prepare_recording

    f = out / f"sandwich-clock-{seed:03d}.json"
    if f.exists():
        return json.loads(f.read_text())
    rec, _, _ = _recording(seed, {})
    opts = CalibrateOptions()
    pre = _prepare_step(rec, opts)
    lik = RaoBlackwellLikelihood.from_recording(prepare_recording(pre.recording, selection=pre.selection),
                                                num_draws=1, gyro_method="sample_cov")
    nom = torch.as_tensor(pre.recording.nominal_position, dtype=torch.float64)
    kw = dict(reference=lik.reference, prior_mean=nom, prior_std=opts.prior_std)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        res = fit_map(lik.acc, lik.omega.mean, lik.omega.cov, lik.acc_noise_std, on_divergence="ignore", **kw)
        rows = []
        for cluster in ("channel", "triad", "sample"):
            for lags in (0, None):
                sw = sandwich_inflation(lik.acc, lik.omega.mean, lik.omega.cov, lik.acc_noise_std, res, lags=lags,
                                        cluster=cluster, **kw)
                rel = sw.get("std_ratio_relative")
                rows.append({"cluster": cluster, "lags": int(sw["lags"]),
                             "std_ratio_median": float(np.median(sw["std_ratio"])),
                             "std_ratio_max": float(np.max(sw["std_ratio"])),
                             "relative_median": None if rel is None else float(np.median(rel))})
    mf = misfit(seed, {})
    doc = {"seed": seed, "has_rests": bool(pre.has_rests), "stated_std": np.asarray(lik.acc_noise_std).tolist(),
           "misfit_rms": mf["misfit_rms"], "signal_rms": mf["signal_rms"], "rows": rows}
    out.mkdir(parents=True, exist_ok=True)
    write_json(f, doc)
    print(f"sandwich clock-{seed:03d}: {rows}", flush=True)
    return doc


def estimated_noise(seed: int, out: Path, conceal: Path) -> dict:
    """Class (2): ``calibrate --model`` of a no-rest case with its cached report (``conceal``:
    percov_conceal's folder) with the noise levels estimated (``noise="estimate"``, untempered: the
    model refuses κ) instead of the stated σ; scored as percov_conceal scores (2 × (300 + 400), seed 0)."""
    from accel_bayes.data.outputs import write_json
    from accel_bayes.pipelines.calibrate import calibrate
    from experiments.percov_conceal import score

    f = out / f"estimate-clock-{seed:03d}.json"
    if f.exists():
        return json.loads(f.read_text())
    rec, _, pos = _recording(seed, {})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        res = calibrate(rec, chains=2, draws=400, warmup=300, seed=0, progress=False,
                        model=conceal / f"clock-{seed:03d}" / "report.json", noise="estimate")
    sc = score(res.positions, pos)
    z = np.asarray(sc["z"])
    doc = {"seed": seed, "z": sc["z"], "z_rms": float(np.sqrt(np.mean(z ** 2))), "max_abs_z": float(np.abs(z).max()),
           "noise_std": (res.settings.get("noise_model") or {}).get("std")}
    out.mkdir(parents=True, exist_ok=True)
    write_json(f, doc)
    print(f"estimate clock-{seed:03d}: z RMS {doc['z_rms']:.2f}, max {doc['max_abs_z']:.2f}", flush=True)
    return doc


def estimate_markdown(docs, conceal: Path) -> str:
    if not docs:
        return ""
    z = np.concatenate([d["z"] for d in docs])
    L = ["", "## Class (2) with the noise levels estimated instead of stated", "",
         f"`calibrate(rec, model=report.json, noise=\"estimate\")` (`estimated_noise`; reports from `{conceal.name}/`), "
         "untempered: `calibrate --model report.json --noise estimate`. The default \"auto\" uses the stated σ on a "
         "recording without rests (percov_conceal.md's **with** column).", "",
         "| case | z RMS | max \\|z\\| | beyond 4 | fitted σ (m/s², min–max) |", "|---|---|---|---|---|"]
    for d in docs:
        zz = np.asarray(d["z"])
        ns = d["noise_std"] or [float("nan")]
        L.append(f"| clock-{d['seed']:03d} | {d['z_rms']:.2f} | {d['max_abs_z']:.2f} | {int((np.abs(zz) > 4).sum())}/{zz.size} "
                 f"| {min(ns):.3f}–{max(ns):.3f} |")
    L.append(f"| pooled | {np.sqrt(np.mean(z ** 2)):.2f} | {np.abs(z).max():.2f} | {int((np.abs(z) > 4).sum())}/{z.size} | |")
    return "\n".join(L) + "\n"


def sandwich_markdown(docs) -> str:
    if not docs:
        return ""
    L = ["## Class (2): the no-rest cases on the stated noise — what the sandwich splits into", "",
         "Plain likelihood (no report), flat φ prior, the recording's stated σ, MAP from the design "
         "(`sandwich_split`). Sandwich/Laplace std ratio, median (max) over the coordinates, by the unit whose "
         "scores are summed (channel: heteroscedasticity only; triad: + within-triad; sample: + across triads) "
         "without lags and with the Newey–West lags (+ time correlation); in brackets the median ratio "
         "relative to what that clustering gives under the model's white noise. Last column: the noise-free "
         "misfit RMS at the true positions against the stated σ (m/s²).", "",
         "| case | channel, 0 lags | channel, NW | triad, 0 lags | triad, NW | sample, 0 lags | sample, NW | "
         "misfit RMS / stated σ |", "|---|---|---|---|---|---|---|---|"]
    for d in docs:
        cells = []
        for r in d["rows"]:
            rel = "" if r["relative_median"] is None else f" [{r['relative_median']:.2f}]"
            cells.append(f"{r['std_ratio_median']:.2f} ({r['std_ratio_max']:.2f}){rel}, L={r['lags']}")
        st = np.ravel(d["stated_std"])
        L.append(f"| clock-{d['seed']:03d} | " + " | ".join(cells) +
                 f" | {d['misfit_rms']:.3f} / {min(st):.3f}–{max(st):.3f} |")
    return "\n".join(L) + "\n"


def run(seed, out: Path) -> dict:
    from accel_bayes.data.outputs import write_json

    f = out / f"clock-{seed:03d}.json"
    if f.exists():
        return json.loads(f.read_text())
    rows = []
    for name, kw in ROWS.items():
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            r = {"row": name, **noise_step_maps(seed, kw), **misfit(seed, kw)}
        r["rho"] = r["signal_sq_sum"] / (12 * r["T"] * float(np.mean(np.square(r["noise_std"]))))
        rows.append(r)
        print(f"clock-{seed:03d} {name}: flat {r['flat_scale']:.3f}, from flat {r['scale']['flat start']:.3f}, "
              f"from design {r['scale']['design start']:.3f}, σ {min(r['noise_std']):.3f}–{max(r['noise_std']):.3f}, "
              f"misfit {r['misfit_rms']:.3f} / signal {r['signal_rms']:.3f}, ρ {r['rho']:.2f} "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)
    from experiments.clockgen import draw_case

    _, truth = draw_case("clock", seed, duration=20.0)
    doc = {"seed": seed, "board": truth["board"], "f_host": truth["f_host"], "rows": rows}
    out.mkdir(parents=True, exist_ok=True)
    write_json(f, doc)
    return doc


def markdown(cases, cmd, secs) -> str:
    now = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    L = ["# vibgeom_probe — why the untempered geometry flips on concealed clock recordings (issue #30 item 4)", "",
         f"Regenerate: `{cmd}` ({now}, {platform.machine()} {platform.system()}, shared 2-core CPU, nice 5; "
         f"per-case results cached in `experiments/out/vibgeom_probe/`; this invocation {secs:.0f} s).", "",
         "What runs: the module docstring of [`vibgeom_probe.py`](vibgeom_probe.py). Per row: the fitted "
         "accelerometer noise σ (m/s², min–max over triads); the geometry scale of the flat-φ MAP, of the "
         "proper-prior MAP started from it (**the pipeline before this issue**) and from the design, and Δ log "
         "posterior (design start − flat start, nats); which one the pipeline now keeps; the noise-free "
         "misfit and centripetal signal RMS (m/s²) at the true positions; ρ (≥ 1: the flat likelihood has a "
         "mode near the true size).", ""]
    for c in cases:
        L += [f"## clock-{c['seed']:03d} ({c['board']}, {c['f_host']} Hz)", "",
              "| row | σ fitted | flat MAP scale | scale from flat start | scale from design | Δ log post | kept | "
              "misfit / signal RMS | ρ |", "|---|---|---|---|---|---|---|---|---|"]
        for r in c["rows"]:
            d = r["log_posterior"]["design start"] - r["log_posterior"]["flat start"]
            L.append(f"| {r['row']} | {min(r['noise_std']):.3f}–{max(r['noise_std']):.3f} | {r['flat_scale']:.3f} | "
                     f"{r['scale']['flat start']:.3f} | {r['scale']['design start']:.3f} | {d:.1f} | "
                     f"{'design' if r['chosen'] == 'design start' else 'flat'} | "
                     f"{r['misfit_rms']:.3f} / {r['signal_rms']:.3f} | {r['rho']:.2f} |")
        L.append("")
    return "\n".join(L) + "\n"


def mimu_markdown(rows) -> str:
    if not rows:
        return ""
    L = ["", "## The six MIMU experiments: which start the noise step keeps", "",
         "calibrate's noise step (estimated noise, empirical φ prior; `noise_step_fits`) on each experiment, "
         "without and (with `--reports`) with its own report's fused gyro posterior. Δ = log posterior "
         "from the design − from the flat MAP (nats); the design start is kept only where Δ > "
         "1 nat, so elsewhere the results are those of the code before the fix.", "",
         "| experiment | path | T | kept | Δ log post |", "|---|---|---|---|---|"]
    for r in rows:
        d = r["log_posterior"]["design start"] - r["log_posterior"]["flat start"]
        L.append(f"| exp_{r['exp']} | {'with report' if r['report'] else 'default'} | {r['T']} | "
                 f"{r['chosen']} | {d:.3g} |")
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1,2,9,10,19")
    ap.add_argument("--sandwich", default="", help="comma-separated no-rest seeds for sandwich_split")
    ap.add_argument("--estimate", default="", help="comma-separated no-rest seeds for estimated_noise")
    ap.add_argument("--conceal", type=Path, default=ROOT / "out" / "percov_conceal",
                    help="percov_conceal's case folder (its cached reports)")
    ap.add_argument("--mimu", default="", help="comma-separated MIMU experiments for mimu_start")
    ap.add_argument("--reports", type=Path, default=None,
                    help="folder of the MIMU reports (exp_N/report.json) for the --model path")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "vibgeom_probe")
    args = ap.parse_args(argv)
    from accel_bayes.data.outputs import write_text
    from experiments._reading import READING_MARKER, kept_reading

    t0 = time.perf_counter()
    cases = [run(int(s), args.out) for s in args.seeds.split(",") if s.strip()]
    sand = [sandwich_split(int(x), args.out) for x in args.sandwich.split(",") if x.strip()]
    est = [estimated_noise(int(x), args.out, args.conceal) for x in args.estimate.split(",") if x.strip()]
    mimu = []
    for e in [int(x) for x in args.mimu.split(",") if x.strip()]:
        mimu.append(mimu_start(e, None, args.out))
        if args.reports is not None:
            mimu.append(mimu_start(e, args.reports / f"exp_{e}" / "report.json", args.out))
    cmd = "PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/vibgeom_probe.py --seeds " + args.seeds
    if sand:
        cmd += f" --sandwich {args.sandwich}"
    if est:
        cmd += f" --estimate {args.estimate}"
    if mimu:
        cmd += f" --mimu {args.mimu}" + (f" --reports {args.reports}" if args.reports else "")
    write_text(DOC, markdown(cases, cmd, time.perf_counter() - t0) + sandwich_markdown(sand) + estimate_markdown(est, args.conceal) + mimu_markdown(mimu) + "\n" + READING_MARKER
               + (kept_reading(DOC) or "\n"))
    print(DOC.read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
