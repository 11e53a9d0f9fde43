"""Faults in the running graph: kill -9 one processing node at a time and restart it.

The graph is the demo's: sensor_sim and the five processing nodes, each started from its
executable with its config file. Each processing node in turn is killed with SIGKILL while the
robot drives; the others must keep running, complementary_fusion must carry on with the inputs
it still has (its /diagnostics saying 'missing: <input>' when the victim fed it), take the
restarted node's output again once it is back (a victim feeding it nothing: its own output
comes back), and its fused pose must stay continuous and
follow the ground truth's motion over the whole run.
"""

import math
import os
import signal

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from harness import Collector, NodeProcess, spin_until
from nav_msgs.msg import Odometry
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Imu, PointCloud2

from sensing_nodes.core.geometry import se2
from sensing_nodes.paths import config_file
from sensing_nodes.ros.conversions import odometry_pose, stamp_to_ns
from sensing_nodes.ros.qos import ESTIMATE_QOS, topic_qos

PROCESSING = ['wheel_odometry', 'gyro_integrator', 'line_extractor', 'icp_matcher',
              'complementary_fusion']
# Victim -> the fusion input it feeds (None: fusion does not use it; it takes the IMU's raw
# rate from the driver, gyro_integrator's /imu/data is for other consumers).
FEEDS = {'wheel_odometry': 'wheel_odom', 'gyro_integrator': None, 'icp_matcher': 'scan_match',
         'line_extractor': None}
# A victim that feeds nothing the fusion takes: its own output, which must come back.
OUTPUTS = {'line_extractor': ('/scan/lines/table', PointCloud2),
           'gyro_integrator': ('/imu/data', Imu)}
RATE = 2.0                         # simulated seconds per wall second
MAX_SPEED_M_S, MAX_TURN_RAD_S = 0.25, math.radians(45.0)   # the default route's limits
DIAG_QOS = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)


def start(name, **params):
    return NodeProcess(name, params_file=config_file(f'{name}.yaml'), params=params).start()


class Graph:
    def __init__(self, probe):
        self.probe = probe
        self.nodes = {name: start(name) for name in PROCESSING}
        self.fused = Collector(probe, Odometry, '/odometry/filtered', ESTIMATE_QOS)
        self.truth = Collector(probe, Odometry, '/ground_truth/odom', ESTIMATE_QOS)
        self.diagnostics = Collector(probe, DiagnosticArray, '/diagnostics', DIAG_QOS)
        assert spin_until(probe, lambda: set(PROCESSING) <= set(probe.get_node_names()), 60), \
            self.logs()
        # The probe is the ground truth's only subscriber: simulated time starts once it matched,
        # so the truth is complete from the first stamp.
        self.nodes['sensor_sim'] = start(
            'sensor_sim', real_time_factor=RATE, wait_for_subscribers=1
        )

    def logs(self):
        return '\n'.join(f'--- {n}\n{p.output()[-1500:]}' for n, p in self.nodes.items())

    def fusion_status(self):
        """Message and values of fusion's newest /diagnostics status (None before the first)."""
        for msg in reversed(self.diagnostics.messages):
            for status in msg.status:
                if status.name == 'complementary_fusion':
                    return status.message, {kv.key: kv.value for kv in status.values}
        return None

    def wait_fusion(self, condition, timeout):
        def check():
            status = self.fusion_status()
            return status is not None and condition(*status)
        return spin_until(self.probe, check, timeout)

    def newest_fused_stamp(self):
        return stamp_to_ns(self.fused.messages[-1].header.stamp) if self.fused.messages else 0

    def stop(self):
        for proc in self.nodes.values():
            proc.stop()
        for c in (self.fused, self.truth, self.diagnostics):
            c.close()


@pytest.fixture(scope='module')
def graph(probe):
    g = Graph(probe)
    yield g
    g.stop()


def truth_pose(graph, stamp):
    """Ground truth pose at a stamp (the newest truth sample at or before it)."""
    stamps = np.array([stamp_to_ns(m.header.stamp) for m in graph.truth.messages])
    i = int(np.searchsorted(stamps, stamp, side='right')) - 1
    assert i >= 0
    return odometry_pose(graph.truth.messages[i])[0], stamps[i]


def test_graph_runs(graph):
    assert graph.wait_fusion(
        lambda message, values: message == 'all enabled inputs present', 60
    ), graph.logs()
    assert spin_until(graph.probe, lambda: len(graph.fused.messages) > 50, 30), graph.logs()


# In this order the matcher's outage falls on a quick turn: the inputs left must carry the
# heading (gyro_integrator's, on the slow 90 deg turn, leaves the fusion's inputs whole).
@pytest.mark.parametrize('victim', ['wheel_odometry', 'icp_matcher', 'line_extractor',
                                    'gyro_integrator'])
def test_kill_and_restart(graph, victim):
    probe = graph.probe
    feeds = FEEDS[victim]
    assert graph.nodes[victim].alive(), graph.logs()
    os.kill(graph.nodes[victim].proc.pid, signal.SIGKILL)
    assert graph.nodes[victim].wait(10) == -signal.SIGKILL
    killed_at = graph.newest_fused_stamp()

    if feeds is not None:
        # Fusion notices, says which input is missing, and keeps publishing from the others.
        assert graph.wait_fusion(lambda message, values: message == f'missing: {feeds}', 30), \
            graph.logs()
    else:
        spin_until(probe, lambda: False, 3.0)
    during = graph.newest_fused_stamp()
    assert spin_until(probe, lambda: graph.newest_fused_stamp() > during + 1e9, 30), graph.logs()
    for name, proc in graph.nodes.items():
        assert name == victim or proc.alive(), \
            f'{name} died (exit {proc.proc.returncode}) with {victim}:\n{graph.logs()}'

    graph.nodes[victim] = start(victim)
    if feeds is not None:
        received = int(graph.fusion_status()[1][f'{feeds}_received'])
        assert graph.wait_fusion(
            lambda message, values: message == 'all enabled inputs present'
            and int(values[f'{feeds}_received']) > received + 5, 60), graph.logs()
    else:
        topic, msg_type = OUTPUTS[victim]
        output = Collector(probe, msg_type, topic, topic_qos(topic))
        assert spin_until(probe, lambda: len(output.messages) >= 3, 60), graph.logs()
        output.close()
    back = graph.newest_fused_stamp()
    assert spin_until(probe, lambda: graph.newest_fused_stamp() > back + 2e9, 30), graph.logs()
    for name, proc in graph.nodes.items():
        assert proc.alive(), (
            f'{name} is not running (exit {proc.proc.returncode}):\n{graph.logs()}'
        )
    graph.outages = getattr(graph, 'outages', []) + [(victim, killed_at, back)]


def test_fused_pose_stayed_continuous_and_followed_the_robot(graph):
    """Over the whole run with its four outages: no jump between consecutive fused poses beyond
    what the robot can move in the stamp time between them, and the fused motion over each
    outage (kill to 2 s after the restart) matches the ground truth's."""
    fused = [(stamp_to_ns(m.header.stamp), odometry_pose(m)[0]) for m in graph.fused.messages]
    assert len(fused) > 500
    stamps = [t for t, _ in fused]
    assert stamps == sorted(stamps), 'fusion went back in time (a reset)'
    # Allowed beyond what the robot can move: 10 cm. When wheel odometry comes back, its first
    # message carries no motion (it only sets the reference), yet fusion publishes the pose of
    # the last scan match with that message's newer stamp; the next scan match then moves the
    # pose by the whole interval (seen: 2.5 cm = 0.1 s at 0.25 m/s); the EKF's first correction
    # after an outage on a loaded machine moved it 5.6 cm (5 cm was the limit before). A restart
    # at a node's origin would be metres off.
    worst = (0.0, 0.0)
    for (t0, p0), (t1, p1) in zip(fused, fused[1:]):
        dt = (t1 - t0) * 1e-9
        step = se2.between(p0, p1)
        excess = (math.hypot(step[0], step[1]) - 1.5 * MAX_SPEED_M_S * dt,
                  abs(step[2]) - 1.5 * MAX_TURN_RAD_S * dt)
        worst = (max(worst[0], excess[0]), max(worst[1], excess[1]))
        assert excess[0] <= 0.10 and excess[1] <= 0.05, (t0, p0, p1)
    print(f'largest step beyond the robot\'s motion: {worst[0]:.3f} m, {worst[1]:.3f} rad')
    by_stamp = dict(fused)
    report = []
    for victim, killed_at, back in getattr(graph, 'outages', []):
        end = back + 2_000_000_000
        t_a = max(t for t in by_stamp if t <= killed_at)
        t_b = max(t for t in by_stamp if t <= end)
        moved = se2.between(by_stamp[t_a], by_stamp[t_b])
        truth_a, _ = truth_pose(graph, t_a)
        truth_b, _ = truth_pose(graph, t_b)
        truth_moved = se2.between(truth_a, truth_b)
        error = (math.hypot(moved[0] - truth_moved[0], moved[1] - truth_moved[1]),
                 abs(float(se2.wrap_angle(moved[2] - truth_moved[2]))))
        report.append((victim, (t_b - t_a) * 1e-9, math.hypot(*truth_moved[:2]), truth_moved[2],
                       error))
    print('\n'.join(f'{v}: {span:.1f} s, truth moved {d:.2f} m / {math.degrees(y):.1f} deg, '
                    f'fused off by {e[0]:.3f} m / {math.degrees(e[1]):.2f} deg'
                    for v, span, d, y, e in report))
    for victim, span, distance, turned, (position_error, heading_error) in report:
        assert position_error <= 0.05 + 0.05 * distance, (victim, report)
        assert heading_error <= math.radians(3.0), (victim, report)


def test_killing_fusion_itself_leaves_the_rest_running(graph):
    """kill -9 complementary_fusion: every other node keeps running and publishing; restarted,
    fusion finds all its inputs again and publishes a new fused pose (in a new odom frame: a
    new process starts at the origin)."""
    probe = graph.probe
    wheel = Collector(probe, Odometry, '/wheel/odom', ESTIMATE_QOS)
    os.kill(graph.nodes['complementary_fusion'].proc.pid, signal.SIGKILL)
    assert graph.nodes['complementary_fusion'].wait(10) == -signal.SIGKILL
    assert spin_until(probe, lambda: len(wheel.messages) >= 100, 30), graph.logs()
    for name, proc in graph.nodes.items():
        assert name == 'complementary_fusion' or proc.alive(), f'{name} died:\n{graph.logs()}'
    wheel.close()

    graph.diagnostics.messages.clear()
    graph.fused.messages.clear()
    graph.nodes['complementary_fusion'] = start('complementary_fusion')
    assert graph.wait_fusion(lambda message, values: message == 'all enabled inputs present'
                             and int(values['fusion_updates']) > 10, 60), \
        (graph.fusion_status(), graph.logs())
    assert spin_until(probe, lambda: len(graph.fused.messages) > 50, 30), graph.logs()
    fused = [odometry_pose(m)[0] for m in graph.fused.messages]
    assert all(np.all(np.isfinite(p)) for p in fused)
    for name, proc in graph.nodes.items():
        assert proc.alive(), (
            f'{name} is not running (exit {proc.proc.returncode}):\n{graph.logs()}'
        )
