"""The rigid-board plausibility check every importer runs (issue #29): values the checksum (or a
CSV file) cannot vouch for, judged against the other IMUs of the same rigid board.

The board is rigid: every gyro, rotated to the array frame, reads the same ω up to its noise and
known errors (bias, scale, misalignment, the sampling skew of free-running IMU clocks), and every
accelerometer reads the same specific force plus the rigid-body term α×r_k + ω×(ω×r_k) of its
nominal position r_k.  Per sample, IMU and array-frame axis:

* **deviation** d = value − median of the OTHER IMUs (accelerometers after subtracting the rigid-
  body term, with ω the gyros' median and α its time derivative): a value is judged against a
  consensus it does not take part in;
* **range**: |d| ≤ floor + ``RANGE_MOTION[sensor]`` · A₁ + ``SPREAD_FACTOR`` · S, with A₁ the
  board's largest change per sample period (median of the IMUs, any axis of that sensor, either
  side of the sample) and S the median over the IMUs of |d| on that axis (the honest spread of the board
  at that instant: scale errors, biases, vibration);
* **jump**: the smaller of the deviation's two one-sample steps, |d(t) − d(t−1)| and
  |d(t) − d(t+1)| (the only step at an end, not counted where the neighbour is itself out of
  range or steps away from its other neighbour), each against
  floor + ``JUMP_MOTION[sensor]`` · g · A₂ + ``SPREAD_FACTOR`` · S_j (g the step's length in
  nominal sample periods, 1 without gaps: an honest deviation changes more across a gap, a wrong
  value does not grow), with A₂ the board's largest
  change of slope per period touching the sample and S_j the IMUs' median step.  Sampling skew makes an
  honest deviation follow the board's rate of change, so its step follows the second
  difference; a wrong value steps away from both of its neighbours.

The motion factors were set on the six shared MIMU4444 recordings, whose ~100 s of vigorous hand
rotation reach the ±2000 °/s range and ±16 g impacts: honest accelerometers there differ by up to
~2 × the board's one-sample change (they see the jerk of impacts at their own sampling instants),
gyros by up to ~0.5 ×.  Their largest ratios and the margins are in ``experiments/mimu_fuzz.md``.

**Full scale.**  Near its range an IMU saturates up to ±3 % before or after another (sensitivity
tolerance), so an axis is exempt at a sample where the end of the scale is *corroborated*: the
board's median is within 1/16 of full scale, or an IMU is saturated (top 0.2 % of the scale) and
its own previous or next sample is within 1/16 too.  A full-scale value that the board and its
own neighbours do not share — in one IMU, or in two hit by one corruption — is not clipping and
is judged like any other.  Where a gyro axis is exempt the
accelerometers of that sample and its neighbours are too (ω, hence the rigid-body term, is not
known there).

Fewer than three IMUs with a sensor: no consensus to judge by, nothing is checked for it.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch

from ..physics.geometry import quat_to_matrix

__all__ = ["SPREAD_FACTOR", "RANGE_MOTION", "JUMP_MOTION", "NEAR_LIMIT_FRACTION", "SATURATED_FRACTION",
           "Plausibility", "rigid_board_check"]

SPREAD_FACTOR = 8.0  # × the IMUs' median deviation: the honest spread at that instant
RANGE_MOTION = {"acc": 3.0, "gyro": 1.0}  # × the board's one-sample change
JUMP_MOTION = {"acc": 2.0, "gyro": 0.5}  # × the board's second difference
NEAR_LIMIT_FRACTION = 30720 / 32768  # 15/16 of full scale: IMUs saturate ±3 % apart
SATURATED_FRACTION = 32704 / 32768  # the top 0.2 % of the scale: this IMU is at its limit


@dataclass
class Plausibility:
    """What :func:`rigid_board_check` found.

    range_ratio, jump_ratio : (T, K, 2) float64 — largest |statistic| / bound over the three
        array-frame axes, [acc, gyro]; −inf where exempt or not checked (a sample fails above 1).
    acc_flagged, gyro_flagged : (T, K) bool — samples failing either test.
    checked : {"acc": bool, "gyro": bool} — whether each sensor had ≥ 3 IMUs to judge by.
    """

    range_ratio: np.ndarray
    jump_ratio: np.ndarray
    acc_flagged: np.ndarray
    gyro_flagged: np.ndarray
    checked: dict

    def rows(self, limit: float = 1.0) -> list:
        """[sample, IMU, "acc"/"gyro", "range"/"jump", ratio] of every failing IMU sensor."""
        out = []
        for test, ratio in (("range", self.range_ratio), ("jump", self.jump_ratio)):
            for i, k, s in zip(*np.nonzero(ratio > limit)):
                out.append([int(i), int(k), ("acc", "gyro")[s], test, round(float(ratio[i, k, s]), 3)])
        return sorted(out)


def _others_median(x: np.ndarray) -> np.ndarray:
    """(…, K) → (…, K): for each IMU the median of the other IMUs' finite values (NaN: absent)."""
    K = x.shape[-1]
    if not np.isnan(x).any() and K % 2 == 0:
        # K even, no gaps: the others are K − 1 (odd) values, their median is the K/2-th smallest
        # of all K where the IMU itself ranks in the lower half, else the (K/2 − 1)-th.
        order = np.argsort(x, axis=-1, kind="stable")
        ys = np.take_along_axis(x, order, -1)
        rank = np.empty_like(order)
        np.put_along_axis(rank, order, np.broadcast_to(np.arange(K), x.shape), -1)
        h = K // 2
        return np.where(rank < h, ys[..., h : h + 1], ys[..., h - 1 : h])
    out = np.empty_like(x)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an absent sensor is NaN on purpose
        for k in range(K):
            out[..., k] = np.nanmedian(np.delete(x, k, axis=-1), axis=-1)
    return out


def _median(x: np.ndarray) -> np.ndarray:
    """Median over the last (IMU) axis, ignoring NaN (an absent sensor)."""
    if not np.isnan(x).any():
        # sorting a handful of IMUs is cheaper than numpy's partition-based (nan)median
        ys = np.sort(x, axis=-1)
        K = x.shape[-1]
        return 0.5 * (ys[..., (K - 1) // 2] + ys[..., K // 2])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(x, axis=-1)


def _board_change(med: np.ndarray, order: int, gap: np.ndarray) -> np.ndarray:
    """(T, 3) the board's largest |change| per nominal sample period over the three axes (median
    of the IMUs) among the differences touching each sample: order 1 the slope, order 2 the
    change of slope from one step to the next.  ``gap`` (T−1,) step lengths in periods: across a
    gap the board's change is taken per period, so a missing packet does not inflate the bound.
    Zero where the stream is too short."""
    n = med.shape[0]
    out = np.zeros_like(med)
    if n <= order:
        return out
    d = np.diff(med, axis=0) / gap[:, None]  # slopes per period
    if order == 2:
        d = np.diff(d, axis=0)
    d = np.nan_to_num(np.abs(d), nan=0.0).max(1, keepdims=True)  # (n − order, 1)
    for s in range(order + 1):
        out[s : s + d.shape[0]] = np.maximum(out[s : s + d.shape[0]], d)
    return out


def _corroborated_limit(x: np.ndarray, limit: np.ndarray) -> np.ndarray:
    """(T, 3) bool: axes where the end of the scale is corroborated (module docstring).
    x : (T, 3, K) array-frame values; limit : (K,) full scale (inf: unknown, never exempt)."""
    frac = np.abs(x) / limit  # NaN for an absent sensor
    near = np.nan_to_num(frac, nan=0.0) >= NEAR_LIMIT_FRACTION
    sat = np.nan_to_num(frac, nan=0.0) >= SATURATED_FRACTION
    own = np.zeros_like(near)
    own[1:] |= near[:-1]
    own[:-1] |= near[1:]
    return (_median(frac) >= NEAR_LIMIT_FRACTION) | (sat & own).any(-1)


def _sensor_frame_to_array(x: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """(T, K, 3) sensor-frame values → (T, 3, K) array frame (v_array = R(q)ᵀ v_sensor)."""
    return np.einsum("kji,tkj->tik", rot, x)


def rigid_board_check(acc, gyro, time, positions, orientations, *, floor_acc: float, floor_gyro: float,
                      acc_range=None, gyro_range=None, period: float | None = None) -> Plausibility:
    """Judge every accelerometer and gyro sample against the rest of the rigid board (module
    docstring).

    acc : (T, K, 3) m/s², gyro : (T, K, 3) rad/s or None — sensor frame, NaN where an IMU lacks
    the sensor.  time : (T,) s.  positions : (K, 3) m, orientations : (K, 4) array → sensor
    quaternions (nominal).  floor_acc (m/s²), floor_gyro (rad/s) : the bounds' floors.
    acc_range, gyro_range : full scale per IMU ((K,) or scalar, m/s² / rad/s; None: unknown, no
    exemption).  period : the nominal sample period, s (default the median step): steps across
    longer gaps are taken per period.
    """
    acc = np.asarray(acc, dtype=np.float64)
    T, K, _ = acc.shape
    time = np.asarray(time, dtype=np.float64)
    q = torch.as_tensor(np.asarray(orientations, dtype=np.float64))
    rot = quat_to_matrix(q).numpy()
    snap = np.rint(rot)
    rot = np.where(np.abs(rot - snap) < 1e-12, snap, rot)  # signed permutations stay exact
    r = np.asarray(positions, dtype=np.float64)
    has = {"acc": ~np.isnan(acc).all(axis=(0, 2))}
    xs = {"acc": _sensor_frame_to_array(acc, rot)}
    if gyro is not None:
        gyro = np.asarray(gyro, dtype=np.float64)
        has["gyro"] = ~np.isnan(gyro).all(axis=(0, 2))
        xs["gyro"] = _sensor_frame_to_array(gyro, rot)
    lim = {}
    for s, rg in (("acc", acc_range), ("gyro", gyro_range)):
        lim[s] = np.full(K, np.inf) if rg is None else np.broadcast_to(np.asarray(rg, dtype=np.float64), (K,)).copy()
        lim[s][~np.isfinite(lim[s])] = np.inf
    checked = {s: bool(s in has and has[s].sum() >= 3) for s in ("acc", "gyro")}
    rng = np.full((T, K, 2), -np.inf)
    jmp = np.full((T, K, 2), -np.inf)
    if T == 0:
        return Plausibility(rng, jmp, np.zeros((T, K), bool), np.zeros((T, K), bool), checked)
    dt = np.diff(time)
    period = float(np.median(dt)) if period is None and dt.size else (period or 1.0)
    gap = np.maximum(np.rint(dt / period), 1.0) if dt.size else dt

    exempt = {}
    if checked["gyro"]:
        g = xs["gyro"]
        exempt["gyro"] = _corroborated_limit(g, lim["gyro"])
        w = _median(g)  # (T, 3) rad/s
        w = np.nan_to_num(w, nan=0.0)
        alpha = np.gradient(w, time, axis=0) if T > 1 else np.zeros_like(w)
        c = r - r[has["acc"]].mean(0)
        lever = np.cross(alpha[:, None], c[None]) + np.cross(w[:, None], np.cross(w[:, None], c[None]))  # (T, K, 3)
        xs["acc"] = xs["acc"] - lever.transpose(0, 2, 1)
        glim = exempt["gyro"].any(1)
        glim[1:] |= exempt["gyro"].any(1)[:-1]
        glim[:-1] |= exempt["gyro"].any(1)[1:]
    else:
        glim = np.zeros(T, dtype=bool)
    if checked["acc"]:
        exempt["acc"] = _corroborated_limit(xs["acc"], lim["acc"]) | glim[:, None]

    floors = {"acc": floor_acc, "gyro": floor_gyro}
    for si, s in enumerate(("acc", "gyro")):
        if not checked[s]:
            continue
        x = np.where(has[s][None, None, :], xs[s], np.nan)
        dev = x - _others_median(x)  # (T, 3, K)
        med = _median(x)
        bound = floors[s] + RANGE_MOTION[s] * _board_change(med, 1, gap) + SPREAD_FACTOR * _median(np.abs(dev))
        out_of_range = np.abs(dev) / bound[..., None]
        out_of_range[exempt[s]] = -np.inf
        rng[..., si] = np.nan_to_num(out_of_range, nan=-np.inf).max(1)
        if T >= 2:
            step = np.abs(np.diff(dev, axis=0))  # (T−1, 3, K)
            j = np.full(dev.shape, np.inf)
            j[1:] = step
            j[:-1] = np.minimum(j[:-1], step)
            spread = SPREAD_FACTOR * _median(j)  # (T, 3)
            a2 = JUMP_MOTION[s] * _board_change(med, 2, gap)
            g = gap[:, None]
            # each side against its own bound (its gap), the smaller ratio counts
            left = step / (floors[s] + a2[1:] * g + spread[1:])[..., None]
            right = step / (floors[s] + a2[:-1] * g + spread[:-1])[..., None]
            ratio = np.full(dev.shape, np.inf)
            ratio[1:] = left
            ratio[:-1] = np.minimum(ratio[:-1], right)
            if T >= 3:
                # An end sample has one step only, to its neighbour: no evidence against it where
                # that neighbour is itself out of range or steps away from its other neighbour.
                ratio[0][(out_of_range[1] > 1) | (right[1] > 1)] = -np.inf
                ratio[-1][(out_of_range[-2] > 1) | (left[-2] > 1)] = -np.inf
            ex = exempt[s].copy()
            ex[1:] |= exempt[s][:-1]
            ex[:-1] |= exempt[s][1:]
            ratio[ex] = -np.inf
            jmp[..., si] = np.nan_to_num(ratio, nan=-np.inf, posinf=-np.inf).max(1)
    bad = (rng > 1) | (jmp > 1)
    return Plausibility(rng, jmp, bad[..., 0], bad[..., 1], checked)
