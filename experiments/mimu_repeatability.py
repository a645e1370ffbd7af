"""Repeatability of the real-data calibration over the six MIMU4444 experiments (issue #6 item 3).

Every experiment goes through the default pipeline, exactly as ``accel-bayes calibrate`` runs it:
import → intrinsics from its own rests → static / clipped / non-rotating samples dropped → noise
estimated (type-II ML at the MAP, tempered by the sandwich factor) → MAP → PmMH (4 × 1000 draws).
Then, per IMU and coordinate:

* posterior mean and std of each experiment, the spread (std, ddof 1) of the six means;
* z of each experiment's mean against the inverse-variance pooled estimate of the other five,
  z = (m_e − m̄_{−e}) / sqrt(s_e² + v_{−e});
* pairwise |m_a − m_b| / sqrt(s_a² + s_b²), max over pairs and coordinates (must be < 4);
* distance of the means from the nominal design (x, y must be within ±2 mm);
* R̂ max and min bulk ESS per experiment (must be < 1.01 and ≥ 400 per coordinate);
* a [C21] Fig. 5-style plot: 50 % ellipses of the six experiments over the board outline.

Optionally (``--intrinsics-draws K``) the uncertainty of the intrinsic calibration is propagated
for one experiment: K intrinsics drawn from their reported covariance
(:func:`accel_bayes.prep.preprocess.draw_intrinsics`), each applied to the raw data and the tempered
MAP refitted with the same noise model; the spread of those MAPs is compared with the posterior
std.

    python experiments/mimu_repeatability.py [--workers 1] [--scheduler ADDR] [--data DIR]
        [--out experiments/out/mimu_repeatability] [--chains 4 --draws 1000 --warmup 1000]
        [--intrinsics-draws 10] [--experiments 1,2,3,4,5,6]

Runtime: ~3–4 min per experiment on one core of the shared 2-core machine (≈ 20–25 min for the
six with ``--workers 1``), plus ~10 s per intrinsics draw.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _dask import add_dask_arguments, dask_client, map_task_groups  # noqa: E402
from _data import data_dir  # noqa: E402

NOMINAL_XY_TOL_M = 2e-3
PAIR_Z_MAX = 4.0
RHAT_MAX = 1.01
ESS_MIN = 400


# ---------------------------------------------------------------------------- tasks (run on workers)

def coordinate_diagnostics(doc: dict, summ, K: int) -> tuple[np.ndarray, np.ndarray]:
    """(R̂, bulk ESS), each (K, 3) per IMU row and axis, from a calibration's positions document
    and ArviZ summary (NaN for the reference IMU, which has no coordinate)."""
    rh = np.full((K, 3), np.nan)
    ess = np.full((K, 3), np.nan)
    for e in doc["imus"]:
        for a, ax in enumerate("xyz"):
            key = f"r[{e['imu']}, {ax}]"
            if key in summ.index:
                rh[e["imu"], a] = float(summ.loc[key, "r_hat"])
                ess[e["imu"], a] = float(summ.loc[key, "ess_bulk"])
    return rh, ess


def run_experiment(exp: int, data: str, out: str, chains: int, draws: int, warmup: int, seed: int) -> dict:
    """Import experiment ``exp`` and calibrate it with the pipeline defaults; write its outputs."""
    from accel_bayes.pipelines.calibrate import calibrate, write_outputs
    from accel_bayes.data.mimu import import_mimu

    t0 = time.perf_counter()
    rec = import_mimu(Path(data) / f"exp_{exp}" / "data.bin.gz")
    res = calibrate(rec, chains=chains, draws=draws, warmup=warmup, seed=seed, progress=False)
    write_outputs(res, Path(out) / f"exp_{exp}", plots=True)
    doc = res.positions
    summ = res.summary
    rh, ess = coordinate_diagnostics(doc, summ, len(doc["imus"]))
    st = res.settings
    nm = st.get("noise_model") or {}
    return {
        "exp": exp,
        "mean": [e["mean"] for e in doc["imus"]],
        "std": [e["std"] for e in doc["imus"]],
        "cov": [e.get("cov", [[0.0] * 3] * 3) for e in doc["imus"]],
        "rhat": rh.tolist(), "ess_bulk": ess.tolist(),
        "rhat_max": doc["diagnostics"]["rhat_max"], "ess_bulk_min": doc["diagnostics"]["ess_bulk_min"],
        "nominal": (np.asarray(rec.nominal_position) - np.asarray(rec.nominal_position)[rec.reference_imu]).tolist(),
        "samples": st["preprocess"]["samples"], "intrinsics": {k: v for k, v in st["preprocess"]["intrinsics"].items()
                                                               if k in ("applied", "how", "rest_error_max_before",
                                                                        "rest_error_max_after")},
        "noise_std": nm.get("std"), "kappa": (nm.get("sandwich") or {}).get("applied"),
        "std_used": nm.get("std_used"),
        "map_positions": None if res.map_result is None else res.map_result.positions.numpy().tolist(),
        "num_draws": st["num_draws"], "acceptance": st["acceptance_rate"], "seconds": res.seconds,
        "wall_seconds": time.perf_counter() - t0,
    }


def intrinsics_sensitivity(exp: int, data: str, n_draws: int, seed: int) -> dict:
    """Propagate the intrinsics' reported uncertainty to the tempered MAP of experiment ``exp``."""
    import torch

    from accel_bayes.pipelines.calibrate import calibrate
    from accel_bayes.model.likelihood import RaoBlackwellLikelihood
    from accel_bayes.prep.prepared import prepare_recording
    from accel_bayes.data.mimu import import_mimu
    from accel_bayes.inference.noise_fit import fit_map_tempered
    from accel_bayes.prep.preprocess import draw_intrinsics, preprocess

    raw = import_mimu(Path(data) / f"exp_{exp}" / "data.bin.gz")
    # the noise model and κ of the default pipeline (one draw: only the MAP stage is needed)
    res = calibrate(raw, chains=1, draws=4, warmup=0, seed=seed, progress=False)
    nm = res.settings["noise_model"]
    std = np.asarray(nm["std_used"])
    kappa = float((nm.get("sandwich") or {}).get("applied") or 1.0)
    pre = preprocess(raw)
    nominal = torch.as_tensor(np.asarray(raw.nominal_position), dtype=torch.float64)

    def tempered_map(rec):
        lik = RaoBlackwellLikelihood.from_recording(prepare_recording(rec, select=pre.keep), num_draws=1,
                                                    gyro_method=res.settings["gyro_method"])
        m = fit_map_tempered(lik.acc, lik.omega.mean, lik.omega.cov, std, kappa, reference=lik.reference,
                             prior_mean=nominal, prior_std=res.settings["prior_std"])
        return m.positions.numpy(), m.position_std().numpy()

    p0, s0 = tempered_map(pre.recording)
    P = []
    for k in range(int(n_draws)):  # a few tens of MAP fits, ~5–10 s each
        P.append(tempered_map(draw_intrinsics(pre.intrinsics, seed * 1000 + k).apply(raw))[0])
    P = np.stack(P)
    spread = P.std(0, ddof=1)
    # reference: the Laplace std of the same tempered posterior (the PmMH std agrees with it to a
    # few % on these data, see the per-experiment results)
    ratio = spread[1:] / s0[1:]
    return {"exp": exp, "draws": int(n_draws), "map_nominal": p0.tolist(), "laplace_std": s0.tolist(),
            "spread": spread.tolist(), "ratio_max": float(ratio.max()), "ratio_median": float(np.median(ratio)),
            "combined_std_increase_max": float(np.sqrt(1 + ratio.max() ** 2) - 1),
            "map_shift_max": float(np.abs(P - p0[None]).max())}


# ---------------------------------------------------------------------------- analysis

def analyse(results: list[dict]) -> dict:
    """Repeatability figures over the experiments (module docstring); arrays (E, K, 3) in metres."""
    E = len(results)
    m = np.array([r["mean"] for r in results], dtype=float)
    s = np.array([r["std"] for r in results], dtype=float)
    nominal = np.array(results[0]["nominal"], dtype=float)
    free = [k for k in range(m.shape[1]) if not np.all(s[:, k] == 0)]
    mf, sf = m[:, free], s[:, free]
    spread = mf.std(0, ddof=1) if E > 1 else np.full(mf.shape[1:], np.nan)
    rms_std = np.sqrt((sf**2).mean(0))
    # leave-one-out z against the inverse-variance pooled estimate of the others
    z_loo = np.full(mf.shape, np.nan)
    if E > 1:
        for e in range(E):
            o = [j for j in range(E) if j != e]
            w = 1.0 / sf[o] ** 2
            pooled = (w * mf[o]).sum(0) / w.sum(0)
            z_loo[e] = (mf[e] - pooled) / np.sqrt(sf[e] ** 2 + 1.0 / w.sum(0))
    pair = []
    for a in range(E):
        for b in range(a + 1, E):
            z = np.abs(mf[a] - mf[b]) / np.sqrt(sf[a] ** 2 + sf[b] ** 2)
            k, ax = np.unravel_index(int(np.argmax(z)), z.shape)
            pair.append({"a": results[a]["exp"], "b": results[b]["exp"], "max_z": float(z.max()),
                         "imu": int(free[k]), "axis": "xyz"[ax]})
    pair_max = max(pair, key=lambda p: p["max_z"]) if pair else None
    dev = mf - nominal[free][None]
    rhat = np.array([r["rhat"] for r in results], dtype=float)[:, free]
    ess = np.array([r["ess_bulk"] for r in results], dtype=float)[:, free]
    zmax = float(pair_max["max_z"]) if pair_max else float("nan")
    z_rms = float(np.sqrt(np.nanmean(z_loo**2))) if E > 1 else float("nan")
    return {
        "experiments": [r["exp"] for r in results], "imus": free,
        "mean": mf.tolist(), "std": sf.tolist(), "spread": spread.tolist(), "rms_std": rms_std.tolist(),
        "spread_over_std": (spread / rms_std).tolist(),
        "spread_over_std_median": float(np.nanmedian(spread / rms_std)),
        "spread_over_std_max": float(np.nanmax(spread / rms_std)),
        "z_loo": z_loo.tolist(), "z_loo_rms": z_rms, "z_loo_max": float(np.nanmax(np.abs(z_loo))),
        "pairs": pair, "pair_max": pair_max,
        "inflation_for_pairs": max(1.0, zmax / PAIR_Z_MAX),
        "inflation_for_unit_z": z_rms,
        "nominal_dev_xy_max": float(np.abs(dev[..., :2]).max()),
        "nominal_dev": dev.tolist(),
        "rhat_max": rhat.reshape(E, -1).max(1).tolist(), "ess_min": ess.reshape(E, -1).min(1).tolist(),
        "checks": {
            "all_calibrated": True,
            "rhat_ok": bool((rhat < RHAT_MAX).all()), "ess_ok": bool((ess >= ESS_MIN).all()),
            "nominal_ok": bool((np.abs(dev[..., :2]) <= NOMINAL_XY_TOL_M).all()),
            "pairs_ok": bool(zmax < PAIR_Z_MAX) if pair else None,
        },
    }


def ellipse_plot(results: list[dict], path: Path, array) -> Path:
    """[C21] Fig. 5 style: 50 % posterior ellipses of every experiment over the board outline,
    one panel per board side (offsets from nominal and ellipses magnified alike)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    from accel_bayes.diagnostics.plots import auto_exaggeration, plot_ellipses

    def moments(r, labels):
        return {"imu": labels, "mean": np.array([r["mean"][k] for k in labels]),
                "cov": np.array([r["cov"][k] for k in labels])}

    nominal = np.array(results[0]["nominal"])
    ref = int(array.reference_imu)
    free = [k for k in range(len(nominal)) if k != ref]
    k_ex = min(auto_exaggeration(moments(r, free), array) for r in results)
    fig, axes = plt.subplots(1, 2, figsize=(12, 6))
    sides = (("top side", [k for k in free if nominal[k, 2] >= 0] or free[:0]),
             ("bottom side", [k for k in free if nominal[k, 2] < 0]))
    for (name, labels), ax in zip(sides, axes):
        for i, r in enumerate(results):
            plot_ellipses(moments(r, labels), array, ax=ax, level=0.5, color=f"C{i}", exaggerate=k_ex)
        ax.set_title(f"{name}: 50 % ellipses, offsets from nominal and ellipses ×{k_ex:g}")
    handles = [Line2D([], [], color=f"C{i}", label=f"exp_{r['exp']}") for i, r in enumerate(results)]
    axes[1].legend(handles=handles, loc="upper right", fontsize=8)
    fig.suptitle("MIMU4444: posterior of the triad positions, six experiments (default pipeline)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def ellipse_zoom_plot(results: list[dict], path: Path) -> Path:
    """One panel per free IMU at true scale: x–y offsets from the nominal design (µm, relative to
    IMU 0) of every experiment's posterior mean with its 50 % and 95 % ellipses."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse

    nominal = np.array(results[0]["nominal"])
    free = [k for k in range(len(nominal)) if not np.allclose(results[0]["std"][k], 0)]
    n = len(free)
    cols = 4
    rows = int(math.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.6 * rows), squeeze=False)
    for ax, k in zip(axes.ravel(), free):
        for i, r in enumerate(results):
            m = (np.array(r["mean"][k][:2]) - nominal[k, :2]) * 1e6
            c = np.array(r["cov"][k])[:2, :2] * 1e12
            vals, vecs = np.linalg.eigh(c)
            ang = math.degrees(math.atan2(vecs[1, -1], vecs[0, -1]))
            for lv, ls in ((0.5, "-"), (0.95, ":")):
                kq = math.sqrt(-2.0 * math.log(1.0 - lv))
                w, h = 2 * kq * np.sqrt(np.clip(vals[::-1], 0, None))
                ax.add_patch(Ellipse(m, w, h, angle=ang, fill=False, color=f"C{i}", ls=ls, lw=1.0))
            ax.plot([m[0]], [m[1]], ".", color=f"C{i}", label=f"exp_{r['exp']}")
        ax.plot([0], [0], "k+", ms=10)
        ax.set_title(f"IMU {k} ({'top' if nominal[k, 2] >= 0 else 'bottom'})", fontsize=9)
        ax.set_xlabel("x − nominal [µm]", fontsize=8)
        ax.set_ylabel("y − nominal [µm]", fontsize=8)
        ax.set_aspect("equal", adjustable="datalim")
        ax.autoscale_view()
        ax.grid(True, lw=0.3)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    axes.ravel()[0].legend(fontsize=7)
    fig.suptitle("posterior means and 50 % (solid) / 95 % (dotted) ellipses per experiment; + = nominal design")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def verdict(ok, text):
    return f"{'PASS' if ok else 'FAIL'}: {text}"


def report_lines(results, an, intr=None) -> list[str]:
    mm, um = 1e3, 1e6
    L = ["## Per experiment", "",
         "| exp | samples kept | σ level (m/s²) | κ | R̂ max | min bulk ESS | max |mean − nominal| x,y (mm) | seconds |",
         "|---|---|---|---|---|---|---|---|"]
    for i, r in enumerate(results):
        sig = r["noise_std"]
        L.append(f"| {r['exp']} | {r['samples']['kept']} of {r['samples']['recording']} | "
                 f"{min(sig):.2f}–{max(sig):.2f} | {r['kappa']:.2f} | {an['rhat_max'][i]:.4f} | {an['ess_min'][i]:.0f} | "
                 f"{np.abs(np.array(an['nominal_dev'][i])[:, :2]).max() * mm:.3f} | {r['seconds']:.0f} |")
    L += ["", "## Per IMU (positions relative to IMU 0; mean over experiments, spread of the six means, RMS posterior std)", "",
          "| IMU | mean x, y, z (mm) | nominal x, y, z (mm) | spread x, y, z (µm) | RMS std x, y, z (µm) | spread/std | max |z_loo| |",
          "|---|---|---|---|---|---|---|"]
    mean = np.array(an["mean"])
    nominal = np.array(results[0]["nominal"])
    for j, k in enumerate(an["imus"]):
        mu = mean[:, j].mean(0) * mm
        sp = np.array(an["spread"][j]) * um
        sd = np.array(an["rms_std"][j]) * um
        zl = np.abs(np.array(an["z_loo"])[:, j]).max()
        L.append(f"| {k} | {mu[0]:.3f}, {mu[1]:.3f}, {mu[2]:.3f} | {nominal[k, 0] * mm:.2f}, {nominal[k, 1] * mm:.2f}, "
                 f"{nominal[k, 2] * mm:.2f} | {sp[0]:.0f}, {sp[1]:.0f}, {sp[2]:.0f} | {sd[0]:.0f}, {sd[1]:.0f}, {sd[2]:.0f} | "
                 f"{np.max(sp / sd):.2f} | {zl:.2f} |")
    c = an["checks"]
    pm = an["pair_max"]
    L += ["", "## Verdicts", "",
          "- " + verdict(c["all_calibrated"], f"all {len(results)} experiments calibrated with the defaults (no manual tuning)"),
          "- " + verdict(c["rhat_ok"] and c["ess_ok"],
                         f"every coordinate R̂ < {RHAT_MAX} and bulk ESS ≥ {ESS_MIN}: worst R̂ {max(an['rhat_max']):.4f}, "
                         f"smallest ESS {min(an['ess_min']):.0f}"),
          "- " + verdict(c["nominal_ok"], f"posterior means within ±2 mm (x, y) of nominal: worst "
                         f"{an['nominal_dev_xy_max'] * mm:.3f} mm"),
          "- " + (verdict(c["pairs_ok"], f"every pair and coordinate within {PAIR_Z_MAX:g} combined std: max "
                          f"{pm['max_z']:.2f} (exp_{pm['a']} vs exp_{pm['b']}, IMU {pm['imu']} {pm['axis']})")
                  if pm else "- pairwise check needs ≥ 2 experiments"),
          f"- spread of the means / RMS posterior std: median {an['spread_over_std_median']:.2f}, max "
          f"{an['spread_over_std_max']:.2f}; RMS of the leave-one-out z {an['z_loo_rms']:.2f} (1 if the posterior "
          f"std matches the scatter), max |z| {an['z_loo_max']:.2f}",
          f"- inflation needed: ×{an['inflation_for_pairs']:.2f} for the pairwise 4σ check, "
          f"×{an['inflation_for_unit_z']:.2f} for unit-variance leave-one-out z"]
    if intr:
        L += ["", "## Intrinsics uncertainty",
              f"exp_{intr['exp']}: {intr['draws']} intrinsics drawn from their reported covariance, tempered MAP refitted: "
              f"spread of the MAPs / Laplace std of the tempered posterior: median {intr['ratio_median']:.3f}, "
              f"max {intr['ratio_max']:.3f}; largest MAP shift {intr['map_shift_max'] * 1e6:.1f} µm "
              f"(adding it in quadrature would widen the posterior std by at most "
              f"{100 * intr['combined_std_increase_max']:.1f} %)"]
    return L


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=None, help="folder with exp_1..exp_6 (default ../shared/data/mimu4444-bcd)")
    ap.add_argument("--out", type=Path, default=HERE / "out" / "mimu_repeatability", help="output folder")
    ap.add_argument("--experiments", default="1,2,3,4,5,6", help="comma-separated experiment numbers")
    ap.add_argument("--chains", type=int, default=4)
    ap.add_argument("--draws", type=int, default=1000)
    ap.add_argument("--warmup", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--intrinsics-draws", type=int, default=10,
                    help="intrinsics draws for the uncertainty propagation (0 skips it)")
    ap.add_argument("--intrinsics-exp", type=int, default=1, help="experiment used for it (default 1)")
    ap.add_argument("--reuse", action="store_true", help="re-analyse OUT/results.json without running anything")
    add_dask_arguments(ap, default_workers=1)
    args = ap.parse_args(argv)
    data = args.data or data_dir()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    exps = [int(x) for x in args.experiments.split(",") if x.strip()]
    t0 = time.perf_counter()
    if args.reuse:
        saved = json.loads((out / "results.json").read_text())
        results, intr = saved["results"], saved.get("intrinsics")
    else:
        groups = [(run_experiment, [dict(exp=e, data=str(data), out=str(out), chains=args.chains, draws=args.draws,
                                         warmup=args.warmup, seed=args.seed) for e in exps])]
        if args.intrinsics_draws > 0:
            groups.append((intrinsics_sensitivity, [dict(exp=args.intrinsics_exp, data=str(data),
                                                         n_draws=args.intrinsics_draws, seed=args.seed)]))
        with dask_client(args) as client:
            got = map_task_groups(client, groups, desc="mimu repeatability")
        results = got[0]
        intr = got[1][0] if len(got) > 1 else None
    an = analyse(results)
    (out / "results.json").write_text(json.dumps({"results": results, "intrinsics": intr, "analysis": an}, indent=1))
    from accel_bayes.physics.arrays import mimu4444_8

    fig = ellipse_plot(results, out / "ellipses.png", mimu4444_8())
    fig_zoom = ellipse_zoom_plot(results, out / "ellipses_zoom.png")
    lines = [f"# MIMU4444 repeatability ({len(results)} experiments, default pipeline)", ""] + report_lines(results, an, intr)
    (out / "report.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"\nwrote {out / 'results.json'}, {out / 'report.md'}, {fig}, {fig_zoom} ({time.perf_counter() - t0:.0f} s)")
    pm = an["pair_max"]
    print(f"RESULT mimu_repeat_pair_max_z: {pm['max_z'] if pm else float('nan'):.3f}")
    print(f"RESULT mimu_repeat_nominal_dev_xy_max: {an['nominal_dev_xy_max'] * 1e3:.3f} mm")
    print(f"RESULT mimu_repeat_rhat_max: {max(an['rhat_max']):.4f}")
    print(f"RESULT mimu_repeat_ess_min: {min(an['ess_min']):.0f}")
    print(f"RESULT mimu_repeat_z_loo_rms: {an['z_loo_rms']:.3f}")
    return 0 if all(v in (True, None) for v in an["checks"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
