"""bench/graph_cpu.py's bookkeeping (no timing asserted): messages per simulated second each
node takes in, from the simulator's parameter file, and CPU time read from /proc."""

import os

from sensing_nodes.bench.graph_cpu import _cpu_seconds, input_rates


def test_input_rates_follow_the_simulator_rates():
    rates = input_rates()
    # config/sensor_sim.yaml: joints 50 Hz, IMU 200 Hz, scans 10 Hz, truth and clock 100 Hz.
    assert rates == {'wheel_odometry': 50.0, 'gyro_integrator': 250.0, 'line_extractor': 10.0,
                     'icp_matcher': 10.0, 'complementary_fusion': 260.0, 'sensor_sim': 460.0}
    assert input_rates({'imu_rate_hz': 1000.0})['gyro_integrator'] == 1050.0


def test_cpu_seconds_of_this_process_and_of_none():
    spent = _cpu_seconds(os.getpid())
    sum(i * i for i in range(200_000))
    assert spent is not None and _cpu_seconds(os.getpid()) > spent
    assert _cpu_seconds(2 ** 22 + 12345) is None   # beyond pid_max: no such process
