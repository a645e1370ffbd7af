"""The physics of an inertial sensor array: the rigid-body signal model and its derivatives.

* :mod:`.jacobians` — every derivative of the kinematics f = Ω(ω)² r + Ω(ω̇) r + s ([C21] eq. 4a)
  that a solver needs, in one place.

The signal model itself is still :mod:`accel_bayes.models` (its move here is the next step of
issue #10).
"""
