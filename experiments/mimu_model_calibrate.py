"""``calibrate --model`` of the six real MIMU4444 experiments, untempered (issues #11 item 5, #30).

Every experiment is calibrated with the same seed and chain length (4 chains × D draws after W
warm-up, seed 0; the issue #30 run used D = W = 500):

* **without** — the default pipeline (``calibrate(rec)``): a noise level per triad at its type-II
  ML, then the likelihood tempered by the sandwich factor κ;
* **with** — ``calibrate(rec, model=report.json)``, the experiment's own mismatch report
  (``experiments/mimu_mismatch.py``): gyro linear blocks inverted, random gyro effects as per-sample
  gyro covariances and, with its ``sampling_clock`` and ``unresolved_motion`` findings, the clocks'
  mean effect taken off and the unresolved motion in the per-sample covariance
  (:mod:`accel_bayes.pipelines.calibrate_model`), NO tempering; the sandwich at the mode recorded,
  and here its decomposition (:func:`decomposition`);
* **with_instant** (optional, ``--variants with_instant``) — the same with ``instant_error=True``:
  each triad's own sampling-instant error times the rate of its output projected out too (off by
  default: ~20× the likelihood's cost);
* **with_jerk_only** (optional, ``--variants with_jerk_only``) — the same with ``angular_jerk=False``
  (CLI ``--no-angular-jerk``): the linear jerk alone, what ``with`` was before the board's angular
  jerk became the default (``bench_likelihood_percov.md``: 2.3× the flat likelihood's cost, bar 4×);
  ``with_angjerk`` (``angular_jerk=True``) is ``with`` itself since then;
* **with_bins** (optional, ``--variants with_bins``) — the same with ``noise_bins=8`` and the flat φ
  prior: the noise level × a factor per |ω̄| octile.

Per experiment and coordinate: posterior mean and std, the sandwich std and its ratio to the
Laplace std at the mode.  Across experiments (:func:`mimu_repeatability.analyse`, the one
implementation): leave-one-out z, z_e = (m_e − m̄_{−e}) / √(s_e² + 1/Σ_{j≠e} s_j⁻²) with m̄_{−e}
the inverse-variance mean of the other five, its RMS (all, exp 1–3, exp 4–6); the spread of the six
means; the x–y spacing of the top IMUs (x of IMUs 4, 6 and −y of IMUs 2, 6; 18.9 mm by design).

    PYTHONPATH=. python3 experiments/mimu_model_calibrate.py --reports experiments/out/mimu_mismatch
        --no-hetero --draws 500 --warmup 500 [--variants with,without,with_instant,with_jerk_only,with_bins]

Results are cached per (variant, experiment) in ``--out``; a rerun only computes what is missing, and
two processes with different ``--variants`` can fill the cache at once.
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
sys.path.insert(0, str(HERE))

from _data import data_dir  # noqa: E402
from _stamp import machine_note  # noqa: E402
from mimu_repeatability import analyse, coordinate_diagnostics  # noqa: E402

from accel_bayes.data.outputs import write_json, write_text  # noqa: E402

VARIANTS = ("without", "with")
# beyond the two the document needs: the model with the noise level × a factor per |ω̄| octile bin
# (the variance growing with the motion, empirical; flat φ prior, which the per-sample rescaling needs)
EXTRA = {"with_bins": dict(noise_bins=8, phi_prior="flat"), "with_instant": dict(instant_error=True),
         "with_angjerk": dict(angular_jerk=True), "with_jerk_only": dict(angular_jerk=False), "with_acc": {}}
# variants calibrated with another report than the experiment's own default one: with_acc takes the report of
# ``mismatch --acc-linear`` on the whole recording (its accelerometer stage on the rest-calibrated outputs),
# the one experiments/mimu_blind_acc.py caches as whole_report.json
ACC_REPORT = "whole_report.json"
AIM_RATIO = 1.15
Z_RMS_BAND = (0.8, 1.25)


def run_one(exp: int, variant: str, data: Path, reports: Path, chains: int, draws: int, warmup: int,
            seed: int, acc_reports: Path | None = None) -> dict:
    """Calibrate experiment ``exp`` without or with its mismatch report (``with_acc``: the report with the
    accelerometer stage, from ``acc_reports``); the numbers the tables need."""
    from accel_bayes.data.mimu import import_mimu
    from accel_bayes.pipelines.calibrate import calibrate

    rec = import_mimu(Path(data) / f"exp_{exp}" / "data.bin.gz")
    model = (None if variant == "without" else acc_reports / f"exp_{exp}" / ACC_REPORT if variant == "with_acc"
             else reports / f"exp_{exp}" / "report.json")
    if model is not None and not model.exists():
        raise SystemExit(f"{model}: no such report (with_acc: run experiments/mimu_blind_acc.py first)")
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        res = calibrate(rec, chains=chains, draws=draws, warmup=warmup, seed=seed, progress=False, model=model,
                        **EXTRA.get(variant, {}))
    doc, st, summ = res.positions, res.settings, res.summary
    rh, ess = coordinate_diagnostics(doc, summ, rec.K)
    nm = st.get("noise_model") or {}
    sw0 = nm.get("sandwich") or {}
    out = {
        "exp": exp, "variant": variant,
        "mean": [e["mean"] for e in doc["imus"]], "std": [e["std"] for e in doc["imus"]],
        "rhat": rh.tolist(), "ess_bulk": ess.tolist(),
        "nominal": (np.asarray(rec.nominal_position) - np.asarray(rec.nominal_position)[rec.reference_imu]).tolist(),
        "noise_std": nm.get("std"), "kappa_applied": sw0.get("applied", 1.0),
        "untempered_ratio_max": sw0.get("std_ratio_max"), "untempered_ratio_median": sw0.get("std_ratio_median"),
        "untempered_kappa": sw0.get("kappa"),
        "num_draws": st["num_draws"], "correlation": st.get("correlation"), "seconds": res.seconds,
        "wall_seconds": time.perf_counter() - t0, "T": st["T"],
    }
    if "model" in st:
        m = st["model"]
        out["model"] = {k: m[k] for k in ("source", "sha256", "used", "skipped", "gyro_posterior")}
        out["sandwich"] = m["sandwich"]
        # with an unresolved_motion finding: the per-sample covariance's record and the flat model's sandwich
        out["unresolved_motion"] = m.get("unresolved_motion")
        out["sandwich_flat"] = m.get("sandwich_flat")
        # with accelerometer blocks: the block term's record and the sandwich before it
        out["acc_blocks"] = m.get("acc_blocks")
        out["sandwich_before_blocks"] = m.get("sandwich_before_blocks")
        out["cov"] = [e.get("cov") for e in doc["imus"]]
        if "percov" in res.extra:
            out["decomposition"] = decomposition(res.extra["percov"], rec, exp)
        out["untempered_ratio_max"] = m["sandwich"]["std_ratio_max"]
        out["untempered_ratio_median"] = m["sandwich"]["std_ratio_median"]
        out["untempered_kappa"] = m["sandwich"]["kappa"]
    return out


SIM_REPS = 3


def decomposition(pc, rec, exp: int) -> dict:
    """Where the per-sample model's sandwich excess sits, at its mode (ω = ω̄), the scores in
    ``sandwich_inflation``'s convention (∂log|M| left out; :mod:`accel_bayes.pipelines.calibrate_model`):
    the meats of ``percov_honesty_probe.py`` (whole sample with Newey–West lags and at lag 0; IMU
    blocks at lag 0), each against the same meat on data simulated from the model at its mode
    (``SIM_REPS`` replicates, seeded by the experiment), as variance factors (median over the
    coordinates): time correlation (NW over lag 0), within-IMU (IMU blocks real / simulated) and
    cross-IMU (sample over IMU blocks, real / simulated); and per quartile of |ω̄| and |ω̈̄|."""
    import torch

    from accel_bayes.inference.noise_fit import per_sample_scores, score_sandwich
    from percov_honesty_probe import block_meat_sandwich, excess_by_quartile, free_of, full_of, simulated_scores

    lik = pc.lik
    A, ref = lik.A, lik.reference
    th = free_of(pc.positions, ref)
    wbar = lik.omega.mean

    def half_logdet_m(t):
        return -0.5 * lik._projection_hot(lik._positions(full_of(t, A, ref))[None])["logdetM"]

    d = per_sample_scores(half_logdet_m, th)[0]
    S = per_sample_scores(lambda t: lik.log_lik_per_sample(full_of(t, A, ref), wbar), th) - d
    Ssim = simulated_scores(lik, th, wbar, torch.Generator().manual_seed(exp), SIM_REPS, lik.phi_prior) - d
    cov = pc.laplace_cov
    r = lambda sw: np.asarray(sw["std_ratio"]) ** 2  # noqa: E731 - variance factors per coordinate
    nw, l0, b0 = r(score_sandwich(S, cov)), r(score_sandwich(S, cov, lags=0)), r(block_meat_sandwich(S, cov, 0))
    snw = r(score_sandwich(Ssim, cov, lags=None)) / SIM_REPS
    s0, sb0 = r(score_sandwich(Ssim, cov, lags=0)) / SIM_REPS, r(block_meat_sandwich(Ssim, cov, 0)) / SIM_REPS
    tk = np.asarray(rec.time)[np.asarray(lik.sample_index)]
    wdd = np.gradient(np.gradient(wbar.numpy(), tk, axis=0), tk, axis=0)
    med = lambda x: float(np.median(x))  # noqa: E731
    return {"in_all": med(nw / snw), "time": med(nw / l0), "within_imu": med(b0 / sb0),
            "cross_imu": med((l0 / s0) / (b0 / sb0)), "simulated_ratio_median": med(np.sqrt(snw)),
            "by_omega_quartile": excess_by_quartile(S, Ssim, cov, wbar.norm(dim=-1), SIM_REPS),
            "by_angular_jerk_quartile": excess_by_quartile(S, Ssim, cov, torch.as_tensor(np.linalg.norm(wdd, axis=1)),
                                                           SIM_REPS)}


HETERO = (("1 level per triad", None, 1), ("× 8 bins of |ω̄|", "omega", 8), ("× 8 bins of |ω̇|", "omega_dot", 8),
          ("× 8 bins of jerk", "jerk", 8))


def heteroscedastic(exp: int, data: Path, reports: Path) -> dict:
    """MAP-level diagnostic: with the model's gyro posterior, the sandwich/Laplace std ratio when the
    accelerometer noise also gets a factor per quantile bin of a motion covariate (type-II ML,
    :func:`accel_bayes.inference.noise_fit.fit_map_with_noise` with ``covariate``; φ prior flat, as the
    rate-bin rescaling needs): |ω̄| (the existing option), |ω̇| (what the ``unexplained`` finding
    says the excess grows with) and the jerk (the detector's top accelerometer covariate: the
    mean over triads of |d acc/dt|).  Does modelling the heteroscedasticity reach the aim?"""
    import torch

    from accel_bayes.data.mimu import import_mimu
    from accel_bayes.model.likelihood import RaoBlackwellLikelihood
    from accel_bayes.physics.effects import output_rates
    from accel_bayes.pipelines.calibrate import _model_gyro_step
    from accel_bayes.model.report_terms import load_model
    from accel_bayes.inference.noise_fit import fit_map_with_noise, sandwich_inflation
    from accel_bayes.model.noise import scale_samples
    from accel_bayes.prep.prepared import prepare_recording
    from accel_bayes.prep.preprocess import preprocess

    raw = import_mimu(Path(data) / f"exp_{exp}" / "data.bin.gz")
    cm = load_model(reports / f"exp_{exp}" / "report.json")
    cm.check_recording(raw)
    pre = preprocess(raw)
    rec = pre.recording
    lik = RaoBlackwellLikelihood.from_recording(prepare_recording(rec, selection=pre.selection), num_draws=1,
                                                gyro_method="calibrated")
    lik, _, _ = _model_gyro_step(lik, rec, cm)
    nominal = torch.as_tensor(np.asarray(rec.nominal_position)[list(lik.imu_labels)], dtype=torch.float64)
    t = np.asarray(rec.time, dtype=float)[lik.sample_index]
    acc_rate, wdot = output_rates(t, lik.acc, lik.omega.mean[:, None])
    cov = {"omega": lik.omega.mean.norm(dim=-1).numpy(), "omega_dot": wdot[:, 0].norm(dim=-1).numpy(),
           "jerk": acc_rate.norm(dim=-1).mean(-1).numpy()}
    rows = []
    for label, key, bins in HETERO:
        c = None if key is None else cov[key]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            res, nm = fit_map_with_noise(lik.acc, lik.omega.mean, lik.omega.cov, lik.acc_noise_std,
                                         reference=lik.reference, prior_mean=nominal, bins=bins, covariate=c)
            s_t = nm.sample_scale(cov["omega"] if c is None else c)
            a_s, w_s, P_s = scale_samples(lik.acc, lik.omega.mean, lik.omega.cov, s_t)
            sw = sandwich_inflation(a_s, w_s, P_s, nm.std, res, reference=lik.reference, prior_mean=nominal)
        if key is None:  # where the misfit sits: the sandwich clustered by channel, triad and sample
            parts = []
            for unit in ("channel", "triad", "sample"):
                for lags in (0, None):
                    sc = sandwich_inflation(a_s, w_s, P_s, nm.std, res, reference=lik.reference, prior_mean=nominal,
                                            cluster=unit, lags=lags)
                    parts.append({"cluster": unit, "lags": int(sc["lags"]),
                                  "relative_max": float(np.max(sc["std_ratio_relative"])),
                                  "relative_median": float(np.median(sc["std_ratio_relative"])),
                                  "white_median": float(np.median(sc["std_ratio_white"]))})
        pos = res.positions.numpy() * 1e3
        rows.append({"variant": label, "covariate": key, "bins": bins, "kappa": float(sw["kappa"]),
                     "ratio_max": float(np.max(sw["std_ratio"])), "ratio_median": float(np.median(sw["std_ratio"])),
                     "bin_scale": [float(v) for v in nm.bin_scale],
                     "spacing_x_mm": float(0.5 * (pos[4, 0] + pos[6, 0])),
                     "spacing_y_mm": float(-0.5 * (pos[2, 1] + pos[6, 1]))})
    return {"exp": exp, "rows": rows, "clusters": parts}


def _free_stack(results, key):
    """(E, 21) of a per-IMU (K, 3) quantity over the free IMUs (1..7), coordinates IMU-major."""
    return np.array([np.asarray(r[key], dtype=float)[1:].reshape(-1) for r in results])


def spacing(results) -> dict:
    """x–y spacing of the top IMUs per experiment (mm): x of IMUs 4 and 6, −y of IMUs 2 and 6."""
    sx, sy = [], []
    for r in results:
        m = np.asarray(r["mean"], dtype=float) * 1e3
        sx.append(0.5 * (m[4, 0] + m[6, 0]))
        sy.append(-0.5 * (m[2, 1] + m[6, 1]))
    sx, sy = np.array(sx), np.array(sy)
    return {"x_mm": sx.tolist(), "y_mm": sy.tolist(), "x_mean": float(sx.mean()), "y_mean": float(sy.mean()),
            "all_min": float(min(sx.min(), sy.min())), "all_max": float(max(sx.max(), sy.max()))}


def spacing_pooled(results) -> dict:
    """Inverse-variance pooled x and y spacing over the experiments, 'mean ± std' (mm), each
    experiment's std from its four coordinates' posterior std (cross-IMU covariances left out)."""
    out = {}
    for ax, (i, j, c, sgn) in (("x", (4, 6, 0, 1)), ("y", (2, 6, 1, -1))):
        v, s2 = [], []
        for r in results:
            m, sd = np.asarray(r["mean"], dtype=float) * 1e3, np.asarray(r["std"], dtype=float) * 1e3
            v.append(sgn * 0.5 * (m[i, c] + m[j, c]))
            s2.append(0.25 * (sd[i, c] ** 2 + sd[j, c] ** 2))
        w = 1 / np.asarray(s2)
        out[ax] = f"{float((w * v).sum() / w.sum()):.3f} ± {float(w.sum() ** -0.5):.3f}"
    return out


def _rel(path: Path) -> str:
    """``path`` relative to the repository when it lies inside it (the document must not name a checkout)."""
    try:
        return str(Path(path).resolve().relative_to(HERE.parent))
    except ValueError:
        return str(path)


def _variant_paragraph(what: str, b: dict, n_exps: int, *, timed: bool) -> str:
    """One optional variant's must-show figures as a sentence (``b``: its :func:`summarise` entry)."""
    zb = np.asarray(b["analysis"]["z_loo"], dtype=float).reshape(n_exps, -1)
    zrb = lambda sl: float(np.sqrt(np.mean(zb[sl] ** 2)))  # noqa: E731
    out = (f"{what}: sandwich/Laplace ratio max {', '.join(_f(x) for x in b['ratio_max'])} (median "
           f"{', '.join(_f(x) for x in b['ratio_median'])}); sandwich/posterior max "
           f"{', '.join(_f(x) for x in b['sandwich_over_posterior_max'])}; LOO z RMS {zrb(slice(None)):.2f} / "
           f"{zrb(slice(0, 3)):.2f} / {zrb(slice(3, 6)):.2f} (all / exp 1–3 / exp 4–6), max |z| {np.abs(zb).max():.2f}; "
           f"median posterior std {', '.join(_f(x, '.0f') for x in b['std_um_median'])} µm; spacing pooled x / y "
           f"{b['spacing_unc']['x']} / {b['spacing_unc']['y']} mm")
    if not timed:
        return out + "."
    return (out + f"; wall time per calibration {', '.join(f'{x:.0f}' for x in b['seconds'])} s. Bar (ratio ≤ 1.3 "
            f"everywhere) with it: {'YES' if all(x <= 1.3 for x in b['ratio_max']) else 'NO'}.")


def layer_shift_um(a: dict, b: dict) -> list | None:
    """(x, y) µm: how far record ``a``'s lower-layer IMUs (more than 1 mm below the reference: the board's
    underside) moved against its upper-layer ones, relative to record ``b`` (reference excluded;
    :func:`mimu_blind_acc.layer_shift` on these records, whose reference is the IMU at the nominal origin);
    None on a one-layer board."""
    from mimu_blind_acc import layer_shift

    ref = int(np.argmin(np.abs(np.asarray(a["nominal"], dtype=float)).sum(1)))
    sh = layer_shift(dict(a, reference_imu=ref), dict(b, reference_imu=ref))
    return None if sh is None else [float(v) for v in sh]


def acc_markdown(results, summ) -> str:
    """with_acc against with, per experiment: the blocks' tolerance, the underside layer's shift, the sandwich
    ratio before / after the blocks, the median std, and the z of their difference."""
    rw = {r["exp"]: r for r in results["with"]}
    L = ["| exp | τ_M % / τ_b m/s² | underside − upper layer, with_acc − with (x, y) µm | z RMS / max of with_acc − "
         "with (combined std) | sandwich/Laplace max: before the blocks → with them | median std with / with_acc "
         "(µm) |", "|---|---|---|---|---|---|"]
    for r in sorted(results["with_acc"], key=lambda r: r["exp"]):
        w = rw[r["exp"]]
        ab = r.get("acc_blocks") or {}
        sh = layer_shift_um(r, w)
        d = (_free_stack([r], "mean") - _free_stack([w], "mean"))[0]
        sd = np.sqrt(_free_stack([r], "std")[0] ** 2 + _free_stack([w], "std")[0] ** 2)
        z = d / sd
        before = (r.get("sandwich_before_blocks") or {}).get("std_ratio_max")
        L.append(f"| {r['exp']} | {100 * ab.get('tau_matrix', float('nan')):.2f} / {ab.get('tau_bias_m_s2', float('nan')):.3f} | "
                 + ("—" if sh is None else f"({sh[0]:+.0f}, {sh[1]:+.0f})")
                 + f" | {np.sqrt(np.mean(z ** 2)):.2f} / {np.abs(z).max():.2f} | "
                 f"{_f(before)} → {r['untempered_ratio_max']:.2f} | "
                 f"{np.median(_free_stack([w], 'std')) * 1e6:.0f} / {np.median(_free_stack([r], 'std')) * 1e6:.0f} |")
    a = summ.get("with_acc") or {}
    if "z_loo_rms_without_cut" in a:
        L += ["", f"The cut common part (the chips' shared 3×3 and offset, drawn from its prior) adds a std of "
                  f"{', '.join(f'{x:.0f}' for x in a['cut_std_um_median'])} µm (median per experiment) that no repeat "
                  f"can check (the same chips in every experiment); without it the LOO z RMS is "
                  f"{a['z_loo_rms_without_cut']:.2f}, max |z| {a['z_loo_max_without_cut']:.2f}."]
    return "\n".join(L)


def decomposition_markdown(results) -> list:
    """The per-sample model's sandwich excess split (:func:`decomposition`), one row per experiment."""
    rs = [r for r in sorted(results["with"], key=lambda r: r["exp"]) if r.get("decomposition")]
    if not rs:
        return []
    rsb = [r for v in ("with_instant", "with_angjerk", "with_jerk_only", "with_bins")
           for r in sorted(results.get(v, []), key=lambda r: r["exp"]) if r.get("decomposition")]
    L = ["## Where the excess sits after the model (negative result's decomposition)", "",
         "At the per-sample model's mode, its scores (`sandwich_inflation`'s convention), variance factors real / "
         "simulated from the model itself at its mode (3 replicates; 1 = what the model predicts), median over the "
         "21 coordinates: *in all* (Newey–West meat), *time* (NW over lag 0, real), *within-IMU* (IMU-block meat: "
         "heteroscedasticity, in-triad correlation, tails), *cross-IMU* (whole sample over IMU blocks); then the "
         "within-IMU / cross-IMU factors per quartile of |ω̄| and of |ω̈̄| (low → high).", "",
         "| exp | in all | time | within-IMU | cross-IMU | by \\|ω̄\\| quartile: within / cross | by \\|ω̈̄\\| "
         "quartile: within / cross |", "|---|---|---|---|---|---|---|"]
    def q(rows):
        return "; ".join(f"{x['imu_block']:.2f} / {x['sample'] / x['imu_block']:.2f}" for x in rows)

    label = {"with_bins": " (× 8 \\|ω̄\\| bins)", "with_instant": " (+ instant error)",
             "with_angjerk": " (+ angular jerk)", "with_jerk_only": " (jerk only)"}
    for r in rs + rsb:
        d = r["decomposition"]
        L.append(f"| {r['exp']}{label.get(r['variant'], '')} | {d['in_all']:.2f} | {d['time']:.2f} | {d['within_imu']:.2f} | {d['cross_imu']:.2f} | "
                 f"{q(d['by_omega_quartile'])} | {q(d['by_angular_jerk_quartile'])} |")
    L += ["", "## The per-sample covariance per experiment", "",
          "| exp | report sha256 (first 16) | band samples | jerk rms, report (m/s³) | jerk rms, fitted here (m/s³) | "
          "type-II gain (nats) | angular jerk rms, fitted here (rad/s³) | its gain over the jerk alone (nats) | "
          "centred age rms (ms) | instant error e, report / fitted (ms) | its gain over the "
          "jerk alone (nats) | triad output rate rms (m/s³) |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    ms = lambda v: "—" if v is None else f"{1e3 * v:.3f}"  # noqa: E731
    for r in rs + [r for r in rsb if r["variant"] in ("with_angjerk", "with_jerk_only")]:
        u = r["unresolved_motion"]
        gi = u.get("instant_error_gain_nats")
        rr = u.get("triad_rate_rms_m_s3")
        ga = u.get("angular_jerk_gain_nats")
        aj = ", ".join("—" if v is None else f"{v:.3g}" for v in (u.get("angular_jerk_rms_fitted_rad_s3") or [None]))
        L.append(f"| {r['exp']}{label.get(r['variant'], '')} | {r['model']['sha256'][:16]} | {', '.join(str(n) for n in u['band_samples'])} | "
                 f"{', '.join(f'{v:.3g}' for v in u['jerk_rms_report_m_s3'])} | "
                 f"{', '.join('—' if v is None else f'{v:.3g}' for v in u['jerk_rms_fitted_m_s3'])} | "
                 f"{u['type2_gain_nats']:.0f} | {aj} | {'—' if ga is None else f'{ga:.0f}'} | "
                 f"{1e3 * u['age_rms_s']:.3f} | "
                 f"{ms(u.get('instant_error_rms_report_s'))} / {ms(u.get('instant_error_rms_fitted_s'))} | "
                 f"{'—' if gi is None else f'{gi:.0f}'} | {'—' if rr is None else f'{rr:.3g}'} |")
    return L + [""]


def summarise(results: dict) -> dict:
    """Per variant: the repeatability analysis, the std ratios, z RMS, spread and spacing."""
    out = {}
    n = len(results["with"])
    for v in [v for v in results if len(results[v]) == n]:
        rs = sorted(results[v], key=lambda r: r["exp"])
        an = analyse(rs)
        s = {"analysis": an, "spacing": spacing(rs), "spacing_unc": spacing_pooled(rs),
             "spread_um": (np.asarray(an["spread"]) * 1e6).tolist(),
             "ratio_max": [r["untempered_ratio_max"] for r in rs],
             "ratio_median": [r["untempered_ratio_median"] for r in rs],
             "kappa": [r["untempered_kappa"] for r in rs], "kappa_applied": [r["kappa_applied"] for r in rs],
             "std_um_median": [float(np.median(_free_stack([r], "std")) * 1e6) for r in rs],
             "seconds": [r["wall_seconds"] for r in rs]}
        if v != "without":
            post = _free_stack(rs, "std")
            sand = np.array([r["sandwich"]["sandwich_std_m"] for r in rs])
            s["sandwich_over_posterior"] = (sand / post).tolist()
            s["sandwich_over_posterior_max"] = (sand / post).max(1).tolist()
            s["sandwich_over_posterior_median"] = np.median(sand / post, 1).tolist()
            # LOO z with each experiment's std replaced by its sandwich std (what an honest std would be)
            rs2 = [dict(r, std=[[0.0, 0.0, 0.0]] + np.asarray(r["sandwich"]["sandwich_std_m"]).reshape(-1, 3).tolist())
                   for r in rs]
            s["z_loo_rms_sandwich"] = analyse(rs2)["z_loo_rms"]
            cut = [(r.get("sandwich") or {}).get("cut_std_m") for r in rs]
            if all(c is not None for c in cut):
                # the cut common part is the same chips' error in every experiment: repeats cannot show it, so
                # LOO z also with each std less the cut's spread (what the repeats can check)
                rs3 = [dict(r, std=[[0.0, 0.0, 0.0]] + np.sqrt(np.clip(_free_stack([r], "std")[0] ** 2
                                                                        - np.asarray(c) ** 2, 0, None))
                            .reshape(-1, 3).tolist()) for r, c in zip(rs, cut)]
                a3 = analyse(rs3)
                s["z_loo_rms_without_cut"] = a3["z_loo_rms"]
                s["z_loo_max_without_cut"] = float(np.nanmax(np.abs(a3["z_loo"])))
                s["cut_std_um_median"] = [float(np.median(c) * 1e6) for c in cut]
        out[v] = s
    return out


MUST_SHOW_COLUMNS = (("without", "without model (default, tempered)"), ("with", "with model (untempered)"),
                     ("with_acc", "with model + accelerometer stage (`mismatch --acc-linear`; untempered)"))


def must_show_table(summ: dict, z: dict) -> list:
    """Issue #30's must-show table, one column per variant present (``z``: variant → (E, 21) LOO z)."""
    cols = [(v, t) for v, t in MUST_SHOW_COLUMNS if v in summ and v in z]
    j = lambda xs, fmt=".2f": ", ".join(_f(x, fmt) for x in xs)  # noqa: E731

    def zr(v, sl):
        return float(np.sqrt(np.mean(z[v][sl] ** 2)))

    def loo(v):
        s = summ[v]
        out = f"{zr(v, slice(None)):.2f} / {zr(v, slice(0, 3)):.2f} / {zr(v, slice(3, 6)):.2f}"
        if "z_loo_rms_sandwich" in s:
            out += f" (with the sandwich std instead: {s['z_loo_rms_sandwich']:.2f})"
        if "z_loo_rms_without_cut" in s:
            out += f" (without the cut's spread: {s['z_loo_rms_without_cut']:.2f})"
        return out

    def spread(v):
        sp = np.ravel(summ[v]["spread_um"])
        return f"{sp.min():.0f}–{np.median(sp):.0f}–{sp.max():.0f}"

    rows = [
        ("sandwich/Laplace std ratio, max over coordinates (per experiment)",
         lambda v, s: j(s["ratio_max"]) + (" (before tempering)" if v == "without" else ""), "≤ 1.3 (aim 1.15)"),
        ("same, median", lambda v, s: j(s["ratio_median"]), ""),
        ("sandwich std / PmMH posterior std, max (median) per experiment",
         lambda v, s: "—" if "sandwich_over_posterior_max" not in s else ", ".join(
             f"{a:.2f} ({b:.2f})" for a, b in zip(s["sandwich_over_posterior_max"],
                                                  s["sandwich_over_posterior_median"])), "≤ 1.3"),
        ("LOO z RMS, all / exp 1–3 / exp 4–6", lambda v, s: loo(v), "0.8–1.25"),
        ("max \\|LOO z\\|, all / exp 4–6", lambda v, s: f"{np.abs(z[v]).max():.2f} / {np.abs(z[v][3:]).max():.2f}",
         "< 4"),
        ("posterior std, median over coordinates (µm)", lambda v, s: j(s["std_um_median"], ".0f"),
         "≤ the default's"),
        ("x–y spacing, pooled (inverse-variance) x / y (mm ± posterior std)",
         lambda v, s: f"{s['spacing_unc']['x']} / {s['spacing_unc']['y']}", "18.9"),
        ("x–y spacing per experiment, x / y (mm)",
         lambda v, s: "; ".join(f"{a:.3f} / {b:.3f}" for a, b in zip(s["spacing"]["x_mm"], s["spacing"]["y_mm"])), ""),
        ("spread of the six means per coordinate (µm), min–median–max", lambda v, s: spread(v), ""),
        ("κ (mean variance ratio) measured / applied", lambda v, s: f"{j(s['kappa'])} / {j(s['kappa_applied'])}", ""),
        ("R̂ max / bulk ESS min over experiments",
         lambda v, s: f"{max(s['analysis']['rhat_max']):.3f} / {min(s['analysis']['ess_min']):.0f}", ""),
        ("wall time per calibration (s, this run's load)", lambda v, s: j(s["seconds"], ".0f"), ""),
    ]
    L = ["| | " + " | ".join(t for _, t in cols) + " | bar |", "|---|" + "---|" * len(cols) + "---|"]
    for name, f, bar in rows:
        L.append(f"| {name} | " + " | ".join(f(v, summ[v]) for v, _ in cols) + f" | {bar} |")
    return L


def pooled_means(rs) -> tuple:
    """(mean (K, 3) m, its std (K, 3) m, median per-experiment std (K, 3) m): the inverse-variance pooled
    position of every IMU over the experiments ``rs`` (records with ``mean``/``std`` (K, 3); the reference's zero
    std gives NaN there)."""
    m = np.array([r["mean"] for r in rs], dtype=float)
    s = np.array([r["std"] for r in rs], dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = 1.0 / s ** 2
        mean = (w * m).sum(0) / w.sum(0)
        return mean, w.sum(0) ** -0.5, np.median(s, 0)


def means_table(results) -> list:
    """Issue #30's "comparison with today's tempered default (means and std) in one table": per IMU and axis the
    six experiments' inverse-variance pooled position ± its std (mm ± µm) and the median per-experiment std (µm),
    for every variant of :data:`MUST_SHOW_COLUMNS` present, beside the design position."""
    cols = [(v, t) for v, t in MUST_SHOW_COLUMNS if len(results.get(v, [])) == len(results["with"])]
    pooled = {v: pooled_means(sorted(results[v], key=lambda r: r["exp"])) for v, _ in cols}
    nominal = np.asarray(results["with"][0]["nominal"], dtype=float)
    L = ["", "## Per IMU: pooled means and std against the tempered default", "",
         "Each coordinate's inverse-variance mean over the six experiments ± its std (mm ± µm), and in brackets the "
         "median of the six runs' posterior std (µm); the design position last.", "",
         "| coordinate | " + " | ".join(t for _, t in cols) + " | design (mm) |", "|---|" + "---|" * len(cols) + "---|"]
    for k in range(nominal.shape[0]):
        if all(np.isnan(pooled[v][0][k]).all() for v, _ in cols):
            continue  # the reference IMU (zero std: nothing to pool)
        for a, ax in enumerate("xyz"):
            cells = [f"{1e3 * pooled[v][0][k, a]:.3f} ± {1e6 * pooled[v][1][k, a]:.0f} ({1e6 * pooled[v][2][k, a]:.0f})"
                     for v, _ in cols]
            L.append(f"| r[{k}, {ax}] | " + " | ".join(cells) + f" | {1e3 * nominal[k, a]:.3f} |")
    return L


def _f(x, fmt=".2f"):
    return "n/a" if x is None else format(x, fmt)


def markdown(results: dict, summ: dict, args) -> str:
    w, m = summ["without"], summ["with"]
    exps = sorted(r["exp"] for r in results["with"])
    z = {v: np.asarray(summ[v]["analysis"]["z_loo"], dtype=float).reshape(len(exps), -1)
         for v in (*VARIANTS, "with_acc") if v in summ}
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    L = ["# `calibrate --model` of the six MIMU4444 experiments, untempered (issues #11 item 5, #30)", "",
         f"Regenerate: `PYTHONPATH=. python3 experiments/mimu_model_calibrate.py --reports {_rel(args.reports)} "
         + (f"--acc-reports {_rel(args.acc_reports)} " if "with_acc" in results else "") + "--no-hetero "
         f"--draws {args.draws} --warmup {args.warmup} --variants {','.join(results)} --out {_rel(args.out)}` "
         f"({stamp}; {machine_note()} at the end, one torch thread; results cached in `{_rel(args.out)}`). Reports: each experiment's own `mismatch` report "
         "(`experiments/mimu_mismatch.py --stage detect`: whole-recording `detect` with its defaults), sha256 in the table below. Each "
         f"experiment is calibrated once per variant, {args.chains} chains × {args.draws} draws after {args.warmup} warm-up, "
         f"seed {args.seed}: **without** — the default pipeline (noise level per triad at its type-II ML, likelihood "
         "tempered by the sandwich factor κ); **with** — `calibrate(rec, model=report.json)`: the gyro linear blocks "
         "inverted, the `timing_wander` findings as per-sample gyro covariances, the `sampling_clock` ages and the "
         "`unresolved_motion` angular acceleration in the fused ω posterior, the unresolved jerk and (the "
         "default since its cost met the 4× bar) the board's angular jerk loaded by the centred data ages (times "
         "the lever arms) in the per-sample likelihood (`model/likelihood_percov.py`, one scale each per report |ω| "
         "band by type-II ML at the MAP, noise levels kept; an IMU the report leaves without a clock on the "
         "clocked IMUs' mean age with its register hold's random age as covariance), chains centred on that likelihood's own mode, **no "
         "tempering**" + ("; **with_instant** — the same with `instant_error=True`: beside the jerk each triad's own "
                          "sampling-instant error times the rate of its output (per-triad covariance e² ρ_kt ρ_ktᵀ, "
                          "one e by type-II ML from the report's `age_error_rms_s`), off by default (~20× the "
                          "likelihood's cost)" if "with_instant" in results else "") + ".", "",
         "Definitions. *Ratio*: sandwich std / Laplace std at the mode of the chains' untempered likelihood, per "
         "coordinate (21 per experiment; `without`: the pipeline's own `sandwich_inflation` before it tempers; "
         "`with`: the per-sample model's own scores in `sandwich_inflation`'s convention, Newey–West lags, "
         "`pipelines/calibrate_model.py`). *LOO z*: for experiment e and coordinate c, z = (m_e − m̄_{−e}) / "
         "√(s_e² + 1/Σ_{j≠e} s_j⁻²), m̄_{−e} the inverse-variance mean of the other five, s the posterior std of "
         "the run (`experiments/mimu_repeatability.py`'s `analyse`); RMS over the values, 1 for honest stds. Every "
         "setting of the model is fixed before any experiment is seen (the scales are fitted per experiment by type-II "
         "ML, as the noise levels are); exp 1–3 and exp 4–6 are reported apart. *Spacing*: x of IMUs 4 and 6 and −y of "
         "IMUs 2 and 6 (top IMUs), averaged per axis; 18.9 mm by design; its std from the posterior std of the four "
         "coordinates (cross-IMU covariances not in positions.json, left out).", "",
         "## Must show (issue #30)", "",
         ] + must_show_table(summ, z) + [""]
    extra = {"with_bins": "The model with the noise level × a factor per |ω̄| octile bin (`noise_bins=8`, flat φ prior: "
                          "the per-sample rescaling needs it; fixed before any experiment was seen)",
             "with_instant": "The model with each triad's instant error (`instant_error=True`, CLI `--instant-error`; "
                             "fixed before any experiment was seen)",
             "with_angjerk": "The model with the board's angular jerk (`angular_jerk=True`, CLI `--angular-jerk`; "
                             "fixed before any experiment was seen, on `angjerk_probe.md`'s likelihood gain)",
             "with_jerk_only": "The model with the linear jerk alone (`angular_jerk=False`, CLI `--no-angular-jerk`: what "
                               "`calibrate --model` did before the angular jerk became its default)",
             "with_acc": "**with_acc** — the model of `mismatch --acc-linear` on the whole recording (its accelerometer "
                         "stage on the rest-calibrated outputs: each triad's linear error the rests leave, "
                         f"`{_rel(args.acc_reports)}/exp_N/{ACC_REPORT}`, written by `experiments/mimu_blind_acc.py`), "
                         "calibrated with every default (the blocks integrated out, τ by type-II ML, their common part "
                         "cut); the sandwich is the integrated target's (Fisher's identity: "
                         "`acc_block_marginal.marginal_scores`)"}
    for v, what in extra.items():
        if v in summ:
            L += [_variant_paragraph(what, summ[v], len(exps),
                                     timed=v in ("with_instant", "with_angjerk", "with_jerk_only", "with_acc")), ""]
    if "with_acc" in summ:
        L += acc_markdown(results, summ), ""
    met = all(x <= 1.3 for x in m["ratio_max"])
    L += [f"**Bar (every coordinate's sandwich/Laplace ratio ≤ 1.3) met with the model: "
          f"{'YES' if met else 'NO'}** (max over experiments {max(m['ratio_max']):.2f})."
          + ("" if "with_acc" not in summ else
             f" With the accelerometer stage as well: **{'YES' if all(x <= 1.3 for x in summ['with_acc']['ratio_max']) else 'NO'}** "
             f"(max {max(summ['with_acc']['ratio_max']):.2f})."), ""]
    L += decomposition_markdown(results)
    L += ["## Per experiment: the model's gyro posterior and the noise levels", "",
          "| exp | T | findings used | skipped | ω shift RMS (rad/s) | median ω std calibrated → model (mrad/s) | "
          "acc levels without (m/s²) | acc levels with (m/s²) |", "|---|---|---|---|---|---|---|---|"]
    rw = {r["exp"]: r for r in results["without"]}
    for r in sorted(results["with"], key=lambda r: r["exp"]):
        mo = r["model"]
        used = ", ".join(f"{u['effect']}[{u['imu']}]" for u in mo["used"])
        sk = ", ".join(f"{u['effect']}[{u['imu']}, {u.get('sensor')}]" for u in mo["skipped"])
        g = mo["gyro_posterior"]
        L.append(f"| {r['exp']} | {r['T']} | {used} | {sk} | {g['omega_shift_rms_rad_s']:.3f} | "
                 f"{1e3 * g['omega_std_median_rad_s']['calibrated']:.2f} → {1e3 * g['omega_std_median_rad_s']['model']:.2f} | "
                 f"{', '.join(f'{x:.2f}' for x in rw[r['exp']]['noise_std'])} | "
                 f"{', '.join(f'{x:.2f}' for x in r['noise_std'])} |")
    L += ["", "## Per coordinate (with model): Laplace std, sandwich std and ratio at the MAP, PmMH posterior std "
          "(µm), each experiment", "",
          "| coordinate | " + " | ".join(f"exp {e}: post / sandwich (ratio)" for e in exps) + " |",
          "|---|" + "---|" * len(exps)]
    names = results["with"][0]["sandwich"]["coordinates"]
    rs = sorted(results["with"], key=lambda r: r["exp"])
    post = _free_stack(rs, "std")
    for c, nmc in enumerate(names):
        L.append(f"| {nmc} | " + " | ".join(
            f"{1e6 * post[i, c]:.0f} / {1e6 * r['sandwich']['sandwich_std_m'][c]:.0f} ({r['sandwich']['std_ratio'][c]:.2f})"
            for i, r in enumerate(rs)) + " |")
    L += ["", "## Per IMU: spread of the six means and RMS posterior std (µm), x / y / z", "",
          "| IMU | spread without | RMS std without | spread with | RMS std with | max \\|z\\| without | max \\|z\\| with |",
          "|---|---|---|---|---|---|---|"]
    for i, k in enumerate(w["analysis"]["imus"]):
        def trip(a):
            return " / ".join(f"{1e6 * v:.0f}" for v in a[i])
        zw = np.abs(np.asarray(w["analysis"]["z_loo"])[:, i]).max()
        zm = np.abs(np.asarray(m["analysis"]["z_loo"])[:, i]).max()
        L.append(f"| {k} | {trip(w['analysis']['spread'])} | {trip(w['analysis']['rms_std'])} | "
                 f"{trip(m['analysis']['spread'])} | {trip(m['analysis']['rms_std'])} | {zw:.2f} | {zm:.2f} |")
    L += means_table(results)
    L += ["", "## Spacing per experiment (mm): x (IMUs 4, 6) / y (IMUs 2, 6)", "",
          "| exp | without | with |", "|---|---|---|"]
    for i, e in enumerate(exps):
        L.append(f"| {e} | {w['spacing']['x_mm'][i]:.3f} / {w['spacing']['y_mm'][i]:.3f} | "
                 f"{m['spacing']['x_mm'][i]:.3f} / {m['spacing']['y_mm'][i]:.3f} |")
    if summ.get("hetero"):
        L += ["", "## Diagnostic (MAP only): the model plus a heteroscedastic accelerometer noise", "",
              "With the model's gyro posterior, the accelerometer noise level per triad times a factor per quantile "
              "bin of a motion covariate, all at their type-II ML (`fit_map_with_noise(..., covariate=)`), φ prior flat "
              "(the per-sample rescaling needs it); sandwich/Laplace std ratio at that MAP, max (median) over the 21 "
              "coordinates, and the MAP's x / y spacing (mm). The flat φ prior itself pulls the spacing inward "
              "(`experiments/mimu_repeatability.md`), so compare the spacing within this table only.", "",
              "| exp | " + " | ".join(r["variant"].replace("|", "\\|") for r in summ["hetero"][0]["rows"]) + " |",
              "|---|" + "---|" * len(summ["hetero"][0]["rows"])]
        for h in summ["hetero"]:
            L.append(f"| {h['exp']} | " + " | ".join(
                f"{r['ratio_max']:.2f} ({r['ratio_median']:.2f}); {r['spacing_x_mm']:.3f} / {r['spacing_y_mm']:.3f}"
                for r in h["rows"]) + " |")
        L += ["", "Where the misfit sits (same MAP, one level per triad): the sandwich with the scores summed per "
              "channel, per triad or per sample (`sandwich_inflation(cluster=)`), each divided by what that clustering "
              "gives under the model's own white noise (`std_ratio_relative`; the white reference of the per-sample "
              "sandwich is 1.00 here), median (max) over the 21 coordinates, without lags / with the Newey–West lags. "
              "Channel: heteroscedasticity alone; triad: + correlation within a triad; sample: + correlation between "
              "the triads of a sample; lags: + correlation in time.", "",
              "| exp | channel | triad | sample |", "|---|---|---|---|"]
        for h in summ["hetero"]:
            by = {(c["cluster"], c["lags"] > 0): c for c in h["clusters"]}
            L.append(f"| {h['exp']} | " + " | ".join(
                f"{by[(u, False)]['relative_median']:.2f} ({by[(u, False)]['relative_max']:.2f}) / "
                f"{by[(u, True)]['relative_median']:.2f} ({by[(u, True)]['relative_max']:.2f})"
                for u in ("channel", "triad", "sample")) + " |")
        L.append("")
        L.append("Bin factors s_b (std ratio, mean s² = 1), exp " + str(summ["hetero"][0]["exp"]) + ": " + "; ".join(
            f"{r['variant']}: " + ", ".join(f"{v:.2f}" for v in r["bin_scale"]) for r in summ["hetero"][0]["rows"][1:]))
    L += ["", "![Sandwich/Laplace std ratio per coordinate, with the model](figures/mimu_model_calibrate_ratio.png)", ""]
    return "\n".join(L) + "\n"


def figure(results: dict, summ: dict, path: Path) -> Path:
    """The per-coordinate sandwich/Laplace ratios with the model (and with the accelerometer stage, when run),
    and what the stage moves: each IMU's x, y with_acc − with per experiment."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mimu_blind_acc import lower_layer

    rs = sorted(results["with"], key=lambda r: r["exp"])
    ra = sorted(results.get("with_acc", []), key=lambda r: r["exp"])
    names = rs[0]["sandwich"]["coordinates"]
    fig, axes = plt.subplots(2 if ra else 1, 1, figsize=(10, 7.5 if ra else 4), squeeze=False)
    ax = axes[0, 0]
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, r in enumerate(rs):
        ax.plot(range(len(names)), r["sandwich"]["std_ratio"], "o-", ms=3, lw=0.8, color=colors[i % 10],
                label=f"exp {r['exp']}")
    for i, r in enumerate(ra):
        ax.plot(range(len(names)), r["sandwich"]["std_ratio"], "x--", ms=3, lw=0.6, color=colors[i % 10],
                label="+ acc stage" if i == 0 else None)
    for r in sorted(results["without"], key=lambda r: r["exp"]):
        ax.axhline(r["untempered_ratio_median"], color="0.6", lw=0.6, ls=":")
    ax.axhline(AIM_RATIO, color="k", ls="--", lw=1, label=f"aim {AIM_RATIO}")
    ax.axhline(1.0, color="k", lw=0.5)
    top = max([1.3] + [r["untempered_ratio_median"] for r in results["without"]])
    ax.set_ylim(0.4, top + 0.1)  # the grey lines of the run without the model inside the frame
    ax.set_xticks(range(len(names)))
    ax.set_xticklabels(names, rotation=90, fontsize=7)
    ax.set_ylabel("sandwich std / Laplace std at the mode")
    ax.set_title("With the mismatch model, untempered (x, dashed: with the accelerometer stage; "
                 "dotted grey: median ratio without the model)", fontsize=9)
    ax.legend(fontsize=7, ncol=4)
    if ra:
        ax = axes[1, 0]
        K = len(ra[0]["mean"])
        for i, (a, w) in enumerate(zip(ra, rs)):
            d = (np.asarray(a["mean"], dtype=float) - np.asarray(w["mean"], dtype=float)) * 1e6
            sd = np.sqrt(np.asarray(a["std"], dtype=float) ** 2 + np.asarray(w["std"], dtype=float) ** 2) * 1e6
            for c, (mk, off) in enumerate((("o", -0.15), ("s", 0.15))):
                x = np.arange(K) + off + 0.04 * (i - 2.5)
                ax.errorbar(x[1:], d[1:, c], yerr=sd[1:, c], fmt=mk, ms=3, lw=0.6, color=colors[i % 10],
                            label=(f"exp {a['exp']}" if c == 0 else None))
        nominal = np.asarray(ra[0]["nominal"], dtype=float)
        low = lower_layer(nominal, int(np.argmin(np.abs(nominal).sum(1))))  # the reference: the IMU at the origin
        ax.set_xticks(range(K))
        ax.set_xticklabels([f"IMU {k}" + (" (under)" if k in low else "") for k in range(K)], fontsize=8)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylabel("with acc stage − with (µm)")
        ax.set_title("Positions the accelerometer stage moves: x (circles, left) and y (squares, right) per IMU, "
                     "± combined std (IMU 0 the reference)", fontsize=9)
        ax.legend(fontsize=7, ncol=6)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


READING_MARK = "<!-- reading: hand-written below this line, kept when the document is regenerated -->"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--reports", type=Path, default=HERE / "out" / "mimu_mismatch")
    ap.add_argument("--acc-reports", type=Path, default=HERE / "out" / "mimu_blind_acc",
                    help=f"variant with_acc: the reports of mismatch --acc-linear on the whole recordings "
                         f"(exp_N/{ACC_REPORT}, written by experiments/mimu_blind_acc.py)")
    ap.add_argument("--out", type=Path, default=HERE / "out" / "mimu_model_calibrate")
    ap.add_argument("--doc", type=Path, default=HERE / "mimu_model_calibrate.md")
    ap.add_argument("--experiments", default="1,2,3,4,5,6")
    ap.add_argument("--chains", type=int, default=4)
    ap.add_argument("--draws", type=int, default=1000)
    ap.add_argument("--warmup", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-hetero", action="store_true", help="skip the MAP-level heteroscedasticity diagnostic")
    ap.add_argument("--variants", default=",".join(VARIANTS),
                    help="compute only these variants (two processes can fill the cache in parallel); the document "
                         "is written when every variant of every experiment is cached")
    args = ap.parse_args(argv)
    data = args.data or data_dir()
    exps = [int(x) for x in args.experiments.split(",")]
    todo = set(args.variants.split(","))
    allv = VARIANTS + tuple(v for v in EXTRA if v in todo or (args.out / v).exists())
    results = {v: [] for v in allv}
    for e in exps:
        for v in allv:
            f = args.out / v / f"exp_{e}.json"
            if f.exists():
                r = json.loads(f.read_text())
            elif v not in todo:
                continue
            else:
                r = run_one(e, v, data, args.reports, args.chains, args.draws, args.warmup, args.seed,
                            acc_reports=args.acc_reports)
                f.parent.mkdir(parents=True, exist_ok=True)
                write_json(f, r)
            print(f"exp {e} {v}: ratio max {r['untempered_ratio_max']:.2f}, {r['wall_seconds']:.0f} s", flush=True)
            results[v].append(r)
    if any(len(results[v]) < len(exps) for v in VARIANTS):
        print("not every variant is cached yet: no document written")
        return 0
    summ = summarise(results)
    hetero = []
    if not args.no_hetero:
        for e in exps:
            f = args.out / "hetero" / f"exp_{e}.json"
            if f.exists():
                h = json.loads(f.read_text())
            else:
                h = heteroscedastic(e, data, args.reports)
                f.parent.mkdir(parents=True, exist_ok=True)
                f.write_text(json.dumps(h, indent=1))
            print(f"exp {e} heteroscedastic: " + ", ".join(f"{r['variant']} {r['ratio_max']:.2f}" for r in h["rows"]),
                  flush=True)
            hetero.append(h)
    summ["hetero"] = hetero
    write_json(args.out / "summary.json", summ)
    figure(results, summ, args.doc.parent / "figures" / "mimu_model_calibrate_ratio.png")
    md = markdown(results, summ, args)
    old = args.doc.read_text() if args.doc.exists() else ""
    tail = old[old.index(READING_MARK):] if READING_MARK in old else READING_MARK + "\n"
    write_text(args.doc, md + "\n" + tail)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
