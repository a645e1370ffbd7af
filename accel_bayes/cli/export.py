"""``accel-bayes export REC --positions positions.json [--intrinsics intrinsics.json]
[--mismatch report.json] [--format kalibr|openvins|kalibr-imu] (-o FILE | --out DIR) [--overwrite]``.

Writes a calibration as a Kalibr-style IMU chain YAML, as OpenVINS' ``kalibr_imu_chain.yaml``
(``%YAML:1.0`` header, intrinsic fields), or as Kalibr's per-IMU input YAMLs (``--format
kalibr-imu --out DIR``: ``DIR/imu0.yaml`` … , the reference IMU first); frames and conventions
in :mod:`accel_bayes.data.export`.  Heavy modules are imported in :func:`run` only.
"""
from __future__ import annotations

from pathlib import Path

FORMATS = ("kalibr", "openvins", "kalibr-imu")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "export",
        help="export a calibration as a Kalibr IMU chain / OpenVINS kalibr_imu_chain.yaml / Kalibr IMU files",
        description=(
            "Write a Kalibr-style IMU chain YAML from a recording and its positions.json: per IMU T_i_b "
            "(4x4, takes a point from the reference IMU's frame to IMU i's frame), noise densities "
            "(sigma/sqrt(rate), the stated rate), random walks (from the rests when they are long enough, "
            "else as stated at import; refused when neither), update rate, time offset where estimated, "
            "and the posterior covariances as extra keys. The reference IMU is always imu0. With "
            "--intrinsics (accel-bayes intrinsics) the OpenVINS fields Ta = T^-1 (lower-triangular, model "
            "kalibr) and R_IMUtoACC = I are written; with --mismatch the gyro couplings (Tw, R_IMUtoGYRO, "
            "Tg) and time offsets of the report. --format openvins adds OpenCV's %%YAML:1.0 header and "
            "writes the intrinsic fields always (identity where not estimated, said so in a comment). "
            "--format kalibr-imu writes Kalibr's per-IMU input files DIR/imu0.yaml, imu1.yaml, ... "
            "(--out DIR; pass them to Kalibr in that order)."
        ),
    )
    p.add_argument("recording", metavar="REC", help="the recording the calibration was made from (.nc, format v1)")
    p.add_argument("--positions", required=True, metavar="JSON", help="positions.json of map / calibrate / selfcal")
    p.add_argument("--intrinsics", default=None, metavar="JSON", help="intrinsics.json of accel-bayes intrinsics (optional)")
    p.add_argument("--mismatch", default=None, metavar="JSON",
                   help="report.json of accel-bayes mismatch: gyro_scale, gyro_g_sensitivity, time_offset (optional)")
    p.add_argument("--format", choices=FORMATS, default="kalibr",
                   help="'kalibr': plain YAML IMU chain (default); 'openvins': %%YAML:1.0 header for cv::FileStorage, "
                        "intrinsic fields always present; 'kalibr-imu': one Kalibr input YAML per IMU (--out DIR)")
    dest = p.add_mutually_exclusive_group(required=True)
    dest.add_argument("-o", "--output", metavar="FILE", help="YAML file to write (kalibr, openvins)")
    dest.add_argument("--out", metavar="DIR", help="directory for imu0.yaml, imu1.yaml, ... (kalibr-imu)")
    p.add_argument("--overwrite", action="store_true", help="replace FILE / the files of an earlier DIR")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..data.output_sets import OutputDir
    from ..data.outputs import OutputFile
    from ..data.paths import require_file
    from ..errors import UserError

    for flag, path in (("REC", args.recording), ("--positions", args.positions), ("--intrinsics", args.intrinsics),
                       ("--mismatch", args.mismatch)):
        if path is not None:
            require_file(path, "file", flag=flag)
    several = args.format == "kalibr-imu"
    if several and args.out is None:
        raise UserError("-o: --format kalibr-imu writes one file per IMU; expected --out DIR")
    if not several and args.out is not None:
        raise UserError(f"--out: --format {args.format} writes one file; expected -o FILE")
    if several:
        target = OutputDir(args.out, overwrite=args.overwrite,
                           inputs=(args.recording, args.positions, args.intrinsics, args.mismatch)).open()
        from ..pipelines.export import export_imu_chain  # torch: after every refusal the file system decides
        written = export_imu_chain(args.recording, args.positions, target.staging, intrinsics=args.intrinsics,
                                   report=args.mismatch, fmt=args.format, overwrite=True)
        target.commit()
        print(f"wrote {', '.join(str(target.final(p)) for p in written)} (Kalibr IMU input files, reference first)")
        return 0
    out = Path(args.output)
    target = OutputFile(out, overwrite=args.overwrite).open()
    from ..pipelines.export import export_imu_chain  # torch: after every refusal the file system decides
    export_imu_chain(args.recording, args.positions, out, intrinsics=args.intrinsics, report=args.mismatch,
                     fmt=args.format, overwrite=args.overwrite)
    target.commit()
    print(f"wrote {out} ({args.format} IMU chain)")
    return 0
