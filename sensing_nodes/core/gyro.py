"""Heading from a gyro: trapezoidal integration of the bias-corrected yaw rate, bias estimation
while the robot stands still, and the heading variance that goes with it.

Frames and units: rates in rad/s about the IMU axes (the IMU is mounted level, so its z rate is
the base yaw rate), accelerations in m/s^2, heading (yaw) in rad in the odom frame, stamps in ns.

Error model (a 2-state Kalman filter over [yaw, z bias]): white rate noise of density
`noise_density` (rad/s/sqrt(Hz)) makes the heading random-walk (variance noise_density^2 * t);
the bias random-walks with density `bias_random_walk` (rad/s/sqrt(s)); the remaining bias
uncertainty makes the heading variance grow with t^2 through the yaw-bias covariance.
While the robot is known to be still, each raw sample measures the bias (a zero-velocity update)
and the heading is held.
"""

from __future__ import annotations

import enum
import math
from collections import deque
from dataclasses import dataclass
from operator import add, mul, sub
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sensing_nodes.core.geometry.se2 import wrap_angle
from sensing_nodes.core.timing import SampleOutcome, StampStep, classify_step


def integrate_rate(stamps_ns: ArrayLike, rate: ArrayLike, bias: float = 0.0, yaw0: float = 0.0
                   ) -> NDArray[np.float64]:
    """Unwrapped heading (rad) at every stamp: rates (rad/s) minus a constant bias, trapezoidal."""
    t = np.asarray(stamps_ns, dtype=np.int64)
    r = np.asarray(rate, dtype=float) - bias
    if t.shape != r.shape:
        raise ValueError(f'{t.size} stamps but {r.size} rates')
    dt = np.diff(t).astype(float) * 1e-9
    return yaw0 + np.concatenate([[0.0], np.cumsum(0.5 * (r[1:] + r[:-1]) * dt)])


def _returned_covariance(p_yaw: float, p_cross: float, p_bias: float) -> tuple[float, float]:
    """(p_yaw, p_cross) of a heading held since the stillness window's start, against today's
    bias variance: the cross term is capped so the [yaw, bias] covariance stays PSD.

    The window's first sample carries the cross-covariance of its own time; bias updates since
    (a still run before a short motion) can have shrunk p_bias below what it needs, and the next
    zero-velocity update then made p_yaw negative (seen: -0.004 rad^2 after a 0.25 s IMU gap)."""
    limit = math.sqrt(max(p_yaw, 0.0) * max(p_bias, 0.0))
    return p_yaw, min(max(p_cross, -limit), limit)


def _zero_velocity_update(yaw: float, p_yaw: float, p_cross: float, p_bias: float, bx: float,
                          by: float, bz: float, zx: float, zy: float, zz: float, r: float):
    """One Kalman update of the [yaw, bias_z] filter while the robot stands still: raw rates
    (zx, zy, zz) (rad/s) measure the bias (bx, by, bz) with variance r (rad^2/s^2); the x and y
    biases take the same gain as z. Returns (yaw, p_yaw, p_cross, p_bias, bx, by, bz), plain
    floats (flat: this runs once per still sample)."""
    s = p_bias + r
    k_yaw, k_bias = p_cross / s, p_bias / s
    # P - K H P, each line using the prior values it needs.
    return (yaw + k_yaw * (zz - bz), p_yaw - k_yaw * p_cross, p_cross - k_yaw * p_bias,
            p_bias - k_bias * p_bias, bx + k_bias * (zx - bx), by + k_bias * (zy - by),
            bz + k_bias * (zz - bz))


@dataclass
class GyroConfig:
    """Stillness detector and error model; rates rad/s, accelerations m/s^2, times s.

    Defaults fit sensor_sim's default IMU (0.001 rad/s and 0.02 m/s^2 white noise per sample at
    200 Hz): thresholds are 3x the per-sample noise.
    """
    bias_estimation: bool = True
    stillness_window_s: float = 0.5
    gyro_std_threshold_rad_s: float = 0.003
    accel_std_threshold_m_s2: float = 0.06
    max_gyro_bias_rad_s: float = 0.05
    noise_density: float = 7.1e-5        # rad/s/sqrt(Hz)
    bias_random_walk: float = 1e-6       # rad/s/sqrt(s)
    initial_bias_sigma_rad_s: float = 0.01
    # the bias estimate before the first stillness (calibrated)
    initial_bias_z_rad_s: float = 0.0
    max_gap_s: float = 0.5
    wheel_timeout_s: float = 0.25
    wheel_still_linear_m_s: float = 1e-3
    wheel_still_angular_rad_s: float = 1e-3

    def problems(self) -> list[tuple[str, str, object]]:
        """(field, problem, value) for every value the integrator cannot run with."""
        out: list[tuple[str, str, object]] = []
        for name in ('stillness_window_s', 'gyro_std_threshold_rad_s', 'accel_std_threshold_m_s2',
                     'max_gyro_bias_rad_s', 'noise_density', 'initial_bias_sigma_rad_s',
                     'max_gap_s', 'wheel_timeout_s', 'wheel_still_linear_m_s',
                     'wheel_still_angular_rad_s'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                out.append((name, 'must be a finite number > 0', value))
        if not (math.isfinite(self.bias_random_walk) and self.bias_random_walk >= 0):
            out.append(('bias_random_walk', 'must be finite and >= 0', self.bias_random_walk))
        return out


class ImuRejection(enum.Enum):
    """Why an IMU sample was not integrated."""
    NON_FINITE = 'non_finite'
    REPEATED_STAMP = 'repeated_stamp'


@dataclass
class ImuUpdate(SampleOutcome):
    """Outcome of one IMU sample (rejection: an ImuRejection); still: the robot stands still."""
    still: bool = False


@dataclass(slots=True)
class _Sample:
    stamp_ns: int
    gyro: tuple[float, float, float]
    accel: tuple[float, float, float]
    yaw: float = 0.0
    p_yaw: float = 0.0
    p_cross: float = 0.0
    shifted: list | None = None      # gyro + accel minus the window's reference, for its sums


class _Window:
    """Samples of the trailing stillness window with running sums for their mean and variance."""

    def __init__(self, window_s: float) -> None:
        self.window_ns = int(round(window_s * 1e9))
        self.samples: deque[_Sample] = deque()
        self._ref = (0.0,) * 6
        self._s1 = [0.0] * 6
        self._s2 = [0.0] * 6

    def clear(self) -> None:
        self.samples.clear()

    def add(self, sample: _Sample) -> None:
        samples = self.samples
        values = sample.gyro + sample.accel
        if not samples:
            # Sums are shifted by the first sample so that squares of ~9.8 m/s^2 do not cancel.
            self._ref = values
            self._s1 = [0.0] * 6
            self._s2 = [0.0] * 6
        # Element-wise through map (C loops: this runs per IMU sample), the same operations.
        shifted = sample.shifted = list(map(sub, values, self._ref))
        self._s1 = list(map(add, self._s1, shifted))
        self._s2 = list(map(add, self._s2, map(mul, shifted, shifted)))
        samples.append(sample)
        while len(samples) > 1 and sample.stamp_ns - samples[1].stamp_ns >= self.window_ns:
            old = samples.popleft().shifted
            self._s1 = list(map(sub, self._s1, old))
            self._s2 = list(map(sub, self._s2, map(mul, old, old)))

    def full(self) -> bool:
        return bool(self.samples) and (
            self.samples[-1].stamp_ns - self.samples[0].stamp_ns >= self.window_ns)

    def quiet(self, gyro_std: float, accel_std: float, max_gyro_mean: float) -> bool:
        """True when every gyro and accelerometer axis std is below its limit and every gyro
        mean within max_gyro_mean (stops at the first axis that fails)."""
        n = len(self.samples)
        s1, s2, ref = self._s1, self._s2, self._ref
        for i in range(6):
            m = s1[i] / n
            var = s2[i] / n - m * m
            if i < 3:
                if var >= gyro_std * gyro_std or abs(m + ref[i]) > max_gyro_mean:
                    return False
            elif var >= accel_std * accel_std:
                return False
        return True


@dataclass
class GyroIntegrator:
    """Integrates one IMU sample at a time: heading, its variance, and the gyro bias.

    Covariance over [yaw, bias_z] is kept as p_yaw, p_cross, p_bias (rad^2, rad^2/s, rad^2/s^2).
    The x and y biases are estimated with the same gain as z (same noise model per axis).
    """
    config: GyroConfig
    yaw: float = 0.0
    bias: tuple[float, float, float] = (0.0, 0.0, 0.0)     # x, y, z (rad/s)
    p_yaw: float = 0.0
    p_cross: float = 0.0
    p_bias: float = -1.0
    stamp_ns: int | None = None
    rate: tuple[float, float, float] = (0.0, 0.0, 0.0)     # bias-corrected x, y, z (rad/s)
    still: bool = False
    calibration_requested: bool = False
    bias_updates: int = 0
    _prev_gyro: tuple[float, float, float] = (0.0, 0.0, 0.0)
    _window: _Window | None = None
    _used_until_ns: int = -1
    _last_dt: float = 0.0
    _wheel_last_ns: int | None = None
    _wheel_motion_ns: int | None = None

    def __post_init__(self) -> None:
        if self.p_bias < 0:
            self.p_bias = self.config.initial_bias_sigma_rad_s ** 2
            self.bias = (self.bias[0], self.bias[1], float(self.config.initial_bias_z_rad_s))
        self._window = _Window(self.config.stillness_window_s)

    # -- wheel odometry gate -------------------------------------------------------------------
    def observe_wheels(self, stamp_ns: int, linear_m_s: float, angular_rad_s: float) -> None:
        """Record a wheel-odometry twist (m/s, rad/s); motion vetoes windows that hold it."""
        if self._wheel_last_ns is not None and stamp_ns < self._wheel_last_ns:
            self._wheel_motion_ns = None       # the wheel stream restarted (looping bag)
        self._wheel_last_ns = stamp_ns
        still = (abs(linear_m_s) <= self.config.wheel_still_linear_m_s
                 and abs(angular_rad_s) <= self.config.wheel_still_angular_rad_s)
        if not still:                          # NaN compares False, so it counts as motion
            self._wheel_motion_ns = stamp_ns

    def wheels_available(self, stamp_ns: int) -> bool:
        """True when a wheel-odometry twist arrived within wheel_timeout_s of stamp_ns."""
        return (self._wheel_last_ns is not None
                and abs(stamp_ns - self._wheel_last_ns) <= self.config.wheel_timeout_s * 1e9)

    # -- services ------------------------------------------------------------------------------
    def request_calibration(self) -> None:
        """Forget the bias confidence: the next still window re-estimates it (even if disabled)."""
        self.p_bias = self.config.initial_bias_sigma_rad_s ** 2
        self.p_cross = 0.0
        self.calibration_requested = True
        self._used_until_ns = -1
        self.still = False

    def reset_heading(self, yaw: float = 0.0) -> None:
        """Heading back to yaw (rad) with zero variance; the bias (the sensor's) is kept."""
        self.yaw = float(yaw)
        self.p_yaw = 0.0
        self.p_cross = 0.0
        self._window.clear()
        self.still = False
        self._used_until_ns = -1        # after a looping bag, stamps restart below it

    # -- main step -----------------------------------------------------------------------------
    def update(self, stamp_ns: int, gyro: Sequence[float], accel: Sequence[float]) -> ImuUpdate:
        """Take one raw sample: rates (rad/s, 3) and accelerations (m/s^2, 3) at stamp_ns."""
        g = (float(gyro[0]), float(gyro[1]), float(gyro[2]))
        a = (float(accel[0]), float(accel[1]), float(accel[2]))
        # One sum is finite exactly when every term is (sensor values never reach 1e308).
        if not math.isfinite(g[0] + g[1] + g[2] + a[0] + a[1] + a[2]):
            return ImuUpdate(False, rejection=ImuRejection.NON_FINITE,
                             note=f'non-finite rate {g} or acceleration {a}')
        step = classify_step(self.stamp_ns, stamp_ns, self.config.max_gap_s)
        if step is StampStep.REPEATED:
            return ImuUpdate(False, step, ImuRejection.REPEATED_STAMP,
                             note=f'duplicate stamp {stamp_ns} ns; sample not integrated')
        note = ''
        sample = _Sample(stamp_ns, g, a)
        if step is StampStep.BACKWARDS:
            note = (f'time went backwards by {(self.stamp_ns - stamp_ns) / 1e9:.3f} s '
                    '(looping bag?): heading reset to 0, bias estimate kept')
            self.reset_heading()
        elif step is StampStep.GAP:
            dt = (stamp_ns - self.stamp_ns) * 1e-9
            guess = (0.5 * (self._prev_gyro[2] + g[2]) - self.bias[2]) * dt
            note = (f'{dt:.3f} s gap (> max_gap_s {self.config.max_gap_s}): not integrated '
                    'across; heading variance widened')
            # The heading change across the gap is unknown: keep the heading and widen its
            # variance by the noise model over the gap plus the turn the edge rates suggest.
            self._propagate(dt)
            self.p_yaw += guess * guess
            self._window.clear()
            self.still = False
        elif step is StampStep.OK:
            dt = (stamp_ns - self.stamp_ns) * 1e-9
            self._last_dt = dt
            self._window.add(sample)
            estimating = self.config.bias_estimation or self.calibration_requested
            still = estimating and self._window_still(stamp_ns)
            if still:
                if not self.still:
                    # Stillness is decided over the whole window, so the robot was already still
                    # at its start: return to the heading held then.
                    first = self._window.samples[0]
                    self.yaw = first.yaw
                    self.p_yaw, self.p_cross = _returned_covariance(first.p_yaw, first.p_cross,
                                                                    self.p_bias)
                self._measure_bias(stamp_ns, dt)
            else:
                self.yaw += (0.5 * (self._prev_gyro[2] + g[2]) - self.bias[2]) * dt
                self._propagate(dt)
            self.still = still
        if step is not StampStep.OK:
            self._window.add(sample)
        sample.yaw, sample.p_yaw, sample.p_cross = self.yaw, self.p_yaw, self.p_cross
        self.stamp_ns = stamp_ns
        self._prev_gyro = g
        bx, by, bz = self.bias
        self.rate = (g[0] - bx, g[1] - by, g[2] - bz)
        return ImuUpdate(True, step, note=note, still=self.still)

    @property
    def heading_variance(self) -> float:
        """Published heading variance (rad^2): the filter's plus a term for the sample convention.

        Trapezoidal integration of samples that are interval means (or of instantaneous samples
        of a changing rate) is off by up to half a sample of rotation; that error does not
        accumulate (it telescopes), so it is added here and not to p_yaw.
        """
        half_sample = 0.5 * self.rate[2] * self._last_dt
        return self.p_yaw + half_sample * half_sample

    @property
    def heading(self) -> float:
        """Integrated heading wrapped into (-pi, pi] (rad)."""
        return float(wrap_angle(self.yaw))

    def rate_variance(self) -> float:
        """Variance (rad^2/s^2) of the latest bias-corrected rate sample, per axis."""
        if self._last_dt <= 0.0:
            return self.p_bias
        return self.config.noise_density ** 2 / self._last_dt + self.p_bias

    def _propagate(self, dt: float) -> None:
        # [yaw, bias]' = F [yaw, bias] with F = [[1, -dt], [0, 1]], plus white rate noise on yaw
        # and the bias random walk.
        self.p_yaw += (-2.0 * dt * self.p_cross + dt * dt * self.p_bias
                       + self.config.noise_density ** 2 * dt)
        self.p_cross -= dt * self.p_bias
        self.p_bias += self.config.bias_random_walk ** 2 * dt

    def _measure_bias(self, stamp_ns: int, dt: float) -> None:
        # Heading held (zero-velocity update), so only the bias random-walks; then every raw
        # sample not used before measures the bias.
        self.p_bias += self.config.bias_random_walk ** 2 * dt
        fresh = []
        for s in reversed(self._window.samples):
            if s.stamp_ns <= self._used_until_ns:
                break
            fresh.append(s.gyro)
        if not fresh:
            return
        m = len(fresh)
        zx, zy, zz = np.mean(fresh, axis=0).tolist() if m > 1 else fresh[0]
        r = self.config.noise_density ** 2 / max(dt, 1e-6) / m
        bx, by, bz = self.bias
        self.yaw, self.p_yaw, self.p_cross, self.p_bias, bx, by, bz = _zero_velocity_update(
            self.yaw, self.p_yaw, self.p_cross, self.p_bias, bx, by, bz, zx, zy, zz, r)
        self.bias = (bx, by, bz)
        self._used_until_ns = stamp_ns
        self.bias_updates += m
        # A requested calibration is done once a whole still window has been measured.
        self.calibration_requested = False

    def _window_still(self, stamp_ns: int) -> bool:
        cfg = self.config
        if not self._window.full() or not self._window.quiet(
            cfg.gyro_std_threshold_rad_s, cfg.accel_std_threshold_m_s2, cfg.max_gyro_bias_rad_s
        ):
            return False
        if self.wheels_available(stamp_ns) and self._wheel_motion_ns is not None:
            return self._wheel_motion_ns < self._window.samples[0].stamp_ns
        return True
