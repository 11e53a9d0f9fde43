"""Per-input time offsets (delay_s): a message stamped t is fused as at t - delay_s, in one place
(ros/fusion_readings.py's ReadingConverter), keyframe names retimed with it; bad values are
refused (node start-up: test_fusion_node.py)."""

import math

import numpy as np
import pytest
from sensor_msgs.msg import Imu

from sensing_nodes.core.fusion.ekf import EkfFusion, EkfSettings
from sensing_nodes.core.fusion.inputs import IMU, SCAN, WHEEL, input_config
from sensing_nodes.core.fusion.timeline import InputRecord
from sensing_nodes.ros.conversions import (
    NOT_MATCHED,
    SCAN_MATCH_KEYFRAME_FRAME,
    make_odometry,
    ns_to_stamp,
)
from sensing_nodes.ros.fusion_readings import ReadingConverter

S = 1_000_000_000
T0 = 100 * S


def _converter(**delays):
    configs = {name: input_config(name, {'delay_s': delays.get(name, 0.0)})
               for name in (WHEEL, IMU, SCAN)}
    return ReadingConverter('ekf', configs)


def test_a_message_stamped_t_is_read_as_at_t_minus_its_inputs_delay():
    converter = _converter(wheel_odom=0.1, imu=-0.02)
    wheel = make_odometry(T0, 'odom', 'base_link', (1.0, 0.0, 0.0), np.eye(3) * 1e-4)
    imu = Imu()
    imu.header.stamp = ns_to_stamp(T0)
    assert converter.stamp_ns(WHEEL, wheel) == T0 - 100_000_000          # 100.1 s -> 100.0 s
    assert converter.stamp_ns(IMU, imu) == T0 + 20_000_000               # stamped early
    assert converter.stamp_ns(SCAN, wheel) == T0                         # no delay: unchanged
    stamp = converter.stamp_ns(WHEEL, wheel)
    reading, problem = converter.reading(WHEEL, wheel, stamp, InputRecord(WHEEL))
    assert problem == '' and reading.stamp_ns == T0 - 100_000_000


def test_a_retimed_match_names_its_keyframes_retimed_too():
    """A keyframe is named by the stamp of icp_matcher's message that started it: with
    scan_match.delay_s 0.05 the match stamped 101 s against the keyframe of 100 s is read as
    100.95 s against 99.95 s, and a message that starts a keyframe still does."""
    converter = _converter(scan_match=0.05)
    first = make_odometry(T0, SCAN_MATCH_KEYFRAME_FRAME, SCAN_MATCH_KEYFRAME_FRAME,
                          (0.0, 0.0, 0.0), np.diag([NOT_MATCHED, 0.0, 0.0]))
    reading, problem = converter.reading(SCAN, first, converter.stamp_ns(SCAN, first),
                                         InputRecord(SCAN))
    assert problem == '' and reading.pose is None and reading.new_keyframe
    assert reading.stamp_ns == T0 - 50_000_000
    msg = make_odometry(T0 + S, SCAN_MATCH_KEYFRAME_FRAME, SCAN_MATCH_KEYFRAME_FRAME,
                        (0.2, 0.0, 0.01), np.eye(3) * 1e-6)
    stamp = converter.stamp_ns(SCAN, msg)
    reading, problem = converter.reading(SCAN, msg, stamp, InputRecord(SCAN))
    assert problem == ''
    assert (reading.stamp_ns, reading.keyframe_ns) == (T0 + S - 50_000_000, T0 - 50_000_000)
    assert reading.new_keyframe


def _fused_x_at(delay_s: float, at_ns: int) -> tuple[int, float]:
    """A robot at 1 m/s along x whose odometry lags by 0.1 s (stamped t, it reports the position
    at t - 0.1 s, x = t - 100 s); absolute poses, fused with wheel_odom.delay_s = delay_s. The
    stamp of the last state, and the state predicted (constant velocity) to at_ns."""
    cfg = input_config(WHEEL, {'pose_mode': 'absolute', 'covariance': 'message',
                               'delay_s': delay_s})
    converter = ReadingConverter('ekf', {WHEEL: cfg})
    ekf = EkfFusion((cfg,), EkfSettings(initial_velocity_std=10.0))
    record = InputRecord(WHEEL)
    for k in range(11):                     # stamps 100.1 s .. 101.1 s, every 0.1 s
        t = T0 + (k + 1) * 100_000_000
        x = (t - 100_000_000 - T0) * 1e-9
        msg = make_odometry(t, 'odom', 'base_link', (x, 0.0, 0.0), np.eye(3) * 1e-8)
        stamp = converter.stamp_ns(WHEEL, msg)
        reading, problem = converter.reading(WHEEL, msg, stamp, record)
        assert problem == ''
        ekf.update(WHEEL, reading)
    last = ekf.state.stamp_ns
    ekf.predict(at_ns)
    return last, ekf.state.pose[0]


def test_fused_as_at_t_minus_delay_puts_a_lagging_odometry_on_the_robot():
    """Worked numbers: the last message, stamped 101.1 s, reports x = 1.0 m. With delay_s 0.1
    it is fused as at 101.0 s, where the robot was at 1.0 m, and the state predicted to 101.1 s
    is at 1.1 m (the truth); without the delay it is fused at 101.1 s: 0.1 m behind."""
    last, x = _fused_x_at(0.1, T0 + 1_100_000_000)
    assert last == T0 + 1_000_000_000
    assert x == pytest.approx(1.1, abs=1e-3)
    last, x = _fused_x_at(0.0, T0 + 1_100_000_000)
    assert last == T0 + 1_100_000_000
    assert x == pytest.approx(1.0, abs=1e-3)


@pytest.mark.parametrize('value', [math.nan, math.inf, -math.inf])
def test_a_delay_that_is_not_finite_is_a_problem(value):
    bad = input_config(WHEEL, {'delay_s': value})
    assert [field for field, _, _ in bad.problems()] == ['delay_s']
    assert input_config(WHEEL, {'delay_s': -0.3}).problems() == []   # stamps early: allowed
