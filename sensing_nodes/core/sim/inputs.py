"""The package's dead reckoning and scan matching over a simulated run, without ROS: the
fusion's input streams, as the nodes would publish them, for accuracy checks of the fusion.

Frames and units as the topics: wheel odometry and scan matching are base_link poses in their
own odom frames (m, rad) with 3x3 covariances over (x, y, yaw); the gyro stream is
gyro_integrator's heading (rad, its variance rad^2) and bias-corrected yaw rate (rad/s); the raw
stream is the IMU's z rate (rad/s). Stamps are int64 ns. The run's samples reach the cores in
the one event order (core/events.py), each at the time it is published; each output is a record
of its stream (WheelSample, GyroSample, ScanSample), stacked into FusionInputs' columns.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.events import time_ordered
from sensing_nodes.core.geometry.scan import scan_to_points
from sensing_nodes.core.gyro import GyroConfig, GyroIntegrator
from sensing_nodes.core.scan_matching import (
    OdometryBuffer,
    ScanMatcherSettings,
    ScanStep,
    make_scan_matcher,
    odometry_guidance,
)
from sensing_nodes.core.sim.simulator import SimParams, SimRun, make_route, simulate
from sensing_nodes.core.sim.world import load_world
from sensing_nodes.core.wheel_odometry import WheelOdometry, WheelOdometryConfig
from sensing_nodes.paths import config_file

JOINTS = ('left_wheel_joint', 'right_wheel_joint')


class WheelSample(NamedTuple):
    """One /wheel/odom output: stamp (ns), pose (x, y, yaw) and its 3x3 covariance in odom,
    twist (vx, vy, wz) in base_link."""

    t: int
    pose: tuple
    covariance: NDArray[np.float64]
    twist: tuple


class GyroSample(NamedTuple):
    """One gyro_integrator output (stamp ns): heading (rad) and its variance, bias-corrected z
    rate (rad/s), the IMU's raw z rate, the z bias estimate and its variance, stillness."""

    t: int
    yaw: float
    yaw_variance: float
    rate: float
    raw_rate: float
    bias: float
    bias_variance: float
    still: bool


class ScanSample(NamedTuple):
    """One published scan match (stamp ns): the cumulative pose and covariance; the keyframe
    match (keyframe stamp, -1: none; relative pose and covariance; whether this scan is the
    next keyframe); the local-map pose (its time, -1: keyframe mode; the map's id, -1: no
    match; pose and covariance)."""

    t: int
    pose: tuple
    covariance: NDArray[np.float64]
    keyframe_t: int
    relative: tuple
    relative_covariance: NDArray[np.float64]
    new_keyframe: bool
    map_t: int
    map_id: int
    map_pose: tuple
    map_covariance: NDArray[np.float64]


@dataclass(frozen=True)
class FusionInputs:
    """Every input of the fusion over one run, plus the ground truth (map frame)."""

    truth_t: NDArray[np.int64]
    truth_pose: NDArray[np.float64]          # (T, 3)
    wheel_t: NDArray[np.int64]
    wheel_pose: NDArray[np.float64]          # (W, 3)
    wheel_cov: NDArray[np.float64]           # (W, 3, 3)
    wheel_twist: NDArray[np.float64]         # (W, 3) vx, vy, wz in base_link
    gyro_t: NDArray[np.int64]
    gyro_yaw: NDArray[np.float64]            # integrated heading (rad)
    gyro_yaw_var: NDArray[np.float64]        # its variance (rad^2)
    gyro_rate: NDArray[np.float64]           # bias-corrected z rate (rad/s)
    raw_rate: NDArray[np.float64]            # the IMU's z rate before any correction (rad/s)
    gyro_bias: NDArray[np.float64]           # the integrator's z bias estimate (rad/s)
    gyro_bias_var: NDArray[np.float64]       # its variance (rad^2/s^2)
    gyro_still: NDArray[np.bool_]            # the integrator stood still (heading corrections)
    scan_t: NDArray[np.int64]
    scan_pose: NDArray[np.float64]           # (S, 3) cumulative matcher pose
    scan_cov: NDArray[np.float64]            # (S, 3, 3)
    scan_keyframe_t: NDArray[np.int64]       # keyframe of each match's relative pose; -1: none
    scan_relative: NDArray[np.float64]       # (S, 3) pose relative to that keyframe
    scan_relative_cov: NDArray[np.float64]   # (S, 3, 3)
    scan_new_keyframe: NDArray[np.bool_]     # this scan is the keyframe of the next matches
    # local_map mode (/scan_match/keyframe_odom): when each scan's map pose is (the sweep's
    # middle; -1: keyframe mode), the map it is in (its first scan's stamp, equal to the time
    # at the scan that starts it; -1: no match), the pose (S, 3) and its covariance (S, 3, 3)
    scan_map_t: NDArray[np.int64]
    scan_map_id: NDArray[np.int64]
    scan_map_pose: NDArray[np.float64]
    scan_map_cov: NDArray[np.float64]
    raw_rate_variance: float = 0.0           # of each raw rate sample (rad^2/s^2)

    @classmethod
    def from_samples(cls, run: SimRun, wheels: list[WheelSample], gyros: list[GyroSample],
                     scans: list[ScanSample]) -> FusionInputs:
        """The run's truth and its streams' samples, each field stacked into a column."""
        def column(samples, field, dtype=np.float64, shape=()):
            return np.array([getattr(s, field) for s in samples],
                            dtype=dtype).reshape((-1, *shape))

        int64, pose, covariance = np.int64, (3,), (3, 3)
        return cls(
            truth_t=run.truth_t, truth_pose=run.truth_pose,
            wheel_t=column(wheels, 't', int64), wheel_pose=column(wheels, 'pose', shape=pose),
            wheel_cov=column(wheels, 'covariance', shape=covariance),
            wheel_twist=column(wheels, 'twist', shape=pose),
            gyro_t=column(gyros, 't', int64), gyro_yaw=column(gyros, 'yaw'),
            gyro_yaw_var=column(gyros, 'yaw_variance'), gyro_rate=column(gyros, 'rate'),
            raw_rate=column(gyros, 'raw_rate'), gyro_bias=column(gyros, 'bias'),
            gyro_bias_var=column(gyros, 'bias_variance'),
            gyro_still=column(gyros, 'still', bool),
            scan_t=column(scans, 't', int64), scan_pose=column(scans, 'pose', shape=pose),
            scan_cov=column(scans, 'covariance', shape=covariance),
            scan_keyframe_t=column(scans, 'keyframe_t', int64),
            scan_relative=column(scans, 'relative', shape=pose),
            scan_relative_cov=column(scans, 'relative_covariance', shape=covariance),
            scan_new_keyframe=column(scans, 'new_keyframe', bool),
            scan_map_t=column(scans, 'map_t', int64), scan_map_id=column(scans, 'map_id', int64),
            scan_map_pose=column(scans, 'map_pose', shape=pose),
            scan_map_cov=column(scans, 'map_covariance', shape=covariance),
            raw_rate_variance=run.params.gyro_noise_std_rad_s ** 2)


def wheel_config(params: SimParams) -> WheelOdometryConfig:
    """Wheel odometry as config/wheel_odometry.yaml sets it for the simulated robot."""
    return WheelOdometryConfig(wheel_radius_m=params.wheel_radius_m,
                               wheel_separation_m=params.wheel_separation_m,
                               right_radius_multiplier=1.01)


def matcher_settings(params: SimParams, **overrides) -> ScanMatcherSettings:
    """The scan matcher as config/icp_matcher.yaml sets it for the simulated robot (its laser
    mount), with any field overridden (mode='keyframe', ...)."""
    return ScanMatcherSettings(
        laser_pose=(params.laser_x_m, params.laser_y_m, params.laser_yaw_rad), **overrides)


def scan_points(run: SimRun, i: int) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """Scan i as the node reads it: valid points (N, 2) in the laser frame and each point's
    beam time after the stamp (s; None when every beam is at the stamp)."""
    points, beams = scan_to_points(run.scan_ranges[i], run.scan_angles, run.scan_range_min,
                                   run.scan_range_max)
    times = beams * run.scan_time_increment if run.scan_time_increment > 0.0 else None
    return points, times


class _RunCores:
    """The dead-reckoning cores over one simulated run as the nodes run them, sample by sample in
    the one event order (core/events.py): wheel odometry (whose poses predict and deskew the
    scans) and, given its config, the gyro integrator with the wheels' stillness veto."""

    def __init__(self, run: SimRun, wheel: WheelOdometryConfig,
                 gyro: GyroConfig | None = None) -> None:
        self.run = run
        self.odometry = WheelOdometry(wheel)
        self.integrator = GyroIntegrator(gyro) if gyro is not None else None
        self.buffer = OdometryBuffer(max_age_s=10.0, max_extrapolation_s=0.1)
        self.last_scan: int | None = None    # stamp of the last scan the matcher published

    def streams(self, imu: bool) -> dict[str, NDArray[np.int64]]:
        """The run's samples by when they are published (a scan after its sweep), ranked."""
        run = self.run
        return {'joints': run.joint_t, **({'imu': run.imu_t} if imu else {}),
                'scan': run.scan_publish_t}

    def joints(self, i: int) -> WheelSample | None:
        """Joint state i into the wheel odometry: its output, if it publishes one."""
        run, odometry = self.run, self.odometry
        stamp = int(run.joint_t[i])
        if not odometry.update(stamp, list(JOINTS), run.joint_position[i], run.joint_velocity[i],
                               JOINTS).publish:
            return None
        self.buffer.add(stamp, odometry.pose)
        if self.integrator is not None:
            self.integrator.observe_wheels(stamp, odometry.twist[0], odometry.twist[2])
        return WheelSample(stamp, odometry.pose, odometry.covariance.copy(), odometry.twist)

    def imu(self, i: int) -> GyroSample | None:
        """IMU sample i into the gyro integrator: its output, if it publishes one."""
        run, integrator = self.run, self.integrator
        stamp = int(run.imu_t[i])
        if not integrator.update(stamp, run.imu_gyro[i], run.imu_accel[i]).publish:
            return None
        return GyroSample(stamp, integrator.heading, integrator.heading_variance,
                          float(integrator.rate[2]), float(run.imu_gyro[i][2]),
                          float(integrator.bias[2]), integrator.p_bias, integrator.still)

    def scan(self, i: int) -> tuple:
        """Scan i as the matcher's process() arguments: stamp, points, the wheel odometry's
        motion since the last published scan, beam times and its motion over the sweep."""
        stamp = int(self.run.scan_t[i])
        points, times = scan_points(self.run, i)
        predicted, sweep = odometry_guidance(self.buffer, self.last_scan, stamp, times)
        return stamp, points, predicted, times, sweep


def _scan_sample(stamp: int, step: ScanStep) -> ScanSample:
    """A published step as the fusion's scan-match streams hold it."""
    match, in_map = step.keyframe, step.local_map
    matched = in_map is not None and in_map.pose is not None
    return ScanSample(
        stamp, step.pose, step.covariance,
        -1 if match is None else match.keyframe_stamp_ns,
        (0.0, 0.0, 0.0) if match is None else match.pose,
        np.zeros((3, 3)) if match is None else match.covariance,
        step.new_keyframe,
        -1 if in_map is None else in_map.time_ns,
        in_map.map_stamp_ns if matched or (in_map is not None and in_map.origin) else -1,
        in_map.pose if matched else (0.0, 0.0, 0.0),
        in_map.covariance if matched else np.zeros((3, 3)))


def scan_inputs(run: SimRun) -> list[tuple]:
    """What the node's matcher is given for each scan of a run, as process() arguments: stamp,
    points, the wheel odometry's motion since the previous scan, beam times and the odometry's
    motion over the sweep (each scan taken when it is published)."""
    cores = _RunCores(run, wheel_config(run.params))
    out = []
    for event in time_ordered(cores.streams(imu=False)):
        if event.source == 'joints':
            cores.joints(event.index)
            continue
        out.append(cores.scan(event.index))
        cores.last_scan = out[-1][0]
    return out


def match_scans(run: SimRun, settings: ScanMatcherSettings | None = None,
                odometry: bool = True, deskew: bool = True) -> tuple[NDArray[np.int64],
                                                                      list[ScanStep]]:
    """The scan matcher alone over a simulated run (scan_inputs): predicted and deskewed by the
    wheel odometry (odometry=True) or by its own velocity; deskew=False ignores the beams'
    times. Returns the scans' stamps and steps."""
    matcher = make_scan_matcher(settings or matcher_settings(run.params))
    stamps, steps = [], []
    for stamp, points, predicted, times, sweep in scan_inputs(run):
        if not odometry:
            predicted = sweep = None
        step = matcher.process(stamp, points, predicted, times if deskew else None, sweep)
        if step.publish:
            stamps.append(stamp)
            steps.append(step)
    return np.array(stamps, dtype=np.int64), steps


def inputs_from_run(run: SimRun, wheel: WheelOdometryConfig | None = None,
                    gyro: GyroConfig | None = None,
                    matcher: ScanMatcherSettings | None = None) -> FusionInputs:
    """Run wheel odometry, the gyro integrator (with the wheel stillness veto) and the scan
    matcher (config/icp_matcher.yaml's: predicted and deskewed by the wheel odometry) over a
    simulated run, each sample when it is published (a scan after its sweep), in the one event
    order."""
    cores = _RunCores(run, wheel or wheel_config(run.params), gyro or GyroConfig())
    scan_matcher = make_scan_matcher(matcher or matcher_settings(run.params))
    wheels: list[WheelSample] = []
    gyros: list[GyroSample] = []
    scans: list[ScanSample] = []
    for event in time_ordered(cores.streams(imu=True)):
        if event.source == 'joints':
            sample = cores.joints(event.index)
            if sample is not None:
                wheels.append(sample)
        elif event.source == 'imu':
            sample = cores.imu(event.index)
            if sample is not None:
                gyros.append(sample)
        else:
            step = scan_matcher.process(*cores.scan(event.index))
            if step.publish:
                cores.last_scan = int(run.scan_t[event.index])
                scans.append(_scan_sample(cores.last_scan, step))
    return FusionInputs.from_samples(run, wheels, gyros, scans)


def simulated_inputs(seed: int = 0, params: SimParams | None = None, laps: float = 1.0,
                     matcher_mode: str = 'local_map') -> FusionInputs:
    """Simulate `laps` of the route (default world) and run the fusion's input chain over it,
    the scan matcher in matcher_mode (the node's default, or 'keyframe')."""
    params = params or SimParams()
    run = simulate(params, load_world(config_file('default_world.yaml')),
                   laps * make_route(params).period_s, seed)
    return inputs_from_run(run, matcher=matcher_settings(params, mode=matcher_mode))


def save(inputs: FusionInputs, path: str) -> None:
    """Write the streams to an .npz file (a cache for repeated experiments)."""
    np.savez_compressed(path, **{k: getattr(inputs, k) for k in FusionInputs.__dataclass_fields__})


def load(path: str) -> FusionInputs:
    """Read streams written by save()."""
    with np.load(path) as data:
        return FusionInputs(**{k: data[k] for k in FusionInputs.__dataclass_fields__})
