"""complementary_fusion's parameters as one dataclass (FusionParameters: names as in its YAML
file and on the node, defaults, ranges and descriptions in its tables) and the one translation
of them into the fusion's whole configuration (SessionConfig): the node declares a table's
parameters and translates their values, as the offline tools do with a parameter file's, so
the two cannot disagree."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sensing_nodes.core.fusion.complementary import FusionSettings
from sensing_nodes.core.fusion.ekf import EkfSettings
from sensing_nodes.core.fusion.inputs import (
    IMU,
    IMU_SOURCES,
    INPUT_DEFAULTS,
    INPUT_PARAMS,
    INPUTS,
    SCAN,
    WHEEL,
    InputConfig,
    input_internal,
    with_fixed,
    with_mask,
)
from sensing_nodes.parameters import (
    Param,
    ParameterError,
    ParameterTable,
    flatten,
    load_parameters,
)
from sensing_nodes.paths import config_file

NODE_NAME = 'complementary_fusion'
METHODS = ('ekf', 'complementary')
# The scan matches each method takes.
SCAN_TOPICS = {'ekf': '/scan_match/keyframe_odom', 'complementary': '/scan_match/odom'}
# The IMU topic each source reads where imu.topic is empty: gyro_integrator's heading, an IMU's
# own orientation, the driver's raw rates (REP 145's names). The complementary filter reads the
# integrated heading.
IMU_TOPICS = {'integrated': '/imu/data', 'orientation': '/imu/data', 'rate': '/imu/data_raw'}


@dataclass(frozen=True)
class FusionParameters:
    """complementary_fusion's parameters: the method, which inputs it fuses and their topics,
    the timeline (s), frames and outputs; with method 'ekf' also the IMU's source and fallback
    mount (roll, pitch, yaw in base_link, rad), each input's settings (max_gap_s 0: the node's)
    and the filter's process noise."""

    method: str = 'ekf'
    use_wheel_odom: bool = True
    use_imu: bool = True
    use_scan_match_position: bool = True
    use_scan_match_heading: bool = True
    alpha: float | None = 0.98            # None: 'auto'
    reorder_window_s: float = 2.0
    flush_after_s: float = 0.5            # wall time
    max_gap_s: float = 2.0
    reset_on_backwards_jump_s: float = 0.0
    input_timeout_s: float = 2.0
    startup_timeout_s: float = 10.0       # stamp time: how long a silent input is waited for
    odom_frame: str = 'odom'
    base_frame: str = 'base_link'
    publish_tf: bool = True
    publish_rate_hz: float = 30.0
    wheel_odom_topic: str = '/wheel/odom'
    imu_topic: str = ''                   # '': the source's (IMU_TOPICS)
    scan_match_topic: str = SCAN_TOPICS['ekf']
    level_with_imu_tilt: bool = False
    # method 'ekf' only
    imu_source: str = 'integrated'
    imu_estimate_bias: bool = False
    imu_mount_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    wheel_odom: InputConfig = INPUT_DEFAULTS[WHEEL]
    imu: InputConfig = INPUT_DEFAULTS[IMU]
    scan_match: InputConfig = INPUT_DEFAULTS[SCAN]
    ekf: EkfSettings = EkfSettings()

    @property
    def enabled(self) -> dict[str, bool]:
        """Per input (WHEEL, IMU, SCAN): fused or not."""
        return {WHEEL: self.use_wheel_odom, IMU: self.use_imu,
                SCAN: self.use_scan_match_position or self.use_scan_match_heading}

    def problems(self) -> list[tuple[str, str, object]]:
        """(field, problem, value) for each setting the fusion cannot run with (of an input:
        only where it is enabled)."""
        out: list[tuple[str, str, object]] = []
        if self.method not in METHODS:
            out.append(('method', "must be 'ekf' or 'complementary'", self.method))
        if self.alpha is not None and not 0.0 <= self.alpha <= 1.0:
            out.append(('alpha', "must be a number in [0, 1] or 'auto'", self.alpha))
        enabled = self.enabled
        if not any(enabled.values()):
            out.append(('use_*', 'at least one input must be enabled', None))
        if not (self.odom_frame and self.base_frame):
            out.append(('odom_frame/base_frame', 'must not be empty', None))
        if self.method != 'ekf':
            return out
        if self.imu_source not in IMU_SOURCES:
            out.append(('imu_source', f'must be one of {IMU_SOURCES}', self.imu_source))
        for name in INPUTS:
            if not enabled[name]:
                continue
            cfg = getattr(self, name)
            out += [(f'{name}.{field}', problem, value)
                    for field, problem, value in cfg.problems()]
            # A retimed input lags (or leads) the others by delay_s in stamp time: the reorder
            # buffer must hold the others that long, or its messages are dropped as late.
            if not abs(cfg.delay_s) <= self.reorder_window_s:
                out.append((f'{name}.delay_s', 'must be within the reorder window (|delay_s| '
                            f'<= reorder_window_s = {self.reorder_window_s:g} s)', cfg.delay_s))
        return out

    def session_config(self) -> SessionConfig:
        """The fusion's configuration these parameters give."""
        enabled = self.enabled
        imu_source, mount, inputs, ekf = 'integrated', (0.0, 0.0, 0.0), (), EkfSettings()
        if self.method == 'ekf':
            imu_source, mount, ekf = self.imu_source, self.imu_mount_rpy, self.ekf
            inputs = self._ekf_inputs(enabled)
        complementary = FusionSettings(
            use_wheel=self.use_wheel_odom, use_gyro=self.use_imu,
            use_scan_position=self.use_scan_match_position,
            use_scan_heading=self.use_scan_match_heading, alpha=self.alpha,
            max_gap_s=self.max_gap_s)
        return SessionConfig(
            method=self.method, enabled=enabled, inputs=inputs, ekf=ekf,
            complementary=complementary,
            topics={WHEEL: self.wheel_odom_topic,
                    IMU: self.imu_topic or IMU_TOPICS.get(imu_source, IMU_TOPICS['integrated']),
                    SCAN: self.scan_match_topic},
            imu_source=imu_source, imu_mount_rpy=mount,
            level_with_imu_tilt=self.level_with_imu_tilt,
            reorder_window_s=self.reorder_window_s, flush_after_s=self.flush_after_s,
            max_gap_s=self.max_gap_s, reset_on_backwards_jump_s=self.reset_on_backwards_jump_s,
            input_timeout_s=self.input_timeout_s, startup_timeout_s=self.startup_timeout_s,
            odom_frame=self.odom_frame,
            base_frame=self.base_frame, publish_tf=self.publish_tf,
            publish_rate_hz=self.publish_rate_hz)

    def _ekf_inputs(self, enabled: Mapping[str, bool]) -> tuple[InputConfig, ...]:
        """The enabled inputs' EKF configurations (use_scan_match_position / _heading switch the
        scan's quantities off)."""
        # The bias is a state for the raw rate always, for the integrated heading on request.
        bias = self.imu_source == 'rate' or (self.imu_source == 'integrated'
                                             and self.imu_estimate_bias)
        fixed = {WHEEL: {}, IMU: {'gyro_bias': bias}, SCAN: {'keyframes': True}}
        configs = []
        for name in INPUTS:
            if not enabled[name]:
                continue
            cfg = with_fixed(getattr(self, name), max_gap_s=self.max_gap_s, **fixed[name])
            if name == SCAN:
                cfg = with_mask(cfg, **({} if self.use_scan_match_position else
                                        {'x': False, 'y': False}),
                                **({} if self.use_scan_match_heading else {'yaw': False}))
            configs.append(cfg)
        return tuple(configs)


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


def _alpha(value: Any) -> float | None:
    """alpha: a number (checked by problems()), or None for 'auto'."""
    if value == 'auto':
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError("must be a number in [0, 1] or 'auto'")
    return float(value)


def _mount(axis: str) -> Param:
    return Param(f'IMU mount {axis} in base_link (rad, ZYX); upside down: roll = pi; the '
                 "fallback where /tf_static gives no base_frame -> the Imu's frame_id",
                 -2 * math.pi, 2 * math.pi, name=f'imu.mount_{axis}_rad')


_DESCRIBED = {
    'method': Param("'ekf' (docs/fusion.md) or 'complementary' (the seed's filter)"),
    'use_wheel_odom': Param('fuse /wheel/odom'),
    'use_imu': Param('fuse the IMU (imu.topic)'),
    'use_scan_match_position': Param('fuse x/y of scan matching'),
    'use_scan_match_heading': Param('fuse the heading of scan matching'),
    'alpha': Param("complementary: weight of the gyro-propagated heading, in [0, 1], or 'auto' "
                   'to derive it each update from the two variances', dynamic=True,
                   to_value=lambda alpha: 'auto' if alpha is None else alpha,
                   from_value=_alpha),
    'reorder_window_s': Param('longest an input may lag the newest (stamp time) and still be '
                              'fused in stamp order; later messages are dropped and counted',
                              0.0, 10.0),
    'flush_after_s': Param('wall time without input after which held inputs are processed',
                           0.01, 60.0),
    'max_gap_s': Param('an input silent longer than this (stamp time) restarts its increments',
                       0.001, 3600.0),
    'reset_on_backwards_jump_s': Param(
        "an input stamp more than this before the same input's previous one means time went "
        'backwards (looping bag): the filter resets', 0.0),
    'input_timeout_s': Param('an enabled input silent for this long is reported missing', 0.01),
    'startup_timeout_s': Param('an enabled input not heard yet is waited for this long (stamp '
                               'time since the first input) before the filter starts without it',
                               0.01),
    'odom_frame': Param('frame of the fused pose'),
    'base_frame': Param('child frame of the fused pose'),
    'publish_tf': Param('broadcast odom_frame -> base_frame on /tf with each output, stamped as '
                        'the output (one owner per tree: turn it off where another node owns '
                        'it)'),
    'publish_rate_hz': Param(
        'outputs (/odometry/filtered, /tf) per second of stamp time: the first fused output in '
        'each new period goes out, with its stamp; 0: one per wheel and scan-match input (every '
        'input still filtered)', 0.0, 1000.0),
    'wheel_odom_topic': Param('wheel odometry topic', name='wheel_odom.topic'),
    'imu_topic': Param("IMU topic (sensor_msgs/Imu); '': the source's, /imu/data_raw for "
                       "imu.source 'rate', /imu/data otherwise (and for method 'complementary')",
                       name='imu.topic'),
    'scan_match_topic': Param('scan matches (icp_matcher): keyframe-relative or in its local '
                              "map (method 'ekf'), or its odometry ('complementary')",
                              name='scan_match.topic'),
    'level_with_imu_tilt': Param(
        "ekf, imu.source 'orientation': count only the horizontal part of body velocities (the "
        "IMU's roll and pitch), for a robot on slopes"),
    'imu_source': Param("'integrated' (gyro_integrator's heading), 'orientation' (the IMU's own "
                        "orientation) or 'rate' (raw gyro rate, bias estimated in the filter)",
                        name='imu.source'),
    'imu_estimate_bias': Param(
        "imu.source 'integrated': estimate the integrator's remaining bias (its heading "
        'increments measure the turn plus bias x interval; observable where another input '
        "measures the heading absolutely: a local map's matches)", name='imu.estimate_bias'),
    'imu_mount_rpy': Param(elements=(_mount('roll'), _mount('pitch'), _mount('yaw'))),
    **{f'{name}.{field}': param for name in INPUTS for field, param in INPUT_PARAMS.items()},
    'ekf.accel_noise_density': Param('how fast vx, vy may change (m/s^2/sqrt(Hz))', 1e-6),
    'ekf.angular_accel_noise_density': Param(
        'how fast the yaw rate may change (rad/s^2/sqrt(Hz))', 1e-6),
    'ekf.bias_random_walk': Param('gyro bias random walk (rad/s/sqrt(s))', 0.0),
    'ekf.initial_bias_std': Param('gyro bias std before any input (rad/s)', 0.0),
    'ekf.speed_std_m_s': Param(
        "the spread of the robot's speeds (m/s): its velocity's uncertainty grows no further, "
        'and dead reckoning faster than the gate allows is refused', 1e-3, 1e3),
    'ekf.yaw_rate_std_rad_s': Param(
        "the spread of the robot's yaw rates (rad/s), as speed_std_m_s", 1e-3, 1e3),
    'ekf.fault_isolation': Param(
        'a refused scan match is checked against the state replayed without each other input '
        'since the last fused match: an input the match and the motion model both contradict '
        'is blamed and its readings dropped instead'),
    'ekf.reacquire_after_s': Param(
        'a scan input refused this long (stamp time) is taken back: the pose doubted as far as '
        'it disagrees with the match, which is fused (s)', 0.0, 3600.0),
    'ekf.reacquire_after_matches': Param('... and refused at least this many matches in a row',
                                         1, 1_000_000),
    'ekf.hold_back_max_s': Param(
        'an input blamed at a scan match is held back until the next match vouches for it '
        'where matches come at most this far apart (s; 0: never, for stamps whose time is '
        'assumed)', 0.0, 60.0),
    'ekf.adaptive_noise': Param(
        "scale the dead reckoning's noise by what the scan matches' innovations show (bounded, "
        'windowed; the scales on /diagnostics)'),
    'ekf.adaptive_window': Param('scan matches the adaptive noise scale follows', 2, 1_000_000),
    'ekf.adaptive_max_scale': Param('largest adaptive noise scale', 1.0, 1e6),
}
# What the node does not expose: each input's fields its kind decides, the EKF's pose noise and
# initial velocity std (the filter's own values).
_INTERNAL = {f'{name}.{field}' for name in INPUTS for field in input_internal(name)} | {
    'ekf.pose_noise_density', 'ekf.initial_velocity_std', 'ekf.isolation_log'}
_EKF_ONLY = {'imu_source', 'imu_estimate_bias', 'imu_mount_rpy', *INPUTS, 'ekf'}

# The parameters each method declares.
FUSION_PARAMETERS: dict[str, ParameterTable[FusionParameters]] = {
    'ekf': ParameterTable(FusionParameters(), _DESCRIBED,
                          prefixes={f'{name}.noise': '' for name in INPUTS}, internal=_INTERNAL),
    'complementary': ParameterTable(
        FusionParameters(method='complementary', scan_match_topic=SCAN_TOPICS['complementary']),
        {k: v for k, v in _DESCRIBED.items() if k.split('.')[0] not in _EKF_ONLY},
        internal=_EKF_ONLY),
}


def fusion_parameters(values: Mapping[str, Any]) -> FusionParameters:
    """complementary_fusion's parameters from their values, nested as in its YAML file or with
    dotted names as the node declares them (absent ones: their defaults; those of the other
    method are not read), checked as the node checks them (ParameterError names the
    parameter)."""
    flat = flatten(values)
    retired = sorted(name for name in flat if name.endswith('.gate_chi2'))
    if retired:
        raise ParameterError(retired[0], 'is gone: every input has a gate, set by its '
                             'gate_probability (the chi-square quantile of its rows; 0.999 by '
                             'default)', flat[retired[0]])
    method = flat.get('method', 'ekf')
    table = FUSION_PARAMETERS.get(method, FUSION_PARAMETERS['ekf']) if isinstance(method, str) \
        else FUSION_PARAMETERS['ekf']
    return table.config(flat)


def session_config(values: Mapping[str, Any]) -> SessionConfig:
    """The fusion's configuration from complementary_fusion's parameter values
    (fusion_parameters)."""
    return fusion_parameters(values).session_config()


def default_config(*files: str | Path, overrides: Mapping[str, Any] | None = None
                   ) -> SessionConfig:
    """The configuration of config/complementary_fusion.yaml, then `files` over it, then
    `overrides` (as the node starts in sensing_pipeline and the launch file)."""
    values = load_parameters(NODE_NAME, config_file(f'{NODE_NAME}.yaml'), *files)
    return session_config({**values, **flatten(overrides or {})})

