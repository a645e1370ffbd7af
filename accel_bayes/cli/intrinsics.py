"""``accel-bayes intrinsics REC -o intrinsics.json [--apply-to OUT.nc] [--g G]``.

Estimates each IMU's accelerometer bias, scale and non-orthogonality and its gyro bias from the
rests of a recording (:mod:`accel_bayes.prep.intrinsics`), writes them as JSON (schema
``accel_bayes.intrinsics/1``), prints a per-IMU table and, with ``--apply-to``, writes the
corrected recording.  REC is a format-v1 recording (.nc) or a MIMU4444 stream (.bin/.bin.gz).
"""
from __future__ import annotations

from pathlib import Path

from ..constants import G0
from . import _options as opt


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "intrinsics",
        help="estimate accelerometer bias/scale/misalignment and gyro bias from the rests of a recording",
        description=(
            "Fit a_true = T (a_raw - b) with T lower-triangular and |a_true| = g to the static segments "
            "of REC (its segment labels, else detected), per IMU, with Laplace uncertainties; gyro bias "
            "from the rest means.  Writes the intrinsics JSON and optionally the corrected recording."
        ),
    )
    p.add_argument("recording", metavar="REC", help="recording (.nc, format v1) or MIMU4444 stream (.bin, .bin.gz)")
    p.add_argument("-o", "--output", required=True, metavar="FILE", help="intrinsics JSON to write")
    p.add_argument("--apply-to", metavar="OUT.nc", default=None,
                   help="also write REC with the intrinsics applied to this recording file")
    p.add_argument("--g", type=opt.positive("m/s^2"), default=G0,
                   help="gravity magnitude, m/s^2 (default %(default)s)")
    p.add_argument("--overwrite", action="store_true", help="replace output files that exist")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..data.outputs import OutputFile
    from ..data.paths import require_file

    # the input, then the targets, before torch is imported
    src, out = require_file(args.recording, "recording file"), Path(args.output)
    targets = [OutputFile(out, overwrite=args.overwrite).open()]
    if args.apply_to:
        targets.append(OutputFile(args.apply_to, overwrite=args.overwrite, flag="--apply-to").open())
    from ..pipelines.intrinsics import intrinsics, write_outputs

    run = intrinsics(src, g=args.g)
    write_outputs(run, out, apply_to=args.apply_to, overwrite=args.overwrite)
    intr = run.intrinsics

    print(f"intrinsics of {src} (g = {intr.g:.6g} m/s², {intr.extra.get('segments')} static segments, "
          f"{intr.n_orientations} distinct orientations)")
    print(f"{'imu':>3} {'rests':>5} {'acc bias [m/s²]':>26} {'scale - 1 [1e-3]':>22} {'misalign [1e-3]':>22} "
          f"{'rms':>7} {'|acc|-g max raw→cal':>20} {'gyro bias [°/s]':>24}")
    for k in range(intr.K):
        if not run.has_acc(k):
            print(f"{k:>3} {'-':>5}  (no accelerometer)")
            continue
        b = " ".join(f"{v:+.3f}" for v in intr.acc_bias[k])
        sc = " ".join(f"{1e3 * (v - 1):+6.2f}" for v in intr.acc_scale[k])
        mi = " ".join(f"{1e3 * v:+6.2f}" for v in intr.acc_misalignment[k])
        gb = " ".join(f"{v:+.3f}" for v in run.gyro_bias_dps[k]) if run.has_gyro_bias(k) else "-"
        print(f"{k:>3} {int(intr.n_rests[k]):>5} {b:>26} {sc:>22} {mi:>22} {intr.residual_rms[k]:7.4f} "
              f"{run.raw_err_max[k]:8.4f} → {run.cal_err_max[k]:.4f} {gb:>24}")
    print(f"acc bias std (median over IMUs/axes): {run.acc_bias_std_median:.2g} m/s²; "
          f"gyro bias std: {run.gyro_bias_std_median_dps:.2g} °/s")
    print(f"wrote {out}")
    if args.apply_to:
        print(f"wrote {args.apply_to} (corrected recording)")
    for t in targets:
        t.commit()
    return 0
