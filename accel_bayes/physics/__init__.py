"""The physics of an inertial sensor array: the rigid-body signal model, its derivatives and the
sensor errors, one definition each.

* :mod:`.jacobians` — every derivative of the kinematics f = Ω(ω)² r + Ω(ω̇) r + s ([C21] eq. 4a)
  that a solver needs.
* :mod:`.effects` — the effects library, one class per physical effect, one module per sensor
  (used by the simulator and by the mismatch detector); the intrinsic calibration and the [S16]
  sensor parameters are conversions of its accelerometer gain + bias.

The signal model itself is still :mod:`accel_bayes.physics.models` (its move here is the next step of
issue #10).
"""
