#!/usr/bin/env python3
"""Probe (issue #30, gyroprobe): does the fused ω carry a COMMON gyro error G (3×3, the true rate
ω = (I + G) ω̄) that the per-IMU gyro corrections cannot see, and that the board's angular-jerk
scale and the short x spacing are absorbing?

Per case, ``calibrate(rec, model=report.json)`` is run up to its per-sample-covariance step and that
step itself (:func:`accel_bayes.pipelines.calibrate_model._model_percov_step`: the unresolved jerk and
angular jerk scales by type-II ML, the mode at ω̄ with its Laplace covariance) gives the baseline.
Then, for G scalar (c I), diagonal and full, two rounds of: (a) G jointly with the free positions
maximising that likelihood (its ``log_lik_given_omega`` at ω = (I + G) ω̄, plus calibrate's Gaussian
position prior), Laplace std from the joint Hessian; (b) the same step rerun on ω = (I + G) ω̄ (scales
refitted by type-II ML, mode refitted).  Reported: the gain in nats (the step's likelihood at its
mode, after → before), the fitted G ± std, the angular-jerk scales per band and the x/y spacing of
the top IMUs before → after.  The concealed cases (``percov_conceal``'s cache, its own reports) are
run as recorded ("none": G must be ~0 within its std) and with a known error put into every gyro
("scale": every gyro × 1.003; "xscale": the array-frame x rate × 1.003).

Why a scalar G cannot be measured by the accelerometers: ω̇_t and s_t are free per sample, so
((1+c)ω)×((1+c)ω×r) = ω×(ω×(1+c)²r) and ω̇×r = (ω̇/(1+c)²)×((1+c)²r): a common scale is exactly an
array scale; only the priors (positions, φ) and the −½ log|M(θ)| term tell them apart.

    PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/gyro_common_probe.py --exps 1,2,5 --cases 15
    ... --exps '' --cases 15 --inject xscale30 --kinds diag0,full0,diag
    ... --exps '' --cases 20 --inject none --kinds diag0,full0,diag
    ... --exps 3,4,6
    ... --from-cache          (the document from all of them)

Writes ``experiments/gyro_common_probe.md`` and ``experiments/out/gyro_common_probe/*.json``.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent
DOC = ROOT / "gyro_common_probe.md"
#: parameters per kind of G; "diag0"/"full0" are traceless (the trace is an array scale, module docstring)
KINDS = {"scalar": 1, "diag": 3, "full": 9, "diag0": 2, "full0": 8}
#: the x–y spacing of the top IMUs as ``mimu_model_calibrate.py`` reads it: x of IMUs 4 and 6, −y of 2 and 6
SPACING_X_IMUS, SPACING_Y_IMUS = (4, 6), (2, 6)


def g_matrix(g: torch.Tensor, kind: str) -> torch.Tensor:
    """The 3×3 common gyro error (dimensionless) of parameters g: c I, diag(g), g as 3×3 row-major, or
    the traceless ones (the last diagonal entry minus the sum of the others)."""
    if kind == "scalar":
        return g[0] * torch.eye(3, dtype=g.dtype)
    if kind == "diag":
        return torch.diag(g)
    if kind == "diag0":
        return torch.diag(torch.cat([g, -g.sum().reshape(1)]))
    if kind == "full0":
        return torch.cat([g, -(g[0] + g[4]).reshape(1)]).reshape(3, 3)
    return g.reshape(3, 3)


def params_of(G: torch.Tensor, kind: str) -> list:
    """The parameters of :func:`g_matrix` that give the 3×3 G of that ``kind`` (its inverse)."""
    d, f = G.diagonal(), G.reshape(-1)
    out = {"scalar": d[:1], "diag": d, "diag0": d[:2], "full": f, "full0": f[:8]}[kind]
    return [float(v) for v in out]


def project(G: np.ndarray, kind: str) -> np.ndarray:
    """The part of a 3×3 G that a ``kind`` can represent (the least-squares projection onto it)."""
    G = np.asarray(G, dtype=np.float64)
    tr = np.trace(G) / 3 * np.eye(3)
    return {"scalar": tr, "diag": np.diag(np.diag(G)), "diag0": np.diag(np.diag(G)) - tr, "full": G,
            "full0": G - tr}[kind]


def corrected_omega(omega_mean: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    """(T, 3) rad/s: ω = (I + G) ω̄ for ω̄ (T, 3) rad/s (a linear map: exact on calibrate's samples
    scaled by 1/√s_t too)."""
    return omega_mean + omega_mean @ G.transpose(0, 1)


def fit_common_gyro(lik, pos0, kind: str, *, prior_mean=None, prior_std=None, g0=None,
                    free_positions: bool = True) -> dict:
    """G (``kind``) jointly with the free positions at the mode of log p(y | (I + G) ω̄, θ) + the
    Gaussian position prior (``prior_mean`` (A, 3) m, ``prior_std`` m; none if None); ω̄ is
    ``lik.omega.mean``.  Any likelihood with ``log_lik_given_omega`` (flat or per-sample).
    ``free_positions`` False: the positions stay at ``pos0`` (A, 3) m, G alone is fitted.

    Returns {"g": (n,), "g_std": (n,) Laplace std (joint Hessian, positions included), "G": 3×3,
    "positions": (A, 3) m, "gain_nats": the objective at the joint mode less at G = 0 with the
    positions refitted, "loglik": the likelihood (no prior) at the joint mode}."""
    A, ref = lik.A, lik.reference
    free = [k for k in range(A) if k != ref]
    n = KINDS[kind]
    pos0 = torch.as_tensor(pos0, dtype=torch.float64)
    mu = None if prior_mean is None else torch.as_tensor(prior_mean, dtype=torch.float64)
    mu = None if mu is None else (mu - mu[ref])[free].reshape(-1)
    w = lik.omega.mean

    def full(th):
        P = torch.zeros(A, 3, dtype=th.dtype)
        P[free] = th.reshape(A - 1, 3)
        return P

    th_fixed = (pos0 - pos0[ref])[free].reshape(-1)

    def nll(x, with_g=True):
        th, g = (x[:-n], x[-n:]) if free_positions else (th_fixed, x)
        om = corrected_omega(w, g_matrix(g, kind)) if with_g else w
        out = -lik.log_lik_given_omega(full(th), om)
        if mu is not None:
            out = out + 0.5 * ((th - mu) / float(prior_std)).square().sum()
        return out

    def mode(x0, with_g):
        x = x0.clone().requires_grad_(True)
        opt = torch.optim.LBFGS([x], max_iter=100, line_search_fn="strong_wolfe", tolerance_grad=1e-9,
                                tolerance_change=1e-14)

        def closure():
            opt.zero_grad()
            loss = nll(x, with_g)
            loss.backward()
            return loss

        for _ in range(3):
            opt.step(closure)
        return x.detach()

    g_start = torch.zeros(n, dtype=torch.float64) if g0 is None else torch.as_tensor(g0, dtype=torch.float64)
    if free_positions:
        x_base = mode(torch.cat([th_fixed, torch.zeros(n, dtype=torch.float64)]), False)
        x_hat = mode(torch.cat([x_base[:-n], g_start]), True)
    else:
        x_base, x_hat = torch.zeros(n, dtype=torch.float64), mode(g_start, True)
    H = torch.autograd.functional.hessian(nll, x_hat)
    cov = torch.linalg.inv(H)
    g = x_hat[-n:]
    th = x_hat[:-n] if free_positions else th_fixed
    with torch.no_grad():
        ll = float(lik.log_lik_given_omega(full(th), corrected_omega(w, g_matrix(g, kind))))
        gain = float(nll(x_base, False) - nll(x_hat, True))
    return {"g": g.tolist(), "g_std": cov.diagonal()[-n:].clamp_min(0).sqrt().tolist(),
            "G": g_matrix(g, kind).tolist(), "positions": full(th), "gain_nats": gain, "loglik": ll}


def spacing(P, labels) -> dict:
    """The x–y spacing of the top IMUs (m, ``mimu_model_calibrate.py``'s reading) of positions P (A, 3)
    relative to the reference row, rows IMU ``labels``; None where an IMU is missing."""
    idx = {int(k): i for i, k in enumerate(labels)}
    P = np.asarray(P, dtype=np.float64)
    dx = [P[idx[k], 0] for k in SPACING_X_IMUS if k in idx]
    dy = [-P[idx[k], 1] for k in SPACING_Y_IMUS if k in idx]
    return {"x_m": float(np.mean(dx)) if len(dx) == 2 else None, "y_m": float(np.mean(dy)) if len(dy) == 2 else None}


def _with_omega(lik, omega_mean):
    """A copy of the noise step's likelihood with the fused ω̄ replaced (the covariances kept)."""
    from accel_bayes.model.gyro_posterior import GyroPosterior

    new = type(lik).__new__(type(lik))
    new.__dict__.update(lik.__dict__)
    new.omega = GyroPosterior(omega_mean, lik.omega.cov, lik.omega.method)
    for k in ("_yu_cache", "_sqrt_lam_cache"):
        new.__dict__.pop(k, None)
    return new


def _ll(step):
    with torch.no_grad():
        return float(step.lik.log_lik_given_omega(step.positions, step.lik.omega.mean)) + step.lik.log_constant


def probe(rec, report, kinds=("diag0", "full0", "scalar", "diag", "full"), rounds: int = 2) -> dict:
    """The baseline step and the G fits of the module docstring on one recording."""

    out = {}

    def step(orig, lik, terms, omega_norm, sample_scale, map_res, nominal_acc, prior_std, **kw):
        labels = list(lik.imu_labels)
        t0 = time.perf_counter()
        base = orig(lik, terms, omega_norm, sample_scale, map_res, nominal_acc, prior_std, **kw)
        sd = base.laplace_cov.diagonal().sqrt()
        out.update(T=int(lik.T), A=int(lik.A), labels=labels, prior_std_m=float(prior_std),
                   loglik_before=_ll(base), spacing_before=spacing(base.positions, labels),
                   angjerk_before=base.record["angular_jerk_rms_fitted_rad_s3"],
                   jerk_before=base.record["jerk_rms_fitted_m_s3"],
                   band_samples=base.record["band_samples"], omega_edges=base.record["omega_edges_rad_s"],
                   laplace_std_before_mm=float(sd.median() * 1e3), fits={})
        for kind in kinds:
            G = torch.zeros(3, 3, dtype=torch.float64)
            cur, hist = base, []
            for _ in range(rounds):
                f = fit_common_gyro(cur.lik, cur.positions, kind, prior_mean=nominal_acc, prior_std=prior_std)
                # cur.lik's ω̄ already carries G: compose, ω = (I + ΔG)(I + G) ω̄
                G = G + g_matrix(torch.as_tensor(f["g"], dtype=torch.float64), kind) @ (torch.eye(3, dtype=torch.float64) + G)
                w = corrected_omega(lik.omega.mean, G)
                mr = None if map_res is None else dataclasses.replace(map_res, positions=f["positions"])
                cur = orig(_with_omega(lik, w), terms, omega_norm, sample_scale, mr, nominal_acc, prior_std, **kw)
                hist.append({"delta_g": f["g"], "delta_g_std": f["g_std"], "joint_gain_nats": f["gain_nats"],
                             "loglik_after_refit": _ll(cur)})
            gs = params_of(G, kind)
            out["fits"][kind] = {
                "G": G.tolist(), "g": [float(v) for v in gs], "g_std": hist[-1]["delta_g_std"],
                "gain_nats": _ll(cur) - out["loglik_before"], "rounds": hist,
                "spacing_after": spacing(cur.positions, labels),
                "angjerk_after": cur.record["angular_jerk_rms_fitted_rad_s3"],
                "jerk_after": cur.record["jerk_rms_fitted_m_s3"],
                "laplace_std_after_mm": float(cur.laplace_cov.diagonal().sqrt().median() * 1e3)}
            out["fits"][kind]["gain_nats_per_sample"] = out["fits"][kind]["gain_nats"] / lik.T
            print(f"  {kind}: G diag {[round(float(v), 5) for v in G.diagonal()]} gain "
                  f"{out['fits'][kind]['gain_nats']:.1f} nats", flush=True)
        out["seconds"] = time.perf_counter() - t0

    from experiments._percov_step import at_percov_step

    at_percov_step(rec, report, step)
    return out


def inject_gyro_error(rec, E):
    """The recording with every gyro reading ω̄ = (I + E) ω (E 3×3 in the ARRAY frame, dimensionless)."""
    from accel_bayes.physics.models import to_array_frame

    q = torch.as_tensor(rec.nominal_orientation, dtype=torch.float64)
    K = q.shape[0]
    # the per-IMU sensor→array maps, read off the library's own rotation: columns are the images of e_i
    basis = torch.eye(3, dtype=torch.float64)[:, None, :].expand(3, K, 3)
    M = to_array_frame(basis, q).permute(1, 2, 0)  # (K, 3 array, 3 sensor)
    g = torch.as_tensor(rec.gyro, dtype=torch.float64)  # (T, K, 3) sensor
    E = torch.as_tensor(E, dtype=torch.float64)
    Ms = M.transpose(1, 2) @ (torch.eye(3, dtype=torch.float64) + E) @ M  # sensor-frame (I + E) per IMU
    new = torch.einsum("kij,tkj->tki", Ms, g)
    return dataclasses.replace(rec, gyro=new.numpy())


#: errors put into every gyro of a concealed case (array frame); "xscale30" is far beyond any real gyro but
#: within the resolution of a 20 s, |ω| < 4 rad/s clockgen case (G's std there is ~4e-2, against ~1e-3 on exp_1)
INJECT = {"none": np.zeros((3, 3)), "scale": 0.003 * np.eye(3), "xscale": np.diag([0.003, 0.0, 0.0]),
          "xscale30": np.diag([0.3, 0.0, 0.0])}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--exps", default="1", help="MIMU experiments (reports in --reports)")
    ap.add_argument("--cases", default="", help="concealed clock seeds (percov_conceal's cache)")
    ap.add_argument("--inject", default="none,scale,xscale", help="errors put into the concealed cases' gyros")
    ap.add_argument("--kinds", default="diag0,full0,scalar,diag,full")
    ap.add_argument("--conceal", type=Path, default=ROOT / "out" / "percov_conceal")
    ap.add_argument("--reports", type=Path, default=ROOT / "out" / "mimu_mismatch")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "gyro_common_probe")
    ap.add_argument("--from-cache", action="store_true",
                    help="compute nothing: the document from every case cached in --out (real ones first)")
    args = ap.parse_args(argv)
    from accel_bayes.data.outputs import write_json, write_text
    from experiments._reading import READING_MARKER, kept_reading

    kinds = tuple(k for k in args.kinds.split(",") if k)
    args.out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    torch.manual_seed(0)
    rows = []
    for exp in [int(s) for s in args.exps.split(",") if s]:
        f = args.out / f"exp_{exp}.json"
        if not f.exists():
            from accel_bayes.data.mimu import import_mimu
            from experiments._data import data_dir
            print(f"exp_{exp}", flush=True)
            rec = import_mimu(Path(data_dir()) / f"exp_{exp}" / "data.bin.gz")
            r = probe(rec, args.reports / f"exp_{exp}" / "report.json", kinds)
            write_json(f, {"case": f"exp_{exp}", "inject": None, **r})
        rows.append(json.loads(f.read_text()))
    for seed in [int(s) for s in args.cases.split(",") if s]:
        for inj in [s for s in args.inject.split(",") if s]:
            f = args.out / f"clock-{seed:03d}-{inj}.json"
            if not f.exists():
                from experiments.percov_conceal import case_recording
                print(f"clock-{seed:03d} {inj}", flush=True)
                case = json.loads((args.conceal / f"clock-{seed:03d}" / "case.json").read_text())
                rec, _, _ = case_recording(seed, case["duration"], case["mount_std_m"], case["acc_intrinsics"])
                E = INJECT[inj]
                r = probe(inject_gyro_error(rec, E), args.conceal / f"clock-{seed:03d}" / "report.json", kinds)
                expect = (np.linalg.inv(np.eye(3) + E) - np.eye(3)).tolist()
                write_json(f, {"case": f"clock-{seed:03d}", "inject": inj, "G_expected": expect, **r})
            rows.append(json.loads(f.read_text()))
    if args.from_cache:
        rows = [json.loads(f.read_text()) for f in sorted(args.out.glob("exp_*.json"))]
        rows += [json.loads(f.read_text()) for f in sorted(args.out.glob("clock-*.json"))]
    write_json(args.out / "summary.json", rows)
    write_text(DOC, document(rows, time.perf_counter() - t_start, argv) + "\n" + READING_MARKER + kept_reading(DOC))
    print(f"wrote {DOC}")
    return 0


def consistency(rows) -> list:
    """Lines: per kind, the real experiments' G pooled by inverse variance per parameter and the χ² of
    their spread about it (the same board and gyros: one G should fit them all)."""
    real = [r for r in rows if r["inject"] is None]
    if len(real) < 2:
        return []
    L = ["", f"Across the real experiments ({', '.join(r['case'] for r in real)}): per parameter the "
         "inverse-variance pooled G ± std (×1e-3) and the χ² of the experiments about it (dof = experiments − 1 "
         "per parameter; summed over the parameters in the last column).", "",
         "| G kind | pooled G ± std (×1e-3) | χ² per parameter | χ² total / dof |", "|---|---|---|---|"]
    for kind in real[0]["fits"]:
        g = np.array([r["fits"][kind]["g"] for r in real])
        s = np.array([r["fits"][kind]["g_std"] for r in real])
        w = s ** -2
        m = (g * w).sum(0) / w.sum(0)
        chi = (((g - m) / s) ** 2).sum(0)
        L.append(f"| {kind} | {', '.join(f'{a * 1e3:.2f}±{b * 1e3:.2f}' for a, b in zip(m, w.sum(0) ** -0.5))} | "
                 f"{', '.join(f'{c:.1f}' for c in chi)} | {chi.sum():.1f} / {chi.size * (len(real) - 1)} |")
    return L


def _mm(v):
    return _f(None if v is None else v * 1e3, "{:.3f}")


def _f(v, f="{:.3g}"):
    return "—" if v is None else f.format(v)


def document(rows, seconds, argv=None) -> str:
    import sys

    from experiments._stamp import run_stamp

    cmd = " ".join(argv if argv is not None else sys.argv[1:])
    L = ["# gyro_common_probe — a common gyro error G in the fused ω (issue #30, gyroprobe)", "",
         f"Regenerate: `PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/gyro_common_probe.py {cmd}` "
         f"({run_stamp()}, nice 5; cached per case in "
         f"`experiments/out/gyro_common_probe/`; this invocation {seconds:.0f} s). Reports: main's "
         "`experiments/out/mimu_mismatch/exp_*/report.json`, sha256 as in `mimu_model_calibrate.md` (checked); "
         "concealed cases and their reports: `percov_conceal`'s cache. The cached rows were made by (same script, "
         "environment): `--exps 1,2,5 --cases 15 --inject none,scale,xscale` (all five kinds), "
         "`--exps '' --cases 15 --inject xscale30 --kinds diag0,full0,diag` and `--exps '' --cases 20 --inject none "
         "--kinds diag0,full0,diag`, then `--exps 3,4,6` (all five kinds), in that order (≈ 28 min in all); the table is the cache's union "
         "(`--from-cache`, `summary.json`).", "",
         "What runs: the script's docstring. G: ω_true = (I + G) ω̄. Gain: the per-sample-covariance likelihood "
         "at its mode (scales refitted by type-II ML on the corrected ω) less the same at G = 0, nats. ± is the "
         "Laplace std of the last round's G (joint Hessian with the positions, position prior included). Spacing: "
         "x of IMUs 4, 6 and −y of IMUs 2, 6 at the mode (`mimu_model_calibrate.py`'s reading); design 18.9 mm.", "",
         "| case | inject | G kind | gain (nats) | per sample | fitted G (diag; full: row-major) ± std (×1e-3) "
         "| expected G (×1e-3) | max abs z vs expected | x / y spacing before → after (mm) | angular-jerk rms per band before → after "
         "(rad/s³) |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for kind, f in r["fits"].items():
            gs = ", ".join(f"{g * 1e3:.3f}±{s * 1e3:.3f}" for g, s in zip(f["g"], f["g_std"]))
            want = None if r.get("G_expected") is None else np.asarray(
                params_of(torch.as_tensor(project(r["G_expected"], kind)), kind))
            exp = "—" if want is None else ", ".join(f"{v * 1e3:.2f}" for v in want)
            zmax = "—" if want is None else f"{np.abs((np.asarray(f['g']) - want) / np.asarray(f['g_std'])).max():.1f}"
            sb, sa = r["spacing_before"], f["spacing_after"]
            L.append(f"| {r['case']} | {r['inject'] or '—'} | {kind} | {f['gain_nats']:.1f} | "
                     f"{f['gain_nats_per_sample']:.4f} | {gs} | {exp} | {zmax} | "
                     f"{_mm(sb['x_m'])} / {_mm(sb['y_m'])} → {_mm(sa['x_m'])} / {_mm(sa['y_m'])} | "
                     f"{', '.join(_f(v) for v in r['angjerk_before'])} → {', '.join(_f(v) for v in f['angjerk_after'])} |")
    L += consistency(rows)
    L += ["", "Per round (ΔG fitted jointly with the positions at fixed scales, its joint gain, then the likelihood "
          "after the scales' refit): `experiments/out/gyro_common_probe/*.json`, key `rounds`.", ""]
    return "\n".join(L) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
