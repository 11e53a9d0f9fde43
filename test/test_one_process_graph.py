"""sensing_graph: the five processing nodes in one process, each with its own name, parameters
and remappings (nothing leaks from one node to another), over real DDS; bad parameters exit 2;
SIGTERM stops it cleanly; the demo in one process. (Its lockstep replay of a shipped bag,
reproducing the recording: test_replay.py.)"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import tempfile

from harness import BIN, spin_until
from rcl_interfaces.srv import GetParameters
from rclpy.parameter import parameter_value_to_python

from sensing_nodes.topics import PROCESSING_NODES

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


def _subscriber_nodes(probe, topic: str) -> set[str]:
    return {i.node_name for i in probe.get_subscriptions_info_by_topic(topic)}


def test_each_node_keeps_its_name_parameters_and_remappings(probe):
    log = tempfile.TemporaryFile('w+')
    proc = subprocess.Popen(
        [*GRAPH, '--param', 'wheel_odometry:odom_frame:=odom_wheels',
         '--param', 'icp_matcher:keyframe_distance_m:=0.25',
         '--remap', 'line_extractor:/scan:=/scan_front'],
        stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
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
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
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
