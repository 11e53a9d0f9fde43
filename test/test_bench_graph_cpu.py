"""bench/graph_cpu.py's bookkeeping (no timing asserted): messages per simulated second each
node takes in, from the simulator's parameter file, and CPU time read from /proc."""

import os
import time

from sensing_nodes.bench.graph_cpu import _cpu_seconds, _memory_mb, input_rates


def test_input_rates_follow_the_simulator_rates():
    rates = input_rates()
    # config/sensor_sim.yaml: joints 50 Hz, IMU 200 Hz, scans 10 Hz, truth and clock 100 Hz.
    assert rates == {'wheel_odometry': 50.0, 'gyro_integrator': 250.0, 'line_extractor': 10.0,
                     'icp_matcher': 10.0, 'complementary_fusion': 260.0, 'sensor_sim': 460.0}
    assert input_rates({'imu_rate_hz': 1000.0})['gyro_integrator'] == 1050.0


def test_cpu_seconds_of_this_process_and_of_none():
    """CPU time (clock ticks of 10 ms in /proc) grows while this process computes: work until it
    does, within 5 s (one fixed loop of ~10 ms stayed within one tick on a fast CPU)."""
    spent = _cpu_seconds(os.getpid())
    assert spent is not None
    deadline = time.monotonic() + 5.0
    while _cpu_seconds(os.getpid()) <= spent and time.monotonic() < deadline:
        sum(i * i for i in range(200_000))
    assert _cpu_seconds(os.getpid()) > spent
    assert _cpu_seconds(2 ** 22 + 12345) is None   # beyond pid_max: no such process


def test_memory_of_this_process_grows_with_an_allocation_and_none_when_gone():
    before = _memory_mb(os.getpid())
    block = bytearray(50_000_000)   # 50 MB touched (zero-filled): resident
    after = _memory_mb(os.getpid())
    assert after['rss_mb'] - before['rss_mb'] > 45.0, (before, after)
    assert after['peak_rss_mb'] >= after['rss_mb'] and after['pss_mb'] <= after['rss_mb']
    del block
    assert _memory_mb(2 ** 22 + 12345) is None


def test_relay_answering_fewer_than_every_message_is_refused_at_start():
    """--answer-every N: one answer per N messages; N below 1 has no meaning (and would divide
    by zero in the relay): exit 2 naming the option, before any process is started."""
    import subprocess
    import sys

    result = subprocess.run([sys.executable, '-m', 'sensing_nodes.bench.graph_cpu', '--floor',
                             '10', '--answer-every', '0'], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 2
    assert '--answer-every 0' in result.stderr
