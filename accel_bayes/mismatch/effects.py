"""Deprecated location of the effects library, kept importable for one release.

The effect classes are physics used by the simulator as much as by the mismatch detector; they
now live in :mod:`accel_bayes.physics.effects` (one module per sensor).  Import from there.
"""
from ..physics.effects import *  # noqa: F401,F403
from ..physics.effects import __all__  # noqa: F401
