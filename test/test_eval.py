"""Relative pose error (Kümmerle et al. 2009), absolute trajectory error and sensing_eval."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from harness import REPO, run_to_exit

from sensing_nodes.core.evaluation.metrics import (
    Relations,
    absolute_trajectory_error,
    align_rigid_2d,
    read_relations,
    relations_from_trajectory,
    relative_pose_errors,
)
from sensing_nodes.core.geometry import se2
from sensing_nodes.tools.eval import evaluate

BAGS = REPO / 'bags'
S = 1_000_000_000


def test_rpe_worked_example():
    # Reference: 1 m straight steps. Estimate: 1.1 m steps, and a 0.1 rad turn in the second.
    relations = Relations(np.array([0, S]), np.array([S, 2 * S]),
                          np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))
    t_est = np.array([0, S, 2 * S])
    est = np.array([[0.0, 0.0, 0.0], [1.1, 0.0, 0.0], [2.2, 0.0, 0.1]])
    errors = relative_pose_errors(relations, t_est, est)
    np.testing.assert_allclose(errors.translation_m, [0.1, 0.1], atol=1e-12)
    np.testing.assert_allclose(errors.rotation_rad, [0.0, 0.1], atol=1e-12)
    summary = errors.summary()
    assert summary['rpe_translation_mean_m'] == pytest.approx(0.1)
    assert summary['rpe_translation_std_m'] == pytest.approx(0.0, abs=1e-12)
    assert summary['rpe_rotation_mean_deg'] == pytest.approx(math.degrees(0.05))
    assert summary['rpe_rotation_std_deg'] == pytest.approx(math.degrees(0.05))


def test_rpe_is_independent_of_the_estimate_frame_and_interpolates():
    rng = np.random.default_rng(3)
    t = np.arange(50) * S // 10
    ref = np.column_stack(
        [
            np.cumsum(rng.uniform(0, 0.1, 50)),
            np.cumsum(rng.uniform(-0.05, 0.05, 50)),
            se2.wrap_angle(np.cumsum(rng.uniform(-0.1, 0.1, 50))),
        ]
    )
    relations = relations_from_trajectory(t, ref, delta_s=0.5)
    assert np.all(relations.t2 - relations.t1 == S // 2)
    # The same trajectory in another frame (odometry starts anywhere) has zero relative error.
    moved = np.column_stack([se2.transform_points((3.0, -2.0, 1.2), ref[:, :2]),
                             se2.wrap_angle(ref[:, 2] + 1.2)])
    errors = relative_pose_errors(relations, t, moved)
    assert errors.translation_m.max() < 1e-12 and errors.rotation_rad.max() < 1e-12
    # Relations beyond the estimate's span are skipped, not extrapolated.
    short = relative_pose_errors(relations, t[:20], moved[:20])
    assert short.skipped == len(relations.t1) - short.translation_m.size > 0


def test_ate_after_rigid_alignment():
    rng = np.random.default_rng(4)
    t = np.arange(30) * S
    ref = np.column_stack([rng.uniform(-5, 5, (30, 2)), np.zeros(30)])
    transform = (1.5, -0.7, 0.6)
    est = np.column_stack([se2.transform_points(se2.inverse(transform), ref[:, :2]), np.zeros(30)])
    np.testing.assert_allclose(align_rigid_2d(ref[:, :2], est[:, :2]), transform, atol=1e-12)
    assert absolute_trajectory_error(t, ref, t, est)['ate_rmse_m'] < 1e-12
    # Two samples of a straight reference displaced sideways by +-d: alignment cannot remove it.
    line = np.column_stack([np.arange(4.0), np.zeros(4), np.zeros(4)])
    bent = line.copy()
    bent[1, 1], bent[2, 1] = 0.1, -0.1
    ate = absolute_trajectory_error(np.arange(4) * S, line, np.arange(4) * S, bent)
    assert ate['ate_max_m'] <= 0.1 + 1e-12 and ate['ate_rmse_m'] > 0.05


def test_ate_is_scored_at_the_reference_stamps():
    """A sparse reference (two scans, 2 s apart) and a dense estimate that is exact at both: ATE
    0, although the estimate's sample between them (the robot's detour to y = 1) is 1 m from
    the reference interpolated there. The estimate is interpolated at the reference's stamps,
    as for RPE."""
    reference = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [4.0, 0.0, 0.0]])
    estimate = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0], [2.0, 0.0, 0.0], [3.0, 0.0, 0.0],
                         [4.0, 0.0, 0.0]])
    ate = absolute_trajectory_error(np.arange(3) * 2 * S, reference, np.arange(5) * S, estimate)
    assert ate['ate_rmse_m'] < 1e-12 and ate['ate_samples'] == 3
    # Reference samples outside the estimate's span are not scored.
    assert absolute_trajectory_error(np.arange(3) * 2 * S, reference, np.arange(3) * S,
                                     estimate[:3])['ate_samples'] == 2


def test_relations_file_parsing(tmp_path):
    path = tmp_path / 'r.relations'
    path.write_text('# t1 t2 x y z roll pitch yaw\n1.5 2.5 0.9 0.1 0 0 0 0.2\n')
    r = read_relations(str(path), time_offset_ns=7)
    assert r.t1.tolist() == [1_500_000_007] and r.t2.tolist() == [2_500_000_007]
    np.testing.assert_allclose(r.motion, [[0.9, 0.1, 0.2]])
    path.write_text('1.5 2.5 0.9 0.1 0 0 0 0.2\n1 2 3\n')
    with pytest.raises(ValueError, match=r'r\.relations:2'):
        read_relations(str(path))


def test_eval_on_the_bags_separates_nominal_from_strong_errors(tmp_path):
    out, png = tmp_path / 'nominal.json', tmp_path / 'nominal.png'
    result = run_to_exit('sensing_eval', [str(BAGS / 'nominal'), '--delta-s', '1.0',
                                          '--json', str(out), '--png', str(png)])
    assert result.returncode == 0, result.stderr
    assert 'RPE translation' in result.stdout and '/wheel/odom' in result.stdout
    assert png.stat().st_size > 10_000
    reports = {'nominal': json.loads(out.read_text())['estimates'],
               'strong_errors': evaluate(BAGS / 'strong_errors', delta_s=1.0)['estimates']}
    nominal, strong = reports['nominal'], reports['strong_errors']
    assert set(nominal) == {'/wheel/odom', '/scan_match/odom', '/odometry/filtered'}
    # Slip, a 3 % radius error and a large gyro bias: wheel odometry's heading error per second
    # grows several-fold, its trajectory error more than tenfold.
    assert (
        strong['/wheel/odom']['rpe_rotation_mean_deg']
        > 5 * nominal['/wheel/odom']['rpe_rotation_mean_deg']
    )
    assert strong['/wheel/odom']['ate_rmse_m'] > 10 * nominal['/wheel/odom']['ate_rmse_m']
    for report in (nominal, strong):
        # The scan matcher and the fusion hold the trajectory to centimetres over the 22 s.
        assert report['/scan_match/odom']['ate_rmse_m'] < 0.05
        assert report['/odometry/filtered']['ate_rmse_m'] < 0.05
        assert report['/odometry/filtered']['rpe_rotation_mean_deg'] < \
            strong['/wheel/odom']['rpe_rotation_mean_deg']


def test_relations_file_gives_the_same_errors_as_the_reference(tmp_path):
    direct = evaluate(BAGS / 'nominal', ['/wheel/odom'], delta_s=1.0)
    t_ref, ref = direct['_trajectories']['/ground_truth/odom']
    relations = relations_from_trajectory(t_ref, ref, 1.0)
    path = tmp_path / 'nominal.relations'
    offset = int(t_ref[0])  # seconds since the first stamp keep full precision in the file
    with path.open('w') as handle:
        for a, b, (x, y, yaw) in zip(relations.t1, relations.t2, relations.motion):
            handle.write(
                f'{(a - offset) / 1e9:.9f} {(b - offset) / 1e9:.9f} '
                f'{x:.17g} {y:.17g} 0 0 0 {yaw:.17g}\n'
            )
    via_file = evaluate(BAGS / 'nominal', ['/wheel/odom'], relations_file=str(path),
                        time_offset_s=offset / 1e9)
    a, b = direct['estimates']['/wheel/odom'], via_file['estimates']['/wheel/odom']
    assert a['relations'] == b['relations'] > 2000
    for key in ('rpe_translation_mean_m', 'rpe_rotation_mean_deg', 'rpe_rotation_std_deg'):
        assert a[key] == pytest.approx(b[key], rel=1e-6)


@pytest.mark.parametrize('args, words', [
    (['{tmp}/none'], ['none', 'no such bag']),
    (['{bags}/nominal', '--topic', '/nope'], ['/nope', 'not in the bag']),
    (['{bags}/nominal', '--topic', '/scan'], ['/scan', 'sensor_msgs/msg/LaserScan']),
    (['{bags}/nominal', '--relations', '{tmp}/bad.relations'], ['bad.relations:1']),
])
def test_bad_input_exits_2_naming_file_and_topic_without_output(tmp_path, args, words):
    (tmp_path / 'bad.relations').write_text('not a relation\n')
    out = tmp_path / 'out.json'
    argv = [a.format(tmp=tmp_path, bags=BAGS) for a in args] + ['--json', str(out)]
    result = run_to_exit('sensing_eval', argv)
    assert result.returncode == 2, result.stdout + result.stderr
    for word in words:
        assert word in result.stderr
    assert not out.exists()


def test_a_valid_bag_without_odometry_is_named_as_such(tmp_path):
    """rosbag2's own cdr_test bag (test_msgs only): the error says there is no Odometry topic and
    what the bag holds (it said 'KeyError: 2; truncated?')."""
    bag = REPO.parent / 'shared' / 'datasets' / 'ros' / 'rosbag2-resources' / 'rosbag2_tests' \
        / 'resources' / 'mcap' / 'cdr_test'
    if not (bag / 'metadata.yaml').is_file():
        pytest.skip(f'rosbag2 test bags not found in {bag}')
    out = tmp_path / 'out.json'
    result = run_to_exit('sensing_eval', [str(bag), '--json', str(out)])
    assert result.returncode == 2, result.stdout + result.stderr
    for word in ('no nav_msgs/msg/Odometry topic', '/array_topic (test_msgs/msg/Arrays)',
                 '--topic'):
        assert word in result.stderr, result.stderr
    assert 'KeyError' not in result.stderr and 'truncated' not in result.stderr
    assert not out.exists()


def _odometry_bag(path, topics: dict[str, list[int]]):
    """A bag of Odometry topics: topic -> header stamps (ns); the pose moves 1 m per second."""
    from sensing_nodes.bags.storage import BagWriter
    from sensing_nodes.ros.conversions import make_odometry

    with BagWriter(path) as bag:
        rows = sorted((stamp, topic) for topic, stamps in topics.items() for stamp in stamps)
        for stamp, topic in rows:
            x = (stamp - S) / S
            bag.write(topic, make_odometry(stamp, 'odom', 'base_link', (x, 0.0, 0.0),
                                           np.eye(3) * 1e-3), stamp)
    return path


def test_fewer_relations_than_asked_are_said_and_too_few_refused(tmp_path):
    """An estimate that spans 10 of the reference's 100 messages scores 9 of its 99 consecutive
    relations: refused (exit 2, naming the shortfall and --min-share) rather than figures from
    9; with --min-share 0 the figures come with '9/99' and a warning saying why."""
    stamps = [S + k * S // 10 for k in range(100)]
    bag = _odometry_bag(tmp_path / 'bag', {'/ground_truth/odom': stamps, '/est': stamps[:10]})
    refused = run_to_exit('sensing_eval', [str(bag)])
    assert refused.returncode == 2, refused.stdout
    assert '/est scores 9 of the 99 relations asked for' in refused.stderr
    assert '90 outside its stamps' in refused.stderr and '--min-share' in refused.stderr
    assert 'RPE' not in refused.stdout
    allowed = run_to_exit('sensing_eval', [str(bag), '--min-share', '0'])
    assert allowed.returncode == 0, allowed.stderr
    assert '9/99' in allowed.stdout and 'warning: /est scores 9 of the 99' in allowed.stderr


def test_a_reference_whose_stamps_repeat_is_not_silently_shrunk(tmp_path):
    """60 reference messages at 6 distinct stamps (a log whose time was lost): 5 relations of
    the 59 asked for, and the refusal says the reference's stamps repeat."""
    stamps = [S + (k // 10) * S for k in range(60)]
    bag = _odometry_bag(tmp_path / 'bag', {'/ground_truth/odom': stamps,
                                           '/est': sorted(set(stamps))})
    result = run_to_exit('sensing_eval', [str(bag)])
    assert result.returncode == 2, result.stdout
    assert '60 messages at only 6 distinct stamps' in result.stderr
    assert 'scores 5 of the 59 relations' in result.stderr
