"""complementary_fusion's parameters (names as in its YAML file and on the node, defaults,
ranges, descriptions) and the one translation of a parameter dict into the fusion's whole
configuration (SessionConfig): the node declares the parameters of these tables and calls
`session_config` with their values, as the offline tools do with a YAML file's, so the two
cannot disagree."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from sensing_nodes.core.fusion.complementary import FusionSettings
from sensing_nodes.core.fusion.ekf import EkfSettings
from sensing_nodes.core.fusion.inputs import (
    IMU,
    IMU_SOURCES,
    INPUT_DEFAULTS,
    INPUT_DESCRIPTIONS,
    INPUTS,
    SCAN,
    WHEEL,
    InputConfig,
    input_config,
    with_mask,
)
from sensing_nodes.paths import config_file

NODE_NAME = 'complementary_fusion'
METHODS = ('ekf', 'complementary')


@dataclass(frozen=True)
class Parameter:
    """One parameter: its default (which also fixes its type), what it means, and its inclusive
    range where it is a number."""

    default: Any
    description: str
    minimum: float | None = None
    maximum: float | None = None


# Every method's, in the node's declaration order.
PARAMETERS: dict[str, Parameter] = {
    'method': Parameter('ekf', "'ekf' (docs/fusion.md) or 'complementary' (the seed's filter)"),
    'use_wheel_odom': Parameter(True, 'fuse /wheel/odom'),
    'use_imu': Parameter(True, 'fuse /imu/data'),
    'use_scan_match_position': Parameter(True, 'fuse x/y of scan matching'),
    'use_scan_match_heading': Parameter(True, 'fuse the heading of scan matching'),
    # a number or 'auto': the node declares it with dynamic typing
    'alpha': Parameter(0.98, "complementary: weight of the gyro-propagated heading, in [0, 1], "
                             "or 'auto' to derive it each update from the two variances"),
    'reorder_window_s': Parameter(2.0, 'longest an input may lag the newest (stamp time) and '
                                       'still be fused in stamp order; later messages are '
                                       'dropped and counted', 0.0, 10.0),
    'flush_after_s': Parameter(0.5, 'wall time without input after which held inputs are '
                                    'processed', 0.01, 60.0),
    'max_gap_s': Parameter(2.0, 'an input silent longer than this (stamp time) restarts its '
                                'increments', 0.001, 3600.0),
    'reset_on_backwards_jump_s': Parameter(
        0.0, "an input stamp more than this before the same input's previous one means time "
             'went backwards (looping bag): the filter resets', 0.0),
    'input_timeout_s': Parameter(2.0, 'an enabled input silent for this long is reported '
                                      'missing', 0.01),
    'startup_timeout_s': Parameter(10.0, 'an enabled input not heard yet is waited for this long '
                                         '(stamp time since the first input) before the filter '
                                         'starts without it', 0.01),
    'odom_frame': Parameter('odom', 'frame of the fused pose'),
    'base_frame': Parameter('base_link', 'child frame of the fused pose'),
    'publish_tf': Parameter(True, 'broadcast odom_frame -> base_frame on /tf with each output, '
                                  'stamped as the output (one owner per tree: turn it off where '
                                  'another node owns it)'),
    'publish_rate_hz': Parameter(
        30.0, 'outputs (/odometry/filtered, /tf) per second of stamp time: the first fused '
              'output in each new period goes out, with its stamp; 0: one per wheel and '
              'scan-match input (every input still filtered)', 0.0, 1000.0),
    'wheel_odom.topic': Parameter('/wheel/odom', 'wheel odometry topic'),
    'imu.topic': Parameter('/imu/data', 'IMU topic (sensor_msgs/Imu)'),
    'level_with_imu_tilt': Parameter(
        False, "ekf, imu.source 'orientation': count only the horizontal part of body "
               "velocities (the IMU's roll and pitch), for a robot on slopes"),
}

# The scan matches each method takes.
SCAN_TOPIC: dict[str, Parameter] = {
    'ekf': Parameter('/scan_match/keyframe_odom', 'keyframe-relative scan matches (icp_matcher)'),
    'complementary': Parameter('/scan_match/odom', 'scan matching poses (icp_matcher)'),
}


def _ekf_parameters() -> dict[str, Parameter]:
    """method 'ekf' only: the IMU's source and mount, each input's (INPUT_DEFAULTS), the
    process noise."""
    table = {'imu.source': Parameter(
        'integrated', "'integrated' (gyro_integrator's heading), 'orientation' (the IMU's own "
                      "orientation) or 'rate' (raw gyro rate, bias estimated in the filter)"),
        'imu.estimate_bias': Parameter(
            False, "imu.source 'integrated': estimate the integrator's remaining bias (its "
                   'heading increments measure the turn plus bias x interval; observable where '
                   "another input measures the heading absolutely: a local map's matches)")}
    for axis in ('roll', 'pitch', 'yaw'):
        table[f'imu.mount_{axis}_rad'] = Parameter(
            0.0, f'IMU mount {axis} in base_link (rad, ZYX); upside down: roll = pi; the '
                 "fallback where /tf_static gives no base_frame -> the Imu's frame_id",
            -2 * math.pi, 2 * math.pi)
    for name in INPUTS:
        for key, default in INPUT_DEFAULTS[name].items():
            numeric = isinstance(default, float) and key != 'delay_s'   # delay_s may be < 0
            table[f'{name}.{key}'] = Parameter(default, INPUT_DESCRIPTIONS[key],
                                               0.0 if numeric else None)
    defaults = EkfSettings()
    table.update({
        'ekf.accel_noise_density': Parameter(
            defaults.accel_noise_density, 'how fast vx, vy may change (m/s^2/sqrt(Hz))', 1e-6),
        'ekf.angular_accel_noise_density': Parameter(
            defaults.angular_accel_noise_density,
            'how fast the yaw rate may change (rad/s^2/sqrt(Hz))', 1e-6),
        'ekf.bias_random_walk': Parameter(defaults.bias_random_walk,
                                          'gyro bias random walk (rad/s/sqrt(s))', 0.0),
        'ekf.initial_bias_std': Parameter(defaults.initial_bias_std,
                                          'gyro bias std before any input (rad/s)', 0.0),
    })
    return table


EKF_PARAMETERS: dict[str, Parameter] = _ekf_parameters()


def parameters_of(method: str) -> dict[str, Parameter]:
    """Every parameter the node declares with this method, in declaration order."""
    table = dict(PARAMETERS)
    if method == 'ekf':
        table.update(EKF_PARAMETERS)
    if method in SCAN_TOPIC:
        table['scan_match.topic'] = SCAN_TOPIC[method]
    return table


class ConfigError(ValueError):
    """A parameter value the fusion cannot run with (the node exits with status 2 on it)."""

    def __init__(self, name: str, problem: str, value: Any = None) -> None:
        detail = f' (got {value!r})' if value is not None else ''
        super().__init__(f"parameter '{name}' {problem}{detail}")
        self.name, self.problem, self.value = name, problem, value


def _require(condition: bool, name: str, problem: str, value: Any = None) -> None:
    if not condition:
        raise ConfigError(name, problem, value)


@dataclass(frozen=True)
class SessionConfig:
    """Everything the fusion runs with: the filter, its inputs and the timeline's settings (s)."""

    method: str                           # 'ekf' or 'complementary'
    enabled: Mapping[str, bool]           # per input (WHEEL, IMU, SCAN)
    inputs: tuple[InputConfig, ...]       # ekf: the enabled inputs (masks applied); else ()
    ekf: EkfSettings
    complementary: FusionSettings
    topics: Mapping[str, str]             # per input
    imu_source: str                       # one of IMU_SOURCES ('integrated' for complementary)
    imu_mount_rpy: tuple[float, float, float]   # rad: the fallback mount of the IMU frame
    level_with_imu_tilt: bool
    reorder_window_s: float
    flush_after_s: float                  # wall time (the node's idle flush)
    max_gap_s: float
    reset_on_backwards_jump_s: float
    input_timeout_s: float
    startup_timeout_s: float              # stamp time: how long a silent input is waited for
    odom_frame: str
    base_frame: str
    publish_tf: bool
    publish_rate_hz: float                # stamp time; 0: every output

    @property
    def input_map(self) -> dict[str, InputConfig]:
        """The EKF inputs by name (empty for the complementary filter)."""
        return {cfg.name: cfg for cfg in self.inputs}


def flatten(params: Mapping[str, Any], prefix: str = '') -> dict[str, Any]:
    """{'imu': {'source': 'rate'}} -> {'imu.source': 'rate'} (dotted names, as ROS 2 reads a
    parameter file's nesting); already dotted names pass unchanged."""
    out: dict[str, Any] = {}
    for key, value in params.items():
        if isinstance(value, Mapping):
            out.update(flatten(value, f'{prefix}{key}.'))
        else:
            out[f'{prefix}{key}'] = value
    return out


def _value(values: Mapping[str, Any], name: str, parameter: Parameter) -> Any:
    """values[name] (the default when absent) checked against the parameter's type and range,
    as the node's declaration checks it."""
    value = values.get(name, parameter.default)
    default = parameter.default
    if isinstance(default, bool):
        _require(isinstance(value, bool), name, 'must be true or false', value)
    elif isinstance(default, (int, float)):
        _require(isinstance(value, (int, float)) and not isinstance(value, bool), name,
                 'must be a number', value)
        value = float(value)
        low, high = parameter.minimum, parameter.maximum
        _require((low is None or value >= low) and (high is None or value <= high), name,
                 f'must be within [{-math.inf if low is None else low:g}, '
                 f'{math.inf if high is None else high:g}]', value)
    elif isinstance(default, str):
        _require(isinstance(value, str), name, 'must be a string', value)
    else:
        _require(isinstance(value, (list, tuple)), name, 'must be a list', value)
    return value


def _alpha(value: Any) -> float | None:
    """alpha: a number in [0, 1], or None for 'auto'."""
    if value == 'auto':
        return None
    _require(isinstance(value, (int, float)) and not isinstance(value, bool)
             and 0.0 <= value <= 1.0, 'alpha', "must be a number in [0, 1] or 'auto'", value)
    return float(value)


def session_config(params: Mapping[str, Any]) -> SessionConfig:
    """The fusion's configuration from complementary_fusion's parameters, nested as in its YAML
    file or with dotted names as the node declares them (absent ones: their defaults); the
    node's validation (ConfigError names the parameter)."""
    flat = flatten(params)
    method = _value(flat, 'method', PARAMETERS['method'])
    _require(method in METHODS, 'method', "must be 'ekf' or 'complementary'", method)
    table = parameters_of(method)
    v = {name: (_alpha(flat.get(name, p.default)) if name == 'alpha' else _value(flat, name, p))
         for name, p in table.items()}
    enabled = {WHEEL: v['use_wheel_odom'], IMU: v['use_imu'],
               SCAN: v['use_scan_match_position'] or v['use_scan_match_heading']}
    _require(any(enabled.values()), 'use_*', 'at least one input must be enabled')
    _require(bool(v['odom_frame']) and bool(v['base_frame']), 'odom_frame/base_frame',
             'must not be empty')
    imu_source, mount, inputs, ekf = 'integrated', (0.0, 0.0, 0.0), (), EkfSettings()
    if method == 'ekf':
        imu_source = v['imu.source']
        _require(imu_source in IMU_SOURCES, 'imu.source', f'must be one of {IMU_SOURCES}',
                 imu_source)
        mount = tuple(v[f'imu.mount_{axis}_rad'] for axis in ('roll', 'pitch', 'yaw'))
        inputs = _ekf_inputs(v, enabled, imu_source)
        ekf = EkfSettings(**{key: v[f'ekf.{key}'] for key in (
            'accel_noise_density', 'angular_accel_noise_density', 'bias_random_walk',
            'initial_bias_std')})
    complementary = FusionSettings(
        use_wheel=v['use_wheel_odom'], use_gyro=v['use_imu'],
        use_scan_position=v['use_scan_match_position'],
        use_scan_heading=v['use_scan_match_heading'], alpha=v['alpha'], max_gap_s=v['max_gap_s'])
    return SessionConfig(
        method=method, enabled=enabled, inputs=inputs, ekf=ekf, complementary=complementary,
        topics={WHEEL: v['wheel_odom.topic'], IMU: v['imu.topic'], SCAN: v['scan_match.topic']},
        imu_source=imu_source, imu_mount_rpy=mount, level_with_imu_tilt=v['level_with_imu_tilt'],
        reorder_window_s=v['reorder_window_s'], flush_after_s=v['flush_after_s'],
        max_gap_s=v['max_gap_s'], reset_on_backwards_jump_s=v['reset_on_backwards_jump_s'],
        input_timeout_s=v['input_timeout_s'], startup_timeout_s=v['startup_timeout_s'],
        odom_frame=v['odom_frame'],
        base_frame=v['base_frame'], publish_tf=v['publish_tf'],
        publish_rate_hz=v['publish_rate_hz'])


def _ekf_inputs(v: Mapping[str, Any], enabled: Mapping[str, bool], imu_source: str
                ) -> tuple[InputConfig, ...]:
    """The enabled inputs' EKF configurations (use_scan_match_position / _heading switch the
    scan's quantities off); the problems of an enabled one raise ConfigError."""
    window_s, max_gap_s = v['reorder_window_s'], v['max_gap_s']
    # The bias is a state for the raw rate always, for the integrated heading on request.
    bias = imu_source == 'rate' or (imu_source == 'integrated' and v['imu.estimate_bias'])
    fixed = {WHEEL: {}, IMU: {'gyro_bias': bias}, SCAN: {'keyframes': True}}
    configs = []
    for name in INPUTS:
        values = {key: v[f'{name}.{key}'] for key in INPUT_DEFAULTS[name]}
        try:
            cfg = input_config(name, values, max_gap_s=max_gap_s, **fixed[name])
        except ValueError as error:
            raise ConfigError(f'{name}.mask', str(error), values['mask']) from None
        if not enabled[name]:
            continue
        for field, problem, value in cfg.problems():
            raise ConfigError(f'{name}.{field}', problem, value)
        # A retimed input lags (or leads) the others by delay_s in stamp time: the reorder
        # buffer must hold the others that long, or its messages are dropped as late.
        _require(abs(cfg.delay_s) <= window_s, f'{name}.delay_s',
                 f'must be within the reorder window (|delay_s| <= reorder_window_s = '
                 f'{window_s:g} s)', cfg.delay_s)
        if name == SCAN:
            cfg = with_mask(cfg, **({} if v['use_scan_match_position'] else
                                    {'x': False, 'y': False}),
                            **({} if v['use_scan_match_heading'] else {'yaw': False}))
        configs.append(cfg)
    return tuple(configs)


def load_params(*files: str | Path) -> dict[str, Any]:
    """complementary_fusion's parameters from ROS 2 parameter files (dotted names), a later
    file's values over an earlier's, as the node reads several --params-file."""
    merged: dict[str, Any] = {}
    for path in files:
        data = yaml.safe_load(Path(path).read_text()) or {}
        for node in ('/**', NODE_NAME, f'/{NODE_NAME}'):
            section = data.get(node, {})
            if isinstance(section, Mapping):
                merged.update(flatten(section.get('ros__parameters', {}) or {}))
    return merged


def default_config(*files: str | Path, overrides: Mapping[str, Any] | None = None
                   ) -> SessionConfig:
    """The configuration of config/complementary_fusion.yaml, then `files` over it, then
    `overrides` (as the node starts in sensing_pipeline and the launch file)."""
    params = load_params(config_file(f'{NODE_NAME}.yaml'), *files)
    return session_config({**params, **flatten(overrides or {})})
