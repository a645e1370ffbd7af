"""``accel-bayes map REC --out DIR``: MAP of the [C21] model by Levenberg–Marquardt.

Samples flagged clipped (``acc_clipped``/``gyro_clipped``) are dropped, as ``calibrate`` does by
default: the model cannot explain a sensor at its range; ``--keep-clipped`` fits them with a
warning on stderr.  Exit status (DESIGN §7.5): 0; 2 refused; 4 when LM stopped without
converging (results written, ``positions.json`` ``diagnostics.converged: false``, one line on stderr).
"""
from __future__ import annotations

import sys

from . import _options as opt


def register(sub) -> None:
    from ..data.outputs import OVERWRITE_DIR_HELP

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
    p.add_argument("--prior-std", type=opt.positive("m"), default=3e-3,
                   help="std of the Gaussian prior around the nominal positions, m (default 3e-3)")
    p.add_argument("--gyro-method", choices=["sample_cov", "sample_cov_mean", "calibrated"], default="sample_cov",
                   help="gyroscope posterior: [C21] eq. 30 as printed (default), its /G variant, or the calibrated-noise form")
    p.add_argument("--select", choices=["all", "rotation"], default="all",
                   help="'rotation' drops samples whose mean gyro rate is below 0.5 rad/s (they carry no information)")
    p.add_argument("--max-iter", type=opt.count(1), default=100, help="LM iteration limit (default 100)")
    p.add_argument("--keep-clipped", action="store_true",
                   help="fit samples where an accelerometer or gyroscope is at its range (dropped by default, as in "
                        "calibrate; a warning on stderr counts the ones fitted)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=_run)


def _run(args) -> int:
    import time

    import numpy as np

    from .. import __version__
    from ..inference.map import fit_map_recording
    from ..data.io import read_recording, recording_sha256
    from ..data.outputs import OutputDir, write_csv
    from ..data.positions import positions_document, write_positions
    # preprocess.clipped_samples moved to the one selection module (issue #10 item 3)
    from ..prep.selection import clipped_mask as clipped_samples
    from ._status import EXIT_OK, untrusted

    rec = read_recording(args.recording)
    out = OutputDir(args.out, overwrite=args.overwrite, inputs=(args.recording,)).open()
    n_clip = int(clipped_samples(rec).sum())
    t0 = time.perf_counter()
    res = fit_map_recording(rec, gyro_method=args.gyro_method, prior_std=args.prior_std,
                            select=None if args.select == "all" else "rotation", drop_clipped=not args.keep_clipped,
                            max_iter=args.max_iter, progress=not args.no_progress)
    seconds = time.perf_counter() - t0
    labels = list(res.imu_labels)
    K = rec.K
    means = np.zeros((K, 3))
    covs = np.zeros((K, 3, 3))
    means[labels] = res.positions.detach().cpu().numpy()
    covs[labels] = res.position_cov().detach().cpu().numpy()
    settings = {"prior_std": args.prior_std, "gyro_method": args.gyro_method, "select": args.select,
                "max_iter": args.max_iter, "converged": bool(res.converged), "reason": res.reason,
                "n_iter": int(res.n_iter), "imus_used": labels, "drop_clipped": not args.keep_clipped,
                "clipped_samples": n_clip}
    reasons = [] if res.converged else [f"LM stopped without converging ({res.reason}); the estimate may be poor"]
    doc = positions_document(method="map", reference_imu=int(rec.reference_imu), means=means, covs=covs,
                             diagnostics={"seconds": seconds, "log_posterior": float(res.log_posterior),
                                          "converged": not reasons, "warnings": reasons},
                             provenance={"version": __version__, "input_sha256": recording_sha256(args.recording),
                                         "seed": None, "settings": settings})
    write_positions(doc, out / "positions.json")
    omega = res.omega.detach().cpu().numpy()
    lik_index = getattr(res, "sample_index", None)
    t = rec.time if lik_index is None else rec.time[lik_index]
    if len(t) != len(omega):
        t = np.arange(len(omega), dtype=float)
    write_csv(out / "omega.csv", np.column_stack([t, omega]), "time_s,omega_x_rad_s,omega_y_rad_s,omega_z_rad_s")
    out.commit()
    std = np.sqrt(np.clip(np.diagonal(covs, axis1=1, axis2=2), 0, None))
    print(f"MAP in {seconds:.1f} s, {res.n_iter} LM iterations ({res.reason}); positions relative to IMU {rec.reference_imu}:")
    if n_clip and not args.keep_clipped:
        print(f"dropped {n_clip} samples flagged clipped (--keep-clipped fits them)")
    print(f"{'IMU':>4} {'x mm':>9} {'y mm':>9} {'z mm':>9} {'std x µm':>9} {'std y µm':>9} {'std z µm':>9}")
    for k in labels:
        print(f"{k:>4} " + " ".join(f"{v * 1e3:9.3f}" for v in means[k]) + " " + " ".join(f"{v * 1e6:9.1f}" for v in std[k]))
    print(f"Wrote {out.target / 'positions.json'} and {out.target / 'omega.csv'}")
    if n_clip and args.keep_clipped:
        print(f"accel-bayes map: warning: --keep-clipped: {n_clip} samples with an accelerometer or gyroscope at its "
              "range are fitted; the model cannot explain them and the estimate may be biased", file=sys.stderr)
    if reasons:
        print(f"warning: {reasons[0]}")
        return untrusted("map", reasons, str(out.target / "positions.json"))
    return EXIT_OK
