"""icp_matcher's /scan_match/keyframe_odom as a ROS user and the fusion read it: frame ids with
stable names (scan_match_map, scan_match_keyframe; no stamp inside any), a map or keyframe
started by the message whose child_frame_id is that frame, and the fusion's readings of the
messages equal to the matcher's own steps in both modes, across a restart of the matcher.
The map or keyframe a match is in stays known where the message that started it is refused,
across the fusion's reset, and for a stream heard mid-way; bags of the encoding before (the
stamp inside the frame ids) read the same; a frame id of neither name is refused, saying why."""

from __future__ import annotations

import math

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message

from sensing_nodes.bench.icp.datasets import simulated_run
from sensing_nodes.core.fusion.ekf import EkfFusion
from sensing_nodes.core.fusion.inputs import SCAN, InputConfig, input_config
from sensing_nodes.core.fusion.timeline import InputRecord
from sensing_nodes.core.scan_matching import ScanStatus, make_scan_matcher
from sensing_nodes.core.sim.inputs import matcher_settings, scan_inputs
from sensing_nodes.core.sim.simulator import SimParams, make_route
from sensing_nodes.nodes.icp_matcher import keyframe_odometry
from sensing_nodes.ros.conversions import (
    NOT_MATCHED,
    SCAN_MATCH_KEYFRAME_FRAME,
    SCAN_MATCH_MAP_FRAME,
    make_odometry,
    ns_to_stamp,
)
from sensing_nodes.ros.fusion_readings import UNHEARD, ReadingConverter

S = 1_000_000_000
T0 = 1_700_000_000 * S
NOTHING = np.diag([NOT_MATCHED, 0.0, 0.0])
MATCH_COV = np.diag([1e-6, 1e-6, 1e-7])


def _converter() -> ReadingConverter:
    return ReadingConverter('ekf', {SCAN: input_config(SCAN, {})})


def _read(converter: ReadingConverter, msg):
    return converter.reading(SCAN, msg, converter.stamp_ns(SCAN, msg), InputRecord(SCAN))


def _old_encoding(step, base_frame: str = 'base_link') -> Odometry:
    """The message as icp_matcher wrote it before the stable frames: the map or keyframe named
    by its stamp inside the frame ids ('map/<ns>', 'keyframe/<ns>', 'keyframe/none')."""
    in_map = step.local_map
    if in_map is not None:
        frame = f'map/{in_map.map_stamp_ns}'
        if in_map.origin:
            return make_odometry(step.stamp_ns, frame, frame, (0.0, 0.0, 0.0), np.zeros((3, 3)))
        if in_map.pose is None:
            return make_odometry(in_map.time_ns, 'keyframe/none', base_frame, (0.0, 0.0, 0.0),
                                 np.zeros((3, 3)))
        return make_odometry(in_map.time_ns, frame, base_frame, in_map.pose, in_map.covariance)
    child = f'keyframe/{step.stamp_ns}' if step.new_keyframe else base_frame
    if step.keyframe is None:
        return make_odometry(step.stamp_ns, 'keyframe/none', child, (0.0, 0.0, 0.0),
                             np.zeros((3, 3)))
    return make_odometry(step.stamp_ns, f'keyframe/{step.keyframe.keyframe_stamp_ns}', child,
                         step.keyframe.pose, step.keyframe.covariance)


@pytest.fixture(scope='module')
def run():
    """12 s of the default route: the still start, then the first straight."""
    return simulated_run(seed=0, laps=12.0 / make_route(SimParams()).period_s)


@pytest.mark.parametrize('mode', ['local_map', 'keyframe'])
def test_the_fusion_reads_back_what_the_matcher_found_in_either_mode(run, mode):
    """Every scan, then the first 20 again (stamps back: the matcher starts a new map or
    keyframe at the earlier stamp): the messages name only the stable frames, and the readings
    carry each step's map (its first scan's stamp) or keyframe, pose and covariance."""
    inputs = scan_inputs(run)
    matcher = make_scan_matcher(matcher_settings(run.params, mode=mode))
    steps = [step for step in (matcher.process(*args) for args in inputs + inputs[:20])
             if step.publish]
    assert sum(step.status is ScanStatus.RESET_BACKWARDS for step in steps) == 1
    frame = SCAN_MATCH_MAP_FRAME if mode == 'local_map' else SCAN_MATCH_KEYFRAME_FRAME
    converter, old = _converter(), _converter()
    starts = matches = 0
    for step in steps:
        msg = deserialize_message(keyframe_odometry(step, 'base_link'), Odometry)
        assert msg.header.frame_id == frame and msg.child_frame_id in (frame, 'base_link')
        reading, problem = _read(converter, msg)
        assert problem == '', problem
        in_map = step.local_map
        if mode == 'local_map' and in_map.origin:
            expected = (step.stamp_ns, None, True, step.stamp_ns, None)
            starts += 1
        elif mode == 'local_map':
            matched = in_map.pose is not None
            expected = (in_map.time_ns, None, False, in_map.map_stamp_ns if matched else None,
                        in_map.pose)
        else:
            match = step.keyframe
            expected = (step.stamp_ns, None if match is None else match.keyframe_stamp_ns,
                        step.new_keyframe, None, None if match is None else match.pose)
            starts += step.new_keyframe
        assert (reading.stamp_ns, reading.keyframe_ns, reading.new_keyframe,
                reading.map_ns) == expected[:4]
        if expected[4] is None:
            assert reading.pose is None
        else:
            matches += 1
            np.testing.assert_allclose(reading.pose, expected[4], atol=1e-12)
            covariance = in_map.covariance if mode == 'local_map' else step.keyframe.covariance
            np.testing.assert_allclose(reading.pose_covariance, covariance, rtol=1e-12)
        # The encoding before the stable frames reads the same.
        before, problem = _read(old, _old_encoding(step))
        assert problem == '' and before.stamp_ns == reading.stamp_ns
        assert (before.keyframe_ns, before.new_keyframe, before.map_ns) == \
            (reading.keyframe_ns, reading.new_keyframe, reading.map_ns)
        assert (before.pose is None) == (reading.pose is None)
    assert matches > 0.9 * len(steps)
    assert starts == 2 if mode == 'local_map' else starts > 10


def test_a_keyframe_started_by_a_refused_message_is_the_one_the_next_matches_are_in():
    """A message that starts a keyframe but is refused (its match is not finite, or its
    quaternion not of unit length) still starts it: the next match is against it, and the EKF
    adopts it from that match, as it would a keyframe whose message came late."""
    converter = _converter()
    first = make_odometry(T0, SCAN_MATCH_KEYFRAME_FRAME, SCAN_MATCH_KEYFRAME_FRAME,
                          (0.0, 0.0, 0.0), NOTHING)
    reading, _ = _read(converter, first)
    assert reading.new_keyframe and reading.pose is None
    bad = make_odometry(T0 + S, SCAN_MATCH_KEYFRAME_FRAME, SCAN_MATCH_KEYFRAME_FRAME,
                        (math.nan, 0.0, 0.0), MATCH_COV)
    assert _read(converter, bad) == (None, 'pose is not finite')
    not_unit = make_odometry(T0 + 2 * S, SCAN_MATCH_KEYFRAME_FRAME, SCAN_MATCH_KEYFRAME_FRAME,
                             (0.1, 0.0, 0.0), MATCH_COV)
    not_unit.pose.pose.orientation.w = 2.0
    assert _read(converter, not_unit) == (None, 'orientation is not a unit quaternion')
    match = make_odometry(T0 + 3 * S, SCAN_MATCH_KEYFRAME_FRAME, 'base_link', (0.1, 0.0, 0.0),
                          MATCH_COV)
    reading, problem = _read(converter, match)
    assert problem == '' and reading.keyframe_ns == T0 + 2 * S and not reading.new_keyframe
    ekf = EkfFusion((InputConfig(SCAN, mask=(True, True, True, False, False, False),
                                 keyframes=True, covariance='message'),))
    ekf.update(SCAN, _read(_converter(), first)[0])
    assert ekf.update(SCAN, reading).note == 'keyframe adopted from its first fused match'


def test_a_stream_heard_mid_way_names_its_map_once_one_starts_and_survives_a_reset():
    """Matches of a map started before the stream was heard share one key no stamp has
    (UNHEARD: the EKF places that map from its first fused match); a new map's first scan names
    the next ones, also after the fusion starts again (the matcher did not)."""
    converter = _converter()
    for k in (1, 2):
        msg = make_odometry(T0 + k * S, SCAN_MATCH_MAP_FRAME, 'base_link', (0.1 * k, 0.0, 0.0),
                            MATCH_COV)
        reading, problem = _read(converter, msg)
        assert problem == '' and reading.map_ns == UNHEARD and reading.keyframe_ns is None
    origin = make_odometry(T0 + 3 * S, SCAN_MATCH_MAP_FRAME, SCAN_MATCH_MAP_FRAME,
                           (0.0, 0.0, 0.0), np.zeros((3, 3)))
    reading, _ = _read(converter, origin)
    assert (reading.map_ns, reading.new_keyframe, reading.pose) == (T0 + 3 * S, True, None)
    converter.reset()
    nothing = make_odometry(T0 + 4 * S, SCAN_MATCH_MAP_FRAME, 'base_link', (0.0, 0.0, 0.0),
                            NOTHING)
    reading, _ = _read(converter, nothing)
    assert (reading.pose, reading.map_ns, reading.new_keyframe) == (None, None, False)
    match = make_odometry(T0 + 5 * S, SCAN_MATCH_MAP_FRAME, 'base_link', (0.3, 0.0, 0.0),
                          MATCH_COV)
    assert _read(converter, match)[0].map_ns == T0 + 3 * S


def test_after_a_silence_longer_than_the_input_timeout_a_match_names_a_map_of_its_own():
    """A matcher restarted under a running fusion (killed, respawned) starts a new map, and the
    message that starts it can go out before the fusion's subscription matched the new publisher:
    after the stream was silent longer than input_timeout_s the next match names a map by its
    own stamp (the EKF places it from that match) instead of the previous map; a shorter pause
    keeps the map."""
    converter = ReadingConverter('ekf', {SCAN: input_config(SCAN, {})}, input_timeout_s=2.0)
    origin = make_odometry(T0, SCAN_MATCH_MAP_FRAME, SCAN_MATCH_MAP_FRAME, (0.0, 0.0, 0.0),
                           np.zeros((3, 3)))
    assert _read(converter, origin)[0].map_ns == T0

    def match(t_ns):
        return _read(converter, make_odometry(t_ns, SCAN_MATCH_MAP_FRAME, 'base_link',
                                              (0.1, 0.0, 0.0), MATCH_COV))[0]

    assert match(T0 + S // 10).map_ns == T0
    assert match(T0 + 21 * S // 10).map_ns == T0          # a 2.0 s pause: the same map
    restarted = T0 + 45 * S // 10                         # 2.4 s silent: its start never came
    assert match(restarted).map_ns == restarted
    assert match(restarted + S // 10).map_ns == restarted
    start = restarted + 2 * S // 10                       # the matcher's next map, heard
    assert _read(converter, make_odometry(start, SCAN_MATCH_MAP_FRAME, SCAN_MATCH_MAP_FRAME,
                                          (0.0, 0.0, 0.0), np.zeros((3, 3))))[0].map_ns == start
    assert match(start + S // 10).map_ns == start


@pytest.mark.parametrize('frame, child, why', [
    ('odom', 'base_link', "frame_id 'odom' is neither scan_match_map nor scan_match_keyframe"),
    ('keyframe/abc', 'base_link', "frame_id 'keyframe/abc' names no keyframe or map"),
])
def test_a_frame_of_neither_name_is_refused_saying_why(frame, child, why):
    msg = make_odometry(T0, frame, child, (0.1, 0.0, 0.0), MATCH_COV)
    msg.header.stamp = ns_to_stamp(T0)
    reading, problem = _read(_converter(), msg)
    assert reading is None and problem.startswith(why)
