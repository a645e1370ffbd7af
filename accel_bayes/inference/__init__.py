"""Inference: the structured LM graph solver (:mod:`.lm`, :mod:`.linear`, :mod:`.damping`,
:mod:`.robust`), the [C21] MAP with its Laplace covariance (:mod:`.map`) and the Cramér–Rao
bound (:mod:`.crb`).  Other modules of this package are added by their own authors; import them
from their modules (nothing heavy is imported here)."""
