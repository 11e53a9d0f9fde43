"""gyro_integrator's configuration: the integrator (core/gyro.py), the IMU's mount and scale,
what restarts it, and its frames; and its parameters."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from sensing_nodes.core.gyro import GyroConfig
from sensing_nodes.parameters import Param, ParameterTable


@dataclass(frozen=True)
class GyroIntegratorParameters:
    """The integrator's settings, the stillness veto from /wheel/odom, the IMU's mount in
    base_frame (roll, pitch, yaw, rad, ZYX) and gyro scale error, and the output's frame."""

    integrator: GyroConfig = field(default_factory=GyroConfig)
    restart_on_backwards: bool = True
    use_wheel_odom: bool = True
    mount_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gyro_scale_error: float = 0.0
    base_frame: str = 'base_link'
    frame_id: str = ''

    def problems(self) -> list[tuple[str, str, object]]:
        """(field, problem, value) for each setting the node cannot run with."""
        return [(f'integrator.{name}', problem, value)
                for name, problem, value in self.integrator.problems()]


def _mount(axis: str) -> Param:
    return Param(f'IMU mount {axis} in base_link (rad, ZYX); upside down: roll = pi',
                 -2 * math.pi, 2 * math.pi, name=f'mount_{axis}_rad')


GYRO_INTEGRATOR_PARAMETERS = ParameterTable(GyroIntegratorParameters(), described={
    'integrator.bias_estimation': Param(
        'estimate the gyro bias whenever the robot stands still'),
    'integrator.stillness_window_s': Param('stillness is decided over this trailing window (s)'),
    'integrator.gyro_std_threshold_rad_s': Param(
        'still only if every gyro axis std over the window is below this (rad/s)'),
    'integrator.accel_std_threshold_m_s2': Param(
        'still only if every accelerometer axis std over the window is below this (m/s^2)'),
    'integrator.max_gyro_bias_rad_s': Param(
        'still only if every gyro axis mean over the window is within this (rad/s)'),
    'integrator.noise_density': Param(
        'white rate noise density (rad/s/sqrt(Hz)): sample std * sqrt(dt)',
        name='gyro_noise_density'),
    'integrator.bias_random_walk': Param('bias random walk density (rad/s/sqrt(s))'),
    'integrator.initial_bias_sigma_rad_s': Param(
        'std of the bias before any calibration (rad/s)'),
    'integrator.initial_bias_z_rad_s': Param(
        'z bias estimate before the first stillness (rad/s; sensing_calibrate writes it)',
        -1.0, 1.0),
    'integrator.max_gap_s': Param('a stamp gap longer than this (s) is not integrated across'),
    'integrator.wheel_timeout_s': Param(
        '/wheel/odom counts as available while its newest stamp is this close (s)'),
    'integrator.wheel_still_linear_m_s': Param(
        '/wheel/odom reports zero motion when |vx| is at most this (m/s)'),
    'integrator.wheel_still_angular_rad_s': Param(
        '/wheel/odom reports zero motion when |wz| is at most this (rad/s)'),
    'restart_on_backwards': Param(
        'a stamp going backwards (looping bag) restarts the integrator from scratch, bias '
        'estimate included, so a replayed bag gives its first outputs again; false: reset the '
        'heading only and keep the bias estimate'),
    'use_wheel_odom': Param('veto stillness while /wheel/odom reports motion (slow turns)'),
    'mount_rpy': Param(elements=(_mount('roll'), _mount('pitch'), _mount('yaw'))),
    'gyro_scale_error': Param(
        'the z rate reads (1 + this) x the true rate; readings are divided by it '
        '(sensing_calibrate writes it)', -0.5, 0.5),
    'base_frame': Param(
        "the robot's base frame: /tf_static's base_frame -> the IMU's frame_id gives the mount "
        'where it is published (else mount_*_rad)'),
    'frame_id': Param('frame of the output; empty: keep the input frame (base_frame when the '
                      'mount rotates: the output is about its axes)'),
}, prefixes={'integrator': ''})
