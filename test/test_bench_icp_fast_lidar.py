"""The fast-LiDAR benchmark's streams are what its figures claim: sensor_sim's 1081 beams over
270 deg at 40 Hz, every beam a point in the default world; the shared Hokuyo demo bag's 360 scans
of 681 beams at 10 Hz; each % of a core is its ms per scan at its rate."""

import math

import pytest

from sensing_nodes.bench.icp import datasets, speed


def test_synthetic_stream_is_a_utm_30lx_class_scanner_at_40_hz():
    figures = speed.synthetic(seconds=2.0, repeats=1)
    assert figures['fast_lidar_beams'] == 1081 and figures['fast_lidar_rate_hz'] == 40.0
    assert figures['fast_lidar_scans'] == 80            # 2 s at 40 Hz
    assert figures['fast_lidar_points_mean'] == 1081.0  # walls within 30 m all round
    assert figures['fast_lidar_core_percent_at_1x'] == pytest.approx(
        figures['fast_lidar_match_ms_per_scan'] * 40.0 / 10.0)


@pytest.mark.skipif(not (datasets.shared_dir('ros') / datasets.HOKUYO_DEMO).is_file(),
                    reason='the shared Hokuyo demo bag is absent')
def test_hokuyo_demo_bag_is_681_beams_at_10_hz():
    figures = speed.hokuyo_demo(repeats=1)
    assert figures['hokuyo_demo_beams'] == 681 and figures['hokuyo_demo_scans'] == 360
    assert math.isclose(figures['hokuyo_demo_rate_hz'], 10.0, rel_tol=0.01)
    assert 500 < figures['hokuyo_demo_points_mean'] <= 681
    assert figures['hokuyo_demo_core_percent_at_1x'] == pytest.approx(
        figures['hokuyo_demo_match_ms_per_scan'] * figures['hokuyo_demo_rate_hz'] / 10.0)
