"""The fusion on the IMU's own rate (imu.source rate, config/complementary_fusion.yaml's default):
the rates summed into heading increments (DeltaAngles), the gyro bias a state of the EKF, and a
graph that runs without gyro_integrator (docs/fusion.md); config/fusion_integrated.yaml fuses
gyro_integrator's heading instead."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from sensor_msgs.msg import Imu

from sensing_nodes.core.fusion.config import default_config
from sensing_nodes.core.fusion.inputs import IMU, DeltaAngles
from sensing_nodes.core.fusion.timeline import InputRecord
from sensing_nodes.paths import config_file
from sensing_nodes.ros.conversions import ns_to_stamp
from sensing_nodes.ros.fusion_readings import ReadingConverter

BAGS = Path(__file__).resolve().parents[1] / 'bags'
MS = 1_000_000


def test_rates_are_summed_over_the_interval_before_each_sample():
    """Delta angles: each rate over the 5 ms before its stamp, its variance times dt^2; nothing
    across a gap longer than max_gap_s, or from a stamp that is not after the previous."""
    angles = DeltaAngles(max_gap_s=0.5)
    for k in range(201):                       # 1 s at 200 Hz, 0.1 rad/s
        angles.add(k * 5 * MS, 0.1, 1e-6)
    assert angles.yaw == pytest.approx(0.1)     # 200 intervals of 5 ms (the first sample: none)
    assert angles.variance == pytest.approx(200 * 1e-6 * 0.005 ** 2)
    angles.add(2000 * MS, 5.0, 1e-6)           # after a 1 s silence: not added
    angles.add(2000 * MS, 5.0, 1e-6)           # a repeated stamp: not added
    assert angles.yaw == pytest.approx(0.1)
    angles.add(2010 * MS, -1.0, 1e-6)          # 10 ms at -1 rad/s
    assert angles.yaw == pytest.approx(0.09)
    angles.reset()
    assert (angles.yaw, angles.variance, angles.stamp_ns) == (0.0, 0.0, None)


def test_a_raw_imu_message_reads_as_its_rate_and_the_summed_heading():
    config = default_config()
    assert config.imu_source == 'rate' and config.input_map[IMU].gyro_bias
    assert config.topics[IMU] == '/imu/data_raw'
    integrated = default_config(config_file('fusion_integrated.yaml'))
    assert integrated.imu_source == 'integrated' and integrated.topics[IMU] == '/imu/data'
    converter = ReadingConverter.for_config(config)
    record = InputRecord(IMU)
    readings = []
    for k in range(3):
        msg = Imu()
        msg.header.stamp = ns_to_stamp(10**18 + k * 5 * MS)
        msg.header.frame_id = 'imu_link'
        msg.orientation_covariance[0] = -1.0                  # a raw IMU: no orientation
        msg.angular_velocity.z = 0.2
        msg.angular_velocity_covariance = [1e-6, 0, 0, 0, 1e-6, 0, 0, 0, 1e-6]
        reading, problem = converter.reading(IMU, msg, converter.stamp_ns(IMU, msg), record)
        assert problem == ''
        readings.append(reading)
    assert [r.twist[2] for r in readings] == [0.2, 0.2, 0.2]
    assert [r.pose[2] for r in readings] == pytest.approx([0.0, 0.001, 0.002])
    assert readings[-1].pose_covariance[2, 2] == pytest.approx(2 * 1e-6 * 0.005 ** 2)
    converter.reset()                                          # a new timeline: from zero
    assert converter.delta_angles.yaw == 0.0


@pytest.mark.parametrize('name, bias', [('strong_errors', 0.03)])
def test_a_graph_without_gyro_integrator_fuses_the_raw_rate(tmp_path, name, bias):
    """sensing_pipeline over the shipped bag with wheel_odometry, line_extractor, icp_matcher
    and the fusion on /imu/data_raw (its default), no gyro_integrator. The
    strong_errors bag: a 1.7 deg/s gyro bias the EKF learns (within 1e-4 rad/s after 22 s; the
    first 2 s stand still), wheels slipping 5 %. Measured: fused RMS 0.0023 m, 0.059 deg (the
    graph with gyro_integrator: 0.0023 m, 0.058 deg); bias 0.03004 rad/s, sigma 3.4e-5."""
    from sensing_nodes.core.evaluation.fusion import track_errors
    from sensing_nodes.graph import pipeline
    from sensing_nodes.tools.eval import load_trajectories
    from sensing_nodes.tools.fuse_bag import fused_outputs

    out = tmp_path / 'out'
    nodes = ('wheel_odometry', 'line_extractor', 'icp_matcher', 'complementary_fusion')
    counts = pipeline.run(BAGS / name, out, nodes, progress=False)
    assert '/imu/data' not in counts and counts['/odometry/filtered'] > 800
    tracks = load_trajectories(out, ['/ground_truth/odom', '/odometry/filtered', '/wheel/odom'])
    truth = tracks['/ground_truth/odom']
    fused = track_errors(*truth, *tracks['/odometry/filtered'])
    wheels = track_errors(*truth, *tracks['/wheel/odom'])
    assert fused['rms_position_m'] < 0.005 and fused['rms_heading_deg'] < 0.1, fused
    assert fused['rms_heading_deg'] < 0.1 * wheels['rms_heading_deg'], (fused, wheels)
    # the bias as the filter has it at the end (the same session over the graph's inputs)
    _, session = fused_outputs(out, [])
    state = session.fusion.state
    sigma = math.sqrt(state.bias_variance)
    assert sigma < 1e-4 and abs(state.bias - bias) < 3 * sigma, (state.bias, sigma)
    assert np.all(np.isfinite(state.covariance))
