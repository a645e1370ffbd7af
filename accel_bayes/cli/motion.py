"""``accel-bayes motion REC --calibration positions.json -o motion.nc [--intrinsics FILE] [--draws N]
[--seed S] [--geometry draws|linear]``.

Estimates ω, ω̇ and the specific force s (at the calibration's reference IMU) for every sample of
REC from a calibrated array (:mod:`accel_bayes.inference.motion_estimate`), with their uncertainty
(measurement noise + the calibration's position uncertainty), writes them as NetCDF and prints
a summary.
"""
from __future__ import annotations

from pathlib import Path

from . import _options as opt


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "motion",
        help="estimate angular velocity/acceleration and specific force per sample from a calibrated array",
        description=(
            "Per-sample weighted least squares for omega, omega_dot and s ([C21] eq. 4) with the geometry of "
            "a positions.json (DESIGN 7.3); uncertainty = noise (Laplace) + geometry (draws or linear). "
            "REC is a format-v1 recording (.nc) or a MIMU4444 stream (.bin, .bin.gz). A calibration whose "
            "accelerometer triads coincide or lie on one line is refused (exit 2): it cannot determine omega_dot."
        ),
    )
    p.add_argument("recording", metavar="REC", help="recording (.nc) or MIMU4444 stream")
    p.add_argument("--calibration", required=True, metavar="positions.json", help="calibrated positions (DESIGN 7.3)")
    p.add_argument("-o", "--output", required=True, metavar="FILE", help="motion NetCDF file to write")
    p.add_argument("--intrinsics", metavar="FILE", default=None, help="intrinsics JSON to apply first")
    p.add_argument("--draws", type=opt.integer(2, also=(0,)), default=200,
                   help="geometry draws (default 200; 0: noise part only)")
    p.add_argument("--seed", type=opt.seed, default=0, help="seed of the geometry draws (default 0)")
    p.add_argument("--geometry", choices=("draws", "linear"), default="draws",
                   help="geometry uncertainty by re-solving per draw (default) or first-order propagation")
    p.add_argument("--acc-noise-std", type=opt.positive("m/s^2"), default=None, metavar="M_S2",
                   help="accelerometer noise std to assume, m/s^2 (default: the recording's stated values)")
    p.add_argument("--gyro-noise-std", type=opt.positive("rad/s"), default=None, metavar="RAD_S",
                   help="gyroscope noise std to assume, rad/s (default: the recording's stated values)")
    p.add_argument("--overwrite", action="store_true", help="replace FILE if it exists")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..data.outputs import OutputFile
    from ..data.paths import require_file

    # the inputs, then the target, before torch is imported
    require_file(args.recording, "recording file")
    cal = require_file(args.calibration, "calibration file", flag="--calibration")
    if args.intrinsics is not None:
        require_file(args.intrinsics, "intrinsics file (JSON)", flag="--intrinsics")
    out = Path(args.output)
    target = OutputFile(out, overwrite=args.overwrite).open()
    from ..pipelines.motion import motion, write_outputs

    run = motion(Path(args.recording), cal, intrinsics=args.intrinsics, draws=args.draws, seed=args.seed,
                 geometry=args.geometry, acc_noise_std=args.acc_noise_std, gyro_noise_std=args.gyro_noise_std)
    write_outputs(run, out, overwrite=args.overwrite)
    target.commit()

    ds = run.dataset
    T = ds.sizes["time"]
    print(f"motion of {args.recording}: {T} samples, origin = reference IMU {ds.attrs['reference_imu']}, "
          f"geometry uncertainty: {ds.attrs['geometry_method']}"
          + (f" ({ds.attrs['draws']} draws, seed {args.seed})" if ds.attrs["geometry_method"] == "draws" else ""))
    print(f"{'':>10} {'max |x|':>12} {'median std':>12} {'  noise':>10} {'geometry':>10}  unit  (medians over all samples)")
    for name, xmax, std, noise, geom, unit in run.rows:
        print(f"{name:>10} {xmax:12.4g} {std:12.3g} {noise:10.3g} {geom:10.3g}  {unit}")
    c = run.chi2_per_dof
    parts = f"chi2/dof (median over samples): {c['all']:.3g}"
    if c["static"] is not None:
        parts += (f" (static {c['static']:.3g}, dynamic {c['dynamic']:.3g}; >> 1: the stated noise does not explain "
                  "the residuals)")
    print(parts)
    n = run.counts
    print(f"gyro clipped: {n['gyro_clipped']} samples, omega needing the accelerometers: "
          f"{n['omega_needs_acc']}, ill-posed: {n['ill_posed']}, not converged: {n['not_converged']}")
    print(f"wrote {out} ({ds.attrs['seconds']:.1f} s)")
    return 0
