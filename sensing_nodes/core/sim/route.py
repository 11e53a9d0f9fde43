"""Scripted routes of a differential-drive robot: legs with trapezoidal velocity profiles.

A route is a list of legs written as short strings (so a ROS string-array parameter can hold it):

    wait SECONDS                      stand still
    straight METRES SPEED_M_S         drive straight (negative metres: backwards)
    turn DEGREES RATE_DEG_S           turn in place (positive: counter-clockwise)
    arc DEGREES RADIUS_M SPEED_M_S    drive forward along a circle (positive: to the left)

Every motion leg starts and ends at rest and ramps with the acceleration limits, so the motion
(distance travelled S(t) and heading change Theta(t), both cumulative) is known in closed form at
any time. The route repeats when time runs past its end.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

_ARITY = {'wait': 1, 'straight': 2, 'turn': 2, 'arc': 3}


@dataclass(frozen=True)
class Leg:
    """One leg: a trapezoidal profile of a progress variable u (m or rad) from 0 to u_total.

    Distance travelled is u * metres_per_u and heading change is u * radians_per_u.
    """

    text: str
    duration_s: float
    u_total: float = 0.0
    u_rate_max: float = 0.0        # peak du/dt actually reached
    u_accel: float = 0.0           # |d2u/dt2| on the ramps
    ramp_s: float = 0.0            # duration of each ramp
    metres_per_u: float = 0.0
    radians_per_u: float = 0.0

    def progress(self, t: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray]:
        """u, du/dt and d2u/dt2 at leg-local times t (s), t in [0, duration_s]."""
        if self.u_total == 0.0:
            zero = np.zeros_like(t)
            return zero, zero, zero
        a, ta, vm, T = self.u_accel, self.ramp_s, self.u_rate_max, self.duration_s
        t = np.clip(t, 0.0, T)
        rising, falling = t < ta, t > T - ta
        u = np.where(rising, 0.5 * a * t * t,
                     np.where(falling, self.u_total - 0.5 * a * (T - t) ** 2,
                              0.5 * a * ta * ta + vm * (t - ta)))
        du = np.where(rising, a * t, np.where(falling, a * (T - t), vm))
        ddu = np.where(rising, a, np.where(falling, -a, 0.0))
        return u, du, ddu


def _trapezoid(text: str, u_total: float, rate: float, accel: float,
               metres_per_u: float, radians_per_u: float) -> Leg:
    if u_total >= rate * rate / accel:
        ramp = rate / accel
        duration = 2.0 * ramp + (u_total - rate * ramp) / rate
    else:                              # too short to reach the rate: a triangle
        rate = math.sqrt(u_total * accel)
        ramp = rate / accel
        duration = 2.0 * ramp
    return Leg(text, duration, u_total, rate, accel, ramp, metres_per_u, radians_per_u)


def parse_leg(text: str, linear_accel_m_s2: float, angular_accel_rad_s2: float) -> Leg:
    """A leg from its text form; ValueError saying what is wrong with it."""
    words = str(text).split()
    if not words or words[0] not in _ARITY:
        raise ValueError(f'{text!r}: a leg starts with one of {", ".join(_ARITY)}')
    kind = words[0]
    if len(words) != 1 + _ARITY[kind]:
        raise ValueError(f'{text!r}: {kind} takes {_ARITY[kind]} number(s)')
    try:
        values = [float(w) for w in words[1:]]
    except ValueError:
        raise ValueError(f'{text!r}: not a number') from None
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f'{text!r}: numbers must be finite')
    if kind == 'wait':
        if values[0] <= 0.0:
            raise ValueError(f'{text!r}: wait needs a positive duration')
        return Leg(text, values[0])
    if kind == 'straight':
        distance, speed = values
        if distance == 0.0 or speed <= 0.0:
            raise ValueError(f'{text!r}: straight needs a non-zero distance and a positive speed')
        return _trapezoid(text, abs(distance), speed, linear_accel_m_s2,
                          math.copysign(1.0, distance), 0.0)
    if kind == 'turn':
        degrees, rate = values
        if degrees == 0.0 or rate <= 0.0:
            raise ValueError(f'{text!r}: turn needs a non-zero angle and a positive rate')
        return _trapezoid(text, math.radians(abs(degrees)), math.radians(rate),
                          angular_accel_rad_s2, 0.0, math.copysign(1.0, degrees))
    degrees, radius, speed = values
    if degrees == 0.0 or radius <= 0.0 or speed <= 0.0:
        raise ValueError(f'{text!r}: arc needs a non-zero angle, a positive radius and speed')
    # Ramp so that neither the linear nor the angular acceleration limit is exceeded.
    accel = min(linear_accel_m_s2, angular_accel_rad_s2 * radius)
    return _trapezoid(text, radius * math.radians(abs(degrees)), speed, accel,
                      1.0, math.copysign(1.0 / radius, degrees))


@dataclass(frozen=True)
class Motion:
    """Body motion at a set of times: cumulative distance S (m) and heading change Theta (rad)
    since the start, forward speed v (m/s), yaw rate w (rad/s), forward acceleration dv/dt
    (m/s^2)."""

    distance: NDArray[np.float64]
    heading: NDArray[np.float64]
    speed: NDArray[np.float64]
    yaw_rate: NDArray[np.float64]
    accel: NDArray[np.float64]


class Route:
    """A scripted route: legs back to back, repeated forever."""

    def __init__(self, legs: list[str] | tuple[str, ...], linear_accel_m_s2: float,
                 angular_accel_rad_s2: float) -> None:
        if not legs:
            raise ValueError('a route needs at least one leg')
        self.legs = [parse_leg(t, linear_accel_m_s2, angular_accel_rad_s2) for t in legs]
        durations = np.array([leg.duration_s for leg in self.legs])
        self.starts = np.concatenate(([0.0], np.cumsum(durations)[:-1]))
        self.period_s = float(durations.sum())
        totals = [(leg.u_total * leg.metres_per_u, leg.u_total * leg.radians_per_u)
                  for leg in self.legs]
        cumulative = np.cumsum(np.vstack(([(0.0, 0.0)], totals)), axis=0)
        self._distance0, self._heading0 = cumulative[:-1, 0], cumulative[:-1, 1]
        self.loop_distance_m, self.loop_heading_rad = cumulative[-1]
        self.path_length_m = float(sum(abs(leg.u_total * leg.metres_per_u) for leg in self.legs))

    def motion(self, t: ArrayLike) -> Motion:
        """Motion at route times t (s since the route started, >= 0), vectorised."""
        t = np.asarray(t, dtype=float)
        loops = np.floor(t / self.period_s)
        local = t - loops * self.period_s
        index = np.clip(np.searchsorted(self.starts, local, side='right') - 1,
                        0, len(self.legs) - 1)
        distance = loops * self.loop_distance_m + self._distance0[index]
        heading = loops * self.loop_heading_rad + self._heading0[index]
        speed, yaw_rate, accel = (np.zeros_like(t) for _ in range(3))
        for i in np.unique(index):
            leg = self.legs[i]
            if leg.u_total == 0.0:
                continue
            mask = index == i
            u, du, ddu = leg.progress(local[mask] - self.starts[i])
            distance[mask] += u * leg.metres_per_u
            heading[mask] += u * leg.radians_per_u
            speed[mask] = du * leg.metres_per_u
            yaw_rate[mask] = du * leg.radians_per_u
            accel[mask] = ddu * leg.metres_per_u
        return Motion(distance, heading, speed, yaw_rate, accel)
