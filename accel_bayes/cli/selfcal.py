"""``accel-bayes selfcal REC --out DIR``: [S16] self-calibration from the accelerometers alone.

Writes, in DIR:

* ``positions.json`` — DESIGN §7.3, method "selfcal": positions relative to the fixed triad's
  IMU (``reference_imu`` = ``--fixed``), Laplace std/cov (motion marginalised), orientations;
* ``poses.csv`` — one row per IMU: label, position (mm, relative to the fixed IMU), Laplace std
  (µm), rotation from the nominal orientation (rotation vector and angle, degrees, sensor
  perturbation q = q_nominal ∘ exp(δ)), RMS angle std (degrees), whether the IMU was fixed;
* ``motion.csv`` — the estimated motion per sample: time, a_lin (m/s²), ω (rad/s), ω̇ (rad/s²),
  array frame;
* ``convergence.png`` — F / number of constraints per LM iteration, total and per constraint
  type ([S16] Fig. 5), the motion-only warm start, the joint run and the re-run marked.

Gyroscopes are ignored.  IMUs without an accelerometer keep their nominal pose with unknown (null)
std.  Exit status: 0 on success; 2 on bad input (one line); 3 when the optimisation diverged
([S16] Table III: positions → 0 or ∞, angular motion → 0 or ∞, non-finite or non-fitting
estimate) — then one line on stderr says why, only ``convergence.png`` is written and no
positions are reported; 4 when LM stopped at its iteration limit without converging — every
file is written, ``positions.json`` has ``diagnostics.converged: false`` and ``warnings``, and
one line on stderr says so (DESIGN §7.5).
"""
from __future__ import annotations

import sys
from pathlib import Path

from . import _options as opt
from ._status import EXIT_DIVERGED, EXIT_OK, untrusted


def register(sub) -> None:
    from ..data.outputs import OVERWRITE_DIR_HELP

    p = sub.add_parser(
        "selfcal",
        help="[S16] self-calibration of accelerometer triads (poses + motion, no gyroscope)",
        description="Self-calibration of an accelerometer array ([S16]): positions and orientations of "
        "all triads relative to one fixed triad, jointly with the motion, from the accelerometer "
        "outputs alone (gyroscopes are ignored). Writes positions.json (method 'selfcal'), poses.csv, "
        "motion.csv and convergence.png. Exit status 3 when the optimisation diverged ([S16] Table III).",
    )
    p.add_argument("recording", metavar="REC", help="recording file (format v1)")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="output directory (created if missing; written as one set, see the README)")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_DIR_HELP)
    p.add_argument("--fixed", type=opt.count(0), default=None,
                   help="label of the IMU whose triad is held at its nominal pose (default: the recording's reference IMU)")
    p.add_argument("--max-iter", type=opt.count(1), default=200, help="LM iteration limit per stage (default 200)")
    p.add_argument("--seed", type=opt.seed, default=None,
                   help="recorded in the provenance only: the self-calibration draws no random numbers")
    p.add_argument("--no-rerun", action="store_true",
                   help="skip the [S16] §VI-A re-run from the estimated poses")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    p.set_defaults(func=_run)


def _fail(msg: str) -> int:
    print(f"accel-bayes selfcal: diverged: {msg}", file=sys.stderr)
    return EXIT_DIVERGED


def plot_convergence(cost_log: list, n_constraints: dict, path, title: str = "") -> None:
    """[S16] Fig. 5 style: F / number of constraints vs iteration (log scale), per constraint type."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from ..data.outputs import save_figure

    x = np.arange(len(cost_log), dtype=float)  # attempts laid end to end over stages and runs
    run = [e.get("run", "first") for e in cost_log]
    n_all = n_constraints["triad"] + n_constraints["process"]
    tot = np.array([e["F"] for e in cost_log]) / n_all
    tri = np.array([e["F_triad"] for e in cost_log]) / n_constraints["triad"]
    pro = np.array([e["F_process"] for e in cost_log]) / max(n_constraints["process"], 1)
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    pos = lambda v: np.where(v > 0, v, np.nan)  # noqa: E731  (zero process cost at a zero-motion start)
    ax.semilogy(x, pos(tot), "k-", lw=2, label="F / all constraints")
    ax.semilogy(x, pos(tri), "C0--", label="triad part / triad constraints")
    ax.semilogy(x, pos(pro), "C1:", label="process part / process constraints")
    stage = [e.get("stage", "joint") for e in cost_log]
    for i in range(1, len(x)):
        if stage[i] != stage[i - 1] or run[i] != run[i - 1]:
            ax.axvline(x[i] - 0.5, color="0.7", lw=0.8)
    for i in range(len(x)):
        if i == 0 or stage[i] != stage[i - 1] or run[i] != run[i - 1]:
            ax.annotate(f"{run[i]}: {stage[i]}", (x[i], 1.0), xycoords=("data", "axes fraction"), fontsize=7,
                        va="top", ha="left", rotation=90, xytext=(2, -2), textcoords="offset points")
    ax.set_xlabel("LM iteration (all stages and runs, end to end)")
    ax.set_ylabel("F / number of constraints")
    ax.set_title(title or "self-calibration convergence ([S16] Fig. 5)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    try:
        save_figure(fig, path, dpi=120)
    finally:
        plt.close(fig)


def _run(args) -> int:
    import time

    import numpy as np
    import torch

    from .. import __version__
    from ..errors import UserError
    from ..physics.geometry import boxminus
    from ..inference.selfcal import self_calibrate
    from ..data.io import read_recording, recording_sha256
    from ..data.outputs import OutputDir, write_csv, write_text
    from ..data.positions import positions_document, write_positions

    rec = read_recording(args.recording)
    K = rec.K
    fixed_label = int(rec.reference_imu if args.fixed is None else args.fixed)
    if not 0 <= fixed_label < K:
        raise UserError(f"--fixed: expected an IMU label in 0..{K - 1}, got {fixed_label}")
    has_acc = np.asarray(rec.has_acc)
    labels = [int(k) for k in np.nonzero(has_acc)[0]]
    if fixed_label not in labels:
        raise UserError(f"--fixed: IMU {fixed_label} has no accelerometer triad")
    if len(labels) < 3:
        raise UserError(f"acc: self-calibration needs at least 3 accelerometer triads, the recording has {len(labels)}")
    acc = np.asarray(rec.acc, dtype=float)[:, labels]
    if not np.isfinite(acc).all():
        bad = sorted({labels[j] for j in np.nonzero(~np.isfinite(acc).all(axis=(0, 2)))[0]})
        raise UserError(f"acc: missing (NaN) samples for IMU(s) {bad}; self-calibration needs every sample "
                        "(the process model links consecutive samples)")
    clipped = 0.0
    if rec.acc_clipped is not None:
        clipped = float(np.asarray(rec.acc_clipped)[:, labels].mean())
    p_nom = np.asarray(rec.nominal_position, dtype=float)
    q_nom = np.asarray(rec.nominal_orientation, dtype=float)
    fixed = labels.index(fixed_label)
    noise = np.asarray(rec.acc_noise_std, dtype=float)[labels]
    try:
        from ..physics.arrays import check_triad_geometry

        check_triad_geometry(torch.as_tensor(p_nom[labels]), labels=labels)
    except ValueError as exc:
        raise UserError(f"nominal_position: {exc}") from None

    out = OutputDir(args.out, overwrite=args.overwrite, inputs=(args.recording,)).open()
    t0 = time.perf_counter()
    res = self_calibrate(acc, np.asarray(rec.time, dtype=float), nominal_positions=p_nom[labels],
                         nominal_orientations=q_nom[labels], fixed=fixed, acc_noise_std=noise,
                         max_iter=args.max_iter, progress=not args.no_progress,
                         rerun_from_estimate=not args.no_rerun)
    seconds = time.perf_counter() - t0
    plot_convergence(res.full_cost_log, res.n_constraints, out / "convergence.png",
                     title=f"selfcal {Path(args.recording).name}: {res.status}")
    if not res.ok:
        out.commit()  # the diagnostics alone are this run's set
        return _fail(f"{res.reason}; no positions reported (see {out.target / 'convergence.png'})")

    # ---- positions.json: relative to the fixed IMU, array frame
    P = res.positions.detach().cpu().numpy()
    Q = res.orientations.detach().cpu().numpy()
    means = p_nom - p_nom[fixed_label]  # IMUs without accelerometer: nominal, unknown std
    covs = np.full((K, 3, 3), np.nan)
    oris = q_nom.copy()
    rel = P - P[fixed]
    pcov = res.position_cov.detach().cpu().numpy() if res.position_cov is not None else np.full((len(labels), 3, 3), np.nan)
    rcov = res.rotation_cov.detach().cpu().numpy() if res.rotation_cov is not None else np.full((len(labels), 3, 3), np.nan)
    for j, k in enumerate(labels):
        means[k] = rel[j]
        covs[k] = pcov[j]
        oris[k] = Q[j]
    covs[fixed_label] = 0.0
    runs = [{k: v for k, v in r.items() if k not in ("positions", "orientations", "states")} for r in res.runs]
    settings = {"fixed": fixed_label, "max_iter": args.max_iter, "rerun_from_estimate": not args.no_rerun,
                "process_variances": "S16 (acc 1e3, int 1e-7, omega_dot 1e3)", "imus_used": labels,
                "acc_noise_std": noise.tolist(), "warm_start_motion": True}
    reasons = [] if res.converged else [f"LM stopped without converging ({res.lm_reason}); the estimate may be poor"]
    diagnostics = {"seconds": seconds, "F": res.cost, "F_per_constraint": res.cost / sum(res.n_constraints.values()),
                   "n_iter": int(sum(r["iterations"] for r in res.runs)), "converged": bool(res.converged),
                   "warnings": reasons,
                   "lm_reason": res.lm_reason, "runs": runs, "acc_clipped_fraction": clipped}
    doc = positions_document(method="selfcal", reference_imu=fixed_label, means=means, covs=covs, orientations=oris,
                             diagnostics=diagnostics,
                             provenance={"version": __version__, "input_sha256": recording_sha256(args.recording),
                                         "seed": args.seed, "settings": settings})
    write_positions(doc, out / "positions.json")

    # ---- poses.csv
    dq = boxminus(torch.as_tensor(oris), torch.as_tensor(q_nom)).numpy()  # q = q_nom ∘ exp(δ)
    ang = np.degrees(np.linalg.norm(dq, axis=-1))
    pstd = np.sqrt(np.clip(np.diagonal(covs, axis1=1, axis2=2), 0, None))
    astd = np.full(K, np.nan)
    for j, k in enumerate(labels):
        astd[k] = np.degrees(np.sqrt(max(np.trace(rcov[j]), 0.0)))
    astd[fixed_label] = 0.0
    header = ("imu,x_mm,y_mm,z_mm,std_x_um,std_y_um,std_z_um,rotvec_x_deg,rotvec_y_deg,rotvec_z_deg,"
              "angle_vs_nominal_deg,angle_std_deg,fixed,has_acc")
    rows = []
    for k in range(K):
        rows.append([k, *(means[k] * 1e3), *(pstd[k] * 1e6), *np.degrees(dq[k]), ang[k], astd[k],
                     int(k == fixed_label), int(has_acc[k])])
    write_text(out / "poses.csv", "".join(
        [header + "\n"] + [",".join(str(int(v)) if i in (0, 12, 13) else ("nan" if not np.isfinite(v) else f"{v:.9g}")
                                    for i, v in enumerate(r)) + "\n" for r in rows]))

    # ---- motion.csv
    X = res.states.detach().cpu().numpy()
    write_csv(out / "motion.csv", np.column_stack([np.asarray(rec.time, dtype=float), X]),
              "time_s,a_lin_x_m_s2,a_lin_y_m_s2,a_lin_z_m_s2,omega_x_rad_s,omega_y_rad_s,omega_z_rad_s,"
              "omega_dot_x_rad_s2,omega_dot_y_rad_s2,omega_dot_z_rad_s2")
    out.commit()

    print(f"self-calibration in {seconds:.1f} s, LM iterations "
          f"{' + '.join(str(r['label']) + ' ' + str(r['iterations']) for r in res.runs)} ({res.lm_reason}); F/constraint "
          f"{res.cost / sum(res.n_constraints.values()):.3g}")
    print(f"poses relative to IMU {fixed_label} (fixed at its nominal pose); rotation = from the nominal orientation:")
    print(f"{'IMU':>4} {'x mm':>9} {'y mm':>9} {'z mm':>9} {'std µm':>8} {'rot °':>8} {'std °':>7}")
    for k in range(K):
        mark = " (fixed)" if k == fixed_label else ("" if has_acc[k] else " (no acc: nominal)")
        sd = np.linalg.norm(pstd[k]) * 1e6 if np.isfinite(pstd[k]).all() else float("nan")
        print(f"{k:>4} " + " ".join(f"{v * 1e3:9.3f}" for v in means[k]) + f" {sd:8.1f} {ang[k]:8.3f} {astd[k]:7.3f}{mark}")
    if clipped > 0:
        print(f"accel-bayes selfcal: warning: {clipped:.2%} of the accelerometer samples are flagged clipped; they are "
              "fitted as they are (the model cannot explain them)", file=sys.stderr)
    if not res.converged:
        print(f"warning: LM stopped without converging ({res.lm_reason}); the estimate may be poor")
    d = out.target
    print(f"Wrote {d / 'positions.json'}, {d / 'poses.csv'}, {d / 'motion.csv'} and {d / 'convergence.png'}")
    if reasons:
        return untrusted("selfcal", reasons, str(d / "positions.json"))
    return EXIT_OK
