"""The statistical model between ``prep`` and ``inference`` (issue #26): the [C21] marginal
likelihood (:mod:`.likelihood`), the gyroscope posterior of ω (:mod:`.gyro_posterior`), the prior
on φ (:mod:`.phi_prior`), the noise levels and tempering (:mod:`.noise`, :mod:`.tempering`) and
a mismatch report read into likelihood terms (:mod:`.report_terms`).  It imports from
``physics``, ``data`` and ``prep`` only; the fits that solve it live in ``inference``.
Import from the modules (nothing heavy is imported here)."""
