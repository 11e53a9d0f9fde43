"""Managed (lifecycle) processing nodes over real DDS, brought up as nav2's lifecycle manager does:
each transition through the node's lifecycle_msgs services (/<node>/change_state,
/<node>/get_state), while the simulated robot's sensor streams keep flowing. The five nodes run
in one `sensing_graph --lifecycle` process (each its own node with its own services); nothing is
published before activate or after deactivate, inputs arriving while inactive are counted, a bad
parameter fails configure and is set right through set_parameters, cleanup removes the node's
topics, shutdown finalizes it. One node executable started managed, as robot.launch.py starts
them, and `ros2 lifecycle` (the vendored ROS 2 command line, where `make venv` installed it) on
another. (ros/processing_node.py; plain nodes, the default: every other node test.)"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import tempfile
from collections import defaultdict

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from harness import BIN, Collector, NodeProcess, laser_scan, publish_until, spin_until
from lifecycle_msgs.msg import State, Transition
from lifecycle_msgs.srv import ChangeState, GetState
from nav_msgs.msg import Odometry
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter
from sensor_msgs.msg import Imu, LaserScan, PointCloud2
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import MarkerArray

from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS, TF_QOS
from sensing_nodes.topics import (
    DIAGNOSTICS,
    FUSED,
    IMU,
    PROCESSING_NODES,
    SCAN,
    SCAN_LINES,
    SCAN_LINES_TABLE,
    SCAN_MATCH,
    SCAN_MATCH_KEYFRAME,
    TF,
    WHEEL_ODOM,
)

GRAPH = [sys.executable, '-m', 'sensing_nodes.tools.graph']
# Every output of the five nodes as configured in config/ (the fusion's odom -> base_link on /tf)
OUTPUTS = {WHEEL_ODOM: Odometry, IMU: Imu, SCAN_LINES: MarkerArray,
           SCAN_LINES_TABLE: PointCloud2, SCAN_MATCH: Odometry, SCAN_MATCH_KEYFRAME: Odometry,
           FUSED: Odometry, TF: TFMessage, DIAGNOSTICS: DiagnosticArray}
BAD_RADIUS = -0.05   # wheel_odometry's wheel_radius_m, given on the command line


class Outputs:
    """What the probe hears on every output topic, by topic (/diagnostics: by node, /tf: only
    the graph's odom -> base_link, sensor_sim publishes its ground truth there too)."""

    def __init__(self, probe) -> None:
        self.received: dict[str, list] = defaultdict(list)
        self.statuses: dict[str, list] = defaultdict(list)   # node -> its /diagnostics statuses
        self.scans = 0                                       # the simulator's, still arriving
        self._subscriptions = [
            probe.create_subscription(msg_type, topic, self._keeper(topic),
                                      TF_QOS if topic == TF else ESTIMATE_QOS)
            for topic, msg_type in OUTPUTS.items()]
        self._subscriptions.append(probe.create_subscription(
            LaserScan, SCAN, lambda _: setattr(self, 'scans', self.scans + 1), SENSOR_QOS))

    def _keeper(self, topic: str):
        def keep(msg) -> None:
            if topic == DIAGNOSTICS:
                for status in msg.status:
                    if status.name in PROCESSING_NODES:
                        self.received[topic].append(status.name)
                        self.statuses[status.name].append(
                            {kv.key: kv.value for kv in status.values})
            elif topic != TF or any(t.header.frame_id == 'odom' for t in msg.transforms):
                self.received[topic].append(msg)
        return keep

    def counts(self) -> dict[str, int]:
        return {topic: len(self.received[topic]) for topic in OUTPUTS}

    def clear(self) -> None:
        self.received.clear()
        self.statuses.clear()

    def writers_matched(self) -> bool:
        return all(s.get_publisher_count() > 0 for s in self._subscriptions)

    def close(self, probe) -> None:
        for subscription in self._subscriptions:
            probe.destroy_subscription(subscription)


class Lifecycle:
    """nav2's lifecycle manager's calls on one node: change_state with a transition id and
    get_state."""

    def __init__(self, probe, node: str) -> None:
        self.probe, self.node = probe, node
        self._change = probe.create_client(ChangeState, f'/{node}/change_state')
        self._get = probe.create_client(GetState, f'/{node}/get_state')
        self._set = probe.create_client(SetParameters, f'/{node}/set_parameters')

    def _call(self, client, request, attempts: int = 1):
        """The service's answer within 30 s. A query (attempts > 1) is asked again after
        30 / attempts s: wait_for_service sees the request side only, and an answer sent before
        the client's response reader has matched the server is lost (one 2-worker make test
        waited 30 s for a get_state)."""
        assert client.wait_for_service(timeout_sec=30.0), (self.node, client.srv_name)
        for _ in range(attempts):
            future = client.call_async(request)
            if spin_until(self.probe, future.done, 30.0 / attempts):
                return future.result()
            client.remove_pending_request(future)
        raise AssertionError(f'{self.node}: no answer on {client.srv_name} within 30 s')

    def change(self, transition: int) -> bool:
        return self._call(self._change, ChangeState.Request(
            transition=Transition(id=transition))).success

    def state(self) -> int:
        return self._call(self._get, GetState.Request(), attempts=3).current_state.id

    def set(self, name: str, value) -> tuple[bool, str]:
        result = self._call(self._set, SetParameters.Request(
            parameters=[Parameter(name, value=value).to_parameter_msg()])).results[0]
        return result.successful, result.reason

    def close(self) -> None:
        for client in (self._change, self._get, self._set):
            self.probe.destroy_client(client)


def _states(managers) -> dict[str, int]:
    return {name: m.state() for name, m in managers.items()}


def _transition(managers, transition: int) -> dict[str, bool]:
    """The transition on every node, in the graph's order (as a lifecycle manager does)."""
    return {name: m.change(transition) for name, m in managers.items()}


def _quiet_while_inputs_flow(probe, outputs: Outputs, seconds: float) -> dict[str, int]:
    """Listen for `seconds` while the simulator's scans keep arriving: what was published."""
    # Its scans reach the probe first: a simulator just started may still be matching it (one
    # 2-worker make test had none within the 1 s window).
    assert spin_until(probe, lambda: outputs.scans > 0, 30.0), 'no scan from the simulator'
    scans = outputs.scans
    spin_until(probe, lambda: False, seconds)
    assert outputs.scans >= scans + 5, 'the simulator stopped: the silence would prove nothing'
    return {topic: n for topic, n in outputs.counts().items() if n}


def test_every_transition_over_lifecycle_services(probe):
    outputs = Outputs(probe)
    managers = {name: Lifecycle(probe, name) for name in PROCESSING_NODES}
    log = tempfile.TemporaryFile('w+')
    graph = subprocess.Popen(
        [*GRAPH, '--lifecycle', '--param', f'wheel_odometry:wheel_radius_m:={BAD_RADIUS}'],
        stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        with NodeProcess('sensor_sim') as sim:
            # unconfigured: the lifecycle services answer, nothing is published
            unconfigured = {name: State.PRIMARY_STATE_UNCONFIGURED for name in PROCESSING_NODES}
            assert _states(managers) == unconfigured
            assert _quiet_while_inputs_flow(probe, outputs, 1.0) == {}

            # configure: the bad wheel radius fails it, the node stays unconfigured; set right
            # through set_parameters, configure succeeds
            configured = _transition(managers, Transition.TRANSITION_CONFIGURE)
            assert configured == {name: name != 'wheel_odometry' for name in PROCESSING_NODES}
            assert _states(managers) == {**unconfigured, **{
                name: State.PRIMARY_STATE_INACTIVE for name in PROCESSING_NODES
                if name != 'wheel_odometry'}}
            log.seek(0)
            assert ("[wheel_odometry]: invalid parameter: parameter 'wheel_radius_m' must be a "
                    f'finite number > 0 (got {BAD_RADIUS})') in log.read()
            wheels = managers['wheel_odometry']
            assert wheels.set('wheel_radius_m', 0.05) == (True, '')
            assert wheels.change(Transition.TRANSITION_CONFIGURE)
            inactive = {name: State.PRIMARY_STATE_INACTIVE for name in PROCESSING_NODES}
            assert _states(managers) == inactive
            # configured: parameters are refused until cleanup; a transition the state has not
            # is refused too (and the node lives on)
            ok, reason = wheels.set('wheel_radius_m', 0.06)
            assert not ok and 'read at configure' in reason, reason
            assert not wheels.change(Transition.TRANSITION_CONFIGURE)

            # inactive: every output's writer exists and has matched the probe, the inputs
            # flow, nothing is published
            assert spin_until(probe, outputs.writers_matched, 30.0), outputs.counts()
            assert _quiet_while_inputs_flow(probe, outputs, 2.0) == {}

            # activate: every output flows, /diagnostics of each node the simulator feeds
            # counts what it dropped while inactive (the fusion's inputs, the others' outputs,
            # were silent then)
            assert _transition(managers, Transition.TRANSITION_ACTIVATE) == dict.fromkeys(
                PROCESSING_NODES, True)
            assert _states(managers) == {name: State.PRIMARY_STATE_ACTIVE
                                         for name in PROCESSING_NODES}
            assert spin_until(probe, lambda: all(outputs.counts().values())
                              and set(outputs.statuses) == set(PROCESSING_NODES), 40.0), \
                outputs.counts()
            dropped = {name: int(outputs.statuses[name][0].get('dropped_inactive', 0))
                       for name in PROCESSING_NODES if name != 'complementary_fusion'}
            assert all(n > 0 for n in dropped.values()), dropped

            # the fusion alone inactive: its inputs, handed over in the process by the active
            # nodes, are dropped and counted, and it publishes nothing until active again
            fusion = managers['complementary_fusion']
            assert fusion.change(Transition.TRANSITION_DEACTIVATE)
            spin_until(probe, lambda: False, 0.5)
            outputs.clear()
            spin_until(probe, lambda: False, 1.5)
            assert outputs.received[WHEEL_ODOM] and outputs.received[IMU], outputs.counts()
            assert not outputs.received[FUSED] and 'complementary_fusion' not in outputs.statuses
            before = outputs.counts()[WHEEL_ODOM]
            assert fusion.change(Transition.TRANSITION_ACTIVATE)
            assert spin_until(probe, lambda: 'complementary_fusion' in outputs.statuses, 10.0)
            assert int(outputs.statuses['complementary_fusion'][0].get(
                'dropped_inactive', 0)) >= before, outputs.statuses['complementary_fusion'][0]

            # deactivate: nothing more is published while the inputs keep flowing (what was in
            # flight when the answers came is let through first)
            assert _transition(managers, Transition.TRANSITION_DEACTIVATE) == dict.fromkeys(
                PROCESSING_NODES, True)
            assert _states(managers) == inactive
            spin_until(probe, lambda: False, 0.5)
            outputs.clear()
            assert _quiet_while_inputs_flow(probe, outputs, 3.0) == {}

            # cleanup: the nodes' topics are gone, the parameters settable again
            assert _transition(managers, Transition.TRANSITION_CLEANUP) == dict.fromkeys(
                PROCESSING_NODES, True)
            assert _states(managers) == unconfigured
            assert spin_until(probe, lambda: not any(
                probe.get_publishers_info_by_topic(topic) for topic in
                (WHEEL_ODOM, IMU, SCAN_LINES, SCAN_MATCH, FUSED)), 30.0)
            assert not {i.node_name for i in probe.get_subscriptions_info_by_topic(SCAN)} & {
                'line_extractor', 'icp_matcher'}
            assert wheels.set('wheel_radius_m', 0.06) == (True, '')

            # shutdown from unconfigured: finalized; the process lives on until stopped
            assert _transition(managers, Transition.TRANSITION_UNCONFIGURED_SHUTDOWN) == \
                dict.fromkeys(PROCESSING_NODES, True)
            assert _states(managers) == {name: State.PRIMARY_STATE_FINALIZED
                                         for name in PROCESSING_NODES}
            assert sim.alive() and graph.poll() is None
        graph.terminate()
        assert graph.wait(20) == 0
    finally:
        if graph.poll() is None:
            graph.kill()
            graph.wait()
        for manager in managers.values():
            manager.close()
        outputs.close(probe)
        log.seek(0)
        text = log.read()
        print(text)   # shown by pytest when the test fails
    assert 'Traceback' not in text, text


def test_a_managed_executable_owns_no_topic_until_configured_and_answers_once_active(probe):
    with NodeProcess('line_extractor', params={'lifecycle': True}) as node:
        manager = Lifecycle(probe, 'line_extractor')
        scans = probe.create_publisher(LaserScan, SCAN, SENSOR_QOS)
        tables = Collector(probe, PointCloud2, SCAN_LINES_TABLE, ESTIMATE_QOS)
        try:
            assert manager.state() == State.PRIMARY_STATE_UNCONFIGURED, node.output()
            assert 'line_extractor' not in {
                i.node_name for i in probe.get_subscriptions_info_by_topic(SCAN)}
            assert manager.change(Transition.TRANSITION_CONFIGURE), node.output()
            assert manager.change(Transition.TRANSITION_ACTIVATE), node.output()
            # a wall 2 m ahead: one line in the table
            scan = laser_scan(1_000_000_000, 2.0 / np.cos(np.radians(np.arange(-45, 46))),
                              angle_min=np.radians(-45.0), increment=np.radians(1.0))
            assert publish_until(probe, scans, scan, lambda: tables.messages, outputs=tables), \
                node.output()
            assert tables.messages[0].width == 1
        finally:
            tables.close()
            probe.destroy_publisher(scans)
            manager.close()
        assert node.stop() == 0, node.output()


@pytest.mark.skipif(
    not (BIN / 'ros2').is_file() or importlib.util.find_spec('ros2lifecycle') is None,
    reason='the ROS 2 command line (ros2 lifecycle) is not in the venv: make venv installs it '
           'from ../shared/vendor/ros2-jazzy where that exists (a ROS install has its own)')
def test_ros2_lifecycle_set_and_get(probe):
    """configure and activate by `ros2 lifecycle set`, the state by `ros2 lifecycle get` (each
    verb takes seconds: the rest of the transitions are the services' test above)."""
    def ros2_lifecycle(*args: str) -> subprocess.CompletedProcess:
        # No daemon, as every ros2 verb the tests run. A verb that has not discovered the node
        # in its spin time (a loaded machine) says so: once more with longer.
        for spin_s in ('3', '8'):
            done = subprocess.run([str(BIN / 'ros2'), 'lifecycle', *args, '--no-daemon',
                                   '--spin-time', spin_s], capture_output=True, text=True,
                                  timeout=60)
            if 'Node not found' not in done.stderr:
                break
        return done

    with NodeProcess('wheel_odometry', params={'lifecycle': True}) as node:
        assert spin_until(probe, lambda: 'wheel_odometry' in probe.get_node_names(), 30.0)
        for transition in ('configure', 'activate'):
            done = ros2_lifecycle('set', '/wheel_odometry', transition)
            assert done.returncode == 0 and done.stdout.strip() == 'Transitioning successful', \
                (transition, done, node.output())
        got = ros2_lifecycle('get', '/wheel_odometry')
        assert got.stdout.strip() == 'active [3]', (got, node.output())
