"""``accel-bayes import-csv SOURCE --array array.toml -o rec.nc [--overwrite]``.

Reads an IMU array's CSV recording — an ASL/EuRoC folder (``imu0/data.csv`` …) or one wide CSV —
with its array description (TOML), puts the IMUs on one time base, finds the rests, estimates
the noise from them and writes a format-v1 recording (DESIGN §7.1); see
:mod:`accel_bayes.data.csv_import`.
"""
from __future__ import annotations

import sys
from pathlib import Path

from . import _options as opt


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "import-csv",
        help="import an IMU array's CSV recording (ASL/EuRoC folders or one wide CSV) as a recording file",
        description=(
            "Import CSV data of an IMU array: SOURCE is a folder in the ASL/EuRoC layout (one sub-folder per "
            "IMU label with data.csv and optionally sensor.yaml) or one wide CSV file (a time column and "
            "three columns per IMU and sensor). The array description (TOML) gives each IMU's label, "
            "nominal position (m), orientation (quaternion w, x, y, z, array -> sensor, or a 3x3 matrix), "
            "sensors, noise and ranges, and the reference IMU. Units come from the header ('[m s^-2]') or "
            "the description's [csv.units]; they are never guessed. IMUs at the reference IMU's rate are put on "
            "its stamps (nearest sample within --time-tolerance) and their own stamps kept in imu_time_offset; "
            "IMUs at different rates keep every sample, on the union of their stamps (NaN where an IMU has none; "
            "in a wide CSV, its cells left empty)."
        ),
    )
    p.add_argument("source", metavar="SOURCE", help="ASL folder (imu0/data.csv, ...) or wide CSV file")
    p.add_argument("--array", required=True, metavar="TOML",
                   help="array description: IMU labels, positions (m), orientations, sensors, noise, ranges")
    p.add_argument("-o", "--output", required=True, metavar="FILE", help="recording file to write (.nc)")
    p.add_argument("--overwrite", action="store_true", help="replace FILE if it exists")
    p.add_argument("--time-tolerance", type=opt.real(0.0, 3600.0, unit="s"), default=None, metavar="SECONDS",
                   help="largest |IMU stamp - reference stamp| accepted when matching samples of IMUs at the "
                        "reference's rate, s (default a quarter of the reference IMU's median sample period)")
    p.add_argument("--noise", choices=("rests", "stated"), default="rests",
                   help="'rests': noise std estimated from the static segments where found, stated otherwise "
                        "(default); 'stated': the description's std (or sensor.yaml density x sqrt(rate)), "
                        "no rest detection")
    p.add_argument("--tol-deg", type=opt.real(0.0, 180.0, lo_open=True, unit="degrees"), default=2.0,
                   help="rests whose gravity directions agree within this angle are one orientation (default 2)")
    p.add_argument("--min-static-s", type=opt.positive("s"), default=3.0,
                   help="shortest static segment kept, seconds (default 3)")
    p.add_argument("--skip-gyro-unit-check", action="store_true",
                   help="import even when the gyro values do not look like rad/s against the accelerometer array "
                        "(e.g. IMUs without a lever arm between them); recorded in the file, so later commands "
                        "skip the check too")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..data.outputs import OutputFile
    from ..data.paths import require_file

    # The inputs first: a wrong input path is the likelier mistake than an existing output; all
    # before torch is imported.
    src = require_file(args.source, "CSV file or ASL folder", directory_ok=True)
    arr = require_file(args.array, "array description file (TOML)", flag="--array")
    out = Path(args.output)
    target = OutputFile(out, overwrite=args.overwrite).open()
    from ..data.csv_import import import_csv, write_imported

    result = import_csv(src, arr, time_tolerance=args.time_tolerance, noise=args.noise, tol_deg=args.tol_deg,
                        min_duration_s=args.min_static_s, check_gyro_units=not args.skip_gyro_unit_check)
    write_imported(result, out, overwrite=args.overwrite)  # validates (DESIGN §7.1) before writing
    target.commit()
    for line in result.lines:
        print(line)
    for w in result.warnings:
        print(f"accel-bayes import-csv: warning: {w}", file=sys.stderr)
    print(f"wrote {out}")
    return 0
