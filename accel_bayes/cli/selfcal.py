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
positions are reported; 4 when LM stopped at its iteration limit without converging, or when the
fit check finds residuals that contradict the stated noise and the motion model (RMS
of the whitened triad or process residuals > 1.5; the reported std are then inflated to match
them) or a board scale the motion does not fix — every file is written, ``positions.json`` has
``diagnostics.fit_check``, ``converged`` and ``warnings``, and one line on stderr says so
(DESIGN §7.5).  A fit that passes the check can still be wrong in scale
(``experiments/s16_fitcheck.md``).
"""
from __future__ import annotations

import sys
from pathlib import Path

from . import _options as opt
from ._status import EXIT_DIVERGED, EXIT_OK, untrusted


def register(sub) -> None:
    from ..data.output_sets import OVERWRITE_DIR_HELP

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
    p.add_argument("--drop-clipped", action="store_true",
                   help="leave out the samples where an accelerometer triad is flagged at its range (default: fit "
                   "every sample as [S16] does); the process model bridges each gap exactly")
    p.add_argument("--no-rerun", action="store_true",
                   help="skip the [S16] §VI-A re-run from the estimated poses")
    p.add_argument("--process-noise", choices=("estimate-snap", "estimate", "s16"), default="estimate-snap",
                   help="motion model: 'estimate-snap' (default: continuous-time model with white noise on the snap "
                   "of the rotation and on the second derivative of the linear acceleration, smooth like hand motion; "
                   "its two intensities estimated from the recording by type-II maximum likelihood, scale at the "
                   "maximum of the Laplace marginal likelihood; issue #12), 'estimate' (the same with white noise on "
                   "the jerk: rougher, its board comes out up to 1 %% small on hand-like motion, "
                   "experiments/s16_handlike.md) or 's16' (the paper's fixed eq. 8 variances)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    p.set_defaults(func=_run)


def _fail(msg: str) -> int:
    print(f"accel-bayes selfcal: diverged: {msg}", file=sys.stderr)
    return EXIT_DIVERGED


def _run(args) -> int:
    from ..data.output_sets import OutputDir
    from ..data.paths import require_file

    # what the file system decides, before torch is imported: the input is there, the target usable
    require_file(args.recording, "recording file")
    target = OutputDir(args.out, overwrite=args.overwrite, inputs=(args.recording,))
    target.check()
    from ..pipelines.selfcal_options import SelfcalOptions

    options = SelfcalOptions.from_args(args)
    from ..data.io import load_recording
    from ..pipelines.selfcal import prepare, selfcal, write_outputs

    loaded = load_recording(args.recording)
    inp = prepare(loaded, options)  # bad input is refused before the output is touched
    out = target.open()
    run = selfcal(inp, options, progress=not args.no_progress)
    res = run.result
    write_outputs(run, out.staging, title=f"selfcal {Path(args.recording).name}: {res.status}")
    if not run.ok:
        out.commit()  # the diagnostics alone are this run's set
        return _fail(f"{res.reason}; no positions reported (see {out.target / 'convergence.png'})")
    out.commit()

    fixed_label, has_acc = inp.fixed_label, inp.has_acc
    print(f"self-calibration in {run.seconds:.1f} s, LM iterations "
          f"{' + '.join(str(r['label']) + ' ' + str(r['iterations']) for r in res.runs)} ({res.lm_reason}); F/constraint "
          f"{res.cost / sum(res.n_constraints.values()):.3g}")
    chk = run.check
    print(f"whitened residual RMS: triad {chk.rms_triad:.3g}, process {chk.rms_process:.3g} (> {chk.rms_limit:g} is a "
          f"misfit); board scale {chk.scale:.5f} ± {chk.scale_std:.2g} relative to the start")
    print(f"poses relative to IMU {fixed_label} (fixed at its nominal pose); rotation = from the nominal orientation:")
    print(f"{'IMU':>4} {'x mm':>9} {'y mm':>9} {'z mm':>9} {'std µm':>8} {'rot °':>8} {'std °':>7}")
    for k in range(len(run.means)):
        mark = " (fixed)" if k == fixed_label else ("" if has_acc[k] else " (no acc: nominal)")
        sd = run.pstd_norm[k] * 1e6
        print(f"{k:>4} " + " ".join(f"{v * 1e3:9.3f}" for v in run.means[k])
              + f" {sd:8.1f} {run.angle[k]:8.3f} {run.angle_std[k]:7.3f}{mark}")
    if inp.clipped > 0:
        print(f"accel-bayes selfcal: warning: {inp.clipped:.2%} of the accelerometer samples are flagged clipped; they "
              "are fitted as they are (the model cannot explain them)", file=sys.stderr)
    if not res.converged:
        print(f"warning: LM stopped without converging ({res.lm_reason}); the estimate may be poor")
    d = out.target
    print(f"Wrote {d / 'positions.json'}, {d / 'poses.csv'}, {d / 'motion.csv'} and {d / 'convergence.png'}")
    if run.warnings:
        return untrusted("selfcal", run.warnings, str(d / "positions.json"))
    return EXIT_OK
