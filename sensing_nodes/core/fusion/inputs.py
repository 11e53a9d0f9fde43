"""The fusion's inputs: their names and processing order, one message of an input as the filters
read it (Reading), what each input contributes (InputConfig: mask, pose mode, covariance source,
noise model, gate, time offsets) and its parameters' defaults. Shared by both filters, the
session, the message conversion (ros/fusion_readings.py) and the tools.

Poses in m and rad (base_link in the source's odom frame, or relative to a keyframe), stamps in
ns, covariances 3x3 over (x, y, yaw) or (vx, vy, wz).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.geometry.se2 import Pose2
from sensing_nodes.parameters import Param, ParameterTable

WHEEL, IMU, SCAN = 'wheel_odom', 'imu', 'scan_match'
INPUTS = (WHEEL, IMU, SCAN)
# Processing rank at equal stamps: dead reckoning up to a stamp is in before the scan match
# at that stamp is fused.
RANK = {WHEEL: 0, IMU: 1, SCAN: 2}
# What the IMU input reads of sensor_msgs/Imu: gyro_integrator's heading, the IMU's own
# orientation, or its raw rate (the bias estimated in the EKF).
IMU_SOURCES = ('integrated', 'orientation', 'rate')
QUANTITIES = ('x', 'y', 'yaw', 'vx', 'vy', 'vyaw')
POSE_MODES = ('absolute', 'relative', 'differential')


@dataclass(frozen=True)
class NoiseModel:
    """Variance of a differential pose input's increment, used when the source publishes a
    static or zero covariance: x and y get variance_per_m per metre travelled (plus
    xy_variance_per_rad per radian turned: where the source's point is not the one it turns
    about), yaw variance_per_rad per radian turned (plus yaw_variance_per_m per metre), each
    at least min_variance."""

    variance_per_m: float = 1e-4          # m^2 per m
    variance_per_rad: float = 1e-3        # rad^2 per rad
    yaw_variance_per_m: float = 1e-4      # rad^2 per m
    yaw_variance_per_s: float = 0.0       # rad^2 per s (a gyro's white rate noise density^2)
    xy_variance_per_rad: float = 0.0      # m^2 per rad
    min_variance: float = 1e-12

    def increment_covariance(self, increment: Pose2, dt: float = 0.0) -> NDArray[np.float64]:
        """3x3 covariance over (x, y, yaw) of a body-frame increment over dt seconds."""
        distance = math.hypot(increment[0], increment[1])
        xy = max(self.variance_per_m * distance + self.xy_variance_per_rad * abs(increment[2]),
                 self.min_variance)
        yaw = max(self.variance_per_rad * abs(increment[2]) + self.yaw_variance_per_m * distance
                  + self.yaw_variance_per_s * dt, self.min_variance)
        return np.diag([xy, xy, yaw])


@dataclass(frozen=True)
class InputConfig:
    """What one input contributes: mask over QUANTITIES, how its pose is read, its gate.

    covariance 'auto' uses the message's covariance unless it is static (does not change
    between messages), zero, or (differential) does not grow by compounding, then the noise
    model; 'message' and 'model' force one of them.
    """

    name: str
    mask: tuple[bool, bool, bool, bool, bool, bool] = (False,) * 6
    pose_mode: str = 'differential'
    covariance: str = 'auto'
    noise: NoiseModel = NoiseModel()
    twist_variance: tuple[float, float, float] = (1e-4, 1e-4, 1e-4)  # when the message has none
    covariance_scale: float = 1.0        # the message's covariance times this (>= 1: distrust)
    # The gate: a reading is refused when its innovation lies beyond this probability's
    # chi-square quantile for its rows (squared Mahalanobis distance).
    gate_probability: float = 0.999
    # The input is a gyro whose bias the filter estimates: a vyaw rate measures wz + bias, a
    # differential yaw measures the heading change + bias x interval.
    gyro_bias: bool = False
    keyframes: bool = False              # pose is relative to a keyframe (scan matcher)
    # Scan matches in a local map's frame (Reading.map_ns): how far that frame may drift from
    # the fused odom frame per metre travelled, x and y (m^2/m) and yaw (rad^2/m), the map
    # offset's random walk.
    map_variance_per_m: float = 0.0
    map_yaw_variance_per_m: float = 0.0
    max_gap_s: float = 2.0               # differential: no increment across a longer silence
    # The reading's yaw is the heading this long before its stamp (s): the fusion reads it as
    # yaw + (the reading's yaw rate) x heading_delay_s. A gyro integrator whose samples are
    # the mean rate over the sample period before their stamp (a delta-angle IMU, as
    # sensor_sim's) and which integrates them by the trapezoid lags by half a period.
    heading_delay_s: float = 0.0
    # The input's messages describe the robot at stamp - delay_s (s; < 0: after the stamp): the
    # whole reading is retimed where messages are read (ros/fusion_readings.py), so it is fused,
    # ordered and published at that time. The node bounds it by its reorder window.
    delay_s: float = 0.0

    def problems(self) -> list[tuple[str, str, object]]:
        """(field, problem, value) for each setting the filter cannot run with."""
        out: list[tuple[str, str, object]] = []
        if self.pose_mode not in POSE_MODES:
            out.append(('pose_mode', f'must be one of {POSE_MODES}', self.pose_mode))
        if self.covariance not in ('auto', 'message', 'model'):
            out.append(('covariance', "must be 'auto', 'message' or 'model'", self.covariance))
        if not (math.isfinite(self.covariance_scale) and self.covariance_scale > 0.0):
            out.append(('covariance_scale', 'must be finite and > 0', self.covariance_scale))
        if not (0.5 <= self.gate_probability < 1.0):
            out.append(('gate_probability', 'must be in [0.5, 1) (the gate cannot be switched '
                        'off)', self.gate_probability))
        if not any(self.mask):
            out.append(('mask', 'must select at least one of ' + ', '.join(QUANTITIES),
                        self.mask))
        for name in ('variance_per_m', 'variance_per_rad', 'yaw_variance_per_m',
                     'yaw_variance_per_s', 'xy_variance_per_rad', 'min_variance'):
            value = getattr(self.noise, name)
            if not (math.isfinite(value) and value >= 0.0):
                out.append((name, 'must be finite and >= 0', value))
        for name in ('map_variance_per_m', 'map_yaw_variance_per_m'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                out.append((name, 'must be finite and >= 0', value))
        if not all(math.isfinite(v) and v > 0.0 for v in self.twist_variance):
            out.append(('twist_variance', 'must be finite and > 0', self.twist_variance))
        if not (math.isfinite(self.heading_delay_s) and self.heading_delay_s >= 0.0):
            out.append(('heading_delay_s', 'must be finite and >= 0', self.heading_delay_s))
        if not math.isfinite(self.delay_s):
            out.append(('delay_s', 'must be finite', self.delay_s))
        return out



@dataclass(frozen=True)
class Reading:
    """One input message, already in base_link / the source's odom frame (m, rad, s).

    pose/pose_covariance: a pose (absolute or cumulative); twist/twist_covariance: body
    velocities (vx, vy, wz); for a keyframe input, pose is relative to keyframe_ns and
    new_keyframe says this stamp starts the next keyframe (pose None: no match, keyframe only),
    or pose is base_link in the frame of the local map map_ns (named by its first scan's stamp).
    """

    stamp_ns: int
    pose: Pose2 | None = None
    pose_covariance: NDArray[np.float64] | None = None
    twist: tuple[float, float, float] | None = None
    twist_covariance: NDArray[np.float64] | None = None
    keyframe_ns: int | None = None
    new_keyframe: bool = False
    map_ns: int | None = None



@dataclass
class DeltaAngles:
    """A gyro's z rates (rad/s) summed into a heading (rad) for the EKF's IMU input with
    imu.source 'rate': each sample taken as the mean rate over the interval since the previous
    one (a delta-angle IMU, as sensor_sim's), no bias removed (the EKF estimates it:
    InputConfig.gyro_bias); its variance (rad^2) grows by the rate's variance x interval^2.
    Across a silence longer than max_gap_s (or a stamp not after the previous) nothing is
    added: the filter does not chain the input's increments across it either."""

    max_gap_s: float
    yaw: float = 0.0
    variance: float = 0.0
    stamp_ns: int | None = None

    def add(self, stamp_ns: int, rate: float, rate_variance: float) -> None:
        previous, self.stamp_ns = self.stamp_ns, stamp_ns
        if previous is None or not 0 < stamp_ns - previous <= self.max_gap_s * 1e9:
            return
        dt = (stamp_ns - previous) * 1e-9
        self.yaw += rate * dt
        self.variance += rate_variance * dt * dt

    def reset(self) -> None:
        self.yaw, self.variance, self.stamp_ns = 0.0, 0.0, None


def with_mask(cfg: InputConfig, **quantities: bool) -> InputConfig:
    """cfg with the named QUANTITIES switched on or off."""
    mask = list(cfg.mask)
    for name, used in quantities.items():
        mask[QUANTITIES.index(name)] = used
    return replace(cfg, mask=tuple(mask))


def mask_from_names(names: list[str] | tuple[str, ...]) -> tuple[bool, ...]:
    """Mask tuple from quantity names (e.g. ['x', 'y', 'yaw']); ValueError for unknown ones."""
    unknown = [n for n in names if n not in QUANTITIES]
    if unknown:
        raise ValueError(f'unknown quantities {unknown}: use {list(QUANTITIES)}')
    return tuple(q in names for q in QUANTITIES)


def mask_names(mask: tuple[bool, ...]) -> list[str]:
    """Mask tuple -> the names of the quantities it selects."""
    return [q for q, used in zip(QUANTITIES, mask) if used]


# Each input's settings as the fusion node's parameters (`<input>.<field>`) give them by default:
# one table for the node, the YAML files and the tools that run the core over a bag. max_gap_s
# 0 is the node's max_gap_s (input_config resolves it).
INPUT_DEFAULTS: dict[str, InputConfig] = {
    WHEEL: InputConfig(WHEEL, mask=mask_from_names(['x', 'y', 'yaw']), covariance='auto',
                       noise=NoiseModel(1e-4, 1e-3, 1e-4, 0.0), max_gap_s=0.0),
    IMU: InputConfig(IMU, mask=mask_from_names(['yaw']), covariance='model',
                     noise=NoiseModel(0.0, 0.0, 0.0, 1e-8),
                     # gyro_integrator's max_gap_s: across a longer silence of its input it holds
                     # the heading (the turn in the gap is not in its output), so no increment
                     # spans one.
                     max_gap_s=0.5),
    SCAN: InputConfig(SCAN, mask=mask_from_names(['x', 'y', 'yaw']), covariance='message',
                      noise=NoiseModel(1e-4, 1e-3, 1e-4, 0.0), max_gap_s=0.0),
}
# An input's gap where neither the node's nor its own is given.
_DEFAULT_GAP_S = InputConfig('').max_gap_s


# What each per-input parameter means (the node's parameter descriptions) and its range, by
# InputConfig field.
INPUT_PARAMS: dict[str, Param] = {
    'mask': Param('quantities fused, of x, y, yaw, vx, vy, vyaw (robot_localization order)',
                  to_value=mask_names, from_value=lambda names: mask_from_names(list(names))),
    'pose_mode': Param("pose quantities: 'absolute', 'relative' (to the first message) or "
                       "'differential' (the motion between consecutive messages)"),
    'covariance': Param("'auto' (the message's unless static or zero, then the noise model), "
                        "'message' or 'model'"),
    'covariance_scale': Param("the message's covariance times this (distrust: > 1)", 0.0),
    'noise.variance_per_m': Param('noise model: x/y variance per metre travelled (m^2/m)', 0.0),
    'noise.variance_per_rad': Param('noise model: yaw variance per radian turned (rad^2/rad)',
                                    0.0),
    'noise.yaw_variance_per_m': Param('noise model: yaw variance per metre travelled (rad^2/m)',
                                      0.0),
    'noise.yaw_variance_per_s': Param('noise model: yaw variance per second (rad^2/s)', 0.0),
    'noise.xy_variance_per_rad': Param('noise model: x/y variance per radian turned (m^2/rad), '
                                       "where the source's point is not the one the robot "
                                       'turns about', 0.0),
    'twist_variance': Param('vx, vy, vyaw variances when the message has none'),
    'gate_probability': Param('refuse a reading whose innovation lies beyond this probability of '
                              'a consistent one (the chi-square quantile of its rows; the gate '
                              'cannot be off)', 0.5, 1.0),
    'max_gap_s': Param('differential: no increment across a longer silence of this input (s); '
                       "0 = the node's max_gap_s, else the shorter of the two", 0.0),
    'heading_delay_s': Param("how far the input's heading lags its stamp (s): its yaw is read as "
                             'yaw + yaw rate x this (sensor_sim: half its IMU period)', 0.0),
    'delay_s': Param("how far the input's stamps lag the robot (s): a message stamped t is fused "
                     'and published as at t - this (< 0: stamps early); within '
                     '+-reorder_window_s'),
    'map_variance_per_m': Param("matches in a local map's frame: how far the map may drift from "
                                'the fused odom frame, x and y variance per metre travelled '
                                '(m^2/m)', 0.0),
    'map_yaw_variance_per_m': Param("matches in a local map's frame: the map's heading drift, "
                                    'variance per metre travelled (rad^2/m)', 0.0),
}
# What no input's parameters set (the input's kind decides), and the fields of one input only.
INPUT_INTERNAL = frozenset({'name', 'gyro_bias', 'keyframes', 'noise.min_variance'})
INPUT_ONLY = {'heading_delay_s': IMU, 'map_variance_per_m': SCAN, 'map_yaw_variance_per_m': SCAN}


def input_internal(name: str) -> frozenset[str]:
    """The InputConfig fields that are no parameter of input `name`."""
    return INPUT_INTERNAL | {f for f, only in INPUT_ONLY.items() if only != name}


INPUT_PARAMETERS: dict[str, ParameterTable[InputConfig]] = {
    name: ParameterTable(INPUT_DEFAULTS[name], described=INPUT_PARAMS, prefixes={'noise': ''},
                         internal=input_internal(name)) for name in INPUTS}


def with_fixed(cfg: InputConfig, **fixed) -> InputConfig:
    """An input as its parameters give it, with what its kind decides (`fixed`: keyframes,
    gyro_bias, max_gap_s: the node-wide gap, which the input's own max_gap_s, when > 0,
    shortens)."""
    if cfg.max_gap_s > 0.0:
        fixed = {**fixed, 'max_gap_s': min(cfg.max_gap_s, fixed.get('max_gap_s', cfg.max_gap_s))}
    else:
        fixed = {'max_gap_s': _DEFAULT_GAP_S, **fixed}
    return replace(cfg, **fixed)


def input_config(name: str, values: dict, **fixed) -> InputConfig:
    """InputConfig of input `name` from its parameter values (by field name; missing ones: its
    INPUT_DEFAULTS), unchecked (problems() tells), with `fixed` (with_fixed). ValueError for an
    unknown quantity in the mask."""
    return with_fixed(INPUT_PARAMETERS[name].build(values), **fixed)
