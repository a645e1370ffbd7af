"""Pipelines: library functions that string the stages together for one recording (calibrate, map,
selfcal, motion, intrinsics, demo).  ``accel_bayes.cli`` only parses arguments, calls these and prints."""
