"""Is the MIMU4444's sample-to-sample data age what the rig's constant offsets cannot hold? (issue #28
item 3, the likely cause of ``rig_mimu_pairs.md``'s z RMS) → ``experiments/rig_mimu_age.md``.

    PYTHONPATH=. python3 experiments/rig_mimu_age.py [--exp exp_1] [--window 30]

The eight-IMU rig of ``experiments/rig_mimu_pairs.py`` (same window, same settings) is fitted twice:
``one`` (one board clock, constant offsets: the model of the pair study) and ``clock`` (each IMU's
stamps shifted by the data age of the detector's clock stage, −age_k(t) as ``imu_time_offset``;
:func:`experiments.rig_mimu_pairs.with_stamps`).  For each fit and IMU the residual's timing
content: per sample the least-squares timing error δ = uᵀr/uᵀu along u = ∂r/∂t (whitened, the
rig model's own time derivative), weight uᵀu; regressed on the clock stage's age_k(t) (weighted,
with a constant).  If the age is what the constant offset misses, the ``one`` fit's δ follow it
(slope near 1: the model's instant is late by the age) and the ``clock`` fit's do not (slope near
0), and χ²/dof drops.  A slope near 0 in both says the age is not in these residuals.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import accel_bayes.inference.rig.solve as rig_solve  # noqa: E402
from accel_bayes.data import outputs  # noqa: E402
from accel_bayes.data.mimu import import_mimu  # noqa: E402
from accel_bayes.inference.rig.model import timing_noise_directions  # noqa: E402
from accel_bayes.physics.effects.clock import clock_age  # noqa: E402
from accel_bayes.physics.geometry import quat_to_matrix  # noqa: E402
from experiments.rig_mimu_pairs import DATA, SETTINGS, window, with_stamps  # noqa: E402
from experiments._stamp import run_stamp  # noqa: E402


def fit_with_residuals(rec):
    """fit_rig and, from its last LM pass, per sample (IMU label, stamp − t₀, δ, weight uᵀu)."""
    seen = {}
    solve = rig_solve.LevenbergMarquardt.solve

    def keep(self, prob):  # the last pass's problem and solution (fit_rig keeps neither)
        out = solve(self, prob)
        seen.update(prob=prob, res=out)
        return out
    rig_solve.LevenbergMarquardt.solve = keep
    try:
        res = rig_solve.fit_rig(rec, SETTINGS)
    finally:
        rig_solve.LevenbergMarquardt.solve = solve
    meas = seen["prob"].chain_residuals[0]
    g, x = seen["res"].values, seen["res"].locals
    data = meas.data
    r = meas.fn(g, x[:-1], x[1:], data).reshape(data.imu.shape + (6,))
    R0 = quat_to_matrix(torch.as_tensor(np.asarray(rec.nominal_orientation, float)[rec.reference_imu]))
    u = timing_noise_directions(g, x[:-1], x[1:], data, R0, np.ones(rec.K))
    uu = (u * u).sum(-1)
    ok = (data.wg > 0) & (uu > 0)
    order = [rec.reference_imu] + [k for k in range(rec.K) if k != rec.reference_imu]
    lab = np.asarray(order)[data.imu[ok].numpy()]
    return res, lab, data.ds[ok].numpy(), ((u * r).sum(-1)[ok] / uu[ok]).numpy(), uu[ok].numpy()


def regress(delta, w, age):
    """Weighted least squares δ = a + b·age: (b, its std, weighted R²)."""
    X = np.c_[np.ones_like(age), age]
    A = X.T @ (w[:, None] * X)
    coef = np.linalg.solve(A, X.T @ (w * delta))
    e = delta - X @ coef
    s2 = float(w @ e ** 2) / max(len(e) - 2, 1)
    tot = float(w @ (delta - np.average(delta, weights=w)) ** 2)
    return float(coef[1]), float(np.sqrt(s2 * np.linalg.inv(A)[1, 1])), 1.0 - float(w @ e ** 2) / tot


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--exp", default="exp_1")
    ap.add_argument("--window", type=float, default=30.0)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    base = window(import_mimu(DATA / args.exp / "data.bin.gz"), args.window)
    fits = json.loads((REPO / "experiments" / "results" / "clock_mimu" / f"{args.exp}.json").read_text())["imus"]
    t0 = float(base.time[0])
    rows, summary = [], []
    for how in ("one", "clock"):
        res, lab, ds, delta, w = fit_with_residuals(with_stamps(base, how, args.exp))
        summary.append(f"| {how} | {res.reason} ({res.n_iter}) | {res.chi2_per_dof:.4f} | "
                       f"{1e3 * (res.time_offset.max() - res.time_offset.min()):.3f} | {res.seconds:.0f} |")
        for f in fits:
            k = f["imu"]
            m = lab == k
            # the read time of each sample: clock mode stamped it at read time − age(read time)
            t = t0 + ds[m]
            if how == "clock":
                read = np.asarray(base.time, float)
                shifted = read - clock_age(torch.as_tensor(read), f["beat_hz"], f["phase"], f["drift_hz_per_s"],
                                           f["width_s"]).numpy()
                t = np.interp(t, shifted, read)
            age = clock_age(torch.as_tensor(t), f["beat_hz"], f["phase"], f["drift_hz_per_s"], f["width_s"]).numpy()
            b, sb, r2 = regress(delta[m], w[m], age)
            rows.append(f"| {how} | {k} | {1e3 * f['width_s']:.2f} | {'yes' if f['accepted'] else 'no'} | "
                        f"{b:+.2f} ± {sb:.2f} | {r2:.3f} |")
        print(summary[-1], flush=True)
    lines = ["# Data age in the MIMU rig residuals (issue #28 item 3)", "",
             f"Regenerate: `PYTHONPATH=. python3 experiments/rig_mimu_age.py --exp {args.exp} --window {args.window:g}` "
             f"({run_stamp()}).", "",
             f"{args.exp}, the window of `rig_mimu_pairs.py` ({base.time[0]:.2f}–{base.time[-1]:.2f} s), eight IMUs; "
             "ages from the clock stage's cache (`experiments/results/clock_mimu/`).", "",
             "| stamps | LM (steps) | χ²/dof | spread of the eight offsets (ms) | fit s |", "|---|---|---|---|---|"]
    lines += summary + ["", "Per IMU: the residual timing error δ regressed on the clock stage's data age "
                        "(weighted by uᵀu; IMU 0 is the reference, whose timing the motion absorbs).", "",
                        "| stamps | IMU | width W (ms) | accepted by the stage | slope dδ/d age | weighted R² |",
                        "|---|---|---|---|---|---|"] + rows
    outputs.write_text(REPO / "experiments" / "rig_mimu_age.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
