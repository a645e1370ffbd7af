"""Posterior diagnostics: ArviZ data, statistics and plots kept apart, as ArviZ 1.x splits them
(arviz-base, arviz-stats, arviz-plots).

* :mod:`.arviz_calls` — every call into ArviZ (so a move to ArviZ 1.x is one module's change):
  PmMH draws → ``InferenceData`` and its NetCDF file, ``az.summary`` / R̂ / ESS, PSIS-LOO and
  ``az.compare``, and ArviZ's trace, rank and autocorrelation plots drawn into the caller's axes.
* :mod:`.stats` — the convergence rule (:func:`~.stats.convergence_check`), posterior moments and
  the check of a posterior against a known truth.
* :mod:`.plots` — the posterior's figures (trace, rank, autocorrelation, the board's ellipses, each
  triad's offset from nominal) and the [S16] convergence plot.
* :mod:`.mismatch_figures` — the mismatch report's figures.

Nothing is imported here: ``from accel_bayes.diagnostics.stats import format_stat`` loads neither
ArviZ's plots nor matplotlib's figures unless that module needs them.  Figures are made without
pyplot, so neither importing these modules nor plotting switches the caller's matplotlib backend.
"""
