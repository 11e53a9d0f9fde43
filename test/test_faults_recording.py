"""SIGINT during a recording leaves a bag that rosbags reads to its last complete message, and
SIGKILL (or a power cut) one the package's tools read up to its last complete chunk, at most
about a second short: sensor_sim --record (the offline recorder) and sensing_demo (the live
graph's recorder)."""

import os
import re
import signal
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
from harness import BIN, run_to_exit

from sensing_nodes.bags.storage import BagReader, read_messages, topic_counts
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


def _children(pid: int) -> list[int]:
    """Process ids whose parent is pid (the demo's node processes, each in a session of its
    own, so killing the demo does not stop them)."""
    found = []
    for stat in Path('/proc').glob('[0-9]*/stat'):
        try:
            fields = stat.read_text().rsplit(')', 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found


def test_sigkill_during_sensor_sim_record_loses_only_the_open_chunk(tmp_path):
    bag = tmp_path / 'bag'
    proc = subprocess.Popen([str(BIN / 'sensor_sim'), '--record', str(bag), '--duration',
                             '3600', '--quiet'])
    deadline = time.monotonic() + 60
    while not ((bag / 'bag.mcap').exists() and (bag / 'bag.mcap').stat().st_size > 2e6) \
            and time.monotonic() < deadline:
        time.sleep(0.1)
    proc.kill()
    assert proc.wait(timeout=30) == -signal.SIGKILL
    assert not (bag / 'metadata.yaml').exists()    # never closed
    assert 'was not closed' in BagReader(bag).damage
    # Every topic reads without a gap from the start: counts agree with the rates over each
    # topic's own span (200 Hz IMU, 10 Hz scans), bag time = header stamp, the last scan whole.
    counts, read = check_bag(bag, ['/scan', '/imu/data_raw', '/joint_states'])
    for topic, rate in (('/imu/data_raw', 200), ('/scan', 10)):
        span_s = (read[topic][-1][0] - read[topic][0][0]) * 1e-9
        assert counts[topic][1] == round(rate * span_s) + 1, topic
    assert len(read['/scan'][-1][1].ranges) == 360
    # The topics end within a chunk (1 s of bag time) of each other.
    ends = [read[t][-1][0] for t in ('/scan', '/imu/data_raw', '/joint_states')]
    assert max(ends) - min(ends) <= 1_000_000_000


def test_sigkill_during_sensing_demo_leaves_a_bag_the_tools_read(tmp_path):
    """The demo (its recorder in the demo process) killed 1.5 s after it printed how many scans
    it had recorded: the bag holds at least those (the recorder flushes every wall second), the
    sensor mounts, and sensing_eval and sensing_pipeline work on it, saying it was cut."""
    out_dir = tmp_path / 'run'
    proc = subprocess.Popen([str(BIN / 'sensing_demo'), '--out', str(out_dir), '--duration',
                             '600'], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    progress: list[tuple[float, int]] = []     # (monotonic time, scans recorded) per line

    def follow() -> None:
        for line in proc.stdout:
            found = re.search(r'scans\s+(\d+)', line)
            if found:
                progress.append((time.monotonic(), int(found.group(1))))

    threading.Thread(target=follow, daemon=True).start()
    children: list[int] = []
    try:
        deadline = time.monotonic() + 150
        while not (progress and progress[-1][1] >= 40) and proc.poll() is None \
                and time.monotonic() < deadline:
            time.sleep(0.05)
        assert progress and progress[-1][1] >= 40, 'the demo did not get going'
        seen_at, scans_seen = progress[-1]
        time.sleep(max(0.0, seen_at + 1.5 - time.monotonic()))
        children = _children(proc.pid)
        proc.kill()
        assert proc.wait(timeout=30) == -signal.SIGKILL
    finally:
        for pid in children or _children(proc.pid):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        if proc.poll() is None:
            proc.kill()
    bag = out_dir / 'bag'
    assert not (bag / 'metadata.yaml').exists()    # never closed
    reader = BagReader(bag)
    assert 'was not closed' in reader.damage
    assert reader.topics['/scan'].count >= scans_seen, (reader.topics['/scan'], scans_seen)
    mounts = {(t.header.frame_id, t.child_frame_id) for _, _, m in
              reader.messages(['/tf_static']) for t in m.transforms}
    assert mounts == {('base_link', 'laser'), ('base_link', 'imu_link')}

    result = run_to_exit('sensing_eval', [str(bag), '--topic', '/wheel/odom'])
    assert result.returncode == 0, result.stderr
    assert 'was not closed' in result.stderr and '/wheel/odom' in result.stdout
    out = tmp_path / 'processed'
    result = run_to_exit('sensing_pipeline', [str(bag), str(out), '--no-progress'], timeout=180)
    assert result.returncode == 0, result.stderr
    assert 'was not closed' in result.stderr
    assert topic_counts(out)['/scan_match/odom'][1] == reader.topics['/scan'].count
