#!/usr/bin/env python3
"""Probe (exploratory, issue #30 item 1): where the per-sample covariance puts the geometry of the
real exp_1 at fixed ω, before it is wired into ``calibrate``.

Per model — the flat likelihood, the per-sample unresolved-jerk covariance, and that with the
scale mixture — the maximum over the positions of the exact log p(y | ω̄, θ) with ω at the gyro
mean (not integrated over its posterior, not the MAP of ``calibrate``: the errors-in-ω bias of
a fixed ω̄ is in all three), its Laplace std, and the array's scale against the design (the
least-squares factor s of the fitted positions on the nominal ones, relative to the reference;
s × 18.9 mm is the x–y spacing).  Noise per triad and ages as in ``bench_likelihood_percov.py``;
the scales fitted by type-II ML at the nominal positions (:mod:`accel_bayes.model.unresolved_fit`);
the prior on φ flat and the empirical one ``calibrate`` uses by default.

    PYTHONPATH=. python3 experiments/percov_map_probe.py

Writes ``experiments/percov_map_probe.md``.
"""
from __future__ import annotations

import os
import platform
import sys
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _data import data_dir  # noqa: E402
from bench_likelihood_percov import exp1_ages, load_experiment, quartile_band, residual_noise  # noqa: E402

from accel_bayes.data.outputs import write_text  # noqa: E402
from accel_bayes.model.likelihood import RaoBlackwellLikelihood  # noqa: E402
from accel_bayes.model.likelihood_percov import with_unresolved_motion  # noqa: E402
from accel_bayes.model.phi_prior import empirical_phi_prior  # noqa: E402
from accel_bayes.model.unresolved_fit import fit_unresolved_scales, fixed_omega_mode  # noqa: E402

SPACING_MM = 18.9
N_INTEGRATED = 16  # draws of ω per sample for the ω-integrated maximum (fixed: common random numbers)


def fixed_omega_max(lik, pos0, z=None):
    """:func:`accel_bayes.model.unresolved_fit.fixed_omega_mode` without a prior (this probe's maxima)."""
    return fixed_omega_mode(lik, pos0, z=z)


def main():
    torch.set_num_threads(1)
    path = data_dir() / "exp_1" / "data.bin.gz"
    if not path.exists():
        print(f"skipped: {path} not found")
        return
    rec, st = load_experiment(path)
    pos0 = st.nominal_positions.clone()
    nom = (pos0 - pos0[st.reference])[[k for k in range(st.A) if k != st.reference]].reshape(-1)
    g = nom / (nom @ nom)  # ∂s/∂θ of the least-squares scale s = ⟨θ, nom⟩/⟨nom, nom⟩
    sigma = residual_noise(st, pos0)
    age = exp1_ages(rec, st)
    band, _ = quartile_band(st.omega.mean.norm(dim=-1))
    rows, res = [], {}
    z = st.sample_z((), N_INTEGRATED, torch.Generator().manual_seed(0))
    for prior_name in ("flat", "empirical"):
        F = None if prior_name == "flat" else empirical_phi_prior(st.acc, st.omega.mean, sigma, pos0)
        flat = RaoBlackwellLikelihood(st.acc, st.omega, sigma, 1, reference=st.reference, phi_prior=F)
        fit = fit_unresolved_scales(flat, age, band, pos0)
        fit_t = fit_unresolved_scales(flat, age, band, pos0, fit_nu=True, noise_factors=np.logspace(-1.5, 0, 10))
        scaled = RaoBlackwellLikelihood(st.acc, st.omega, sigma * fit_t.noise_factor, 1, reference=st.reference,
                                        phi_prior=F)
        models = (("flat", flat, ""),
                  ("per-sample jerk", with_unresolved_motion(flat, age, fit.jerk_rms[band]),
                   f"jerk_rms {', '.join(f'{float(v):.3g}' for v in fit.jerk_rms)} m/s³"),
                  ("per-sample jerk + mixture", with_unresolved_motion(scaled, age, fit_t.jerk_rms[band], nu=fit_t.nu),
                   f"ν = {fit_t.nu:.3g}, noise × {fit_t.noise_factor:.3f}"))
        for name, lik, note in models:
            th, cov = fixed_omega_max(lik, pos0)
            x = (th - th[st.reference])[[k for k in range(st.A) if k != st.reference]].reshape(-1)
            s = float(x @ g)
            s_sd = float(g @ cov @ g) ** 0.5
            th_i, _ = fixed_omega_max(lik, pos0, z=z)
            s_i = float((th_i - th_i[st.reference])[[k for k in range(st.A) if k != st.reference]].reshape(-1) @ g)
            res[(prior_name, name)] = (s, s_sd, float(cov.diagonal().sqrt().median()), s_i)
            rows.append(f"| {prior_name} | {name} | {note} | {1e6 * float(cov.diagonal().sqrt().median()):.1f} | "
                        f"{s:.5f} ± {s_sd:.5f} | {SPACING_MM * s:.3f} ± {SPACING_MM * s_sd:.3f} | {s_i:.5f} |")
            print(rows[-1])
    (fm, fs, fstd, fi), (jm, _, jstd, _), (tm, ts, tstd, ti) = (res[("empirical", n)] for n in (
        "flat", "per-sample jerk", "per-sample jerk + mixture"))
    now = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    text = "\n".join([
        "# The per-sample covariance at fixed ω on exp_1: where it puts the geometry (exploratory)",
        "",
        f"Regenerate: `PYTHONPATH=. python3 experiments/percov_map_probe.py` ({now}, {platform.machine()} "
        f"{platform.system()}, shared 2-core CPU, load average {os.getloadavg()[0]:.1f}).",
        "",
        "Maximum of log p(y | ω̄, θ) over the positions with ω fixed at the gyro mean (eq. 30 posterior mean), "
        "Laplace std from its Hessian; noise per triad the flat model's residual rms at the nominal positions; "
        "data ages from `results/clock_mimu/exp_1.json`; scales by type-II ML at the nominal positions, per |ω| "
        "quartile band. Scale s: least-squares factor of the fitted positions on the design; s × 18.9 mm the x–y "
        "spacing. Not `calibrate`'s posterior (ω is not integrated, no tempering, no sandwich): a first look at "
        "what the per-sample terms do to the geometry before they are wired in. Last column: the maximum of "
        f"log p̂ over the positions on one fixed set of draws (N = {N_INTEGRATED} per sample), ω integrated.",
        "",
        "| φ prior | model | fitted | median Laplace std µm | scale s | spacing mm | scale s, ω integrated |",
        "|---|---|---|---|---|---|---|",
        *rows,
        "",
        "Reading (the numbers of the table above, with the empirical φ prior): the Gaussian per-sample jerk term "
        f"moves the scale by {(jm - fm) / fs:+.1f} flat-model std and changes the median Laplace std by "
        f"{100 * (jstd / fstd - 1):+.0f} % (the loaded channels count less); the scale mixture fitted in-sample "
        f"(ν = {fit_t.nu:.2g}, the last fit above) changes the std by {100 * (tstd / fstd - 1):+.0f} % and the scale by {100 * (tm - fm):+.2f} % — "
        f"{(tm - fm) / ts:+.0f} of its own std. With ω fixed at ω̄ the centripetal term is biased by the gyro "
        "noise (E[ω̄²] > ω²), most in relative terms at small |ω|, which the heavy-tailed model weights up; with "
        f"ω integrated (the last column: the maximum of log p̂ on fixed draws, N = {N_INTEGRATED}) the mixture's "
        f"scale differs from the flat model's by {100 * (ti - fi):+.2f} % instead of {100 * (tm - fm):+.2f} %. "
        "The mixture is not ready for calibration until that difference is understood (ν is fitted in-sample at "
        "the nominal θ; the residuals grow with |ω| (accel_bayes.model.noise), which a per-sample scale with one "
        "prior for all bands treats as tails).",
        "",
    ])
    write_text(HERE / "percov_map_probe.md", text)


if __name__ == "__main__":
    main()
