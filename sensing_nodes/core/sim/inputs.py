"""The package's dead reckoning and scan matching over a simulated run, without ROS: the
fusion's input streams, as the nodes would publish them, for accuracy checks of the fusion.

Frames and units as the topics: wheel odometry and scan matching are base_link poses in their
own odom frames (m, rad) with 3x3 covariances over (x, y, yaw); the gyro stream is
gyro_integrator's heading (rad, its variance rad^2) and bias-corrected yaw rate (rad/s); the raw
stream is the IMU's z rate (rad/s). Stamps are int64 ns.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

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


def scan_inputs(run: SimRun) -> list[tuple]:
    """What the node's matcher is given for each scan of a run, as process() arguments: stamp,
    points, the wheel odometry's motion since the previous scan, beam times and the odometry's
    motion over the sweep (each scan taken when it is published)."""
    wheels = WheelOdometry(wheel_config(run.params))
    buffer = OdometryBuffer(max_age_s=10.0, max_extrapolation_s=0.1)
    events = sorted([(int(t), 0, i) for i, t in enumerate(run.joint_t)]
                    + [(int(t), 2, i) for i, t in enumerate(run.scan_publish_t)])
    out, last_scan = [], None
    for stamp, kind, i in events:
        if kind == 0:
            if wheels.update(stamp, list(JOINTS), run.joint_position[i], run.joint_velocity[i],
                             JOINTS).publish:
                buffer.add(stamp, wheels.pose)
            continue
        scan_stamp = int(run.scan_t[i])
        points, times = scan_points(run, i)
        predicted, sweep = odometry_guidance(buffer, last_scan, scan_stamp, times)
        out.append((scan_stamp, points, predicted, times, sweep))
        last_scan = scan_stamp
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


# long: one loop over the events in publishing order, a branch per sensor, as the graph runs
# them.
def inputs_from_run(run: SimRun, wheel: WheelOdometryConfig | None = None,
                    gyro: GyroConfig | None = None,
                    matcher: ScanMatcherSettings | None = None) -> FusionInputs:
    """Run wheel odometry, the gyro integrator (with the wheel stillness veto) and the scan
    matcher (config/icp_matcher.yaml's: predicted and deskewed by the wheel odometry) over a
    simulated run, each sample when it is published (a scan after its sweep)."""
    params = run.params
    odometry = WheelOdometry(wheel or wheel_config(params))
    integrator = GyroIntegrator(gyro or GyroConfig())
    scan_matcher = make_scan_matcher(matcher or matcher_settings(params))
    buffer = OdometryBuffer(max_age_s=10.0, max_extrapolation_s=0.1)
    wt, wp, wc, wtw = [], [], [], []
    gt, gy, gv, gr, raw, gb, gbv, gs = [], [], [], [], [], [], [], []
    st, sp, sc, skt, srel, src, snew = [], [], [], [], [], [], []
    smt, smi, smp, smc = [], [], [], []
    # Same-time order as the graph delivers it closely enough: joints, IMU, then scans.
    events = sorted([(int(t), 0, i) for i, t in enumerate(run.joint_t)]
                    + [(int(t), 1, i) for i, t in enumerate(run.imu_t)]
                    + [(int(t), 2, i) for i, t in enumerate(run.scan_publish_t)])
    last_scan = None
    for stamp, kind, i in events:
        if kind == 0:
            result = odometry.update(stamp, list(JOINTS), run.joint_position[i],
                                     run.joint_velocity[i], JOINTS)
            if result.publish:
                wt.append(stamp)
                wp.append(odometry.pose)
                wc.append(odometry.covariance.copy())
                wtw.append(odometry.twist)
                buffer.add(stamp, odometry.pose)
                integrator.observe_wheels(stamp, odometry.twist[0], odometry.twist[2])
        elif kind == 1:
            result = integrator.update(stamp, run.imu_gyro[i], run.imu_accel[i])
            if result.publish:
                gt.append(stamp)
                gy.append(integrator.heading)
                gv.append(integrator.heading_variance)
                gr.append(float(integrator.rate[2]))
                raw.append(float(run.imu_gyro[i][2]))
                gb.append(float(integrator.bias[2]))
                gbv.append(integrator.p_bias)
                gs.append(integrator.still)
        else:
            stamp = int(run.scan_t[i])
            points, times = scan_points(run, i)
            predicted, sweep = odometry_guidance(buffer, last_scan, stamp, times)
            step = scan_matcher.process(stamp, points, predicted, times, sweep)
            if not step.publish:
                continue
            last_scan = stamp
            st.append(stamp)
            sp.append(step.pose)
            sc.append(step.covariance)
            match, in_map = step.keyframe, step.local_map
            skt.append(-1 if match is None else match.keyframe_stamp_ns)
            srel.append((0.0, 0.0, 0.0) if match is None else match.pose)
            src.append(np.zeros((3, 3)) if match is None else match.covariance)
            snew.append(step.new_keyframe)
            matched = in_map is not None and in_map.pose is not None
            smt.append(-1 if in_map is None else in_map.time_ns)
            smi.append(in_map.map_stamp_ns if matched or (in_map is not None and in_map.origin)
                       else -1)
            smp.append(in_map.pose if matched else (0.0, 0.0, 0.0))
            smc.append(in_map.covariance if matched else np.zeros((3, 3)))
    return FusionInputs(
        truth_t=run.truth_t, truth_pose=run.truth_pose,
        wheel_t=np.array(wt, dtype=np.int64), wheel_pose=np.array(wp), wheel_cov=np.array(wc),
        wheel_twist=np.array(wtw),
        gyro_t=np.array(gt, dtype=np.int64), gyro_yaw=np.array(gy), gyro_yaw_var=np.array(gv),
        gyro_rate=np.array(gr), raw_rate=np.array(raw), gyro_bias=np.array(gb),
        gyro_bias_var=np.array(gbv), gyro_still=np.array(gs, dtype=bool),
        scan_t=np.array(st, dtype=np.int64), scan_pose=np.array(sp), scan_cov=np.array(sc),
        scan_keyframe_t=np.array(skt, dtype=np.int64), scan_relative=np.array(srel),
        scan_relative_cov=np.array(src).reshape(-1, 3, 3),
        scan_new_keyframe=np.array(snew, dtype=bool),
        scan_map_t=np.array(smt, dtype=np.int64), scan_map_id=np.array(smi, dtype=np.int64),
        scan_map_pose=np.array(smp).reshape(-1, 3), scan_map_cov=np.array(smc).reshape(-1, 3, 3),
        raw_rate_variance=params.gyro_noise_std_rad_s ** 2)


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
