"""sensing_replay: lockstep replay of the project's bags through the real node processes
reproduces the recorded outputs, twice in a row and after time jumps backwards; bad input is
refused with the file and topic named and nothing left behind."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from harness import REPO, run_to_exit
from rclpy.serialization import deserialize_message

from sensing_nodes.bag import BagWriter, message_class, topic_counts
from sensing_nodes.tools.replay import (
    DEFAULT_EXPECTATIONS,
    compare_outputs,
    load_bag,
    marker_array_stamp_ns,
    output_messages,
)

BAGS = REPO / 'bags'
# Every output of the graph that is a function of the inputs (not /diagnostics: wall-clock timer).
OUTPUTS = {'/wheel/odom', '/imu/data', '/scan/lines', '/scan/lines/table', '/scan_match/odom',
           '/odometry/filtered'}
# rclpy's CDR serialiser leaves the 3 alignment bytes after each of Marker's bools (frame_locked,
# mesh_use_embedded_materials) uninitialised, so MarkerArray bytes differ run to run while every
# field is equal. Every other output is compared byte for byte.
VALUE_EQUAL_ONLY = {'/scan/lines'}
NODE_LOGS = ('wheel_odometry', 'gyro_integrator', 'line_extractor', 'icp_matcher',
             'complementary_fusion')


REGENERATE = ('if a node\'s output changed on purpose, regenerate the bags: '
              '.venv/bin/python -m sensing_nodes.tools.replay --make-bags bags/')


def _assert_reproduces(recorded: Path, replayed: Path, hint: str = REGENERATE) -> None:
    types = {t: v[0] for t, v in topic_counts(recorded).items()}
    report = compare_outputs(output_messages(recorded, OUTPUTS), output_messages(replayed, OUTPUTS),
                             types)
    for topic, entry in report.items():
        assert entry['expected'] == entry['actual'] > 0, (topic, entry, hint)
        assert entry['max_difference'] == 0.0, (topic, entry, hint)
        if topic not in VALUE_EQUAL_ONLY:
            assert entry['identical'] == entry['expected'], (topic, entry, hint)


def _replay(args: list[str], timeout: float = 150.0):
    return run_to_exit('sensing_replay', [*args, '--no-progress'], timeout=timeout)


def test_nominal_bag_reproduced_twice_back_to_back_with_every_node_reset(tmp_path):
    out, logs = tmp_path / 'out', tmp_path / 'logs'
    result = _replay([str(BAGS / 'nominal'), str(out), '--launch', '--loops', '2',
                      '--logs', str(logs)])
    assert result.returncode == 0, result.stdout + result.stderr
    assert 'MISSING' not in result.stdout
    # Pass 2 follows a jump back in time and equals pass 1; both equal the recording (made by an
    # earlier lockstep replay, so this is also "twice in a row").
    _assert_reproduces(out / 'pass-1', out / 'pass-2', 'not deterministic across a loop')
    _assert_reproduces(BAGS / 'nominal', out / 'pass-1')
    _assert_reproduces(BAGS / 'nominal', out / 'pass-2')
    for node in NODE_LOGS:
        text = (logs / 'logs' / f'{node}.log').read_text()
        assert 'backwards' in text, f'{node} did not report time going backwards:\n{text}'


def test_strong_errors_bag_reproduced(tmp_path):
    out = tmp_path / 'out'
    result = _replay([str(BAGS / 'strong_errors'), str(out), '--launch', '--check'])
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.count('reproduced:') == len(OUTPUTS) and 'DIFFERS' not in result.stdout
    _assert_reproduces(BAGS / 'strong_errors', out)
    # The output bag holds the inputs and ground truth too, so it replays like the original.
    counts = topic_counts(out)
    original = topic_counts(BAGS / 'strong_errors')
    for topic in ('/scan', '/imu/data_raw', '/joint_states', '/ground_truth/odom', '/clock'):
        assert counts[topic] == original[topic]


def test_timed_mode_feeds_the_line_extractor_every_scan(tmp_path):
    out = tmp_path / 'out'
    result = _replay([str(BAGS / 'nominal'), str(out), '--launch', '--mode', 'timed',
                      '--rate', '5', '--nodes', 'line_extractor', '--expect',
                      '/scan=/scan/lines,/scan/lines/table'])
    assert result.returncode == 0, result.stdout + result.stderr
    counts = topic_counts(out)
    scans = counts['/scan'][1]
    assert counts['/scan/lines/table'][1] == scans and counts['/scan/lines'][1] == scans
    _assert_table_equal(BAGS / 'nominal', out)


def _assert_table_equal(recorded: Path, replayed: Path) -> None:
    a = output_messages(recorded, {'/scan/lines/table'})['/scan/lines/table']
    b = output_messages(replayed, {'/scan/lines/table'})['/scan/lines/table']
    assert a == b


# -- bad input: no graph needed, the bag is checked before anything is started -------------------
def _small_bag(path: Path, topics: dict[str, object]) -> Path:
    with BagWriter(path) as bag:
        for topic, msg in topics.items():
            bag.write(topic, msg, 1_700_000_000_000_000_000)
    return path


def _assert_refused(result, *words, out: Path) -> None:
    assert result.returncode == 2, result.stdout + result.stderr
    for word in words:
        assert word in result.stderr, result.stderr
    assert not out.exists()
    assert not any(p.name.startswith(f'.{out.name}') for p in out.parent.iterdir())


def test_missing_bag_is_refused(tmp_path):
    out = tmp_path / 'out'
    result = _replay([str(tmp_path / 'no_such_bag'), str(out)])
    _assert_refused(result, 'no_such_bag', 'no such bag', out=out)


def test_truncated_bag_is_refused_before_anything_is_sent(tmp_path):
    bag = tmp_path / 'cut'
    shutil.copytree(BAGS / 'nominal', bag)
    mcap = bag / 'nominal.mcap'
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])
    out = tmp_path / 'out'
    result = _replay([str(bag), str(out), '--launch'])
    _assert_refused(result, str(bag), 'truncated', out=out)


def test_bag_without_an_input_topic_is_refused(tmp_path):
    from sensor_msgs.msg import Imu, LaserScan

    bag = _small_bag(tmp_path / 'partial', {'/scan': LaserScan(), '/imu/data_raw': Imu()})
    out = tmp_path / 'out'
    result = _replay([str(bag), str(out), '--launch'])
    _assert_refused(result, str(bag), '/joint_states', 'not in the bag', out=out)


def test_bag_with_a_wrong_type_is_refused(tmp_path):
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Imu, JointState

    bag = _small_bag(tmp_path / 'wrong', {'/scan': Odometry(), '/imu/data_raw': Imu(),
                                          '/joint_states': JointState()})
    out = tmp_path / 'out'
    result = _replay([str(bag), str(out), '--launch'])
    _assert_refused(result, str(bag), '/scan', 'nav_msgs/msg/Odometry',
                    'sensor_msgs/msg/LaserScan', out=out)


def test_existing_output_is_not_overwritten(tmp_path):
    out = tmp_path / 'out'
    out.mkdir()
    (out / 'keep').write_text('x')
    result = _replay([str(BAGS / 'nominal'), str(out)])
    assert result.returncode == 2 and 'already exists' in result.stderr
    assert (out / 'keep').read_text() == 'x'


# -- pieces -----------------------------------------------------------------------------------------
def test_bag_order_is_stamp_order_with_ties_as_stored():
    bag = load_bag(BAGS / 'nominal')
    stamps = [s for _, s, _ in bag.messages]
    assert stamps == sorted(stamps)
    first_scan = next(s for t, s, _ in bag.messages if t == '/scan')
    inputs = {'/clock', '/ground_truth/odom', '/imu/data_raw', '/joint_states', '/scan'}
    at = [t for t, s, _ in bag.messages if s == first_scan + 100_000_000 and t in inputs]
    # The simulator writes a tick's samples in this order; the replay keeps it.
    assert at == ['/clock', '/ground_truth/odom', '/imu/data_raw', '/joint_states', '/scan']


def test_marker_array_stamp_is_read_from_the_first_marker():
    from visualization_msgs.msg import Marker, MarkerArray
    from rclpy.serialization import serialize_message

    msg = MarkerArray(markers=[Marker(), Marker()])
    msg.markers[0].header.stamp.sec, msg.markers[0].header.stamp.nanosec = 17, 250
    assert marker_array_stamp_ns(serialize_message(msg), 5) == 17_000_000_250
    assert marker_array_stamp_ns(serialize_message(MarkerArray()), 5) == 5


def test_every_expected_output_carries_its_input_stamp():
    """The expectation table holds for the recording: one output per input, same stamp."""
    bag = BAGS / 'nominal'
    counts = topic_counts(bag)
    for source, outputs in DEFAULT_EXPECTATIONS.items():
        stamps = [s for _, s, _ in _messages(bag, source)]
        for output in outputs:
            assert counts[output][1] == counts[source][1]
            got = [s for _, s, _ in _messages(bag, output)]
            assert got == stamps, output


def _messages(bag: Path, topic: str):
    from rosbags.rosbag2 import Reader

    with Reader(bag) as reader:
        connections = [c for c in reader.connections if c.topic == topic]
        msg_type = message_class(connections[0].msgtype)
        for c, stamp, raw in reader.messages(connections=connections):
            yield topic, stamp, deserialize_message(raw, msg_type)


def test_a_node_failing_at_start_up_is_an_error_without_output(tmp_path):
    out = tmp_path / 'out'
    result = _replay([str(BAGS / 'nominal'), str(out), '--launch', '--nodes', 'icp_matcher',
                      '--expect', '/scan=/scan_match/odom', '--param',
                      'icp_matcher:method:=nonsense'], timeout=60)
    _assert_refused(result, 'icp_matcher', 'exited at start-up', 'node logs in', out=out)
    log_dir = Path(result.stderr.split('node logs in ')[1].split()[0])
    assert "invalid parameter" in (log_dir / 'icp_matcher.log').read_text()
    shutil.rmtree(log_dir.parent)
