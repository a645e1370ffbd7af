"""Inference: the LM package (:mod:`.lm`: the structured graph solver, its batched mode and their
pieces — damping, linear solvers, robust kernels, stopping rules), the PmMH package
(:mod:`.mcmc`: kernel, proposals, adaptation, runner with checkpoints, priors), the [C21] MAP
with its Laplace covariance (:mod:`.map`), the Cramér–Rao bound (:mod:`.crb`), the [S16]
self-calibration (:mod:`.selfcal`) and the conventional calibration (:mod:`.conventional`).
Import them from their modules (nothing heavy is imported here)."""
