"""The rig branch of ``accel-bayes calibrate`` (issue #28 item 1): printing and exit status only;
the work is :mod:`accel_bayes.pipelines.rig`."""
from __future__ import annotations

import sys

from ._status import EXIT_OK, untrusted


def calibrate_if_rig(args, out) -> int | None:
    """Run the rig pipeline when ``args.recording`` is a rig (see :func:`~accel_bayes.pipelines.rig.is_rig`)
    and return the exit status; None for every other recording (the [C21] pipeline goes on)."""
    from ..data import io
    from ..pipelines.rig import calibrate_rig, format_rig_table, is_rig, write_rig_outputs

    rec = io.read_recording(args.recording)
    if not is_rig(rec):
        return None
    print("accel-bayes calibrate: a rig (< 3 accelerometer triads or separately stamped IMUs): rig model, "
          "Laplace posterior at the MAP; the PmMH options do not apply", file=sys.stderr)
    run = calibrate_rig(args.recording)
    paths = write_rig_outputs(run, out.staging)
    out.commit()
    print(format_rig_table(run))
    print(f"files: {', '.join(str(out.final(p)) for p in paths.values())}")
    res = run.result
    for w in res.warnings:
        print(f"accel-bayes calibrate: warning: {w}", file=sys.stderr)
    reasons = []
    if res.unidentified:
        reasons.append("unidentified (not excited by the motion): " + ", ".join(
            f"IMU {k} {p['parameter']}" for k, p in ((d["imu"], d) for d in run.positions["diagnostics"]["unidentified"])))
    if not res.converged:
        reasons.append(f"the optimisation stopped unconverged ({res.reason})")
    if reasons:
        return untrusted("calibrate", reasons, str(out.final(paths["positions"])))
    return EXIT_OK
