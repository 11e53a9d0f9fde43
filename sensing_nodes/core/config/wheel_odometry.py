"""wheel_odometry's configuration: the dead reckoning (core/wheel_odometry.py), the joints it
reads, the covariance it publishes and its frames; and its parameters."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from sensing_nodes.core.wheel_odometry import WheelOdometryConfig
from sensing_nodes.parameters import Param, ParameterTable

COVARIANCE_MODES = ('propagated', 'static')


@dataclass(frozen=True)
class WheelOdometryParameters:
    """Joint names, the odometry's geometry and error model, the published covariance (the
    error model's, or the static variances: x, y m^2, yaw rad^2; vx, vy, wz) and frames."""

    left_wheel_joint: str = 'left_wheel_joint'
    right_wheel_joint: str = 'right_wheel_joint'
    odometry: WheelOdometryConfig = field(default_factory=WheelOdometryConfig)
    covariance_mode: str = 'propagated'
    static_pose_variances: tuple[float, float, float] = (1e-3, 1e-3, 1e-3)
    static_twist_variances: tuple[float, float, float] = (1e-3, 1e-9, 1e-3)
    odom_frame: str = 'odom'
    base_frame: str = 'base_link'
    publish_tf: bool = False

    def problems(self) -> list[tuple[str, str, object]]:
        """(field, problem, value) for each setting the node cannot run with."""
        out = [(f'odometry.{name}', problem, value)
               for name, problem, value in self.odometry.problems()]
        for name in ('left_wheel_joint', 'right_wheel_joint'):
            if not getattr(self, name):
                out.append((name, 'must not be empty', getattr(self, name)))
        if self.left_wheel_joint == self.right_wheel_joint:
            out.append(('right_wheel_joint', 'must differ from left_wheel_joint',
                        self.right_wheel_joint))
        if self.covariance_mode not in COVARIANCE_MODES:
            out.append(('covariance_mode', "must be 'propagated' or 'static'",
                        self.covariance_mode))
        for name in ('static_pose_variances', 'static_twist_variances'):
            values = getattr(self, name)
            if not (len(values) == 3 and all(math.isfinite(v) and v >= 0.0 for v in values)):
                out.append((name, 'must be three finite variances >= 0', list(values)))
        if not (self.odom_frame and self.base_frame):
            out.append(('odom_frame/base_frame', 'must not be empty', None))
        return out


WHEEL_ODOMETRY_PARAMETERS = ParameterTable(WheelOdometryParameters(), described={
    'left_wheel_joint': Param('name of the left wheel joint'),
    'right_wheel_joint': Param('name of the right wheel joint'),
    'odometry.wheel_radius_m': Param('nominal wheel radius (m)'),
    'odometry.wheel_separation_m': Param('distance between the wheel contact points (m)'),
    'odometry.left_radius_multiplier': Param(
        'calibration: left radius = wheel_radius_m * this', 0.5, 1.5),
    'odometry.right_radius_multiplier': Param(
        'calibration: right radius = wheel_radius_m * this', 0.5, 1.5),
    'odometry.method': Param("'exact_arc' (default) or 'euler' (the textbook update, for "
                             'teaching)', name='integration_method'),
    # One variance for both wheels.
    'odometry.variance_per_m': Param(
        'random error model: variance (m^2) of a wheel distance is this * |distance (m)|', 0.0,
        name='wheel_variance_per_m', to_value=lambda pair: pair[0],
        from_value=lambda value: (float(value), float(value))),
    'odometry.max_gap_s': Param('a stamp gap longer than this (s) is not integrated across'),
    'odometry.max_wheel_speed_rad_s': Param(
        'fastest plausible wheel rate (rad/s): larger increments are wrapped encoder readings, '
        'or rejected'),
    'odometry.radius_multiplier_std': Param(
        "systematic error model: std of each wheel's relative radius error (what calibration "
        'leaves)', 0.0, 0.49),
    'covariance_mode': Param("'propagated' (from the wheel error model) or 'static' (the lists "
                             'below)'),
    'static_pose_variances': Param("with covariance_mode 'static': variances of x, y (m^2), "
                                   'yaw (rad^2)'),
    'static_twist_variances': Param("with covariance_mode 'static': variances of vx, vy, wz"),
    'odom_frame': Param('frame of the published pose'),
    'base_frame': Param('child frame (robot base)'),
    'publish_tf': Param('broadcast odom_frame -> base_frame on /tf (one owner per tree: the '
                        'fusion broadcasts it by default)'),
}, prefixes={'odometry': ''})
