"""`sensor_sim --record`: a rosbag2 MCAP bag without DDS, deterministic for a seed, equal to the
batch simulation, and read back identically by rosbags (+ rclpy) and by mcap-ros2-support."""

import hashlib
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from harness import REPO, run_to_exit

from sensing_nodes.bags.storage import read_messages, topic_counts, type_name
from sensing_nodes.core.sim import simulator as sim
from sensing_nodes.core.sim.world import load_world

DURATION = 8.0
RATES = {'/clock': 100.0, '/ground_truth/odom': 100.0, '/imu/data_raw': 200.0,
         '/joint_states': 50.0, '/scan': 10.0}


def record(path: Path, seed: int, *extra: str):
    result = run_to_exit('sensor_sim', ['--record', str(path), '--duration', str(DURATION),
                                        '--seed', str(seed), '--quiet', *extra])
    assert result.returncode == 0, result.stdout + result.stderr
    return result


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    """Two recordings with seed 5 (same directory name, different parents) and one with seed 6."""
    root = tmp_path_factory.mktemp('bags')
    paths = {}
    for name, seed in (('a', 5), ('b', 5), ('c', 6)):
        (root / name).mkdir()
        paths[name] = root / name / 'run'
        record(paths[name], seed)
    return paths


def mcap_file(bag: Path) -> Path:
    (path,) = bag.glob('*.mcap')
    return path


def raw_messages(bag: Path):
    from mcap.reader import make_reader

    with open(mcap_file(bag), 'rb') as f:
        return [(c.topic, m.log_time, m.data) for _, c, m in make_reader(f).iter_messages()]


def fields_equal(a, b, path=''):
    """Every field of rclpy message a equals the same field of b (any message object)."""
    for name in a.get_fields_and_field_types():
        va, vb = getattr(a, name), getattr(b, name)
        if hasattr(va, 'get_fields_and_field_types'):
            fields_equal(va, vb, f'{path}.{name}')
        elif isinstance(va, str) or (isinstance(va, list) and va and isinstance(va[0], str)):
            assert va == vb, f'{path}.{name}'
        else:
            np.testing.assert_array_equal(np.asarray(va), np.asarray(vb), err_msg=f'{path}.{name}')


def test_bag_has_every_topic_at_its_rate_and_valid_metadata(bags):
    counts = topic_counts(bags['a'])
    assert set(counts) == set(RATES)
    for topic, rate in RATES.items():
        # both ends included; the scan stamped at the end goes out 0.1 s later (its sweep)
        expected = round(rate * DURATION) + (0 if topic == '/scan' else 1)
        assert counts[topic][1] == expected, topic
    meta = yaml.safe_load((bags['a'] / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['storage_identifier'] == 'mcap'
    assert meta['starting_time']['nanoseconds_since_epoch'] == sim.SimParams().start_ns
    assert meta['duration']['nanoseconds'] == int(DURATION * 1e9)


def test_same_seed_same_messages_and_metadata_different_seed_different_noise(bags):
    a, b, c = (raw_messages(bags[k]) for k in 'abc')
    assert (bags['a'] / 'metadata.yaml').read_bytes() == (bags['b'] / 'metadata.yaml').read_bytes()
    assert [(t, s) for t, s, _ in a] == [(t, s) for t, s, _ in b]
    # Messages are stored in canonical CDR (padding zero), so the .mcap files are byte-identical.
    assert hashlib.sha256(mcap_file(bags['a']).read_bytes()).hexdigest() \
        == hashlib.sha256(mcap_file(bags['b']).read_bytes()).hexdigest()
    msgs = {k: list(read_messages(bags[k])) for k in 'abc'}
    for (ta, sa, ma), (tb, sb, mb) in zip(msgs['a'], msgs['b']):
        assert (ta, sa) == (tb, sb)
        assert ma == mb, (ta, sa)
    by_topic = {k: {} for k in 'ac'}
    for k in 'ac':
        for topic, _, msg in msgs[k]:
            by_topic[k].setdefault(topic, []).append(msg)
    assert by_topic['a']['/ground_truth/odom'] == by_topic['c']['/ground_truth/odom']
    for topic in ('/scan', '/imu/data_raw'):
        differ = sum(x != y for x, y in zip(by_topic['a'][topic], by_topic['c'][topic]))
        assert differ == len(by_topic['a'][topic]), topic       # every noisy sample differs


def test_bag_holds_exactly_the_batch_simulation(bags):
    world = load_world(REPO / 'config' / 'default_world.yaml')
    run = sim.simulate(sim.SimParams(), world, DURATION, seed=5)
    got = {}
    for topic, stamp, msg in read_messages(bags['a']):
        t = msg.header.stamp if hasattr(msg, 'header') else msg.clock
        # bag time = when the message goes out: its stamp, a scan's when its sweep has ended
        sweep = 10**8 if topic == '/scan' else 0
        assert stamp == t.sec * 10**9 + t.nanosec + sweep
        got.setdefault(topic, []).append(msg)
    scans = got['/scan']
    ranges = np.array([m.ranges for m in scans], dtype=np.float32)
    np.testing.assert_array_equal(ranges, run.scan_ranges)
    assert scans[0].time_increment == pytest.approx(0.1 / 360)
    assert scans[0].header.frame_id == 'laser'
    assert scans[0].angle_min == pytest.approx(run.scan_angle_min)
    assert scans[0].angle_increment == pytest.approx(run.scan_angle_increment)
    assert (scans[0].range_min, scans[0].range_max) == pytest.approx((0.12, 8.0))
    imus = got['/imu/data_raw']
    gyro = [[m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z] for m in imus]
    np.testing.assert_array_equal(gyro, run.imu_gyro)
    np.testing.assert_array_equal([[m.linear_acceleration.x, m.linear_acceleration.y,
                                    m.linear_acceleration.z] for m in imus], run.imu_accel)
    assert imus[0].header.frame_id == 'imu_link'
    assert imus[0].orientation_covariance[0] == -1.0
    gyro_var = sim.SimParams().gyro_noise_std_rad_s ** 2
    assert imus[0].angular_velocity_covariance[8] == pytest.approx(gyro_var)
    assert imus[0].linear_acceleration_covariance[0] == pytest.approx(0.02 ** 2)
    joints = got['/joint_states']
    assert list(joints[0].name) == ['left_wheel_joint', 'right_wheel_joint']
    np.testing.assert_array_equal([m.position for m in joints], run.joint_position)
    np.testing.assert_array_equal([m.velocity for m in joints], run.joint_velocity)
    truth = got['/ground_truth/odom']
    assert (truth[0].header.frame_id, truth[0].child_frame_id) == ('map', 'base_link')
    xy = np.array([[m.pose.pose.position.x, m.pose.pose.position.y] for m in truth])
    np.testing.assert_array_equal(xy, run.truth_pose[:, :2])
    yaw = np.array([2.0 * math.atan2(m.pose.pose.orientation.z, m.pose.pose.orientation.w)
                    for m in truth])
    np.testing.assert_allclose(
        np.angle(np.exp(1j * (yaw - run.truth_pose[:, 2]))), 0.0, atol=1e-12
    )
    twist = [[m.twist.twist.linear.x, m.twist.twist.angular.z] for m in truth]
    np.testing.assert_array_equal(twist, run.truth_twist)


def test_rosbags_and_mcap_ros2_readers_agree(bags):
    from mcap_ros2.reader import read_ros2_messages

    ours = list(read_messages(bags['a']))
    theirs = list(read_ros2_messages(str(mcap_file(bags['a']))))
    assert len(ours) == len(theirs) == sum(c for _, c in topic_counts(bags['a']).values())
    for (topic, stamp, msg), other in zip(ours, theirs):
        assert (topic, stamp) == (other.channel.topic, other.log_time_ns)
        assert other.schema.name == type_name(msg)
        fields_equal(msg, other.ros_msg, topic)


def test_shipped_params_file_records_the_defaults(tmp_path):
    record(tmp_path / 'from_file', 5, '--params-file', str(REPO / 'config' / 'sensor_sim.yaml'))
    (tmp_path / 'x').mkdir()
    record(tmp_path / 'x' / 'from_file', 5)
    assert (tmp_path / 'from_file' / 'metadata.yaml').read_text() \
        == (tmp_path / 'x' / 'from_file' / 'metadata.yaml').read_text()
    a, b = (list(read_messages(p, ['/scan']))
            for p in (tmp_path / 'from_file', tmp_path / 'x' / 'from_file'))
    assert a == b


def params_file(tmp_path, **values) -> Path:
    path = tmp_path / 'params.yaml'
    path.write_text(yaml.safe_dump({'sensor_sim': {'ros__parameters': values}}))
    return path


@pytest.mark.parametrize('values, name', [
    ({'wheel_radius_m': -0.05}, 'wheel_radius_m'),
    ({'scan_beams': 0}, 'scan_beams'),
    ({'range_min_m': 8.0, 'range_max_m': 8.0}, 'range_min_m'),
    ({'world_file': '/nonexistent/world.yaml'}, 'world_file'),
    ({'route': ['straight fast']}, 'route'),
])
def test_bad_parameters_exit_2_naming_the_parameter_and_write_nothing(tmp_path, values, name):
    out = tmp_path / 'bag'
    result = run_to_exit('sensor_sim', ['--record', str(out), '--duration', '2',
                                        '--params-file', str(params_file(tmp_path, **values))])
    assert result.returncode == 2, result.stdout + result.stderr
    assert f"parameter '{name}'" in result.stderr
    assert not out.exists()


def test_malformed_world_and_params_files_exit_2(tmp_path):
    world = tmp_path / 'world.yaml'
    world.write_text('walls:\n  - [0, 0, 1]\n')
    bad_world = params_file(tmp_path, world_file=str(world))
    result = run_to_exit('sensor_sim', ['--record', str(tmp_path / 'bag'), '--duration', '1',
                                        '--params-file', str(bad_world)])
    assert result.returncode == 2 and "parameter 'world_file'" in result.stderr
    assert 'walls[0]' in result.stderr
    garbage = tmp_path / 'garbage.yaml'
    garbage.write_text('sensor_sim: {ros__parameters: [1, 2\n')
    result = run_to_exit('sensor_sim', ['--record', str(tmp_path / 'bag'), '--duration', '1',
                                        '--params-file', str(garbage)])
    assert result.returncode == 2 and "parameter 'params_file'" in result.stderr
    existing = tmp_path / 'exists'
    existing.mkdir()
    result = run_to_exit('sensor_sim', ['--record', str(existing), '--duration', '1'])
    assert result.returncode == 2 and "parameter 'record'" in result.stderr
    assert not (tmp_path / 'bag').exists()


def test_publish_clock_false_leaves_clock_out_of_the_bag(tmp_path):
    record(tmp_path / 'bag', 1, '--params-file', str(params_file(tmp_path, publish_clock=False)))
    assert set(topic_counts(tmp_path / 'bag')) == set(RATES) - {'/clock'}


def test_ros_args_override_the_params_file_in_record_mode(tmp_path):
    base = params_file(tmp_path, scan_beams=180, seed=1)
    record(tmp_path / 'bag', 3, '--params-file', str(base),
           '--ros-args', '-p', 'scan_beams:=720', '-p', "route:=['wait 1']")
    scans = [m for _, _, m in read_messages(tmp_path / 'bag', ['/scan'])]
    assert len(scans[0].ranges) == 720
    truth = [m for _, _, m in read_messages(tmp_path / 'bag', ['/ground_truth/odom'])]
    assert all(m.twist.twist.linear.x == 0.0 for m in truth)        # the route is 'wait 1'
    result = run_to_exit('sensor_sim', ['--record', str(tmp_path / 'bad'), '--duration', '1',
                                        '--ros-args', '-p', 'scan_beams:=0'])
    assert result.returncode == 2 and "parameter 'scan_beams'" in result.stderr
