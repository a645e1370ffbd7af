#!/usr/bin/env python3
"""Diagnostic (issue #30, the negative result's next physics): the instant error's isotropic part.

After the triads' own instant error on their output rates (``model/likelihood_percov.py``, "Instant
error"), the remaining sandwich excess on the real board is a within-IMU variance that grows with
|ω̄| (``mimu_model_calibrate.md``, decomposition).  The same instant error ε_kt also multiplies the
unresolved jerk m_t (the detector's y = (d + ε) m + e): variance e² s_b² per channel, isotropic, zero
in the slowest band and ≈ (0.27 ms × 6500 m/s³)² ≈ 3 (m/s²)² in the fastest — the likelihood keeps
one constant level σ_k² per triad instead.  This probe puts it in: per report |ω| band b a noise
level σ_w,k² + e² s_b² (σ_w,k² the white part, by moment: the band-weighted mean of the levels kept
equal to the calibration's σ_k², floored at a tenth of it), each band its own φ-projection M_b (the
samples of a band share Λ_b, so the likelihood is the sum of per-band per-sample-covariance
likelihoods), the jerk scales s_b and e as ``calibrate --model`` fitted them.  Measured at the mode
at ω̄ (no chains): the sandwich/Laplace std ratio per coordinate in ``sandwich_inflation``'s
convention (each band's −½ log|M_b| share taken off its samples' scores), against the same figure
of ``calibrate --model``'s likelihood by the same procedure (its mode at ω̄ without the position
prior, band-wise scores).  The probe's settings were chosen after
seeing exp 1–3: a diagnostic for the next step, not a calibration setting.

    PYTHONPATH=. python3 experiments/percov_isotropic_probe.py --reports DIR --experiments 1

Writes ``experiments/percov_isotropic_probe.md`` (cache in ``experiments/out/percov_isotropic``).
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _data import data_dir  # noqa: E402

from accel_bayes.data.outputs import write_json, write_text  # noqa: E402


class _Stop(Exception):
    pass


def percov_step(exp: int, reports: Path):
    """``calibrate --model``'s per-sample step of experiment ``exp`` (its likelihood, mode, Laplace
    covariance and record), the chains not run."""
    import accel_bayes.pipelines.calibrate as cal
    from accel_bayes.data.mimu import import_mimu

    rec = import_mimu(data_dir() / f"exp_{exp}" / "data.bin.gz")
    seen = {}
    real = cal._model_percov_step

    def grab(lik, terms, omega_norm, *a, **k):
        seen["pc"] = real(lik, terms, omega_norm, *a, **k)
        seen["omega_norm"] = omega_norm
        seen["edges"] = terms.parameters["omega_edges"]
        raise _Stop

    cal._model_percov_step = grab
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cal.calibrate(rec, chains=1, draws=10, warmup=10, seed=0, progress=False, instant_error=True,
                          model=reports / f"exp_{exp}" / "report.json")
    except _Stop:
        pass
    finally:
        cal._model_percov_step = real
    return seen


class BandSplit:
    """Σ_b of per-sample-covariance likelihoods on each band's samples with its own noise levels."""

    def __init__(self, lik, band, sigma_b):
        from accel_bayes.model.likelihood import RaoBlackwellLikelihood
        from accel_bayes.model.likelihood_percov import with_unresolved_motion

        self.A, self.reference, self.dtype, self.omega, self.T = lik.A, lik.reference, lik.dtype, lik.omega, lik.T
        self.parts = []
        for b in range(int(band.max()) + 1):
            idx = torch.nonzero(band == b).reshape(-1)
            if len(idx) == 0:
                continue
            base = RaoBlackwellLikelihood(lik.acc[idx], lik.omega.select(idx), sigma_b[b], 1, reference=lik.reference,
                                          phi_prior=lik.phi_prior)
            part = with_unresolved_motion(base, lik.age[idx], lik.jerk_std[idx], rate=lik.rate[idx],
                                          instant_std=lik.instant_std)
            self.parts.append((idx, part))

    def log_lik_given_omega(self, P, w):
        return sum(part.log_lik_given_omega(P, w[idx]) for idx, part in self.parts)

    def scores(self, th, full):
        from accel_bayes.inference.noise_fit import per_sample_scores

        S = torch.zeros(self.T, len(th), dtype=torch.float64)
        for idx, part in self.parts:
            w = self.omega.mean[idx]
            s = per_sample_scores(lambda t, part=part, w=w: part.log_lik_per_sample(full(t), w), th)
            m = per_sample_scores(lambda t, part=part: -0.5 * part._projection_hot(part._positions(full(t))[None])[
                "logdetM"], th)[0]
            S[idx] = s - m
        return S


def run(exp: int, reports: Path) -> dict:
    from accel_bayes.inference.noise_fit import score_sandwich
    from accel_bayes.model.unresolved_fit import fixed_omega_mode

    t0 = time.perf_counter()
    seen = percov_step(exp, reports)
    pc = seen["pc"]
    lik = pc.lik
    band = torch.bucketize(torch.as_tensor(seen["omega_norm"], dtype=torch.float64),
                           torch.as_tensor(seen["edges"], dtype=torch.float64), right=True)
    s_b = torch.as_tensor(pc.record["jerk_rms_fitted_scaled"], dtype=torch.float64)
    e = float(lik.instant_std)
    iso = (e * s_b) ** 2  # (B,) (m/s²)² per channel
    frac = torch.bincount(band, minlength=len(s_b)).to(torch.float64) / lik.T
    sig2 = lik.acc_noise_std.square()  # (A, 3)
    white = torch.maximum(sig2 - float((frac * iso).sum()), 0.1 * sig2)
    A, ref = lik.A, lik.reference
    free = [k for k in range(A) if k != ref]

    def full(th):
        P = torch.zeros(A, 3, dtype=th.dtype)
        P[free] = th.reshape(A - 1, 3)
        return P

    out = {"exp": exp, "reference": ref, "instant_std_s": e, "iso_rms_m_s2": iso.sqrt().tolist(), "band_fraction": frac.tolist(),
           "white_rms_m_s2": float(white.mean().sqrt()), "sigma_rms_m_s2": float(sig2.mean().sqrt())}
    # the same procedure (mode at ω̄ without the position prior, band-wise scores) on calibrate --model's
    # likelihood (one level per triad in every band) and with the isotropic part
    for key, sig in (("base", [lik.acc_noise_std] * len(s_b)), ("iso", [(white + float(v)).sqrt() for v in iso])):
        split = BandSplit(lik, band, sig)
        P, cov = fixed_omega_mode(split, pc.positions)
        th = (P - P[ref])[free].reshape(-1)
        ratio = np.asarray(score_sandwich(split.scores(th, full), cov)["std_ratio"])
        out[key] = {"ratio": ratio.tolist(), "ratio_max": float(ratio.max()), "ratio_median": float(np.median(ratio)),
                    "laplace_std_m": cov.diagonal().sqrt().tolist(), "mode_m": P.tolist()}
    out["mode_shift_m"] = float((torch.as_tensor(out["iso"]["mode_m"]) - torch.as_tensor(out["base"]["mode_m"]))
                                .norm(dim=-1).max())
    out["seconds"] = time.perf_counter() - t0
    return out


def loo_z(rows, key) -> np.ndarray:
    """(E, n) leave-one-out z of the free coordinates from each row's mode and Laplace std under ``key``."""
    # the reference row of each mode is zeros; the free coordinates in Laplace order are the others
    m = np.array([np.asarray(r[key]["mode_m"])[[k for k in range(len(r[key]["mode_m"])) if k != r.get("reference", 0)]]
                  .reshape(-1) for r in rows])
    s = np.array([r[key]["laplace_std_m"] for r in rows])
    out = np.zeros_like(m)
    for e in range(len(rows)):
        o = [j for j in range(len(rows)) if j != e]
        w = 1 / s[o] ** 2
        out[e] = (m[e] - (w * m[o]).sum(0) / w.sum(0)) / np.sqrt(s[e] ** 2 + 1 / w.sum(0))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reports", type=Path, default=HERE / "out" / "mimu_mismatch")
    ap.add_argument("--experiments", default="1")
    ap.add_argument("--out", type=Path, default=HERE / "out" / "percov_isotropic")
    ap.add_argument("--md", type=Path, default=HERE / "percov_isotropic_probe.md")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    rows = []
    for e in [int(x) for x in args.experiments.split(",")]:
        f = args.out / f"exp_{e}.json"
        if f.exists():
            r = json.loads(f.read_text())
        else:
            r = run(e, args.reports)
            f.parent.mkdir(parents=True, exist_ok=True)
            write_json(f, r)
        rows.append(r)
        print(f"exp {e}: ratio max {r['base']['ratio_max']:.2f} -> {r['iso']['ratio_max']:.2f}", flush=True)
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    L = ["# The instant error's isotropic part e² s_b² per |ω| band (issue #30, next physics probe)", "",
         f"Regenerate: `PYTHONPATH=. python3 experiments/percov_isotropic_probe.py --reports {args.reports} "
         f"--experiments {args.experiments}` ({stamp}, {platform.machine()} {platform.system()}, shared 2-core CPU "
         "under load, one torch thread). What it measures and why: the module docstring. Chosen after seeing "
         "exp 1–3 of `mimu_model_calibrate.md`: a diagnostic, not a calibration setting. At the mode at ω̄, no chains.",
         "", "| exp | e (ms) | e·s_b per band (m/s²) | σ rms: calibrate / white part (m/s²) | ratio max (median): "
         "calibrate --model --instant-error likelihood | ratio max (median): + e² s_b² per band | Laplace std median (µm): "
         "calibrate --model --instant-error / + e² s_b² | mode shift (µm, max over IMUs) |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        b, i = r["base"], r["iso"]
        L.append(f"| {r['exp']} | {1e3 * r['instant_std_s']:.3f} | {', '.join(f'{v:.2f}' for v in r['iso_rms_m_s2'])} | "
                 f"{r['sigma_rms_m_s2']:.2f} / {r['white_rms_m_s2']:.2f} | {b['ratio_max']:.2f} ({b['ratio_median']:.2f}) | "
                 f"{i['ratio_max']:.2f} ({i['ratio_median']:.2f}) | {1e6 * np.median(b['laplace_std_m']):.0f} / "
                 f"{1e6 * np.median(i['laplace_std_m']):.0f} | {1e6 * r['mode_shift_m']:.0f} |")
    if len(rows) > 2:
        L += ["", "Across the experiments, at the modes with their Laplace std (no chains): leave-one-out z of each "
              "coordinate, z = (m_e − m̄_{−e}) / √(s_e² + 1/Σ_{j≠e} s_j⁻²), m̄_{−e} the inverse-variance mean of the others "
              "(`mimu_model_calibrate.md`'s definition, here on modes and Laplace std).", "",
              "| likelihood | LOO z RMS, all / first three / last three | max \|z\| |", "|---|---|---|"]
        for key, label in (("base", "calibrate --model --instant-error"), ("iso", "+ e² s_b² per band")):
            z = loo_z(rows, key)
            h = len(z) // 2
            L.append(f"| {label} | {np.sqrt(np.mean(z ** 2)):.2f} / {np.sqrt(np.mean(z[:h] ** 2)):.2f} / "
                     f"{np.sqrt(np.mean(z[h:] ** 2)):.2f} | {np.abs(z).max():.2f} |")
    write_text(args.md, "\n".join(L) + "\n")
    print("\n".join(L))


if __name__ == "__main__":
    main()
