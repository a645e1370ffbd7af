"""Is the posterior calibrated with the default (empirical-Bayes) prior on φ? (issue #15 must-shows 1–2)

Two sets of data, ``calibrate`` with its defaults, once with the default ``phi_prior="empirical"``
and once with ``phi_prior="flat"`` ([C21] as published), on the same data:

* ``--set demo`` — the demo configuration (mimu8, smooth motion, T = 600 at 100 Hz, true
  positions = nominal + N(0, (0.3 mm)²)) over simulator seeds 1..n (package simulator);
* ``--set boards`` — the 20 random boards and the two regression boards of
  ``experiments/_boards.py`` (independent simulator ``_conceal``, 6–10 IMUs over 6–16 cm,
  100–250 Hz, T ≈ 2500, no rests).

Per run, :func:`accel_bayes.diagnostics.stats.truth_check` gives the posterior mean's error
e = m − truth in the posterior's own units:

* the Mahalanobis χ² = eᵀC⁻¹e, χ²_d distributed when the posterior is calibrated (d = 3 × the
  free IMUs); over the runs the sum is χ² with Σd dof (99 % band), and the per-run CDF values
  F_χ²_d(χ²) are uniform (KS test);
* the radial z: the error along the board's scale mode, in std, N(0, 1) when calibrated; its
  mean over runs must be within ±2 standard errors of 0 (the flat prior's inward pull makes it
  negative).

    python experiments/phi_prior_calibration.py [--set demo] [--seeds 50] [--workers 2]
    python experiments/phi_prior_calibration.py --set boards [--workers 2]

Writes ``experiments/phi_prior_calibration.md`` (demo) or ``experiments/phi_prior_boards.md``
(boards), the per-run CSV in ``experiments/out/`` and a PNG next to the document.
"""
from __future__ import annotations

import argparse
import csv
import io
import math
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

FORMS = ("empirical", "flat")


def _case(data_set: str, seed: int):
    """(name, recording, truth relative to the reference IMU (K, 3) m) of run ``seed``."""
    if data_set == "demo":
        from accel_bayes.physics import arrays
        from accel_bayes.pipelines.demo import DEFAULTS as DEMO
        from accel_bayes.simulate import simulate

        sim = simulate(arrays.preset(DEMO["preset"]), DEMO["motion"], T=DEMO["T"], rate=DEMO["rate"], seed=seed,
                       position_error_std=DEMO["position_error"])
        return f"seed {seed}", sim.recording, np.asarray(sim.truth["true_position_relative"])
    import _boards

    name, case = _boards.all_boards()[seed]
    return name, case.recording, np.asarray(case.truth["true_relative_position"])


def one_run(seed: int, form: str, data_set: str = "demo") -> dict:
    """Calibrate run ``seed`` of ``data_set`` with ``phi_prior=form``; the truth statistics."""
    import warnings

    from accel_bayes.diagnostics.stats import truth_check
    from accel_bayes.pipelines.calibrate import calibrate
    from scipy import stats

    name, rec, truth = _case(data_set, seed)
    # demo: the fixed run length the demo configuration always had (4 chains × (1000 + 1000)), so
    # that this study measures the likelihood alone; boards: every default, the run length included
    fixed = dict(chains=4, draws=1000, warmup=1000) if data_set == "demo" else {}
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = calibrate(rec, seed=seed, progress=False, phi_prior=form, **fixed)
    tc = truth_check(res.idata, truth)
    d = res.positions["diagnostics"]
    labels = [int(k) for k in res.idata.posterior["r"].coords["imu"].values]
    m = res.idata.posterior["r"].values.reshape(-1, len(labels), 3).mean(0)
    u = truth[labels]
    return {"seed": seed, "name": name, "K": int(rec.K), "T": int(res.settings["T"]), "form": form, "chi2": tc["chi2"], "dof": tc["dof"],
            "cdf": float(stats.chi2.cdf(tc["chi2"], tc["dof"])), "radial_z": tc["radial_z"],
            "scale": float((m * u).sum() / (u * u).sum()), "rhat_max": d["rhat_max"], "ess_bulk_min": d["ess_bulk_min"],
            "draws": int(res.settings["draws"]), "seconds": time.perf_counter() - t0}


def summarize(rows: list[dict]) -> dict:
    from scipy import stats

    out = {}
    for form in FORMS:
        r = [x for x in rows if x["form"] == form]
        if not r:
            continue
        n = len(r)
        chi2 = np.array([x["chi2"] for x in r])
        dof = int(sum(x["dof"] for x in r))
        z = np.array([x["radial_z"] for x in r])
        cdf = np.array([x["cdf"] for x in r])
        lo, hi = stats.chi2.ppf([0.005, 0.995], dof)
        ks = stats.kstest(cdf, "uniform")
        se = z.std(ddof=1) / math.sqrt(n)
        sc = np.array([x["scale"] for x in r])
        out[form] = {
            "n": n, "chi2_sum": float(chi2.sum()), "dof": dof, "band": (float(lo), float(hi)),
            "chi2_ok": bool(lo <= chi2.sum() <= hi), "z_mean": float(z.mean()), "z_se": float(se),
            "z_ok": bool(abs(z.mean()) <= 2 * se), "ks_stat": float(ks.statistic), "ks_p": float(ks.pvalue),
            "ks_ok": bool(ks.pvalue >= 0.01), "scale_mean": float(sc.mean()),
            "scale_se": float(sc.std(ddof=1) / math.sqrt(n)),
            "rhat_max": float(max(x["rhat_max"] for x in r)), "ess_min": float(min(x["ess_bulk_min"] for x in r)),
            "seconds_median": float(np.median([x["seconds"] for x in r])),
        }
    return out


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    for form, col in zip(FORMS, ("C0", "C3")):
        r = [x for x in rows if x["form"] == form]
        if not r:
            continue
        cdf = np.sort([x["cdf"] for x in r])
        n = len(cdf)
        ax[0].step(cdf, np.arange(1, n + 1) / n, where="post", color=col, label=f"phi_prior={form}")
        z = np.array([x["radial_z"] for x in r])
        ax[1].hist(z, bins=np.linspace(-5, 3, 33), alpha=0.5, color=col, label=f"{form}: mean {z.mean():+.2f}")
    ax[0].plot([0, 1], [0, 1], "k:", lw=1, label="calibrated (uniform)")
    ax[0].set_xlabel("per-run χ²_d CDF of the Mahalanobis error")
    ax[0].set_ylabel("empirical CDF over runs")
    ax[0].legend(loc="upper left", fontsize=8)
    ax[0].set_title("Mahalanobis error of the posterior mean")
    xs = np.linspace(-5, 3, 200)
    nz = len([x for x in rows if x["form"] == FORMS[0]]) or len(rows)
    ax[1].plot(xs, nz * 0.25 * np.exp(-0.5 * xs**2) / math.sqrt(2 * math.pi), "k:", lw=1, label="N(0, 1)")
    ax[1].set_xlabel("error along the board's scale mode (posterior std)")
    ax[1].set_ylabel("runs")
    ax[1].legend(loc="upper left", fontsize=8)
    ax[1].set_title("radial z (< 0: fitted board too small)")
    fig.tight_layout()
    from accel_bayes.data.outputs import write_bytes

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    write_bytes(path, buf.getvalue())


def document(rows, summ, args, wall) -> str:
    if args.set == "demo":
        cmd = f"python experiments/phi_prior_calibration.py --seeds {args.seeds} --workers {args.workers}"
        what = ["Demo configuration (mimu8, smooth motion, T = 600 at 100 Hz, true positions = nominal + "
                "N(0, (0.3 mm)²)),",
                f"seeds 1–{args.seeds}; `calibrate` with its defaults, 4 chains × (1000 + 1000) iterations, and "
                "`phi_prior` =",
                "empirical (default) or flat, on the same data. Statistics of `diagnostics.stats.truth_check` (21 free "
                "coordinates per run)."]
    else:
        cmd = f"python experiments/phi_prior_calibration.py --set boards --workers {args.workers}"
        if args.forms != ",".join(FORMS):
            cmd += f" --forms {args.forms}"
        what = ["The 20 random boards and the two regression boards of `experiments/_boards.py` (independent",
                "simulator `_conceal`: 6–10 IMUs over 6–16 cm, smooth random motion, 100–250 Hz, T ≈ 2500, no",
                "rests), `calibrate` with its defaults and `phi_prior` = empirical (default) or flat, on the same data.",
                "Statistics of `diagnostics.stats.truth_check` (3 × (K − 1) free coordinates per board)."]
    lines = [
        "# Calibration of the posterior: empirical-Bayes prior on φ (default) against the flat prior"
        + (" — 22 boards" if args.set == "boards" else ""),
        "",
        f"Generated by `{cmd}` ({wall / 60:.0f} min on the shared 2-core machine).",
        *what,
        "",
        "| statistic | target | empirical (default) | flat |",
        "|---|---|---|---|",
    ]

    def cell(form, key):
        s = summ.get(form)
        if s is None:
            return "–"
        if key == "chi2":
            return f"{s['chi2_sum']:.0f} ({'PASS' if s['chi2_ok'] else 'FAIL'})"
        if key == "z":
            return f"{s['z_mean']:+.3f} ± {s['z_se']:.3f} ({'PASS' if s['z_ok'] else 'FAIL'})"
        if key == "ks":
            return f"D = {s['ks_stat']:.3f}, p = {s['ks_p']:.3g} ({'PASS' if s['ks_ok'] else 'FAIL'})"
        if key == "scale":
            return f"{s['scale_mean']:.5f} ± {s['scale_se']:.5f}"
        if key == "conv":
            return f"{s['rhat_max']:.4f} / {s['ess_min']:.0f}"
        if key == "sec":
            return f"{s['seconds_median']:.1f}"
        raise KeyError(key)

    any_s = next(iter(summ.values()))
    lines += [
        f"| Σ Mahalanobis χ² over runs | 99 % band of χ²_{any_s['dof']}: {any_s['band'][0]:.0f}–{any_s['band'][1]:.0f} "
        f"| {cell('empirical', 'chi2')} | {cell('flat', 'chi2')} |",
        f"| mean radial z ± SE | within ±2 SE of 0 | {cell('empirical', 'z')} | {cell('flat', 'z')} |",
        f"| KS test of the per-run χ² CDF values | p ≥ 0.01 | {cell('empirical', 'ks')} | {cell('flat', 'ks')} |",
        f"| array scale (posterior mean · truth / ‖truth‖²) | 1 | {cell('empirical', 'scale')} | {cell('flat', 'scale')} |",
        f"| worst R̂ / smallest bulk ESS over runs | < 1.01 / ≥ 400 | {cell('empirical', 'conv')} | {cell('flat', 'conv')} |",
        f"| median seconds per calibration | | {cell('empirical', 'sec')} | {cell('flat', 'sec')} |",
        "",
        f"![CDF of the per-run χ² values and histogram of the radial z]({Path(args.out).with_suffix('.png').name})",
        "",
        f"Per-run values: `experiments/out/{Path(args.out).stem}.csv`.",
        "",
    ]
    if args.set == "boards":
        lines += ["| board | K | T used | form | χ² / dof | radial z | scale − 1 | R̂ max | bulk ESS min | draws | s |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for x in sorted(rows, key=lambda r: (r["seed"], r["form"])):
            lines.append(f"| {x['name']} | {x['K']} | {x['T']} | {x['form']} | {x['chi2']:.1f} / {x['dof']} | "
                         f"{x['radial_z']:+.2f} | {x['scale'] - 1:+.5f} | {x['rhat_max']:.4f} | {x['ess_bulk_min']:.0f} | "
                         f"{x['draws']} | {x['seconds']:.0f} |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    from _dask import add_dask_arguments, dask_client, map_tasks

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--set", choices=("demo", "boards"), default="demo",
                    help="demo configuration over seeds, or the 22 boards of experiments/_boards.py")
    ap.add_argument("--seeds", type=int, default=50, help="--set demo: number of simulated data sets (seeds 1..n)")
    ap.add_argument("--forms", default=",".join(FORMS), help="comma-separated phi_prior forms to run")
    ap.add_argument("--out", default=None,
                    help="results document (default experiments/phi_prior_calibration.md or phi_prior_boards.md)")
    add_dask_arguments(ap)
    args = ap.parse_args(argv)
    if args.out is None:
        args.out = str(HERE / ("phi_prior_calibration.md" if args.set == "demo" else "phi_prior_boards.md"))
    forms = [f for f in args.forms.split(",") if f]
    if not set(forms) <= set(FORMS) or args.seeds < 2:
        ap.error(f"--forms: expected a subset of {FORMS}; --seeds: expected >= 2")
    t0 = time.perf_counter()
    runs = range(1, args.seeds + 1) if args.set == "demo" else range(22)
    params = [dict(seed=s, form=f, data_set=args.set) for s in runs for f in forms]
    with dask_client(args) as client:
        rows = map_tasks(client, one_run, params, desc="calibrations")
    wall = time.perf_counter() - t0
    summ = summarize(rows)
    from accel_bayes.data.outputs import write_text

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]))
    w.writeheader()
    w.writerows(rows)
    (HERE / "out").mkdir(exist_ok=True)
    write_text(HERE / "out" / f"{Path(args.out).stem}.csv", buf.getvalue())
    plot(rows, Path(args.out).with_suffix(".png"))
    write_text(args.out, document(rows, summ, args, wall))
    for form, s in summ.items():
        print(f"{form}: chi2 {s['chi2_sum']:.0f} in {s['band'][0]:.0f}-{s['band'][1]:.0f} {s['chi2_ok']}, "
              f"z {s['z_mean']:+.3f}±{s['z_se']:.3f} {s['z_ok']}, KS p {s['ks_p']:.3g} {s['ks_ok']}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
