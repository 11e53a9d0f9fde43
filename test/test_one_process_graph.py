"""sensing_graph: the five processing nodes in one process, each with its own name, parameters
and remappings (nothing leaks from one node to another), over real DDS; bad parameters exit 2;
SIGTERM stops it cleanly; its in-process edges (a topic between its nodes on DDS only while a
subscriber outside listens, and the same messages there as with --over-dds); the demo in one
process. (Its lockstep replay of a shipped bag, reproducing the recording: test_replay.py.)"""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager

import pytest
from harness import BIN, REPO, Collector, spin_until
from nav_msgs.msg import Odometry
from rcl_interfaces.srv import GetParameters
from rclpy.parameter import parameter_value_to_python

from sensing_nodes.bags.input_bag import load_bag
from sensing_nodes.bags.stamps import leading_stamp_ns
from sensing_nodes.bags.storage import message_class
from sensing_nodes.graph.compare import compare_outputs
from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS
from sensing_nodes.topics import FUSED, IMU, IMU_RAW, JOINT_STATES, PROCESSING_NODES, WHEEL_ODOM

GRAPH = [sys.executable, '-m', 'sensing_nodes.tools.graph']


def _get(probe, node: str, names: list[str]) -> dict:
    """Parameter values of a running node, through its get_parameters service."""
    client = probe.create_client(GetParameters, f'/{node}/get_parameters')
    try:
        assert client.wait_for_service(timeout_sec=20.0), node
        future = client.call_async(GetParameters.Request(names=names))
        assert spin_until(probe, future.done, 20.0), node
        return {n: parameter_value_to_python(v) for n, v in zip(names, future.result().values)}
    finally:
        probe.destroy_client(client)


@contextmanager
def _graph(args: list[str], log):
    """sensing_graph with `args` as a child process logging to `log`; killed on the way out
    if the test did not stop it."""
    proc = subprocess.Popen([*GRAPH, *args], stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _terminate(proc) -> None:
    """SIGTERM, as a service manager stops the graph: it must end cleanly."""
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(20) == 0


def _subscriber_nodes(probe, topic: str) -> set[str]:
    return {i.node_name for i in probe.get_subscriptions_info_by_topic(topic)}


def test_each_node_keeps_its_name_parameters_and_remappings(probe):
    log = tempfile.TemporaryFile('w+')
    with _graph(['--param', 'wheel_odometry:odom_frame:=odom_wheels',
                 '--param', 'icp_matcher:keyframe_distance_m:=0.25',
                 '--remap', 'line_extractor:/scan:=/scan_front'], log) as proc:
        assert spin_until(probe, lambda: set(PROCESSING_NODES) <= set(probe.get_node_names())
                          and _subscriber_nodes(probe, '/scan_front'), 60.0), \
            probe.get_node_names()
        # Its own override; the other node with a parameter of that name keeps its file's value.
        assert _get(probe, 'wheel_odometry', ['odom_frame', 'right_radius_multiplier']) == {
            'odom_frame': 'odom_wheels', 'right_radius_multiplier': 1.01}   # 1.01: its yaml
        assert _get(probe, 'icp_matcher', ['odom_frame', 'keyframe_distance_m']) == {
            'odom_frame': 'odom', 'keyframe_distance_m': 0.25}
        # The remapping is the line extractor's alone: the matcher still takes /scan.
        assert _subscriber_nodes(probe, '/scan_front') == {'line_extractor'}
        assert _subscriber_nodes(probe, '/scan') == {'icp_matcher'}
        assert 'wheel_odometry' in _subscriber_nodes(probe, '/joint_states')
        # Plain nodes (the default): not managed, no lifecycle service (test_lifecycle.py).
        assert _get(probe, 'line_extractor', ['lifecycle']) == {'lifecycle': False}
        assert not [name for name, _ in probe.get_service_names_and_types()
                    if name.endswith('/change_state')]
        _terminate(proc)
    log.seek(0)
    text = log.read()
    assert 'Traceback' not in text, text
    for node in PROCESSING_NODES:   # each node logs under its own name
        assert f'[{node}]' in text, text


def test_a_bad_parameter_of_any_node_exits_2_naming_node_and_parameter():
    result = subprocess.run([*GRAPH, '--param', 'complementary_fusion:method:=kalmanish'],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2, result.stdout + result.stderr
    assert '[complementary_fusion] invalid parameter' in result.stderr, result.stderr
    assert "'method'" in result.stderr and 'Traceback' not in result.stderr, result.stderr
    for bad in (['--param', 'no_such_node:x:=1'], ['--remap', 'icp_matcher:/scan'],
                ['--params-file', '/nonexistent.yaml']):
        result = subprocess.run([*GRAPH, *bad], capture_output=True, text=True, timeout=60)
        assert result.returncode == 2 and 'sensing_graph: error' in result.stderr, (bad, result)


def _in_process_counts(log: str) -> dict[str, tuple[int, int, int]]:
    """sensing_graph's exit lines: topic -> (handed over in-process, on DDS, not on DDS)."""
    return {m[1]: (int(m[2]), int(m[3]), int(m[4])) for m in re.finditer(
        r'sensing_graph: (\S+): (\d+) handed over in-process, (\d+) published on DDS, '
        r'(\d+) not', log)}


def _publish_at(probe, publishers, messages, rate: float) -> None:
    """(topic, bag time, CDR bytes) in bag order, each at its bag time / rate from now."""
    start, first = time.monotonic(), messages[0][1]
    for topic, stamp, raw in messages:
        while (due := start + (stamp - first) * 1e-9 / rate) > time.monotonic():
            spin_until(probe, lambda: False, min(due - time.monotonic(), 0.005))
        publishers[topic].publish(raw)


@pytest.mark.parametrize('over_dds', [False, True], ids=['in_process', 'over_dds'])
def test_internal_topics_on_dds_only_while_a_subscriber_outside_listens(probe, over_dds):
    """wheel_odometry, gyro_integrator and the fusion in one process, fed 6 s of bags/nominal
    (at 2x) from this process: in-process, /wheel/odom goes on DDS only while someone outside
    the process subscribes (none for the first half, the graph's counts at exit say so, and the
    fusion answers anyway), /imu/data (the fusion reads the raw IMU) not at all; the probe that
    subscribes /wheel/odom for the second half receives every message published on DDS from
    then on, equal to what the five node processes recorded in the bag over DDS (the replay's
    tolerance), as with --over-dds."""
    bag = load_bag(REPO / 'bags' / 'nominal')
    first = bag.messages[0][1]
    inputs = [m for m in bag.messages if m[0] in (JOINT_STATES, IMU_RAW) and m[1] < first + 6e9]
    half = len(inputs) // 2
    publishers = {t: probe.create_publisher(message_class(bag.types[t]), t, SENSOR_QOS)
                  for t in (JOINT_STATES, IMU_RAW)}
    fused = Collector(probe, Odometry, FUSED, ESTIMATE_QOS)
    log = tempfile.TemporaryFile('w+')
    wheel = []
    try:
        with _graph(['--nodes', 'wheel_odometry,gyro_integrator,complementary_fusion',
                     *(['--over-dds'] if over_dds else [])], log) as proc:
            assert spin_until(probe, lambda: fused.matched() and all(
                p.get_subscription_count() for p in publishers.values()), 60.0)
            spin_until(probe, lambda: False, 0.5)   # the graph's writers match the probe too
            _publish_at(probe, publishers, inputs[:half], 2.0)
            assert spin_until(probe, lambda: fused.messages, 10.0), 'the fusion never answered'
            subscription = probe.create_subscription(Odometry, WHEEL_ODOM, wheel.append,
                                                     ESTIMATE_QOS, raw=True)
            assert spin_until(probe, lambda: subscription.get_publisher_count() > 0, 20.0)
            spin_until(probe, lambda: False, 1.0)   # ... and the graph's writer this reader
            _publish_at(probe, publishers, inputs[half:], 2.0)
            joints = sum(m[0] == JOINT_STATES for m in inputs[half:])
            spin_until(probe, lambda: len(wheel) >= joints, 10.0)
            spin_until(probe, lambda: False, 1.0)   # the graph's last inputs processed: quiet
            _terminate(proc)
    finally:
        fused.close()
        log.seek(0)
        text = log.read()
        print(text)   # shown by pytest when the test fails
    assert 'Traceback' not in text, text
    counts = _in_process_counts(text)
    if over_dds:
        assert 'in-process edges off (--over-dds)' in text and not counts, text
    else:
        assert 'in-process edges: ' in text, text
        # Every joint state published was processed and its odometry handed over (none lost
        # on the way in: the comparison below needs them all); /imu/data not even made:
        # nobody takes it, inside (the fusion reads the raw IMU itself) or outside ...
        assert counts[WHEEL_ODOM][0] == sum(m[0] == JOINT_STATES for m in inputs), counts
        assert counts[IMU] == (0, 0, 0), counts
        # ... and /wheel/odom on DDS only to the probe
        handed, on_dds, not_on_dds = counts[WHEEL_ODOM]
        assert on_dds == len(wheel) and on_dds + not_on_dds == handed, (counts, len(wheel))
        assert not_on_dds >= sum(m[0] == JOINT_STATES for m in inputs[:half]), counts
    # What the probe heard: the bag's messages of those stamps, computed over DDS there.
    assert len(wheel) >= joints - 5, (len(wheel), joints)
    stamps = {leading_stamp_ns(raw) for raw in wheel}
    recorded = [(leading_stamp_ns(raw), raw) for t, _, raw in bag.messages
                if t == WHEEL_ODOM and leading_stamp_ns(raw) in stamps]
    report = compare_outputs({WHEEL_ODOM: recorded},
                             {WHEEL_ODOM: [(leading_stamp_ns(raw), raw) for raw in wheel]},
                             {WHEEL_ODOM: bag.types[WHEEL_ODOM]})[WHEEL_ODOM]
    assert report['reproduced'] and report['expected'] == len(wheel), report


# The lockstep replay through one sensing_graph process reproducing the recorded bag (with
# --check, under a forced OpenBLAS kernel): test_replay.py's
# test_strong_errors_bag_reproduced_under_two_blas_kernels[0].


def test_demo_in_one_process_scores_every_estimate(tmp_path):
    out = tmp_path / 'run'
    result = subprocess.run(
        [str(BIN / 'sensing_demo'), '--one-process', '--duration', '15', '--out', str(out),
         '--quiet'], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    assert sorted(p.name for p in (out / 'logs').iterdir()) == ['sensing_graph.log',
                                                                'sensor_sim.log']
    report = json.loads((out / 'report.json').read_text())
    # 15 s of 10 Hz scans stamped from 0 s; the one stamped at 15 s ends its sweep after the run
    assert report['scans']['published_by_sim'] == 150
    for name, entry in report['estimates'].items():
        assert not entry.get('missing'), name
    # The simulated route's first 15 s: the fusion ends within centimetres of the truth.
    assert report['estimates']['fused']['final_position_error_m'] < 0.05, report['estimates']
