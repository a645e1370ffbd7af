"""An independent first-principles generator of clocked IMU arrays and rigs (issue #27 item 1,
issue #28's concealed rigs).  numpy/scipy only for the physics; ``accel_bayes.data`` only to hold
and write the recording.  See ``experiments/clockgen.md``.

Pieces: :mod:`.motion` (exact rigid-body motion), :mod:`.sensing` (Clock, DLPF, SensorErrors,
HostReader), :mod:`.cases` (boards, :func:`draw_case`, :func:`write_case`), :mod:`.rig`.
"""
from .cases import board, draw_case, matrix_to_quat, quat_to_matrix, write_case  # noqa: F401
from .motion import G0, Motion, body_rate, draw_motion, exp_so3  # noqa: F401
from .sensing import DLPF, DLPF2, Clock, HostReader, SensorErrors, beat_frequency  # noqa: F401
