"""sensing_pipeline: the nodes' work over a bag without DDS equals a lockstep replay through the
real node processes (the shipped bags hold such a replay's outputs; a converted CARMEN log is
replayed here), compared with the replay's own check; bad input and bad parameters exit 2 with
nothing written."""

from __future__ import annotations

import gzip
import os
import subprocess
import sys
from pathlib import Path

import pytest
from harness import REPO, run_to_exit

from sensing_nodes.bags.storage import BagReader, canonical_cdr, read_messages, topic_counts
from sensing_nodes.graph.compare import compare_outputs, output_messages

BAGS = REPO / 'bags'
CARMEN = REPO.parent / 'shared' / 'datasets' / 'carmen'
# What the lockstep replay records of the graph (not /diagnostics: a wall-clock timer).
OUTPUTS = {'/wheel/odom', '/imu/data', '/scan/lines', '/scan/lines/table', '/scan_match/odom',
           '/odometry/filtered'}
# docs/real-data.md: the matcher and the seed's filter on a CARMEN log.
REAL_DATA_PARAMS = [
    'icp_matcher:laser_x_m:=0.0', 'icp_matcher:max_gap_s:=60.0',
    'icp_matcher:odom_max_extrapolation_s:=1.0', 'complementary_fusion:method:=complementary',
    'complementary_fusion:use_imu:=false', 'complementary_fusion:alpha:=auto',
    'complementary_fusion:max_gap_s:=60.0', 'complementary_fusion:input_timeout_s:=60.0',
    'complementary_fusion:reorder_window_s:=10.0']


def _pipeline(args: list[str], timeout: float = 300.0) -> subprocess.CompletedProcess:
    """sensing_pipeline as a module (a console script added to setup.py exists only once the
    package is reinstalled)."""
    env = {**os.environ, 'PYTHONPATH': os.pathsep.join(
        [str(REPO), *filter(None, [os.environ.get('PYTHONPATH')])])}
    return subprocess.run([sys.executable, '-m', 'sensing_nodes.tools.pipeline', *args,
                           '--no-progress'], capture_output=True, text=True, timeout=timeout,
                          env=env)


def _assert_equal_outputs(recorded: Path, produced: Path, topics: set[str]) -> None:
    """The replay's comparison: every message at the same bag time, floats within its
    tolerance, everything else equal."""
    types = {t: v[0] for t, v in topic_counts(recorded).items()}
    report = compare_outputs(output_messages(recorded, topics), output_messages(produced, topics),
                             types)
    assert set(report) == topics
    for topic, entry in report.items():
        assert entry['expected'] == entry['actual'] > 0, (topic, entry)
        assert entry['reproduced'], (topic, entry)


@pytest.mark.parametrize('name', ['nominal', 'strong_errors'])
def test_shipped_bag_outputs_equal_the_lockstep_replay(tmp_path, name):
    out = tmp_path / 'out'
    result = _pipeline([str(BAGS / name), str(out)])
    assert result.returncode == 0, result.stdout + result.stderr
    # /tf (the fusion's odom -> base_link) too: the replay and the pipeline record it alike.
    _assert_equal_outputs(BAGS / name, out, OUTPUTS | {'/tf'})
    counts, original = topic_counts(out), topic_counts(BAGS / name)
    # The bag's other topics come along unchanged; the matcher's keyframe-relative output (which
    # the replay does not record) is there too; /diagnostics (wall-clock timer) is not.
    for topic in ('/scan', '/imu/data_raw', '/joint_states', '/ground_truth/odom', '/clock'):
        assert counts[topic] == original[topic]
    assert counts['/scan_match/keyframe_odom'][1] == original['/scan'][1]
    assert '/diagnostics' not in counts
    # The outputs are stored as the nodes packed them, without the writer's canonical_cdr:
    # they must be canonical CDR already.
    reader = BagReader(out)
    for topic, _, raw in reader.raw():
        if topic in OUTPUTS | {'/tf', '/scan_match/keyframe_odom'}:
            assert canonical_cdr(raw, reader.topics[topic].msgtype) == bytes(raw), topic


def test_subset_of_nodes_takes_the_recorded_upstream_outputs(tmp_path):
    """Only the fusion: it takes /wheel/odom, /imu/data_raw and the keyframe matches from the bag
    (what the other nodes published when it was recorded) and gives the same fused poses."""
    out = tmp_path / 'out'
    first = tmp_path / 'first'
    assert _pipeline([str(BAGS / 'nominal'), str(first)]).returncode == 0
    result = _pipeline([str(first), str(out), '--nodes', 'complementary_fusion'])
    assert result.returncode == 0, result.stdout + result.stderr
    _assert_equal_outputs(BAGS / 'nominal', out, {'/odometry/filtered'})


def test_called_in_process_it_leaves_the_discovery_range_as_it_found_it(tmp_path, monkeypatch):
    """Its nodes are built with discovery off, but the caller's environment keeps its own
    range: a test session's later graphs inherited OFF once and discovered nothing."""
    from sensing_nodes.tools import pipeline

    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    first = tmp_path / 'first'
    assert _pipeline([str(BAGS / 'nominal'), str(first)]).returncode == 0
    assert pipeline.main([str(first), str(tmp_path / 'out'), '--nodes', 'complementary_fusion',
                          '--no-progress']) == 0
    assert os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'


def test_parameters_reach_the_nodes(tmp_path):
    """--param and --params-file change what the node computes: no scan has a 6-beam line
    that is 50 m long."""
    params = tmp_path / 'lines.yaml'
    params.write_text('line_extractor:\n  ros__parameters:\n    min_line_points: 7\n')
    out = tmp_path / 'out'
    result = _pipeline([str(BAGS / 'nominal'), str(out), '--nodes', 'line_extractor',
                        '--params-file', str(params),
                        '--param', 'line_extractor:min_line_length:=50.0'])
    assert result.returncode == 0, result.stdout + result.stderr
    tables = [m for _, _, m in read_messages(out, ['/scan/lines/table'])]
    assert len(tables) == 220 and all(m.width == 0 for m in tables)
    recorded = [m for _, _, m in read_messages(BAGS / 'nominal', ['/scan/lines/table'])]
    assert sum(m.width for m in recorded) > 0
    assert set(topic_counts(out)) >= {'/scan', '/scan/lines'}


@pytest.mark.parametrize('args, message', [
    (['--param', 'line_extractor:min_line_points:=1'], "parameter"),
    (['--param', 'icp_matcher:method:=point_to_plane'], "'method'"),
    (['--param', 'nonsense:x:=1'], 'NODE:NAME:=VALUE'),
    (['--nodes', 'wheel_odometry,nonsense'], 'unknown node'),
    (['--remap', 'scan'], '/BAG_TOPIC:=/TOPIC'),
])
def test_bad_parameters_exit_2_without_output(tmp_path, args, message):
    out = tmp_path / 'out'
    result = _pipeline([str(BAGS / 'nominal'), str(out), *args])
    assert result.returncode == 2, result.stdout + result.stderr
    assert message in result.stderr
    assert not out.exists() and not any(tmp_path.iterdir())


def test_bad_input_exits_2_naming_the_file(tmp_path):
    missing = tmp_path / 'none'
    result = _pipeline([str(missing), str(tmp_path / 'out')])
    assert result.returncode == 2 and str(missing) in result.stderr
    existing = tmp_path / 'exists'
    existing.mkdir()
    result = _pipeline([str(BAGS / 'nominal'), str(existing)])
    assert result.returncode == 2 and 'already exists' in result.stderr
    # A bag whose /scan holds another type.
    from nav_msgs.msg import Odometry

    from sensing_nodes.bags.storage import BagWriter

    wrong = tmp_path / 'wrong'
    with BagWriter(wrong) as bag:
        bag.write('/scan', Odometry(), 1)
    result = _pipeline([str(wrong), str(tmp_path / 'out2'), '--nodes', 'line_extractor'])
    assert result.returncode == 2 and '/scan holds nav_msgs/msg/Odometry' in result.stderr
    assert not (tmp_path / 'out2').exists()
    # Nothing in the bag for the chosen nodes.
    result = _pipeline([str(wrong), str(tmp_path / 'out3'), '--nodes', 'gyro_integrator'])
    assert result.returncode == 2 and 'no topic the nodes take (/imu/data_raw, /wheel/odom)' \
        in result.stderr, result.stderr
    assert not (tmp_path / 'out3').exists()


@pytest.mark.skipif(not CARMEN.is_dir(), reason=f'CARMEN logs not found in {CARMEN}')
def test_carmen_log_outputs_equal_the_lockstep_replay(tmp_path):
    """The first 30 scans of the ACES log, converted, through the matcher and the seed's
    filter (docs/real-data.md's commands): the pipeline gives what the replay through the real
    node processes gives."""
    from sensing_nodes.tools.carmen_to_bag import convert

    log = tmp_path / 'aces-head.log'
    lines, scans = [], 0
    with gzip.open(CARMEN / 'aces-corrected.log.gz', 'rt') as source:
        for line in source:
            scans += line.startswith('FLASER')
            if scans > 30:
                break
            lines.append(line)
    log.write_text(''.join(lines))
    bag = tmp_path / 'aces'
    convert(log, bag)
    replayed = tmp_path / 'replayed'
    params = [a for p in REAL_DATA_PARAMS for a in ('--param', p)]
    result = run_to_exit(
        'sensing_replay',
        [
            str(bag),
            str(replayed),
            '--launch',
            '--nodes',
            'icp_matcher,complementary_fusion',
            '--expect',
            '/scan=/scan_match/odom',
            # The fusion answers every /odom stamp, later (its reorder window): the replay keeps
            # at most 50 answers outstanding, so the fusion's queue (reliable, keep last 100)
            # cannot overrun on a loaded machine (with /odom unanswered and 20 ms between
            # messages, a 2-worker run once had one fused output fewer than the pipeline), and
            # checks every stamp came.
            '--expect',
            '/odom=/odometry/filtered',
            '--remap',
            '/odom:=/wheel/odom',
            *params,
            '--no-progress',
        ],
        timeout=300.0,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    out = tmp_path / 'out'
    result = _pipeline([str(bag), str(out), '--nodes', 'icp_matcher,complementary_fusion',
                        '--remap', '/odom:=/wheel/odom', *params])
    assert result.returncode == 0, result.stdout + result.stderr
    _assert_equal_outputs(replayed, out, {'/scan_match/odom', '/odometry/filtered'})
    assert sum(1 for _ in BagReader(out).raw(['/scan_match/odom'])) == 30
