#!/usr/bin/env python3
"""Is the real accelerometer misfit the same per-sample sampling-instant error as the gyros'?

Hypothesis (experiments/acc_timing_check.md): each IMU of the MIMU4444 samples its accelerometer
AND its gyroscope at the same random instant t + δ_kt (free-running sensor clock, δ white from
sample to sample, ~1 ms wide).  The gyro error is then δ_kt ω̇_t (resolved at 62.5 Hz), the
accelerometer error δ_kt times the TRUE jerk of the board at that IMU (not resolved at 62.5 Hz).

The test is a cross-sensor prediction.  From the nominal fit's GYRO residual alone,

    δ_kt = r_gyro,kt · ġ_kt / |ġ_kt|²      (ġ_kt = prep.gyro_rate, the fitted rate's derivative)

and, per sample t, the ACCELEROMETER residuals of the K IMUs (array frame a_kt = R_kᵀ r_acc,kt)
are fitted by one free 3-vector j_t (a jerk, m/s³):

    a_kt ≈ (δ_kt − mean_k δ_kt) j_t,    j_t = Σ_k d_k a_k / Σ_k d_k²   (d = centred δ)

The explained share Σ_t |Σ_k d_k a_k|² / Σ_k d_k² over Σ_t Σ_k |a_kt|² is compared with the same
share when the δ rows are shuffled across samples (the null: three free parameters per sample
soak up about 1/(K−1) of the power whatever δ is).  A ``common`` per-sample acc error is
orthogonal to the centred δ, so it neither helps nor hurts.

Preparation (the package's own): ``accel_bayes.mismatch.prepare`` → ``baseline_fit`` → the
detector's gyro linear stage helpers (``accel_bayes.mismatch.gyro_linear.relative_blocks`` and
``corrected_gyro``: regress every gyro on the fitted rates, correct, refit with
``fit_model(prep_c, (), init=fit, laplace=False)``, twice) → output rates of the last fit
(``output_rates``, as ``baseline_fit`` sets them).  No detector rounds.

    python experiments/acc_timing_check.py real            # the six MIMU4444 recordings
    python experiments/acc_timing_check.py sim             # simulated controls (_conceal.make_multi_case):
                                                           # one-IMU sampling_jitter, its clean twin, and the
                                                           # twin with every IMU jittered (all_jitter_case)
    python experiments/acc_timing_check.py report          # tables + figure + experiments/acc_timing_check.md
    python experiments/acc_timing_check.py all             # the three in turn

Results: experiments/results/acc_timing_check/{real,sim}.jsonl (one line per recording, resumable;
``--redo`` recomputes).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
OUT = HERE / "results" / "acc_timing_check"
MD = HERE / "acc_timing_check.md"
FIG = HERE / "figures" / "acc_timing_check_shares.png"
EXPERIMENTS = [f"exp_{i}" for i in range(1, 7)]
SIM_SEEDS = [1700003, 1700006, 1700009]
SIM_EFFECTS = ("sampling_jitter", "none", "all_jitter")
N_SHUFFLE = 20


# ----------------------------------------------------------------------------- estimators (tested)

def instant_errors(res_gyro: np.ndarray, gyro_rate: np.ndarray, floor: float = 1e-9) -> np.ndarray:
    """δ_kt = r·ġ/|ġ|² (s): the per-sample sampling-instant error that best explains each gyro's
    residual (T, K, 3) along its rate of change ġ (T, K, 3, rad/s²).  Returns (T, K)."""
    n2 = (gyro_rate ** 2).sum(-1)
    return (res_gyro * gyro_rate).sum(-1) / np.maximum(n2, floor)


def jerk_fit(a: np.ndarray, delta: np.ndarray, sel: np.ndarray | None = None) -> dict:
    """Per sample t, a_kt ≈ d_kt j_t with d = δ − mean_k δ and one free 3-vector j_t.

    a (T, K, 3) residuals in a common frame, delta (T, K).  Returns {"share": explained power /
    total power over ``sel`` (all samples when None), "share_imu" (K,) the same per IMU,
    "j" (T, 3), "d" (T, K) centred δ, "explained_t"/"total_t" (T,)}."""
    T, K, _ = a.shape
    sel = np.ones(T, bool) if sel is None else np.asarray(sel, bool)
    d = delta - delta.mean(1, keepdims=True)
    dd = (d ** 2).sum(1)
    j = np.einsum("tk,tki->ti", d, a) / np.maximum(dd, 1e-300)[:, None]
    pred = d[:, :, None] * j[:, None, :]
    tot_tk = (a ** 2).sum(-1)
    res_tk = ((a - pred) ** 2).sum(-1)
    share_imu = 1 - res_tk[sel].sum(0) / tot_tk[sel].sum(0)
    explained_t = tot_tk.sum(1) - res_tk.sum(1)
    total_t = tot_tk.sum(1)
    return {"share": float(explained_t[sel].sum() / total_t[sel].sum()), "share_imu": share_imu,
            "j": j, "d": d, "explained_t": explained_t, "total_t": total_t}


def shuffled_shares(a: np.ndarray, delta: np.ndarray, sel: np.ndarray | None = None,
                    n: int = N_SHUFFLE, seed: int = 0, per_imu: bool = False):
    """The null of :func:`jerk_fit`: the same share with the δ rows (all K IMUs of one sample
    together) permuted among the selected samples, ``n`` times.  Returns (n,) shares, and with
    ``per_imu`` also (n, K) per-IMU shares."""
    T = a.shape[0]
    idx = np.flatnonzero(np.ones(T, bool) if sel is None else np.asarray(sel, bool))
    rng = np.random.default_rng(seed)
    out, imu = [], []
    for _ in range(n):
        dl = delta[idx][rng.permutation(len(idx))]
        jf = jerk_fit(a[idx], dl)
        out.append(jf["share"])
        imu.append(jf["share_imu"])
    return (np.asarray(out), np.asarray(imu)) if per_imu else np.asarray(out)


def within_sample_corr(a: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Per sample, the correlation across the K IMUs of |a_kt| with |δ_kt − mean_k δ_kt|.  (T,)."""
    x = np.linalg.norm(a, axis=-1)
    y = np.abs(delta - delta.mean(1, keepdims=True))
    x = x - x.mean(1, keepdims=True)
    y = y - y.mean(1, keepdims=True)
    den = np.sqrt((x ** 2).sum(1) * (y ** 2).sum(1))
    return (x * y).sum(1) / np.where(den > 0, den, np.nan)


# ----------------------------------------------------------------------------- the pipeline

def fitted(rec, passes: int = 2) -> dict:
    """Prepare ``rec``, baseline fit, remove the gyros' relative linear errors with the detector
    stage's helpers (``passes`` regress/correct/refit rounds) and return numpy arrays of the
    last nominal fit: res_acc, res_gyro (T, K, 3, sensor frame), acc_rate, gyro_rate, omega (T, 3),
    time (T,), R (K, 3, 3 array → sensor), sigma_acc/sigma_gyro (K,), nominal positions (K, 3)."""
    import torch

    from accel_bayes.mismatch import baseline_fit, prepare
    from accel_bayes.mismatch.fit import fit_model
    from accel_bayes.mismatch.gyro_linear import corrected_gyro, relative_blocks
    from accel_bayes.physics.effects.base import output_rates
    from accel_bayes.physics.geometry import quat_to_matrix

    t0 = time.perf_counter()
    prep = prepare(rec)
    base, _ = baseline_fit(prep)
    imus = [int(k) for k in np.flatnonzero(prep.has_gyro)]
    fit, prep_c = base, prep
    for _ in range(int(passes)):
        rel = relative_blocks(prep, fit.ctx.gyro, imus)
        prep_c = corrected_gyro(prep, rel["A"], rel["b"])
        fit = fit_model(prep_c, (), init=fit, laplace=False)
    acc_rate, gyro_rate = output_rates(prep_c.time, fit.ctx.acc, fit.ctx.gyro)
    ok = (prep_c.m_acc.min(-1).values.min(-1).values > 0) & (prep_c.m_gyro.min(-1).values.min(-1).values > 0)
    return {"res_acc": fit.res_acc.detach().numpy(), "res_gyro": fit.res_gyro.detach().numpy(),
            "acc_rate": acc_rate.numpy(), "gyro_rate": gyro_rate.numpy(),
            "omega": fit.x.detach().numpy()[:, :3], "time": prep_c.time.numpy(),
            "R": quat_to_matrix(torch.as_tensor(prep_c.q)).numpy(), "ok": ok.numpy(),
            "sigma_acc": prep_c.sigma_acc.numpy(), "sigma_gyro": prep_c.sigma_gyro.numpy(),
            "nominal": prep_c.nominal.numpy(), "rec_time": np.asarray(prep_c.rec.time, dtype=float),
            "fit_seconds": time.perf_counter() - t0}


def _pairs(nominal: np.ndarray, tol: float = 1e-3) -> list:
    """IMU pairs sharing x, y (within ``tol`` m) of the design: top/bottom of the PCB."""
    K = len(nominal)
    return [(i, j) for i in range(K) for j in range(i + 1, K)
            if np.linalg.norm(nominal[i, :2] - nominal[j, :2]) < tol]


def statistics(F: dict, n_shuffle: int = N_SHUFFLE, truth: dict | None = None) -> dict:
    """Every number of the report from one :func:`fitted` result (module docstring)."""
    R = F["R"]
    ok = F["ok"]
    a = np.einsum("kji,tkj->tki", R, F["res_acc"])          # array frame
    ar = np.einsum("kji,tkj->tki", R, F["acc_rate"])
    delta = instant_errors(F["res_gyro"], F["gyro_rate"])
    T, K, _ = a.shape
    ng2 = (F["gyro_rate"] ** 2).sum(-1).min(1)
    big = ok & (ng2 > np.median(ng2[ok]))
    wn = np.linalg.norm(F["omega"], axis=1)
    out = {"T": int(T), "K": int(K), "n_ok": int(ok.sum()), "n_big": int(big.sum()),
           "fit_seconds": F["fit_seconds"],
           "acc_res_rms": np.sqrt((a[ok] ** 2).sum(-1).mean(0)).tolist(),
           "sigma_acc": F["sigma_acc"].tolist(), "sigma_gyro": F["sigma_gyro"].tolist()}
    # (a) shares
    for name, sel in (("all", ok), ("big", big)):
        jf = jerk_fit(a, delta, sel)
        sh, sh_imu = shuffled_shares(a, delta, sel, n_shuffle, seed=1, per_imu=True)
        out[f"share_{name}"] = jf["share"]
        out[f"share_{name}_imu"] = jf["share_imu"].tolist()
        out[f"null_{name}_imu"] = sh_imu.mean(0).tolist()
        out[f"null_{name}_mean"], out[f"null_{name}_sd"] = float(sh.mean()), float(sh.std(ddof=1))
    q = np.quantile(wn[ok], [0, .25, .5, .75, 1])
    out["omega_quartile_edges_dps"] = np.degrees(q).tolist()
    out["quartiles"] = []
    for i, (lo, hi) in enumerate(zip(q[:-1], q[1:])):
        sel = ok & (wn >= lo) & ((wn < hi) if i < 3 else (wn <= hi))
        jf = jerk_fit(a, delta, sel)
        sh = shuffled_shares(a, delta, sel, max(5, n_shuffle // 4), seed=2 + i)
        out["quartiles"].append({"omega_median_dps": float(np.degrees(np.median(wn[sel]))),
                                 "acc_res_rms": float(np.sqrt((a[sel] ** 2).sum(-1).mean())),
                                 "share": jf["share"], "null_mean": float(sh.mean()), "null_sd": float(sh.std(ddof=1))})
    # (b) within-sample correlation
    c = within_sample_corr(a, delta)[big]
    rng = np.random.default_rng(3)
    cn = within_sample_corr(a[big], delta[big][rng.permutation(int(big.sum()))])
    out["corr_median"], out["corr_null_median"] = float(np.nanmedian(c)), float(np.nanmedian(cn))
    # (c) the fitted jerk against the resolved acc rate
    jf = jerk_fit(a, delta, big)
    j = jf["j"][big]
    ar_mean = ar.mean(1)[big]
    jn, arn = np.linalg.norm(j, axis=1), np.linalg.norm(ar_mean, axis=1)
    out["j_median"], out["j_rms"] = float(np.median(jn)), float(np.sqrt((jn ** 2).mean()))
    out["acc_rate_median"], out["acc_rate_rms"] = float(np.median(arn)), float(np.sqrt((arn ** 2).mean()))
    out["j_cos_acc_rate_median_abs"] = float(np.median(np.abs((j * ar_mean).sum(1)) / np.maximum(jn * arn, 1e-300)))
    out["j_on_acc_rate_slope"] = float((j * ar_mean).sum() / (ar_mean ** 2).sum())
    jall = jf["j"]
    dtt = np.diff(F["time"])
    cons = (dtt < 1.5 * np.median(dtt)) & big[:-1] & big[1:]
    out["j_lag1"] = float(np.mean([np.corrcoef(jall[:-1][cons, i], jall[1:][cons, i])[0, 1] for i in range(3)]))
    out["j_corr_abs_omega"] = float(np.corrcoef(jn, wn[big])[0, 1])
    u = ar / np.maximum(np.linalg.norm(ar, axis=-1, keepdims=True), 1e-300)
    along = ((a * u).sum(-1) ** 2)[big].sum()
    out["share_along_acc_rate"] = float(along / (a[big] ** 2).sum())
    # the parameter-free prediction with the RESOLVED jerk: a_k ≈ d_k ȧ_k (array frame)
    d = delta - delta.mean(1, keepdims=True)
    pred = d[:, :, None] * ar
    pred = pred - pred.mean(1, keepdims=True)
    out["share_resolved_jerk"] = float(1 - ((a - pred) ** 2)[big].sum() / (a[big] ** 2).sum())
    # (d) instant-error width per IMU (larger-|ġ| half), with the gyro noise's share removed
    rms = np.sqrt((d[big] ** 2).mean(0))
    ng2k = (F["gyro_rate"] ** 2).sum(-1)[big]
    noise = np.sqrt((F["sigma_gyro"][None] ** 2 / ng2k).mean(0) * (K - 1) / K)
    out["delta_rms_ms"] = (rms * 1e3).tolist()
    out["width_ms"] = (rms * np.sqrt(12) * 1e3).tolist()
    out["width_ms_noise_removed_uncentred"] = (np.sqrt(np.maximum(rms ** 2 - noise ** 2, 0) * K / (K - 1)) * np.sqrt(12) * 1e3).tolist()
    out["delta_noise_rms_ms"] = (noise * 1e3).tolist()
    # the shape of the δ distribution: excess kurtosis of the centred δ (uniform δ, centred over K:
    # the Monte Carlo value below; Gaussian: 0)
    kz = lambda x: float(((x - x.mean()) ** 4).mean() / ((x - x.mean()) ** 2).mean() ** 2 - 3)  # noqa: E731
    out["delta_excess_kurtosis"] = [kz(d[big, k]) for k in range(K)]
    u0 = np.random.default_rng(5).uniform(-0.5, 0.5, (200000, K))
    out["kurtosis_uniform_centred"] = kz((u0 - u0.mean(1, keepdims=True))[:, 0])
    # a stretch of the centred δ (the longest run of consecutive samples, ≤ 300), for the figure
    dtt = np.diff(F["time"])
    brk = np.r_[0, np.flatnonzero(dtt > 1.5 * np.median(dtt)) + 1, T]
    i0 = int(np.argmax(np.diff(brk)))
    lo, hi = int(brk[i0]), int(min(brk[i0 + 1], brk[i0] + 300))
    out["delta_snippet_ms"] = (d[lo:hi] * 1e3).round(4).tolist()
    out["delta_snippet_t"] = (F["time"][lo:hi] - F["time"][lo]).round(4).tolist()
    out["delta_snippet_big"] = big[lo:hi].tolist()
    # (e) lag-1 autocorrelation on consecutive pairs, both in the larger-|ġ| half
    dt = np.diff(F["time"])
    cons = (dt < 1.5 * np.median(dt)) & big[:-1] & big[1:]
    out["lag1"] = [float(np.corrcoef(d[:-1][cons, k], d[1:][cons, k])[0, 1]) for k in range(K)]
    out["n_lag_pairs"] = int(cons.sum())
    # (f) lag-0 cross-correlation of the centred δ; PCB pairs vs the other pairs
    C = np.corrcoef(d[big].T)
    pairs = _pairs(F["nominal"])
    iu = [(i, j) for i in range(K) for j in range(i + 1, K)]
    out["pcb_pairs"] = pairs
    out["corr_pcb_pairs"] = [float(C[i, j]) for i, j in pairs]
    out["corr_other_pairs_mean"] = float(np.mean([C[i, j] for i, j in iu if (i, j) not in pairs]))
    out["corr_expected_independent"] = -1.0 / (K - 1)
    out["delta_corr_matrix"] = C.tolist()
    if truth is not None:
        out.update(_truth_stats(F, truth, a, ar, delta, big, np.asarray(out["null_big_imu"])))
    return out


def _truth_stats(F, truth, a, ar, delta, big, _null_imu) -> dict:
    """On a simulated case: the jittered IMU's own numbers and the estimated δ against the true
    instants (matched by sample time)."""
    k = truth.get("imu")
    out = {"effect": truth.get("effect"), "imu": k, "magnitude_ms": (truth.get("magnitude") or 0) * 1e3}
    if truth.get("effect") == "all_jitter":
        inst = np.asarray(truth["instants"], dtype=float)
        tt = np.asarray(truth["_time"], dtype=float)
        idx = np.clip(np.searchsorted(tt, F["rec_time"] - 1e-9), 0, len(tt) - 1)
        sel = big & (np.abs(tt[idx] - F["rec_time"]) < 1e-6)
        dt_ = inst[idx] - inst[idx].mean(1, keepdims=True)
        d = delta - delta.mean(1, keepdims=True)
        out["corr_delta_true"] = float(np.corrcoef(d[sel].ravel(), dt_[sel].ravel())[0, 1])
        out["slope_delta_on_true"] = float((d[sel] * dt_[sel]).sum() / (dt_[sel] ** 2).sum())
        out["share_big_true_instants"] = jerk_fit(a, inst[idx], sel)["share"]
        return out
    if k is None or truth.get("effect") != "sampling_jitter":
        return out
    inst = np.asarray(truth["parameters"]["instants"], dtype=float)
    tt = np.asarray(truth["_time"], dtype=float)  # the simulated recording's sample times
    idx = np.clip(np.searchsorted(tt, F["rec_time"] - 1e-9), 0, len(inst) - 1)
    matched = np.abs(tt[idx] - F["rec_time"]) < 1e-6
    true_d = inst[idx]
    d = delta - delta.mean(1, keepdims=True)
    sel = big & matched
    out["n_matched"] = int(matched.sum())
    out["corr_delta_true"] = float(np.corrcoef(d[sel, k], true_d[sel] - true_d[sel].mean())[0, 1])
    out["slope_delta_on_true"] = float(np.polyfit(true_d[sel], d[sel, k], 1)[0])
    jf = jerk_fit(a, delta, big)
    out["share_jittered_imu"] = float(jf["share_imu"][k])
    out["null_jittered_imu"] = float(_null_imu[k])
    others = [i for i in range(a.shape[1]) if i != k]
    out["share_other_imus_mean"] = float(np.mean(jf["share_imu"][others]))
    out["jittered_imu_acc_rms"] = float(np.sqrt((a[big, k] ** 2).sum(-1).mean()))
    out["other_imus_acc_rms"] = float(np.sqrt((a[big][:, others] ** 2).sum(-1).mean()))
    # with the true instants (and the resolved jerk): how much could the structure explain at most
    td = np.zeros_like(delta)
    td[:, k] = true_d
    out["share_big_true_instants"] = jerk_fit(a, td, sel)["share"]
    return out


def all_jitter_case(seed: int, width: float = 1e-3, T: int | None = None):
    """The clean twin of ``make_multi_case(seed, "none")`` with EVERY IMU (acc and gyro together)
    sampled at t + δ_kt, δ_kt ~ U(−w/2, w/2) i.i.d. over samples and IMUs: the hypothesis as the
    independent simulator's kinematics write it (same motion, geometry, linear gyro errors and
    noise draws as the twin; the simulator only jitters one IMU itself).  Returns (recording,
    truth) with truth["instants"] (T, K) s."""
    import dataclasses

    from _conceal import RotvecTrajectory, board, make_multi_case, sensor_outputs

    case = make_multi_case(seed, "none", T=T, gyro_linear=True)
    tr, rec = case.truth, case.recording
    t = np.asarray(rec.time, dtype=float)
    traj = RotvecTrajectory.from_dict(tr["trajectory"])
    Rk = board(tr["board"]).rotations
    pts = np.repeat(np.asarray(tr["true_position"])[:, None, :], 3, axis=1)
    K = Rk.shape[0]
    delta = np.random.default_rng([int(seed), 7]).uniform(-width / 2, width / 2, (len(t), K))
    acc, w = np.empty((len(t), K, 3)), np.empty((len(t), K, 3))
    for k in range(K):
        a_k, g_k = sensor_outputs(traj, t + delta[:, k], Rk[k:k + 1], pts[k:k + 1])
        acc[:, k], w[:, k] = a_k[:, 0], g_k[:, 0]
    E, b = np.asarray(tr["gyro_linear"]["matrix"]), np.asarray(tr["gyro_linear"]["bias"])
    gyro = np.einsum("kij,tkj->tki", np.eye(3)[None] + E, w) + b[None]
    acc = acc + (np.asarray(rec.acc) - case.clean_acc)        # the twin's own noise draws
    gyro = gyro + (np.asarray(rec.gyro) - case.clean_gyro)
    rec2 = dataclasses.replace(rec, acc=acc, gyro=gyro)
    return rec2, {"effect": "all_jitter", "imu": None, "magnitude": width, "instants": delta, "_time": t}


# ----------------------------------------------------------------------------- stages

def _done(path: Path) -> set:
    if not path.exists():
        return set()
    return {json.loads(line)["name"] for line in path.read_text().splitlines() if line.strip()}


def _drop(path: Path, names) -> None:
    """Remove the rows of ``names`` from ``path`` (``--redo``)."""
    if path.exists():
        keep = [ln for ln in path.read_text().splitlines() if ln.strip() and json.loads(ln)["name"] not in set(names)]
        path.write_text("".join(ln + "\n" for ln in keep))


def _append(path: Path, row: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a") as f:
        f.write(json.dumps(row) + "\n")


def _rows(path: Path) -> list:
    if not path.exists():
        return []
    rows = {}
    for line in path.read_text().splitlines():
        if line.strip():
            r = json.loads(line)
            rows[r["name"]] = r
    return list(rows.values())


def stage_real(args):
    from _data import data_dir

    from accel_bayes.data.mimu import import_mimu

    path = OUT / "real.jsonl"
    if args.redo:
        _drop(path, args.only or EXPERIMENTS)
    done = _done(path)
    for exp in args.only or EXPERIMENTS:
        if exp in done:
            continue
        t0 = time.perf_counter()
        rec = import_mimu(data_dir() / exp / "data.bin.gz")
        row = {"name": exp, **statistics(fitted(rec), args.shuffles)}
        row["seconds"] = time.perf_counter() - t0
        _append(path, row)
        print(f"{exp}: share big {row['share_big']:.3f} (null {row['null_big_mean']:.3f} ± {row['null_big_sd']:.3f}), "
              f"corr {row['corr_median']:.2f}, width {np.round(row['width_ms'], 2)} ms, {row['seconds']:.0f} s", flush=True)


def stage_sim(args):
    from _conceal import make_multi_case

    path = OUT / "sim.jsonl"
    if args.redo:
        _drop(path, [f"{e}-{sd}" for sd in args.seeds for e in SIM_EFFECTS])
    done = _done(path)
    for seed in args.seeds:
        for effect in SIM_EFFECTS:
            name = f"{effect}-{seed}"
            if name in done:
                continue
            t0 = time.perf_counter()
            if effect == "all_jitter":
                recording, truth = all_jitter_case(seed, T=args.sim_T)
            else:
                case = make_multi_case(seed, effect, T=args.sim_T, gyro_linear=True)
                recording = case.recording
                truth = dict(case.truth)
                truth["_time"] = np.asarray(case.recording.time, dtype=float)
                if effect == "none":
                    truth = {"effect": "none", "imu": None, "magnitude": 0.0}
            row = {"name": name, "seed": seed, **statistics(fitted(recording), args.shuffles, truth)}
            row["seconds"] = time.perf_counter() - t0
            _append(path, row)
            extra = ""
            if effect == "all_jitter":
                extra = (f", corr(δ̂, δ) {row['corr_delta_true']:.2f}, slope j on ȧ {row['j_on_acc_rate_slope']:.2f}, "
                         f"resolved-ȧ share {row['share_resolved_jerk']:.3f}")
            elif effect == "sampling_jitter":
                extra = (f", jittered IMU {row['imu']} w {row['magnitude_ms']:.2f} ms: own share {row['share_jittered_imu']:.3f} "
                         f"(null {row['null_jittered_imu']:.3f}), slope j on ȧ {row['j_on_acc_rate_slope']:.2f}, "
                         f"resolved-ȧ share {row['share_resolved_jerk']:.3f}, corr(δ̂, δ) {row['corr_delta_true']:.2f}")
            print(f"{name}: share big {row['share_big']:.3f} (null {row['null_big_mean']:.3f} ± {row['null_big_sd']:.3f})"
                  f"{extra}, {row['seconds']:.0f} s", flush=True)


def _f(x, nd=3):
    return "—" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f"{x:.{nd}f}"


def figure(real: list, sim: list) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(2, 2, figsize=(13, 9))
    axs = axs.ravel()
    ax = axs[0]
    names = [r["name"] for r in real] + [r["name"].replace("sampling_jitter", "sim 1-IMU jitter").replace("all_jitter", "sim all-IMU jitter").replace("none", "sim clean") for r in sim]
    rows = real + sim
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [r["share_big"] for r in rows], 0.4, label="gyro-derived δ")
    ax.bar(x + 0.2, [r["null_big_mean"] for r in rows], 0.4, yerr=[2 * r["null_big_sd"] for r in rows],
           label="δ shuffled across samples (mean ± 2 sd)", color="0.6")
    ax.set_xticks(x, names, rotation=60, ha="right", fontsize=8)
    ax.set_ylabel("share of acc residual power explained")
    ax.set_title("(a) (δ_k − mean δ)·j_t fit, larger-|ġ| half")
    ax.legend(fontsize=8)
    ax = axs[1]
    for r in real:
        ax.plot([qq["omega_median_dps"] for qq in r["quartiles"]], [qq["share"] for qq in r["quartiles"]], "o-", label=r["name"])
    for r in real[:1]:
        ax.plot([qq["omega_median_dps"] for qq in r["quartiles"]], [qq["null_mean"] for qq in r["quartiles"]], "k--",
                label="shuffled δ (exp_1)")
    ax.set_xlabel("median |ω| of the quartile (°/s)")
    ax.set_ylabel("share explained")
    ax.set_title("(a) per |ω| quartile, real recordings")
    ax.legend(fontsize=7)
    ax = axs[2]
    for r in real:
        ax.plot(np.arange(r["K"]), r["width_ms"], "o-", label=r["name"])
    ax.axhline(1.0, color="k", ls=":", lw=1, label="1 ms")
    ax.set_xlabel("IMU")
    ax.set_ylabel("√12 × RMS(δ − mean δ) (ms)")
    ax.set_title("(d) implied instant-error width, larger-|ġ| half")
    ax.legend(fontsize=7, ncol=2)
    ax = axs[3]
    r0 = real[0]
    tt, dd = np.asarray(r0["delta_snippet_t"]), np.asarray(r0["delta_snippet_ms"])
    bb = np.asarray(r0["delta_snippet_big"], bool)
    for k in (0, 1, 5):
        line, = ax.plot(tt, np.where(bb, dd[:, k], np.nan), "-", lw=1.2, label=f"IMU {k}")
        ax.plot(tt, np.where(bb, np.nan, dd[:, k]), ":", lw=0.8, color=line.get_color())
    ax.set_ylim(-1.5, 1.5)
    ax.set_xlabel("time from the start of the stretch (s)")
    ax.set_ylabel("δ_k − mean δ (ms), from the gyro residual")
    ax.set_title(f"(e) gyro-derived instant error, {r0['name']}, longest consecutive run\n"
                 "(solid: larger-|ġ| half; dotted: smaller |ġ|, where δ is noisy)", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    FIG.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(FIG, dpi=110)
    plt.close(fig)


def tables(real: list, sim: list) -> str:
    L = []
    L.append("| recording | n (all / big) | acc res RMS (m/s²) | share all | null all | share big | null big (mean ± sd) | per-IMU share big (min–max) |")
    L.append("|---|---|---|---|---|---|---|---|")
    for r in real + sim:
        L.append(f"| {r['name']} | {r['n_ok']} / {r['n_big']} | {np.sqrt(np.mean(np.square(r['acc_res_rms']))):.2f} | "
                 f"{_f(r['share_all'])} | {_f(r['null_all_mean'])} ± {_f(r['null_all_sd'])} | {_f(r['share_big'])} | "
                 f"{_f(r['null_big_mean'])} ± {_f(r['null_big_sd'])} | {min(r['share_big_imu']):.2f}–{max(r['share_big_imu']):.2f} |")
    t1 = "\n".join(L)
    L = ["| recording | " + " | ".join(f"Q{i + 1}" for i in range(4)) + " |", "|---|---|---|---|---|"]
    for r in real + sim:
        cells = [f"{qq['omega_median_dps']:.0f} °/s, {qq['acc_res_rms']:.2f} m/s²: {qq['share']:.3f} (null {qq['null_mean']:.3f})"
                 for qq in r["quartiles"]]
        L.append(f"| {r['name']} | " + " | ".join(cells) + " |")
    t2 = "\n".join(L)
    L = ["| recording | corr median (null) | median / RMS \\|j\\| (m/s³) | median / RMS \\|ȧ\\| resolved (m/s³) | "
         "median \\|cos(j, ȧ)\\| | slope j on ȧ | acc res share along ȧ | share, resolved ȧ, no free parameter |",
         "|---|---|---|---|---|---|---|---|"]
    for r in real + sim:
        L.append(f"| {r['name']} | {r['corr_median']:.2f} ({r['corr_null_median']:.2f}) | {r['j_median']:.0f} / {r['j_rms']:.0f} | "
                 f"{r['acc_rate_median']:.0f} / {r['acc_rate_rms']:.0f} | {r['j_cos_acc_rate_median_abs']:.2f} | "
                 f"{r['j_on_acc_rate_slope']:.2f} | {r['share_along_acc_rate']:.2f} | {r['share_resolved_jerk']:.3f} |")
    t3 = "\n".join(L)
    L = ["| recording | width √12·RMS(δ−mean δ) per IMU 0–7 (ms) | gyro-noise δ RMS (ms, mean) | width, noise removed, uncentred (ms, mean) | lag-1 per IMU | PCB pairs: corr of δ (other pairs mean; independent −1/7 = −0.14) |",
         "|---|---|---|---|---|---|"]
    for r in real + sim:
        pc = ", ".join(f"{i}-{j}: {c:.2f}" for (i, j), c in zip(r["pcb_pairs"], r["corr_pcb_pairs"]))
        L.append(f"| {r['name']} | {' '.join(f'{w:.2f}' for w in r['width_ms'])} | {np.mean(r['delta_noise_rms_ms']):.3f} | "
                 f"{np.mean(r['width_ms_noise_removed_uncentred']):.2f} | {' '.join(f'{v:.2f}' for v in r['lag1'])} | "
                 f"{pc or '—'} ({r['corr_other_pairs_mean']:.2f}) |")
    t4 = "\n".join(L)
    L = ["| case | jittered IMU | true width (ms) | corr(δ̂_k, true δ) | slope δ̂ on δ | share of that IMU's acc residual | mean share other IMUs | its acc res RMS / others (m/s²) | share big, true instants |",
         "|---|---|---|---|---|---|---|---|---|"]
    for r in sim:
        if r.get("effect") != "sampling_jitter":
            continue
        L.append(f"| {r['name']} | {r['imu']} | {r['magnitude_ms']:.2f} | {r['corr_delta_true']:.3f} | {r['slope_delta_on_true']:.2f} | "
                 f"{r['share_jittered_imu']:.3f} (null {r['null_jittered_imu']:.3f}) | {r['share_other_imus_mean']:.3f} | {r['jittered_imu_acc_rms']:.3f} / {r['other_imus_acc_rms']:.3f} | "
                 f"{r['share_big_true_instants']:.3f} |")
    t5 = "\n".join(L)
    return t1, t2, t3, t4, t5


def stage_report(args):
    real = sorted(_rows(OUT / "real.jsonl"), key=lambda r: r["name"])
    sim = sorted(_rows(OUT / "sim.jsonl"), key=lambda r: (r["seed"], r["name"]))
    figure(real, sim)
    t1, t2, t3, t4, t5 = tables(real, sim)
    tpl = (HERE / "acc_timing_check.md.in").read_text() if (HERE / "acc_timing_check.md.in").exists() else None
    body = {"T1": t1, "T2": t2, "T3": t3, "T4": t4, "T5": t5}
    if tpl is None:
        MD.write_text("\n\n".join(body.values()) + "\n")
    else:
        for k, v in body.items():
            tpl = tpl.replace("{{" + k + "}}", v)
        MD.write_text(tpl)
    print(f"wrote {MD} and {FIG}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("stage", choices=["real", "sim", "report", "all"])
    ap.add_argument("--only", nargs="*", help="real experiments to run (default all six)")
    ap.add_argument("--seeds", nargs="*", type=int, default=SIM_SEEDS)
    ap.add_argument("--sim-T", type=int, default=None, help="samples per simulated case (default: the simulator's draw)")
    ap.add_argument("--shuffles", type=int, default=N_SHUFFLE)
    ap.add_argument("--redo", action="store_true")
    args = ap.parse_args(argv)
    if args.stage in ("real", "all"):
        stage_real(args)
    if args.stage in ("sim", "all"):
        stage_sim(args)
    if args.stage in ("report", "all"):
        stage_report(args)


if __name__ == "__main__":
    main()
