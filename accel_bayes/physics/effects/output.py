"""Effects on the whole output of a sensor: clipping at an unstated range (saturation), noise
larger than stated (noise_level), and the finding-only ``unexplained``.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from ...errors import UserError
from .base import AXES, Effect, Param, register_effect, _axis_index, _fmt, _onehot


def _imus_by_sensor(layout):
    """(sensor, [IMU indices that carry it]) for "acc" then "gyro", sensors no IMU carries left out:
    the candidate channels of the whole-output effects."""
    for sensor, has in (("acc", layout.has_acc), ("gyro", layout.has_gyro)):
        ks = [int(k) for k in np.flatnonzero(np.asarray(has, bool))]
        if ks:
            yield sensor, ks


@register_effect
class Saturation(Effect):
    """Outputs clipped at ±``limit`` (m/s² or rad/s) — a range smaller than stated, or unflagged
    clipping.  Channel(s): one sensor ("acc" or "gyro") and either one IMU axis or, with
    imu=None and axis=None, every channel of that sensor.  Kind "clip": applied after all mean
    effects (likelihood treatment in the module docstring).  ``clipped_fraction`` is derived
    (fraction of the channel's samples whose unclipped model output exceeds the limit)."""

    name = "saturation"
    description = "samples clipped at the sensor range"
    kind = "clip"
    local_imu = True
    local_axis = True
    sensor = "both"
    options = ("sensor",)
    derived = ("clipped_fraction",)
    parameters = (Param("limit", (), "m s-2 or rad s-1", None, "clipping level", null=math.inf),)

    def __init__(self, imu=None, axis=None, params=None, sensor: str = "acc"):
        if sensor not in ("acc", "gyro"):
            raise UserError(f"saturation: sensor: expected 'acc' or 'gyro', got {sensor!r}")
        self.which = sensor
        if (imu is None) != (axis is None):
            raise UserError("saturation: give both imu and axis (one channel) or neither (every channel)")
        if imu is None:
            # the all-channels variant: bypass the local checks of the base class
            self.imu, self.axis, self.axis_index = None, None, None
            self._init_params(params)
        else:
            super().__init__(imu, axis, params)

    def location(self):
        return {"imu": self.imu, "axis": self.axis, "sensor": self.which}

    @classmethod
    def candidates(cls, layout):
        out = []
        for sensor, ks in _imus_by_sensor(layout):
            out += [cls(imu=k, axis=a, sensor=sensor) for k in ks for a in AXES]
            out.append(cls(sensor=sensor))
        return out

    def channel_mask(self, K: int, like: torch.Tensor) -> torch.Tensor:
        if self.imu is None:
            return torch.ones(K, 3, dtype=torch.bool, device=like.device)
        return _onehot(K, self.imu, self.axis_index, like).bool()

    def transform(self, params, acc, gyro, ctx):
        L = self._p(params)["limit"]
        y = acc if self.which == "acc" else gyro
        m = self.channel_mask(y.shape[1], y)
        clipped = torch.minimum(torch.maximum(y, -L), L)
        new = torch.where(m, clipped, y)
        return (new, gyro) if self.which == "acc" else (acc, new)

    def update_stats(self, acc, gyro) -> None:
        """``clipped_fraction``: share of the channel(s)' samples beyond the limit."""
        with torch.no_grad():
            y = acc if self.which == "acc" else gyro
            m = self.channel_mask(y.shape[1], y)
            L = float(self.params["limit"])
            self.stats["clipped_fraction"] = float((y.abs() > L)[:, m].double().mean()) if bool(m.any()) else 0.0

    def outputs_at_limit(self, y: torch.Tensor, sigma: torch.Tensor, n_sigma: float, mask=None) -> int:
        """How many recorded outputs of the effect's channel(s) lie within ``n_sigma`` stated-noise standard
        deviations of ±limit: y (T, K, 3) the sensor's outputs (m/s² or rad/s; NaN or ``mask`` 0 = missing),
        sigma (K,) its stated noise.  A clip flattens every peak beyond the range, so real clipping holds
        several outputs at L; a limit that no output reaches cuts only the model's own peaks
        (``experiments/saturation_guard_probe.md``)."""
        with torch.no_grad():
            L = float(self.params["limit"])
            m = self.channel_mask(y.shape[1], y)[None].expand_as(y)
            ok = torch.isfinite(y) & m & (True if mask is None else (torch.as_tensor(mask) > 0))
            near = (y.abs() - L).abs() <= n_sigma * torch.as_tensor(sigma, dtype=y.dtype)[None, :, None]
            return int((near & ok).sum())

    def report_parameters(self, params=None):
        L = float(self._p(params)["limit"])
        return {"limit": L, "clipped_fraction": float(self.stats.get("clipped_fraction", float("nan"))),
                "sensor": self.which}

    def explain(self, params=None):
        L = float(self._p(params)["limit"])
        unit = "m/s²" if self.which == "acc" else "rad/s"
        where = (f"the {self.axis} axis of IMU {self.imu}'s {'accelerometer' if self.which == 'acc' else 'gyroscope'}"
                 if self.imu is not None else f"every {'accelerometer' if self.which == 'acc' else 'gyroscope'} channel")
        frac = self.stats.get("clipped_fraction")
        tail = f" ({100 * frac:.2g} % of its samples)" if frac is not None and math.isfinite(frac) else ""
        return f"Readings of {where} are clipped at ±{_fmt(L, unit)}{tail}, below what the motion reached."


# ------------------------------------------------------------------------------------ noise

@register_effect
class NoiseLevel(Effect):
    """Noise larger than stated: the white-noise std of one sensor ("acc" or "gyro") of IMU k
    (or, with imu=None, of every IMU) is ``factor`` × the stated one.  Kind "noise": no mean
    change; likelihood term −n·log(factor) − ½ Σ r²/(factor² σ²)."""

    name = "noise_level"
    description = "noise larger than stated"
    kind = "noise"
    local_imu = True
    local_axis = False
    sensor = "both"
    options = ("sensor",)
    parameters = (Param("factor", (), "1", None, "× stated standard deviation", null=1.0),)

    def __init__(self, imu=None, axis=None, params=None, sensor: str = "acc"):
        if sensor not in ("acc", "gyro"):
            raise UserError(f"noise_level: sensor: expected 'acc' or 'gyro', got {sensor!r}")
        self.which = sensor
        if imu is None:
            if axis is not None:
                raise UserError("noise_level: is not local to one axis; axis must be None")
            self.imu, self.axis, self.axis_index = None, None, None
            self._init_params(params)
        else:
            super().__init__(imu, axis, params)

    def location(self):
        return {"imu": self.imu, "axis": None, "sensor": self.which}

    @classmethod
    def candidates(cls, layout):
        out = []
        for sensor, ks in _imus_by_sensor(layout):
            out += [cls(imu=k, sensor=sensor) for k in ks]
            out.append(cls(sensor=sensor))
        return out

    def noise_factors(self, params, K):
        f = float(self._p(params)["factor"])
        fa = torch.ones(K, dtype=torch.float64)
        fg = torch.ones(K, dtype=torch.float64)
        tgt = fa if self.which == "acc" else fg
        if self.imu is None:
            tgt[:] = f
        else:
            tgt[self.imu] = f
        return fa, fg

    def report_parameters(self, params=None):
        return {"factor": float(self._p(params)["factor"]), "sensor": self.which}

    def explain(self, params=None):
        f = float(self._p(params)["factor"])
        what = "accelerometer" if self.which == "acc" else "gyroscope"
        where = f"IMU {self.imu}'s {what}" if self.imu is not None else f"every {what}"
        return f"The noise of {where} is {f:.3g}× the level stated in the recording."


# ------------------------------------------------------------------------------------ finding only

@register_effect
class Unexplained(Effect):
    """A located mismatch that no candidate explains.  Not a signal model: it carries the
    location (IMU, axis, sensor, regime/time window) and the size of the excess."""

    name = "unexplained"
    description = "a located mismatch that no candidate explains"
    kind = "finding"
    local_imu = False
    local_axis = False
    sensor = "both"
    parameters = ()

    def __init__(self, imu=None, axis=None, params=None, sensor=None, where=None, excess=None,
                 characterisation=None):
        self.imu = None if imu is None else int(imu)
        # one sentence from accel_bayes.mismatch.characterise: what the excess scales with and its shape
        self.characterisation = characterisation
        self.axis = axis
        self.axis_index = None if axis is None else _axis_index(axis)
        self.which = sensor
        self.where = dict(where or {})
        self.excess = dict(excess or {})
        self.params, self.std, self.stats = {}, {}, {}

    def location(self):
        return {"imu": self.imu, "axis": self.axis, "sensor": self.which}

    @classmethod
    def candidates(cls, layout):
        return []

    def report_parameters(self, params=None):
        return dict(self.excess)

    def explain(self, params=None):
        what = {"acc": "accelerometer", "gyro": "gyroscope"}.get(self.which, "sensor")
        where = f"the {self.axis} axis of IMU {self.imu}'s {what}" if self.imu is not None else "the recording"
        reg = self.where.get("regime")
        tw = self.where.get("time_s")
        when = f" in the '{reg}' regime" if reg else ""
        if tw:
            when += f" between {tw[0]:.3g} s and {tw[1]:.3g} s"
        ratio = self.excess.get("chi2_ratio")
        size = f" (residual power {ratio:.3g}× the stated noise)" if ratio else ""
        text = (f"Residuals of {where} exceed the stated noise{when}{size}, and none of the candidate effects "
                f"explains them.")
        if self.characterisation:
            text += " " + self.characterisation
        return text
