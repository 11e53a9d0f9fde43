"""SIGINT during a recording leaves a bag that rosbags reads to its last complete message:
sensor_sim --record (the offline recorder) and sensing_demo (the live graph's recorder)."""

import signal
import subprocess
import time

import numpy as np
from harness import BIN

from sensing_nodes.bags.storage import read_messages, topic_counts
from sensing_nodes.ros.conversions import stamp_to_ns


def interrupt(cmd, ready, settle_s, timeout=60.0):
    """Start cmd, wait until ready() holds and settle_s more, send SIGINT; (exit code, output)."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + timeout
    while not ready() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(settle_s)
    assert proc.poll() is None, 'the recording ended before it was interrupted'
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=60)
    return proc.returncode, out


def check_bag(path, header_topics):
    """Every message the metadata counts reads back, in order, and the last of each is whole."""
    counts = topic_counts(path)
    read: dict[str, list] = {topic: [] for topic in counts}
    for topic, bag_ns, msg in read_messages(path):
        read[topic].append((bag_ns, msg))
    for topic, (_, count) in counts.items():
        assert len(read[topic]) == count, (topic, len(read[topic]), count)
    for topic in header_topics:
        stamps = [stamp_to_ns(m.header.stamp) for _, m in read[topic]]
        assert stamps and stamps == sorted(stamps), topic
        # bag time = when the message went out: its header stamp, a scan's when its sweep
        # ended (0.1 s later by default)
        sweep = 10**8 if topic == '/scan' else 0
        assert [ns for ns, _ in read[topic]] == [s + sweep for s in stamps], topic
    return counts, read


def test_sigint_during_sensor_sim_record_leaves_a_readable_bag(tmp_path):
    bag = tmp_path / 'bag'
    code, out = interrupt([str(BIN / 'sensor_sim'), '--record', str(bag), '--duration', '3600',
                           '--quiet'], lambda: (bag / 'bag.mcap').exists(), 2.0)
    assert code != 0, out                    # interrupted, not finished
    counts, read = check_bag(bag, ['/scan', '/imu/data_raw', '/joint_states'])
    assert counts['/scan'][1] > 5 and counts['/imu/data_raw'][1] > 100, counts
    # The recording was cut short, not truncated mid-message: the last scan is a whole scan.
    last_scan = read['/scan'][-1][1]
    assert len(last_scan.ranges) == 360 and np.isfinite(last_scan.angle_increment)
    # Sample counts agree with the rates up to the interruption (200 Hz IMU, 10 Hz scans).
    span_s = (read['/imu/data_raw'][-1][0] - read['/imu/data_raw'][0][0]) * 1e-9
    assert abs(counts['/imu/data_raw'][1] - (200 * span_s + 1)) <= 1
    assert abs(counts['/scan'][1] - 10 * span_s) <= 2


def test_sigint_during_sensing_demo_leaves_a_readable_bag(tmp_path):
    out_dir = tmp_path / 'run'
    sim_log = out_dir / 'logs' / 'sensor_sim.log'

    def simulation_started() -> bool:                # the graph is up (slow on a loaded machine)
        return sim_log.exists() and 'the graph is connected: starting' in sim_log.read_text()

    code, out = interrupt([str(BIN / 'sensing_demo'), '--out', str(out_dir), '--duration', '600',
                           '--quiet'], simulation_started, 6.0)
    assert code != 0, out
    counts, read = check_bag(out_dir / 'bag', [])
    assert counts['/scan'][1] > 0 and counts['/odometry/filtered'][1] > 0, (counts, out)
    for topic in ('/scan', '/wheel/odom', '/odometry/filtered'):
        stamps = [stamp_to_ns(m.header.stamp) for _, m in read[topic]]
        assert stamps == sorted(stamps), topic
