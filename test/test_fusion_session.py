"""One fusion session (core/fusion/session.py) behind every caller: on a shipped bag's fusion
inputs, the node's processor as sensing_pipeline drives it, the bag-fusing tool
(sensing_fuse_bag) and the evaluation's driver (core/evaluation/fusion.run_session, which
run_ekf and run_complementary use) give identical outputs, and they equal what the node
published over DDS in the lockstep replay the bag was recorded with. Plus the session's
timeline rules on worked examples, and the one parameter translation (session_config)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu

from sensing_nodes.bags.input_bag import load_bag
from sensing_nodes.bags.storage import topic_counts
from sensing_nodes.core.evaluation.fusion import run_session
from sensing_nodes.core.fusion.config import NODE_NAME, default_config, session_config
from sensing_nodes.core.fusion.inputs import IMU, INPUTS, SCAN, WHEEL, Reading
from sensing_nodes.core.fusion.session import FusionSession
from sensing_nodes.core.fusion.timeline import InputRecord
from sensing_nodes.graph import pipeline
from sensing_nodes.graph.compare import compare_outputs, output_messages
from sensing_nodes.parameters import ParameterError, load_parameters
from sensing_nodes.paths import config_file
from sensing_nodes.ros.cdr import cdr_decoder
from sensing_nodes.ros.conversions import odometry_pose, stamp_to_ns
from sensing_nodes.ros.fusion_readings import ReadingConverter
from sensing_nodes.tools.fuse_bag import fused_outputs

BAG = Path(__file__).resolve().parents[1] / 'bags' / 'nominal'
FUSED = '/odometry/filtered'
S = 1_000_000_000


@pytest.fixture(scope='module')
def inputs_bag(tmp_path_factory) -> Path:
    """The nominal bag through the five nodes (sensing_pipeline): it then holds the fusion's
    every input, the keyframe-relative matches included (the shipped bag has no copy)."""
    out = tmp_path_factory.mktemp('session') / 'inputs'
    pipeline.run(BAG, out, ('wheel_odometry', 'gyro_integrator', 'line_extractor',
                            'icp_matcher', 'complementary_fusion'), progress=False)
    return out


def _decoded(raws: list[bytes]) -> tuple[list[int], np.ndarray, np.ndarray]:
    """Stamps, poses (N, 3) and covariances (N, 3, 3) of /odometry/filtered CDR bytes."""
    decode = cdr_decoder(Odometry)
    stamps, poses, covariances = [], [], []
    for raw in raws:
        msg = decode(raw)
        pose, cov = odometry_pose(msg)
        stamps.append(stamp_to_ns(msg.header.stamp))
        poses.append(pose)
        covariances.append(cov)
    return stamps, np.array(poses), np.array(covariances)


def _bag_readings(bag: Path, config) -> list[tuple[str, Reading]]:
    """The bag's fusion inputs (bag order) read by the node's converter, as (name, Reading)."""
    converter = ReadingConverter.for_config(config)
    topics = {config.topics[name]: name for name in INPUTS if config.enabled[name]}
    records = {name: InputRecord(name) for name in INPUTS}
    decoders = {'nav_msgs/msg/Odometry': cdr_decoder(Odometry),
                'sensor_msgs/msg/Imu': cdr_decoder(Imu)}
    types = {t: v[0] for t, v in topic_counts(bag).items()}
    readings = []
    for topic, _, raw in load_bag(bag).messages:
        name = topics.get(topic)
        if name is None:
            continue
        msg = decoders[types[topic]](raw)
        reading, problem = converter.reading(name, msg, converter.stamp_ns(name, msg),
                                             records[name])
        assert reading is not None, problem
        readings.append((name, reading))
    return readings


@pytest.mark.parametrize('method', ['ekf', 'complementary'])
def test_every_caller_gives_the_same_outputs(inputs_bag, tmp_path, method):
    overrides = [f'method:={method}']
    # sensing_pipeline, the fusion alone over its inputs
    out = tmp_path / 'fused'
    pipeline.run(inputs_bag, out, ('complementary_fusion',), progress=False,
                 node_params={'complementary_fusion': [a for o in overrides for a in ('-p', o)]})
    written = load_bag(out).messages
    from_pipeline = {t: [raw for topic, _, raw in written if topic == t] for t in (FUSED, '/tf')}
    # the bag-fusing tool: the node's processor over the bag
    tool, session = fused_outputs(inputs_bag, overrides=overrides)
    from_tool = {t: [raw for topic, raw in tool if topic == t] for t in (FUSED, '/tf')}
    assert from_tool == from_pipeline                      # the same bytes, /tf included
    # 22 s: 30 Hz of the dead reckoning (publish_rate_hz: 661 periods) plus every scan match:
    # the EKF's 220 (in the local map) at their sweeps' middles, each its own output (878: a
    # match that opens a 30 Hz period is that period's output); the complementary filter's
    # (/scan_match/odom) at the scans' stamps, which the wheels share: one output a stamp
    published = len(from_tool[FUSED])
    assert published == session.counts['published']
    assert 661 + 200 < published <= 661 + 220 if method == 'ekf' else published == 661
    # the evaluation's driver over the same messages, read by the node's converter
    config = default_config(overrides={'method': method})
    track = run_session(config, _bag_readings(inputs_bag, config))
    stamps, poses, covariances = _decoded(from_tool[FUSED])
    assert track.t.tolist() == stamps
    assert np.array_equal(track.pose[:, :2], poses[:, :2])
    # yaw went through a quaternion in the message
    assert np.allclose(track.pose[:, 2], poses[:, 2], rtol=0.0, atol=1e-12)
    assert np.array_equal(track.covariance, covariances)


def test_the_outputs_equal_the_nodes_over_dds(inputs_bag, tmp_path):
    """The shipped bag's /odometry/filtered and /tf are what the node published over DDS in a
    lockstep replay (bags/README.md): the session in the pipeline reproduces them."""
    out = tmp_path / 'fused'
    pipeline.run(inputs_bag, out, ('complementary_fusion',), progress=False)
    topics = {FUSED, '/tf'}
    types = {t: v[0] for t, v in topic_counts(BAG).items()}
    report = compare_outputs(output_messages(BAG, topics), output_messages(out, topics), types)
    for topic, entry in report.items():
        assert entry['expected'] == entry['actual'] > 0 and entry['reproduced'], (topic, entry)


# -- the session's rules on worked examples ----------------------------------------------------
def _wheels_only(**params):
    return session_config({'use_imu': False, 'use_scan_match_position': False,
                           'use_scan_match_heading': False, **params})


def _wheel(stamp_ns: int, x: float) -> Reading:
    return Reading(stamp_ns, (x, 0.0, 0.0), np.diag([1e-4, 1e-4, 1e-5]) * (1.0 + x))


def _yaw(stamp_ns: int) -> Reading:
    return Reading(stamp_ns, (0.0, 0.0, 0.0), np.diag([0.0, 0.0, 1e-6]), (0.0, 0.0, 0.0))


def test_readings_are_fused_in_stamp_order_once_every_input_has_reached_them():
    """Wheels ahead of the IMU: held until the IMU reaches their stamps (the watermark), then
    fused in stamp order, wheel before IMU at equal stamps; an IMU reading older than what was
    fused is dropped and counted; a silent input is waited for at most reorder_window_s."""
    session = FusionSession(session_config({'use_scan_match_position': False,
                                            'use_scan_match_heading': False,
                                            'reorder_window_s': 0.5}))
    out = []
    for k in range(3):
        out += session.feed(WHEEL, _wheel(k * S // 10, 0.1 * k))
    assert out == [] and session.held() == 3
    out += session.feed(IMU, _yaw(0)) + session.feed(IMU, _yaw(S // 10))
    assert [stamp for stamp, _ in out] == [0, S // 10]       # outputs at the wheels' stamps
    assert [r.processed for r in session.records.values()][:2] == [2, 2]
    out = session.feed(WHEEL, _wheel(S, 1.0))                # the IMU silent: the window
    assert [stamp for stamp, _ in out] == [2 * S // 10]      # releases what is 0.5 s older
    assert session.feed(IMU, _yaw(15 * S // 100)) == []      # before 0.2 s, already fused
    assert session.counts['imu_dropped_late'] == 1 and session.resets == 0
    assert [n.key for n in session.take_notices()] == ['imu_late']
    assert [stamp for stamp, _ in session.flush()] == [S]


def test_the_filter_starts_once_every_input_has_spoken():
    config = session_config({'use_scan_match_position': False,
                             'use_scan_match_heading': False})
    session = FusionSession(config)
    for k in range(5):                                         # the IMU alone for 0.4 s
        session.feed(IMU, _yaw(k * S // 10))
    out = session.feed(WHEEL, _wheel(4 * S // 10, 0.0)) + session.flush()
    assert session.counts['before_every_input'] == 4          # the IMU's 0 .. 0.3 s
    assert [stamp for stamp, _ in out] == [4 * S // 10]
    assert any('every input has spoken' in n.text for n in session.take_notices())


def test_an_input_not_heard_yet_is_waited_for_then_started_without():
    """Nodes started together come up in any order: the IMU heard 3 s of stamps after the
    wheels (beyond the reorder window and input_timeout_s, 2 s each) is waited for, what came
    before it is held and not fused, and nothing of it is dropped late. Never heard within
    startup_timeout_s (10 s), the filter starts without it, from the first reading."""
    config = session_config({'use_scan_match_position': False,
                             'use_scan_match_heading': False})
    assert (config.input_timeout_s, config.reorder_window_s, config.startup_timeout_s) == \
        (2.0, 2.0, 10.0)
    session = FusionSession(config)
    out = [o for k in range(30) for o in session.feed(WHEEL, _wheel(k * S // 10, 0.0))]
    assert out == [] and session.held() == 30
    assert [n.text for n in session.take_notices()] == [   # told after input_timeout_s
        'waiting for imu (/imu/data): not heard yet; fusing starts once every enabled input '
        'has spoken (at most 10 s of stamps)']
    out = session.feed(IMU, _yaw(3 * S)) + session.feed(WHEEL, _wheel(31 * S // 10, 0.0)) + \
        session.feed(IMU, _yaw(31 * S // 10)) + session.flush()
    assert [stamp for stamp, _ in out] == [31 * S // 10]
    assert session.counts['before_every_input'] == 30 and session.buffer.late == 0
    assert not any('starting without' in n.text for n in session.take_notices())

    session = FusionSession(config)
    out = [o for k in range(102) for o in session.feed(WHEEL, _wheel(k * S // 10, 0.0))]
    assert out[0][0] == 0 and session.counts['before_every_input'] == 0
    assert any(n.text == 'starting without imu (/imu/data) (not heard in 10.1 s of stamps)'
               for n in session.take_notices())


def test_time_going_backwards_resets_and_the_new_timeline_repeats_the_first():
    session = FusionSession(_wheels_only(reorder_window_s=0.0))
    first = [session.feed(WHEEL, _wheel(k * S // 10, 0.1 * k)) for k in range(5)]
    first = [o for batch in first for o in batch] + session.flush()
    again = [session.feed(WHEEL, _wheel(k * S // 10, 0.1 * k)) for k in range(5)]
    again = [o for batch in again for o in batch] + session.flush()
    assert session.resets == 1 and session.counts['resets'] == 1
    assert [s for s, _ in again] == [s for s, _ in first]
    assert [st.pose for _, st in again] == [st.pose for _, st in first]


def test_set_pose_fuses_what_is_held_first_and_refuses_a_bad_pose():
    session = FusionSession(session_config({'use_scan_match_position': False,
                                            'use_scan_match_heading': False}))
    session.feed(WHEEL, _wheel(0, 0.0))                       # held: the IMU may still speak
    session.feed(WHEEL, _wheel(S // 10, 0.1))
    out = session.set_pose((5.0, 1.0, 0.5), np.diag([0.01, 0.01, 0.001]))
    assert [stamp for stamp, _ in out] == [0, S // 10]        # the held readings first
    after = session.feed(WHEEL, _wheel(2 * S // 10, 0.2)) + session.flush()
    assert after[-1][1].pose[0] > 5.0                         # going on from the new pose
    assert session.set_pose((np.nan, 0.0, 0.0), np.eye(3)) == []
    assert session.counts['set_pose'] == 1 and session.counts['set_pose_rejected'] == 1


def _drive(publish_rate_hz: float) -> tuple[FusionSession, list]:
    """1 s of wheels and IMU at 50 Hz and keyframe scan matches at 10 Hz (at wheel stamps),
    straight at 0.5 m/s, from a stamp where a 30 Hz period starts; (session, [(name, stamp,
    state)] of every output)."""
    period = 33_333_333
    t0 = 1000 * period
    config = default_config(overrides={'publish_rate_hz': publish_rate_hz})
    names = {}
    session = FusionSession(config, on_output=lambda s, st: names.setdefault(s, []))
    out = []
    for k in range(50):
        t = t0 + k * 20_000_000
        readings = [(WHEEL, Reading(t, (0.01 * k, 0.0, 0.0), np.eye(3) * 1e-4 * (k + 1))),
                    (IMU, Reading(t, (0.0, 0.0, 0.0), np.diag([0.0, 0.0, 1e-6]),
                                  (0.0, 0.0, 0.0)))]
        if k % 5 == 0:
            match = Reading(t, (0.01 * k, 0.0, 0.0), np.eye(3) * 1e-6, keyframe_ns=t0,
                            new_keyframe=k == 0) if k else Reading(t, new_keyframe=True)
            readings.append((SCAN, match))
        for name, reading in readings:
            out += [(name, stamp, state) for stamp, state in session.feed(name, reading)]
    # (which input each output came from: the session's order at equal stamps)
    out += [(None, stamp, state) for stamp, state in session.flush()]
    return session, out, t0


def test_outputs_at_the_rate_are_the_first_of_each_period_and_every_scan_match():
    """publish_rate_hz 30 (the default): the same filter (every reading fused, the state read
    as at every rate), of its outputs the first in each 1/30 s of stamp time and every scan
    match's. Wheels at 50 Hz from the start of a period: per 100 ms the outputs at 0 (the
    wheels', IMU's and scan match's readings at that stamp, one output after all three), 40
    and 80 ms (the first in each 33.3 ms): 30 outputs a second instead of 50."""
    _, every, t0 = _drive(0.0)
    session, thinned, _ = _drive(30.0)
    assert len(every) == 50 and len(thinned) == 30
    ms = [(stamp - t0) // 1_000_000 for _, stamp, _ in thinned]
    expected = []
    for tenth in range(10):
        base = 100 * tenth
        expected += [base, base + 40, base + 80]      # wheel and scan match, wheel, wheel
    assert ms == expected
    # the same states as at every output: thinning publishes less, it filters the same
    states = {}
    for _, stamp, state in every:
        states.setdefault(stamp, []).append(state)
    for i, (_, stamp, state) in enumerate(thinned):
        same_stamp = [s for _, s2, s in thinned[:i] if s2 == stamp]
        reference = states[stamp][len(same_stamp)]
        assert state.pose == reference.pose
        assert np.array_equal(state.covariance, reference.covariance)
    assert session.outputs.rate_hz() == pytest.approx(29 / 0.98)   # 30 outputs in 0.98 s
    # The outputs trail the newest input by up to the scan matches' period: a wheel reading
    # waits in the reorder buffer until every input has reached its stamp (0.1 s before the
    # next match); at the end (980 ms, an output) by nothing.
    assert session.output_lag_s() == pytest.approx((0.0, 0.1))
    assert session.output_lag_s() == pytest.approx((0.0, 0.0))     # the most since the last call


# -- the one parameter translation ---------------------------------------------------------------
def test_scan_position_and_heading_switches_apply_offline_as_in_the_node():
    """use_scan_match_position / _heading switch the scan match's quantities off, whoever
    translates the parameters (the evaluation's inputs_from_params did not)."""
    config = default_config(overrides={'use_scan_match_heading': False})
    assert config.input_map[SCAN].mask[:3] == (True, True, False)
    config = default_config(overrides={'use_scan_match_position': False})
    assert config.input_map[SCAN].mask[:3] == (False, False, True)


@pytest.mark.parametrize('params, name', [
    ({'alpha': 1.5}, 'alpha'), ({'alpha': 'fast'}, 'alpha'),
    ({'reorder_window_s': -1.0}, 'reorder_window_s'),
    ({'wheel_odom': {'delay_s': 2.5}}, 'wheel_odom.delay_s'),
    ({'imu': {'delay_s': float('nan')}}, 'imu.delay_s'),
    ({'imu': {'source': 'magnetometer'}}, 'imu.source'),
    ({'wheel_odom': {'mask': ['z']}}, 'wheel_odom.mask'),
    ({'use_wheel_odom': False, 'use_imu': False, 'use_scan_match_position': False,
      'use_scan_match_heading': False}, 'use_*'),
])
def test_bad_parameters_are_refused_naming_them(params, name):
    with pytest.raises(ParameterError) as error:
        session_config(params)
    assert error.value.name == name and f"'{name}'" in str(error.value)


def test_parameter_files_layer_as_the_node_reads_them():
    params = load_parameters(NODE_NAME, config_file('complementary_fusion.yaml'),
                         config_file('fusion_jackal_test2.yaml'))
    assert params['wheel_odom.covariance_scale'] == 10.0      # from the first file
    assert params['wheel_odom.mask'] == ['vx', 'vy', 'vyaw']  # the second's over it
    config = session_config(params)
    assert not config.enabled[SCAN] and config.imu_source == 'orientation'
    assert config.topics[WHEEL] == '/jackal_velocity_controller/odom'


def test_the_tool_says_why_it_cannot_fuse_a_bag(capsys):
    """sensing_fuse_bag: an enabled input missing from the bag, or a bad parameter: exit 2 with
    the reason; a final position further than --tolerance from --expect: exit 1."""
    from sensing_nodes.tools.fuse_bag import main

    assert main([str(BAG)]) == 2           # the shipped bag has no keyframe matches
    assert 'no topic /scan_match/keyframe_odom' in capsys.readouterr().err
    assert main([str(BAG), '--param', 'alpha:=1.5']) == 2
    assert "parameter 'alpha'" in capsys.readouterr().err
    wheels_and_gyro = ['--param', 'use_scan_match_position:=false',
                       '--param', 'use_scan_match_heading:=false']
    assert main([str(BAG), *wheels_and_gyro, '--expect', '0.0', '0.0']) == 1
    assert 'from the expected one' in capsys.readouterr().err
