"""The sensing chain of one IMU: its own sampling clock, the datasheet low-pass, sensor errors,
the int16 register, and the host that reads it (numpy/scipy only).

Data age.  The host reads IMU k at r_n = t₀ + n/f_h + s_k (+ jitter); the register then holds the
sample of the latest internal tick t_m ≤ r_n, so the data age is a_n = r_n − t_m ∈ [0, 1/f_k)
with f_k = f_int(1 + ε_k) the IMU's true internal rate.  With constant ε and no jitter the ticks
are t_m = (m − c)/f_k, hence a_n = frac(f_k r_n + c)/f_k and f_k r_n advances by f_k/f_h per
read: a_n is a sawtooth sampled at f_h whose phase advances by 2π·frac(f_k/f_h) per read.  Its
apparent (beat) frequency is

    f_beat = f_k − f_h·round(f_k/f_h) ∈ [−f_h/2, f_h/2],

e.g. f_int = 1 kHz, f_h = 62.5 Hz, ε = −0.243 % → f_beat = −2.43 Hz (the age falls by
|f_beat|/f_k of a tick per read).  Nothing in the simulation uses this formula: the ages come from
the simulated tick times (:class:`HostReader`), and the tests check the formula against them.
"""
from __future__ import annotations

import numpy as np
from scipy import signal

#: int16 register full scales of the MPU-6050/9150 at ±16 g and ±2000 °/s (LSB sizes in SI)
ACC_LSB = 9.80665 / 2048.0           # m/s² per count
GYRO_LSB = np.pi / 180.0 / 16.4      # rad/s per count
#: datasheet DLPF setting 2 (MPU-6050/9150 register 26): bandwidth (Hz), delay (s)
DLPF2 = {"acc": (94.0, 3.0e-3), "gyro": (98.0, 2.8e-3)}


def beat_frequency(f_int, eps, f_host):
    """Apparent frequency (Hz) of the data-age sawtooth of an IMU ticking at f_int(1+eps) read at f_host."""
    f = f_int * (1.0 + np.asarray(eps, float))
    return f - f_host * np.round(f / f_host)


class Clock:
    """A free-running sampling clock: rate f_int·(1 + ε + a·sin(2πt/P + ψ)) Hz, tick phase c.

    The count is θ(t) = c + f_int·(t + εt + a·P/(2π)·(cos ψ − cos(2πt/P + ψ))); ticks are the
    instants where θ is an integer (solved by Newton's method to 1e-13 s).  The sinusoidal term is
    a slow temperature drift of the rate (a = 0: none).
    """

    def __init__(self, f_int, eps=0.0, phase=0.0, drift_amp=0.0, drift_period=200.0, drift_phase=0.0):
        self.f_int, self.eps, self.phase = float(f_int), float(eps), float(phase)
        self.a, self.P, self.psi = float(drift_amp), float(drift_period), float(drift_phase)

    def count(self, t):
        """θ(t), ticks counted since t = 0 plus the phase c (dimensionless)."""
        w = 2 * np.pi / self.P
        drift = self.a / w * (np.cos(self.psi) - np.cos(w * t + self.psi))
        return self.phase + self.f_int * (t * (1 + self.eps) + drift)

    def rate(self, t):
        """Instantaneous tick rate dθ/dt (Hz)."""
        return self.f_int * (1 + self.eps + self.a * np.sin(2 * np.pi * t / self.P + self.psi))

    def ticks(self, t_a, t_b):
        """All tick instants in [t_a, t_b] (s), increasing."""
        m = np.arange(np.ceil(self.count(t_a)), np.floor(self.count(t_b)) + 1)
        t = (m - self.phase) / (self.f_int * (1 + self.eps))
        for _ in range(20):
            step = (self.count(t) - m) / self.rate(t)
            t = t - step
            if np.max(np.abs(step), initial=0.0) < 1e-13:
                break
        return t


class DLPF:
    """Datasheet digital low-pass run on the internal samples at the nominal internal rate.

    Choice: a 2nd-order Butterworth IIR (bilinear) in cascade with a 2-tap fractional-delay FIR
    (plus whole-sample delays) that brings the DC group delay to the datasheet delay exactly; the
    Butterworth's corner is set so that the cascade is −3 dB at the datasheet bandwidth.  A 2-pole filter alone cannot have both: with 94 Hz bandwidth its
    delay is ≈ 2.4 ms, and a 2-pole with a 3.0 ms delay has at most ≈ 75 Hz bandwidth.  The delay
    is in internal samples, so an IMU whose clock runs fast by ε delays by delay/(1+ε) in seconds.
    ``bandwidth=None`` is no filter (pass-through, zero delay).
    """

    def __init__(self, bandwidth, delay, f_int):
        self.bandwidth, self.delay, self.f_int = bandwidth, float(delay), float(f_int)
        if bandwidth is None:
            self.b, self.a = np.array([1.0]), np.array([1.0])
            self.delay = 0.0
            return
        # the 2-tap FIR droops a little at high frequency: the Butterworth's corner is solved so
        # that the cascade's −3 dB point is the datasheet bandwidth
        from scipy.optimize import brentq
        fc = brentq(lambda fc: abs(self._design(fc)[2]) - 2**-0.5, bandwidth, min(1.3 * bandwidth, 0.49 * f_int),
                    xtol=1e-9)
        self.b, self.a, _ = self._design(fc)
        self.corner = fc

    def _design(self, fc):
        """(b, a, response at the bandwidth) of Butterworth(fc) · fractional delay to ``self.delay``."""
        b, a = signal.butter(2, fc, fs=self.f_int)
        extra = self.delay * self.f_int - self.dc_delay_samples(b, a)
        if extra < 0:
            raise ValueError(f"delay: {self.delay} s is below the Butterworth's own "
                             f"{self.dc_delay_samples(b, a) / self.f_int} s")
        n0, alpha = int(np.floor(extra)), extra - np.floor(extra)
        fir = np.zeros(n0 + 2)
        fir[n0], fir[n0 + 1] = 1 - alpha, alpha
        b = np.convolve(b, fir)
        return b, a, signal.freqz(b, a, worN=[self.bandwidth], fs=self.f_int)[1][0]

    @staticmethod
    def dc_delay_samples(b, a):
        """DC group delay (samples) of B(z)/A(z): Σk·b_k/Σb_k − Σk·a_k/Σa_k."""
        k = np.arange(max(len(b), len(a)))
        return (k[:len(b)] @ b) / b.sum() - (k[:len(a)] @ a) / a.sum()

    def noise_gain(self):
        """RMS gain of the filter for white input: sqrt(Σ h²) over its impulse response."""
        h = signal.lfilter(self.b, self.a, np.r_[1.0, np.zeros(4000)])
        return float(np.sqrt(np.sum(h**2)))

    def __call__(self, x):
        """Filter (N, ...) samples along axis 0, starting in steady state at x[0]."""
        if self.bandwidth is None:
            return x.copy()
        zi = signal.lfilter_zi(self.b, self.a)
        zi = zi.reshape((-1,) + (1,) * (x.ndim - 1)) * x[:1]
        return signal.lfilter(self.b, self.a, x, axis=0, zi=zi)[0]

    def params(self):
        return {"type": "butterworth2+fractional_delay" if self.bandwidth else "none",
                "butterworth_corner_hz": getattr(self, "corner", None),
                "bandwidth_hz": self.bandwidth, "delay_s_nominal": self.delay, "f_int_nominal": self.f_int,
                "b": self.b.tolist(), "a": self.a.tolist()}


class SensorErrors:
    """y = M x + b + bias random walk + white noise for one triad (SI units).

    M = I + E (scale and misalignment, dimensionless), b constant bias; ``noise_std`` is the std of
    the noise at the *register* (after the low-pass), so the input noise is scaled up by 1/noise
    gain; ``rw_std`` (unit/√s) drives a bias random walk at the internal ticks.
    """

    def __init__(self, M=None, bias=None, noise_std=0.0, rw_std=0.0):
        self.M = np.eye(3) if M is None else np.asarray(M, float)
        self.bias = np.zeros(3) if bias is None else np.asarray(bias, float)
        self.noise_std, self.rw_std = float(noise_std), float(rw_std)

    def apply(self, x, t, rng, gain=1.0):
        """Corrupt true values x (N, 3) taken at instants t (N,) s; rng draws noise and walk."""
        y = x @ self.M.T + self.bias
        noise = rng.normal(size=x.shape)  # drawn always so that twins share the stream
        y = y + self.noise_std / gain * noise
        if self.rw_std > 0:
            dt = np.diff(t, prepend=t[0])
            y = y + np.cumsum(self.rw_std * np.sqrt(dt)[:, None] * rng.normal(size=x.shape), axis=0)
        return y

    def params(self):
        return {"M": self.M.tolist(), "bias": self.bias.tolist(), "noise_std": self.noise_std,
                "rw_std": self.rw_std}


def quantise(y, lsb, enabled=True):
    """int16 register: round to the LSB (unit per count), clip at ±32767/−32768; returns (y, clipped)."""
    if not enabled:
        return y, np.zeros(y.shape[:-1], bool)
    raw = np.round(y / lsb)
    clipped = ((raw > 32767) | (raw < -32768)).any(-1)
    return np.clip(raw, -32768, 32767) * lsb, clipped


class HostReader:
    """The host reads every IMU's register at t₀ + n/f_h + skew_k + jitter (s).

    ``jitter`` is the upper end (s) of a uniform read latency drawn per read and IMU (0: none).
    :meth:`read` returns the index of the latest tick at or before each read — the register — and
    the data age.  A tick within 1 ns before the read counts as latched: float round-off must not
    turn the twins' exactly coincident ticks into a full-tick age.
    """

    def __init__(self, f_host, skew, jitter=0.0):
        self.f_host, self.skew, self.jitter = float(f_host), np.asarray(skew, float), float(jitter)

    def read_times(self, n_reads, rng):
        """(n_reads, K) true read instants and the (n_reads,) host stamps n/f_h (s)."""
        stamps = np.arange(n_reads) / self.f_host
        jit = rng.uniform(0.0, self.jitter, (n_reads, len(self.skew))) if self.jitter > 0 else 0.0
        return stamps[:, None] + self.skew[None, :] + jit, stamps

    @staticmethod
    def read(ticks, r):
        """Register index into ``ticks`` for read instants r, and the data age r − tick (s)."""
        idx = np.searchsorted(ticks, r + 1e-9, side="right") - 1
        if np.any(idx < 0):
            raise ValueError("read before the first tick: start the clock earlier")
        return idx, np.maximum(r - ticks[idx], 0.0)
