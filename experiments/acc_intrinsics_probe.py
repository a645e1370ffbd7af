#!/usr/bin/env python3
"""Probe (issue #30, accprobe): do per-triad ACCELEROMETER scale / cross-axis errors (the intrinsics
the model takes as known) carry the board's ~1e5 rad/s³ angular-jerk scales and the short x spacing?

The hypothesis (``gyro_common_probe.md``'s reading): a triad's gain error K_k multiplies everything
that triad reads, including the centripetal term ω×(ω×r_k) ∝ |ω|² r_k, so it is triad-specific and
grows with |ω|² — what a common gyro error G cannot carry.  Corrected data y_k ← (I + K_k) y_k (array
frame, dimensionless K), K_k a scale c_k I ("scale"), a diagonal ("diag") or a symmetric 3×3 ("sym",
six numbers; the antisymmetric part would be a small rotation of the triad, a mounting angle: another
effect, not fitted here).

Same step as ``gyro_common_probe.py`` (its interception is reused): ``calibrate(rec, model=report)``
is run up to its per-sample-covariance step, which gives the baseline; then per kind (a) K jointly
with the free positions at the mode of that step's ``log_lik_given_omega`` at ω̄ on the corrected
data PLUS the Jacobian T Σ_k log|I + K_k| (the data are transformed: without it shrinking every y
would "gain"), plus calibrate's position prior; Laplace std from the joint Hessian; (b) the step
rerun on the corrected data (jerk / angular-jerk scales refitted by type-II ML, mode refitted).
Gain: (b)'s likelihood at its mode plus the Jacobian, less the baseline's, nats.

Identifiability.  A COMMON isotropic scale (the same c on every triad) is exactly an array scale:
N((1+c)y; G(r)u + H(r)φ, Q)(1+c)^{3A} = N(y; G(r/(1+c))u + H(r/(1+c))φ, Q/(1+c)²) — positions and
noise level rescaled; only the position prior, the φ prior and the fixed noise level see it.  So the
reference triad (calibrate's position origin) keeps K = 0 and every other K_k is RELATIVE to it:
the data identify K_k − K_ref (per-triad differences: through the common specific force s_t, which
every triad reads, as well as through the centripetal term).  A common ANISOTROPIC error of all
triads is identified only through ω×(ω×r) and would appear here as the same K on every non-reference
triad (and zero on the reference, which then carries minus it).

Controls (concealed clockgen cases, ``percov_conceal``'s cache, their own detector reports, the
generator's acc intrinsics inverted exactly, ``known``): "none" — K must be ≈ 0 within its std;
"scale5" — triad ``INJECT_TRIAD``'s readings × 1.005 (isotropic: the same in every frame), so
K on that triad must come out ≈ 1/1.005 − 1 = −4.98·10⁻³ and ≈ 0 elsewhere.

    PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/acc_intrinsics_probe.py --exps 1
    ... --exps 2,5
    ... --exps '' --cases 15 --inject none,scale5
    ... --exps 3,4,6
    ... --exps '' --cases 20 --inject none,scale5
    ... --from-cache            (the document from all of them, nothing computed)

Writes ``experiments/acc_intrinsics_probe.md`` and ``experiments/out/acc_intrinsics_probe/*.json``.
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import torch

from experiments._percov_step import at_percov_step

from experiments.gyro_common_probe import _ll, _mm, _f, spacing

ROOT = Path(__file__).resolve().parent
DOC = ROOT / "acc_intrinsics_probe.md"
#: parameters per non-reference triad, per kind of K
KINDS = {"scale": 1, "diag": 3, "sym": 6}
#: the symmetric K's parameters: xx, yy, zz, xy, xz, yz
_SYM = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
#: the concealed triad that gets the injected gain error, and the errors (readings × (1 + e))
INJECT_TRIAD = 3
INJECT = {"none": 0.0, "scale5": 0.005}


def k_matrices(p: torch.Tensor, kind: str, A: int, reference: int) -> torch.Tensor:
    """(A, 3, 3) dimensionless K_k from parameters p ((A − 1)·n, triad-major over the non-reference
    triads); the reference triad's K is 0 (module docstring, "Identifiability")."""
    n = KINDS[kind]
    free = [k for k in range(A) if k != reference]
    P = p.reshape(A - 1, n)
    if kind == "scale":
        Kf = P[:, :1, None] * torch.eye(3, dtype=p.dtype)
    elif kind == "diag":
        Kf = torch.diag_embed(P)
    else:
        rows = []
        for i in range(3):
            for j in range(3):
                a, b = min(i, j), max(i, j)
                rows.append(P[:, _SYM.index((a, b))])
        Kf = torch.stack(rows, -1).reshape(A - 1, 3, 3)
    K = torch.zeros(A, 3, 3, dtype=p.dtype)
    K[free] = Kf
    return K


def params_of(K: torch.Tensor, kind: str, reference: int) -> list:
    """The parameters of :func:`k_matrices` for (A, 3, 3) K of that ``kind`` (its inverse)."""
    K = torch.as_tensor(K, dtype=torch.float64)
    free = [k for k in range(K.shape[0]) if k != reference]
    Kf = K[free]
    if kind == "scale":
        out = Kf[:, 0, 0:1]
    elif kind == "diag":
        out = Kf.diagonal(0, 1, 2)
    else:
        out = torch.stack([Kf[:, a, b] for a, b in _SYM], -1)
    return [float(v) for v in out.reshape(-1)]


def corrected_acc(acc: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(T, A, 3) m/s²: y_k ← (I + K_k) y_k, acc (T, A, 3) array frame, K (A, 3, 3)."""
    return acc + torch.einsum("kij,tkj->tki", K, acc)


def log_jacobian(K: torch.Tensor, T: int) -> torch.Tensor:
    """T Σ_k log|det(I + K_k)| nats: the density of the recorded data given the model of the corrected."""
    return T * torch.linalg.slogdet(torch.eye(3, dtype=K.dtype) + K)[1].sum()


def with_acc(lik, K: torch.Tensor):
    """A shallow copy of a (flat or per-sample) likelihood whose data are (I + K_k) y_k; θ-free caches
    that depend on y dropped (differentiable in K when K requires grad)."""
    new = copy.copy(lik)
    new.acc = corrected_acc(lik.acc, K)
    new.y = new.acc.reshape(lik.T, 3 * lik.A)
    new.__dict__.pop("_yu_cache", None)
    return new


def with_noise_scale(lik, alpha: torch.Tensor):
    """A shallow copy of a (flat or per-sample) likelihood whose triad k's noise std is α_k times
    ``lik``'s (α (A,), differentiable); its ``log_constant`` follows, and the λ^½-whitened loadings of
    the per-sample covariance (built at construction) are rescaled to the new λ."""
    A, T = lik.A, lik.T
    ratio = (1.0 / alpha).repeat_interleave(3)  # new λ^½ / old λ^½, per row
    new = copy.copy(lik)
    new.lam = lik.lam * ratio.square()
    new.acc_noise_std = lik.acc_noise_std * alpha.reshape(A, *([1] * (lik.acc_noise_std.dim() - 1)))
    new._sqrt_lam_cache = lik._sqrt_lam * ratio
    new.log_constant = lik.log_constant + T * float(ratio.detach().log().sum())
    for key in ("_yu_cache", "_tf_cache"):
        new.__dict__.pop(key, None)
    if getattr(lik, "W", None) is not None:
        new.W = lik.W * ratio[None, :, None]
    if getattr(lik, "_blocks", None) is not None:
        k, wk = lik._blocks
        new._blocks = (k, wk * ratio.view(A, 3)[k][..., None])
    return new


def fit_acc_gain(lik, pos0, kind: str, *, prior_mean=None, prior_std=None) -> dict:
    """K (``kind``) jointly with the free positions AND the triads' noise levels at the mode of
    log p(y | ω̄, θ, K, α) (the Jacobian included) + the Gaussian position prior (``prior_mean``
    (A, 3) m, ``prior_std`` m; none if None).  α_k multiplies triad k's noise std: without it an
    isotropic K_k would stand in for the noise level the noise step fitted under the flat model
    ((1+c)³N((1+c)y; μ, σ²) = N(y; μ/(1+c), σ²/(1+c)²)), not for the physics.

    Returns {"k": params, "k_std": Laplace std (joint Hessian, positions and α included), "K":
    (A, 3, 3), "alpha": (A,), "alpha_base": (A,) α at K = 0, "positions": (A, 3) m, "gain_nats": the
    objective at the joint mode less at K = 0 (positions and α refitted), "alpha_gain_nats": the
    objective at K = 0 with α refitted less with α = 1}."""
    A, ref, T = lik.A, lik.reference, lik.T
    free = [k for k in range(A) if k != ref]
    n = KINDS[kind] * (A - 1)
    m = 3 * (A - 1)
    pos0 = torch.as_tensor(pos0, dtype=torch.float64)
    mu = None if prior_mean is None else torch.as_tensor(prior_mean, dtype=torch.float64)
    mu = None if mu is None else (mu - mu[ref])[free].reshape(-1)
    w = lik.omega.mean

    def full(th):
        P = torch.zeros(A, 3, dtype=th.dtype)
        P[free] = th.reshape(A - 1, 3)
        return P

    def nll(x, with_k=True):
        th, a, p = x[:m], x[m:m + A], x[m + A:]
        cur = with_noise_scale(lik, a.exp())
        out = 3 * T * a.sum()  # −T Σ log λ^½ change: the noise density's normaliser
        if with_k:
            K = k_matrices(p, kind, A, ref)
            out = out - with_acc(cur, K).log_lik_given_omega(full(th), w) - log_jacobian(K, T)
        else:
            out = out - cur.log_lik_given_omega(full(th), w)
        if mu is not None:
            out = out + 0.5 * ((th - mu) / float(prior_std)).square().sum()
        return out

    def mode(x0, with_k, fixed_alpha=False):
        x = x0.clone().requires_grad_(True)
        opt = torch.optim.LBFGS([x], max_iter=100, line_search_fn="strong_wolfe", tolerance_grad=1e-9,
                                tolerance_change=1e-14)
        mask = torch.ones_like(x0)
        if fixed_alpha:
            mask[m:m + A] = 0

        def closure():
            opt.zero_grad()
            loss = nll(x, with_k)
            loss.backward()
            x.grad.mul_(mask)
            return loss

        for _ in range(3):
            opt.step(closure)
        return x.detach()

    th0 = (pos0 - pos0[ref])[free].reshape(-1)
    x0 = torch.cat([th0, torch.zeros(A + n, dtype=torch.float64)])
    x_unit = mode(x0, False, fixed_alpha=True)
    x_base = mode(x_unit, False)
    x_hat = mode(x_base, True)
    H = torch.autograd.functional.hessian(nll, x_hat)
    cov = torch.linalg.inv(H)
    p = x_hat[m + A:]
    with torch.no_grad():
        gain = float(nll(x_base, False) - nll(x_hat, True))
        alpha_gain = float(nll(x_unit, False) - nll(x_base, False))
    return {"k": p.tolist(), "k_std": cov.diagonal()[m + A:].clamp_min(0).sqrt().tolist(),
            "K": k_matrices(p, kind, A, ref).tolist(), "alpha": x_hat[m:m + A].exp().tolist(),
            "alpha_base": x_base[m:m + A].exp().tolist(), "positions": full(x_hat[:m]), "gain_nats": gain,
            "alpha_gain_nats": alpha_gain}


def probe(rec, report, kinds=("scale", "diag", "sym")) -> dict:
    """The baseline step and the K fits of the module docstring on one recording."""

    out = {}

    def step(orig, lik, terms, omega_norm, sample_scale, map_res, nominal_acc, prior_std, **kw):
        labels = list(lik.imu_labels)
        t0 = time.perf_counter()
        base = orig(lik, terms, omega_norm, sample_scale, map_res, nominal_acc, prior_std, **kw)
        out.update(T=int(lik.T), A=int(lik.A), labels=labels, reference=int(lik.reference),
                   prior_std_m=float(prior_std), loglik_before=_ll(base),
                   spacing_before=spacing(base.positions, labels),
                   angjerk_before=base.record["angular_jerk_rms_fitted_rad_s3"],
                   jerk_before=base.record["jerk_rms_fitted_m_s3"], band_samples=base.record["band_samples"],
                   laplace_std_before_mm=float(base.laplace_cov.diagonal().sqrt().median() * 1e3), fits={})
        for kind in kinds:
            t1 = time.perf_counter()
            f = fit_acc_gain(base.lik, base.positions, kind, prior_mean=nominal_acc, prior_std=prior_std)
            K = torch.as_tensor(f["K"], dtype=torch.float64)
            mr = None if map_res is None else dataclasses.replace(map_res, positions=f["positions"])
            noisy = with_noise_scale(lik, torch.as_tensor(f["alpha"], dtype=torch.float64))
            cur = orig(with_acc(noisy, K), terms, omega_norm, sample_scale, mr, nominal_acc, prior_std, **kw)
            gain = _ll(cur) + float(log_jacobian(K, lik.T)) - out["loglik_before"]
            # the same step with the noise levels alone refitted (K = 0): what α is worth by itself
            if "loglik_alpha_only" not in out:
                mr0 = None if map_res is None else dataclasses.replace(map_res, positions=base.positions)
                alone = orig(with_noise_scale(lik, torch.as_tensor(f["alpha_base"], dtype=torch.float64)), terms,
                             omega_norm, sample_scale, mr0, nominal_acc, prior_std, **kw)
                out.update(loglik_alpha_only=_ll(alone), alpha_only=f["alpha_base"],
                           spacing_alpha_only=spacing(alone.positions, labels),
                           angjerk_alpha_only=alone.record["angular_jerk_rms_fitted_rad_s3"])
            out["fits"][kind] = {
                "K": f["K"], "k": f["k"], "k_std": f["k_std"], "joint_gain_nats": f["gain_nats"],
                "alpha": f["alpha"], "alpha_gain_joint_nats": f["alpha_gain_nats"],
                "gain_nats": gain, "gain_nats_per_sample": gain / lik.T,
                "gain_over_alpha_nats": _ll(cur) + float(log_jacobian(K, lik.T)) - out["loglik_alpha_only"],
                "spacing_joint": spacing(f["positions"], labels), "spacing_after": spacing(cur.positions, labels),
                "angjerk_after": cur.record["angular_jerk_rms_fitted_rad_s3"],
                "jerk_after": cur.record["jerk_rms_fitted_m_s3"],
                "laplace_std_after_mm": float(cur.laplace_cov.diagonal().sqrt().median() * 1e3),
                "seconds": time.perf_counter() - t1}
            print(f"  {kind}: gain {gain:.1f} nats (joint {f['gain_nats']:.1f}), "
                  f"{time.perf_counter() - t1:.0f} s", flush=True)
        out["seconds"] = time.perf_counter() - t0

    at_percov_step(rec, report, step)
    return out


def inject_acc_gain(rec, triad: int, e: float):
    """The recording with IMU row ``triad``'s accelerometer readings × (1 + e) (isotropic: any frame)."""
    acc = np.asarray(rec.acc, dtype=np.float64).copy()
    acc[:, triad] *= 1.0 + e
    return dataclasses.replace(rec, acc=acc)


def expected_k(inject: str, A: int, reference: int, kind: str) -> list:
    """The K parameters a correct fit should find on a concealed case with ``inject`` (module docstring)."""
    K = torch.zeros(A, 3, 3, dtype=torch.float64)
    e = INJECT[inject]
    if e and INJECT_TRIAD != reference:
        K[INJECT_TRIAD] = (1.0 / (1.0 + e) - 1.0) * torch.eye(3, dtype=torch.float64)
    return params_of(K, kind, reference)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--exps", default="1", help="MIMU experiments (reports in --reports)")
    ap.add_argument("--cases", default="", help="concealed clock seeds (percov_conceal's cache)")
    ap.add_argument("--inject", default="none,scale5", help="gain errors put into the concealed cases' triad "
                    f"{INJECT_TRIAD}: " + ", ".join(INJECT))
    ap.add_argument("--kinds", default="scale,diag,sym")
    ap.add_argument("--conceal", type=Path, default=ROOT / "out" / "percov_conceal")
    ap.add_argument("--reports", type=Path, default=ROOT / "out" / "mimu_mismatch")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "acc_intrinsics_probe")
    ap.add_argument("--from-cache", action="store_true",
                    help="compute nothing: the document from every case cached in --out (real ones first)")
    args = ap.parse_args(argv)
    if args.from_cache:
        args.exps, args.cases = "", ""
    from accel_bayes.data.outputs import write_json, write_text
    from accel_bayes.errors import UserError
    from experiments._reading import READING_MARKER, kept_reading

    kinds = tuple(k for k in args.kinds.split(",") if k)
    bad = [k for k in kinds if k not in KINDS] + [s for s in args.inject.split(",") if s and s not in INJECT]
    if bad:
        raise UserError(f"--kinds/--inject: expected {sorted(KINDS)} / {sorted(INJECT)}, got {bad}")
    args.out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    torch.manual_seed(0)
    for exp in [int(s) for s in args.exps.split(",") if s]:
        f = args.out / f"exp_{exp}.json"
        if not f.exists():
            from accel_bayes.data.mimu import import_mimu
            from experiments._data import data_dir
            print(f"exp_{exp}", flush=True)
            rec = import_mimu(Path(data_dir()) / f"exp_{exp}" / "data.bin.gz")
            r = probe(rec, args.reports / f"exp_{exp}" / "report.json", kinds)
            write_json(f, {"case": f"exp_{exp}", "inject": None, **r})
    for seed in [int(s) for s in args.cases.split(",") if s]:
        for inj in [s for s in args.inject.split(",") if s]:
            f = args.out / f"clock-{seed:03d}-{inj}.json"
            if not f.exists():
                from experiments.percov_conceal import case_recording
                print(f"clock-{seed:03d} {inj}", flush=True)
                case = json.loads((args.conceal / f"clock-{seed:03d}" / "case.json").read_text())
                rec, _, _ = case_recording(seed, case["duration"], case["mount_std_m"], case["acc_intrinsics"])
                r = probe(inject_acc_gain(rec, INJECT_TRIAD, INJECT[inj]),
                          args.conceal / f"clock-{seed:03d}" / "report.json", kinds)
                write_json(f, {"case": f"clock-{seed:03d}", "inject": inj, **r})
    rows = [json.loads(f.read_text()) for f in sorted(args.out.glob("exp_*.json"))]
    rows += [json.loads(f.read_text()) for f in sorted(args.out.glob("clock-*.json"))]
    write_json(args.out / "summary.json", rows)
    write_text(DOC, document(rows, time.perf_counter() - t_start, argv) + "\n" + READING_MARKER + kept_reading(DOC))
    print(f"wrote {DOC}")
    return 0


def consistency(rows) -> list:
    """Lines: per kind, the real experiments' K pooled by inverse variance per parameter and the χ² of
    their spread about it (the same board and triads: one K per triad should fit them all)."""
    real = [r for r in rows if r["inject"] is None]
    if len(real) < 2:
        return []
    L = ["", f"Across the real experiments ({', '.join(r['case'] for r in real)}): per kind the inverse-variance "
         "pooled K ± std (×1e-3, per non-reference triad as in the table) and the χ² of the experiments about it "
         "(dof = (experiments − 1) × parameters).", "",
         "| K kind | pooled K ± std (×1e-3) | χ² total / dof | largest χ² of one parameter |", "|---|---|---|---|"]
    for kind in real[0]["fits"]:
        have = [r for r in real if kind in r["fits"]]
        if len(have) < 2:
            continue
        k = np.array([r["fits"][kind]["k"] for r in have])
        s = np.array([r["fits"][kind]["k_std"] for r in have])
        w = s ** -2
        m = (k * w).sum(0) / w.sum(0)
        chi = (((k - m) / s) ** 2).sum(0)
        L.append(f"| {kind} | {_params(m, w.sum(0) ** -0.5, KINDS[kind], have[0])} | "
                 f"{chi.sum():.1f} / {chi.size * (len(have) - 1)} | {chi.max():.1f} |")
    return L


def _params(k, s, n, row) -> str:
    """'IMU label: values ± std (×1e-3)' per non-reference triad."""
    labels = [lab for i, lab in enumerate(row["labels"]) if i != row["reference"]]
    out = []
    for j, lab in enumerate(labels):
        vals = ", ".join(f"{a * 1e3:.2f}±{b * 1e3:.2f}" for a, b in zip(k[j * n:(j + 1) * n], s[j * n:(j + 1) * n]))
        out.append(f"{lab}: {vals}")
    return "; ".join(out)


def document(rows, seconds, argv=None) -> str:
    import sys

    from experiments._stamp import run_stamp

    cmd = " ".join(argv if argv is not None else sys.argv[1:])
    L = ["# acc_intrinsics_probe — per-triad accelerometer gain errors K_k (issue #30, accprobe)", "",
         f"Regenerate: `PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/acc_intrinsics_probe.py {cmd}` "
         f"({run_stamp()}, nice 5; cached per case in "
         f"`experiments/out/acc_intrinsics_probe/`; this invocation {seconds:.0f} s; the document is the cache's "
         "union). Reports: main's `experiments/out/mimu_mismatch/exp_*/report.json`, sha256 as in "
         "`mimu_model_calibrate.md` (checked); concealed cases and their reports: `percov_conceal`'s cache. The "
         "cached rows were made by the invocations in the script's docstring, in that order.", "",
         "What runs: the script's docstring. K: y_k ← (I + K_k) y_k, array frame, the reference triad's K = 0 (a "
         "common isotropic scale is an array scale; docstring, \"Identifiability\"). Gain: the per-sample-covariance "
         "likelihood at its mode (scales refitted by type-II ML on the corrected data, each triad's noise std × α_k "
         "refitted jointly with K and the positions) plus the Jacobian T Σ log|I + K_k|, less the baseline (K = 0, "
         "α = 1, i.e. `calibrate --model`'s own step), nats; the row \"none\" is α alone, and \"gain over the noise "
         "refit alone\" is K's own share. ± is the Laplace std (joint Hessian with the positions, "
         "position prior included). Spacing: x of IMUs 4, 6 and −y of IMUs 2, 6 at the mode (design 18.9 mm). "
         "Angular-jerk rms per |ω| band, fitted by type-II ML at the step.", "",
         "| case | inject | K kind | gain (nats) | per sample | gain over the noise refit alone (nats) | fitted K per non-reference IMU ± std (×1e-3; sym: xx, yy, "
         "zz, xy, xz, yz) | max abs z vs expected | x / y spacing before → after (mm) | angular-jerk rms per band "
         "before → after (rad/s³) |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "loglik_alpha_only" in r:
            sb, sa = r["spacing_before"], r["spacing_alpha_only"]
            g = r["loglik_alpha_only"] - r["loglik_before"]
            L.append(f"| {r['case']} | {r['inject'] or '—'} | none (noise levels α alone: "
                     f"{', '.join(f'{a:.3f}' for a in r['alpha_only'])}) | {g:.1f} | {g / r['T']:.4f} | — | — | — | "
                     f"{_mm(sb['x_m'])} / {_mm(sb['y_m'])} → {_mm(sa['x_m'])} / {_mm(sa['y_m'])} | "
                     f"{', '.join(_f(v) for v in r['angjerk_before'])} → "
                     f"{', '.join(_f(v) for v in r['angjerk_alpha_only'])} |")
        for kind, f in r["fits"].items():
            zmax = "—"
            if r["inject"] is not None:
                want = np.asarray(expected_k(r["inject"], r["A"], r["reference"], kind))
                zmax = f"{np.abs((np.asarray(f['k']) - want) / np.asarray(f['k_std'])).max():.1f}"
            sb, sa = r["spacing_before"], f["spacing_after"]
            L.append(f"| {r['case']} | {r['inject'] or '—'} | {kind} | {f['gain_nats']:.1f} | "
                     f"{f['gain_nats_per_sample']:.4f} | {f['gain_over_alpha_nats']:.1f} | {_params(f['k'], f['k_std'], KINDS[kind], r)} | {zmax} | "
                     f"{_mm(sb['x_m'])} / {_mm(sb['y_m'])} → {_mm(sa['x_m'])} / {_mm(sa['y_m'])} | "
                     f"{', '.join(_f(v) for v in r['angjerk_before'])} → "
                     f"{', '.join(_f(v) for v in f['angjerk_after'])} |")
    L += consistency(rows)
    L += ["", f"Concealed cases: triad row {INJECT_TRIAD} gets the injected gain; expected K there "
          f"1/1.005 − 1 = {(1 / 1.005 - 1) * 1e3:.2f}×10⁻³ (scale5), 0 elsewhere and for \"none\".", ""]
    return "\n".join(L) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
