"""``accel-bayes export``'s library function: read a calibration's inputs (recording, positions,
intrinsics, mismatch report; paths or objects) and write the Kalibr / OpenVINS files that
:mod:`accel_bayes.data.export` formats.  Here, above ``prep``, because reading ``intrinsics.json``
needs :class:`~accel_bayes.prep.intrinsics.Intrinsics`.
"""
from __future__ import annotations

import json
from pathlib import Path

from ..data.export import imu_chain, kalibr_imu_files
from ..data.io import load_recording
from ..data.outputs import write_text
from ..data.positions import read_positions
from ..errors import UserError
from ..prep.intrinsics import Intrinsics

__all__ = ["export_imu_chain"]


def export_imu_chain(recording, positions, output, *, intrinsics=None, report=None, fmt: str = "kalibr",
                     overwrite: bool = False) -> list[Path]:
    """Read the inputs (paths or objects), build the ``fmt`` text and write it atomically.

    ``output``: the YAML file for "kalibr" / "openvins"; for "kalibr-imu" an existing directory
    that receives ``imu0.yaml`` … (reference first).  ``recording``: a path (read with
    :func:`accel_bayes.data.io.load_recording`) or a :class:`~accel_bayes.data.recording.Recording`; ``positions``: path or
    document; ``intrinsics``: path, :class:`~accel_bayes.prep.intrinsics.Intrinsics` or None
    (not used by "kalibr-imu"); ``report``: path, dict or None.  Returns the written paths."""
    names = {}
    loaded = load_recording(recording)
    if loaded.path is not None:
        names["recording"] = Path(loaded.path).name
    recording = loaded.recording
    if not isinstance(positions, dict):
        names["positions"] = Path(positions).name
    positions = read_positions(positions)
    if intrinsics is not None and not isinstance(intrinsics, Intrinsics):
        names["intrinsics"] = Path(intrinsics).name
        intrinsics = Intrinsics.from_json(intrinsics)
    if report is not None and not isinstance(report, dict):
        p = Path(report)
        if not p.is_file():
            raise FileNotFoundError(f"{p}: no such mismatch report")
        names["report"] = p.name
        try:
            report = json.loads(p.read_text(encoding="utf-8"))
        except ValueError as exc:
            raise UserError(f"{p}: not valid JSON ({exc})") from None
    if fmt == "kalibr-imu":
        if intrinsics is not None:
            raise UserError("--intrinsics: Kalibr's IMU input files hold no intrinsics; expected it only with "
                            "--format kalibr or openvins")
        files = kalibr_imu_files(recording, positions, report, input_names=names)
        return [write_text(Path(output) / n, t, overwrite=overwrite) for n, t in files.items()]
    text = imu_chain(recording, positions, intrinsics, report, fmt=fmt, input_names=names)
    return [write_text(output, text, overwrite=overwrite)]
