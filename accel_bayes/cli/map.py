"""``accel-bayes map REC --out DIR``: MAP of the [C21] model by Levenberg–Marquardt.

Samples flagged clipped (``acc_clipped``/``gyro_clipped``) are dropped, as ``calibrate`` does by
default: the model cannot explain a sensor at its range; ``--keep-clipped`` fits them with a
warning on stderr.  Exit status (DESIGN §7.5): 0; 2 refused; 4 when LM stopped without
converging (results written, ``positions.json`` ``diagnostics.converged: false``, one line on stderr).
"""
from __future__ import annotations

import sys

from ..constants import DEFAULT_PRIOR_STD
from . import _options as opt


def register(sub) -> None:
    from ..data.output_sets import OVERWRITE_DIR_HELP

    p = sub.add_parser(
        "map",
        help="MAP positions of the accelerometer triads ([C21] model, LM solver)",
        description="Maximum a posteriori positions of the accelerometer triads (θ and ω_t jointly, "
        "the linear motion projected out), with the Laplace covariance. Writes positions.json "
        "(method 'map') and omega.csv (the angular velocity at the mode).",
    )
    p.add_argument("recording", metavar="REC", help="recording file (format v1)")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="output directory (created if missing; written as one set, see the README)")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_DIR_HELP)
    p.add_argument("--prior-std", type=opt.positive("m"), default=DEFAULT_PRIOR_STD,
                   help="std of the Gaussian prior around the nominal positions, m (default %(default)g)")
    p.add_argument("--gyro-method", choices=["sample_cov", "sample_cov_mean", "calibrated"], default="sample_cov",
                   help="gyroscope posterior: [C21] eq. 30 as printed (default), its /G variant, or the calibrated-noise form")
    p.add_argument("--select", choices=["all", "rotation"], default="all",
                   help="'rotation' drops samples whose mean gyro rate is below 0.5 rad/s (they carry no information)")
    p.add_argument("--max-iter", type=opt.count(1), default=100, help="LM iteration limit (default 100)")
    p.add_argument("--keep-clipped", action="store_true",
                   help="fit samples where an accelerometer or gyroscope is at its range (dropped by default, as in "
                        "calibrate; a warning on stderr counts the ones fitted)")
    p.add_argument("--phi-prior", choices=("empirical", "flat"), default="empirical",
                   help="prior on φ = [ω̇; s]: 'empirical' (default, estimated from the recording) or 'flat' ([C21])")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=_run)


def _run(args) -> int:
    from ..data.output_sets import OutputDir
    from ..data.paths import require_file
    from ._status import EXIT_OK, untrusted

    # the input first (a wrong path is the likelier mistake), then the target, then torch
    require_file(args.recording, "recording file")
    out = OutputDir(args.out, overwrite=args.overwrite, inputs=(args.recording,)).open()
    from ..data.io import load_recording
    from ..pipelines.map import map_positions, write_outputs

    rec = load_recording(args.recording)
    run = map_positions(rec, gyro_method=args.gyro_method, prior_std=args.prior_std, select=args.select,
                        drop_clipped=not args.keep_clipped, max_iter=args.max_iter, progress=not args.no_progress,
                        phi_prior=args.phi_prior)
    write_outputs(run, out.staging)
    out.commit()
    res, n_clip = run.result, run.n_clipped
    print(f"MAP in {run.seconds:.1f} s, {res.n_iter} LM iterations ({res.reason}); positions relative to IMU "
          f"{run.reference_imu}:")
    if n_clip and not args.keep_clipped:
        print(f"dropped {n_clip} samples flagged clipped (--keep-clipped fits them)")
    print(f"{'IMU':>4} {'x mm':>9} {'y mm':>9} {'z mm':>9} {'std x µm':>9} {'std y µm':>9} {'std z µm':>9}")
    for k in run.labels:
        print(f"{k:>4} " + " ".join(f"{v * 1e3:9.3f}" for v in run.means[k]) + " "
              + " ".join(f"{v * 1e6:9.1f}" for v in run.std[k]))
    print(f"Wrote {out.target / 'positions.json'} and {out.target / 'omega.csv'}")
    if n_clip and args.keep_clipped:
        print(f"accel-bayes map: warning: --keep-clipped: {n_clip} samples with an accelerometer or gyroscope at its "
              "range are fitted; the model cannot explain them and the estimate may be biased", file=sys.stderr)
    if run.warnings:
        print(f"warning: {run.warnings[0]}")
        return untrusted("map", run.warnings, str(out.target / "positions.json"))
    return EXIT_OK
