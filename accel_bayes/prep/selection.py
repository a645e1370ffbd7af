"""THE sample selection: which samples of a recording a fit uses, and why the others were dropped.

Every fit of the package (the [C21] likelihood and MAP, the PmMH calibration, the mismatch
refits) takes its samples from :func:`select_samples`, so the same recording with the same
options gives the same samples everywhere (issue #10, item 3).  Reasons, counted exclusively in
this order (a sample dropped for an earlier reason is not counted again):

* ``static`` — inside a rest (ω = 0 there: no information on the positions, [C21] §IV-C; the
  rests serve the intrinsic calibration instead);
* ``clipped`` — some accelerometer or gyroscope (of the IMUs used) is flagged at its range
  (``acc_clipped``/``gyro_clipped``, DESIGN §7.1): the output is censored, not a measurement;
* ``flagged`` — some accelerometer or gyroscope (of the IMUs used) is distrusted by its importer's
  plausibility check (``acc_flagged``/``gyro_flagged``, DESIGN §7.1): the rigid board contradicts
  the value, so it is likely a corrupted reading, not a measurement;
* ``non_finite`` — no used gyroscope has a finite reading, so the rotation rate (and the
  motion state of the sample) is undefined;
* ``slow`` — the rotation rate |ω̄_t| (:func:`rotation_rate`) is below ``min_rotation`` rad/s:
  the centripetal term that carries the positions is then tiny ([C21] §IV-C);
* ``user`` — not in the caller's own mask or index list.

The result is a frozen :class:`Selection`: the (T,) ``keep`` mask, the kept indices, and the
kept samples as contiguous runs with the gaps between them — what a process model or a finite-
difference rate needs, since consecutive kept indices are not always consecutive samples.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..constants import DEFAULT_MIN_ROTATION  # noqa: F401  (re-exported; likelihood re-exports it too)
from ..errors import UserError, nonnegative

__all__ = ["Selection", "select_samples", "rotation_rate", "clipped_mask", "flagged_mask", "check_min_rotation",
           "REASONS",
           "DEFAULT_MIN_ROTATION"]


REASONS = ("static", "clipped", "flagged", "non_finite", "slow", "user")


def _labels(present, imus) -> np.ndarray:
    """Labels of the IMUs that have the sensor (``present`` (K,) bool), restricted to ``imus``."""
    present = np.asarray(present, dtype=bool)
    lab = np.flatnonzero(present)
    if imus is not None:
        lab = np.intersect1d(lab, np.asarray([int(k) for k in imus], dtype=int))
    return lab


def rotation_rate(recording, gyro_imus=None) -> np.ndarray:
    """(T,) rotation rate |ω̄_t| in rad/s: the norm of the inverse-variance-weighted mean of the
    gyroscopes (array frame, nominal orientations) of the IMUs with one (or of ``gyro_imus``).

    Weights 1/σ_k² (``gyro_noise_std``) make ω̄_t the minimum-variance estimate of the common ω;
    with equal σ it is the plain mean.  A gyro with any non-finite axis at a sample is left out of
    that sample's mean (weights renormalised); a sample with no finite gyro gets NaN.  Without
    gyroscope data this is an error (no rate can be computed).
    """
    if recording.gyro is None or not np.asarray(recording.has_gyro).any():
        raise UserError("recording: has no gyroscope data; the rotation rate cannot be computed")
    lab = _labels(recording.has_gyro, gyro_imus)
    if len(lab) == 0:
        raise UserError(f"gyro_imus: expected IMUs with gyroscope data, got {list(gyro_imus)}")
    g = recording.gyro_tensor("array").numpy()[:, lab]  # (T, G, 3) rad/s
    sd = np.asarray(recording.gyro_noise_std, dtype=np.float64)[lab]
    w = 1.0 / sd**2
    if not (np.isfinite(w).all() and (w > 0).all()):
        w = np.ones_like(sd)  # unusable stated noise: weigh the gyros equally
    ok = np.isfinite(g).all(-1)  # (T, G)
    wt = np.where(ok, w[None, :], 0.0)
    den = wt.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.einsum("tg,tgi->ti", wt, np.where(ok[..., None], g, 0.0)) / den[:, None]
    rate = np.linalg.norm(mean, axis=-1)
    rate[den <= 0] = np.nan
    return rate


def clipped_mask(recording, acc_imus=None, gyro_imus=None, *, kind: str = "clipped") -> np.ndarray:
    """(T,) bool: samples where any accelerometer or gyroscope (of an IMU that has that sensor,
    restricted to ``acc_imus``/``gyro_imus`` when given) is flagged at its range
    (``acc_clipped``/``gyro_clipped``, DESIGN §7.1; ``kind="flagged"``: the importer's
    plausibility marks ``acc_flagged``/``gyro_flagged`` instead); all False without flags."""
    clip = np.zeros(recording.T, dtype=bool)
    for nm, present, imus in ((f"acc_{kind}", recording.has_acc, acc_imus),
                              (f"gyro_{kind}", recording.has_gyro, gyro_imus)):
        flags = getattr(recording, nm)
        if flags is not None:
            clip |= np.asarray(flags, dtype=bool)[:, _labels(present, imus)].any(-1)
    return clip


def flagged_mask(recording, acc_imus=None, gyro_imus=None) -> np.ndarray:
    """(T,) bool: samples where any used accelerometer or gyroscope is marked implausible by its
    importer (``acc_flagged``/``gyro_flagged``, DESIGN §7.1); all False without marks."""
    return clipped_mask(recording, acc_imus, gyro_imus, kind="flagged")


def _runs(mask: np.ndarray) -> np.ndarray:
    """(n, 2) int (start, stop) of the maximal runs of True in a (T,) bool mask (stop exclusive)."""
    m = np.concatenate(([False], np.asarray(mask, dtype=bool), [False]))
    d = np.flatnonzero(m[1:] != m[:-1])
    return d.reshape(-1, 2).astype(np.int64)


@dataclass(frozen=True, eq=False)  # eq=False: arrays have no single truth value; identity is equality
class Selection:
    """The samples a fit uses (:func:`select_samples`).

    keep : (T,) bool — the samples to use.
    dropped : {reason: count} for every reason of :data:`REASONS` (exclusive, in that order).
    index : (n,) int — the kept sample indices (``np.flatnonzero(keep)``).
    runs : (R, 2) int — the kept samples as contiguous runs [start, stop) of the recording.
    gaps : (R−1, 2) int — the dropped stretches [start, stop) between consecutive runs (where the
        time series is broken; dropped samples before the first or after the last run are not gaps).
    min_rotation : the threshold used, rad/s (0: no rotation test).
    settings : the switches used (drop_static, drop_clipped, drop_flagged, user given).
    rotation_rate : (T,) |ω̄_t| rad/s (:func:`rotation_rate`), or None without gyroscope data.
    """

    keep: np.ndarray
    dropped: dict
    index: np.ndarray
    runs: np.ndarray
    gaps: np.ndarray
    min_rotation: float
    settings: dict = field(default_factory=dict)
    rotation_rate: np.ndarray | None = field(default=None, repr=False)

    @property
    def T(self) -> int:
        return int(self.keep.shape[0])

    @property
    def n_kept(self) -> int:
        return int(self.index.shape[0])

    @property
    def kept_runs(self) -> int:
        """Number of contiguous runs of kept samples (1: one unbroken stretch)."""
        return int(self.runs.shape[0])

    def summary(self) -> str:
        """One line: kept out of T, the drops by reason, the runs."""
        d = ", ".join(f"{self.dropped[r]} {r}" for r in REASONS if self.dropped.get(r))
        return (f"samples: kept {self.n_kept} of {self.T} in {self.kept_runs} run(s); dropped "
                f"{d or 'none'} (min_rotation {self.min_rotation:g} rad/s)")

    def to_dict(self) -> dict:
        """JSON-ready counts and settings (no per-sample arrays)."""
        return {"recording": self.T, "kept": self.n_kept, "dropped": {r: int(self.dropped[r]) for r in REASONS},
                "kept_runs": self.kept_runs, "min_rotation": float(self.min_rotation), **self.settings}


def check_min_rotation(min_rotation) -> float:
    """``min_rotation`` as a float of rad/s ≥ 0 (None → 0, no rotation test); a UserError naming
    the option otherwise.  Callers check it before any expensive step."""
    if min_rotation is None:
        return 0.0
    return nonnegative(min_rotation, "min_rotation", "rad/s")


def _user_mask(user, T: int) -> np.ndarray:
    """(T,) bool from a bool mask or integer sample indices."""
    sel = np.asarray(user)
    if sel.dtype == bool:
        if sel.shape != (T,):
            raise UserError(f"select: a bool mask must have shape ({T},), got {sel.shape}")
        return sel.copy()
    m = np.zeros(T, dtype=bool)
    m[sel.astype(int)] = True
    return m


def select_samples(recording, *, static=None, drop_static: bool = True, drop_clipped: bool = True,
                   drop_flagged: bool = True, min_rotation: float | None = DEFAULT_MIN_ROTATION, user=None, acc_imus=None,
                   gyro_imus=None, use_gyro: bool = True) -> Selection:
    """Select the samples of ``recording`` a fit uses (module docstring: reasons and order).

    recording : a :class:`~accel_bayes.data.recording.Recording` (the rotation test reads its
        gyroscopes, so pass the recording with the intrinsics applied when they are).
    static : (T,) bool mask of the rests, or None (no rests).
    drop_static, drop_clipped, drop_flagged : switches for those three reasons.
    min_rotation : rad/s; samples with |ω̄_t| < this are dropped (None or 0: no rotation test).
    user : None, a (T,) bool mask or integer sample indices: further samples to keep (ANDed).
    acc_imus, gyro_imus : IMU labels whose flags (and, for gyros, readings) count; None = every
        IMU that has the sensor.
    use_gyro : False for a fit that ignores the gyroscopes ([S16] self-calibration): their flags
        and readings then count for nothing (no ``non_finite`` or ``slow`` test, acc flags only).

    Without gyroscope data there is no ``non_finite`` or ``slow`` test.  Never raises for an empty
    selection: the caller says which of its options to relax.
    """
    T = int(recording.T)
    min_rotation = check_min_rotation(min_rotation)
    has_gyro = use_gyro and recording.gyro is not None and np.asarray(recording.has_gyro).any()
    if not use_gyro:
        gyro_imus = []
    w = rotation_rate(recording, gyro_imus) if has_gyro else None

    tests = []
    if drop_static and static is not None:
        st = np.asarray(static, dtype=bool)
        if st.shape != (T,):
            raise UserError(f"static: a bool mask must have shape ({T},), got {st.shape}")
        tests.append(("static", st))
    if drop_clipped:
        tests.append(("clipped", clipped_mask(recording, acc_imus, gyro_imus)))
    if drop_flagged:
        tests.append(("flagged", flagged_mask(recording, acc_imus, gyro_imus)))
    if w is not None:
        tests.append(("non_finite", ~np.isfinite(w)))
        if min_rotation > 0:
            with np.errstate(invalid="ignore"):
                tests.append(("slow", np.isfinite(w) & (w < min_rotation)))
    if user is not None:
        tests.append(("user", ~_user_mask(user, T)))

    keep = np.ones(T, dtype=bool)
    dropped = dict.fromkeys(REASONS, 0)
    for reason, drop in tests:
        dropped[reason] = int((keep & drop).sum())
        keep &= ~drop
    runs = _runs(keep)
    gaps = np.stack((runs[:-1, 1], runs[1:, 0]), -1) if len(runs) > 1 else np.zeros((0, 2), dtype=np.int64)
    for a in (keep, runs, gaps):
        a.setflags(write=False)  # frozen all the way down: a Selection is shared by several fits
    index = np.flatnonzero(keep)
    index.setflags(write=False)
    if w is not None:
        w.setflags(write=False)
    settings = {"drop_static": bool(drop_static), "drop_clipped": bool(drop_clipped),
                "drop_flagged": bool(drop_flagged), "user": user is not None,
                "use_gyro": bool(use_gyro)}
    return Selection(keep=keep, dropped=dropped, index=index, runs=runs, gaps=gaps, min_rotation=min_rotation,
                     settings=settings, rotation_rate=w)
