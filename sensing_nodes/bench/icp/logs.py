"""The scan matcher on the CARMEN logs through docs/real-data.md's commands (carmen_to_bag,
sensing_pipeline with icp_matcher and complementary_fusion, sensing_eval), each matcher mode
side by side: docs/real-data.md's tables.

For every log and mode: ATE (m) and consecutive-scan RPE (mean and median, m / deg) of the
odometry (/odom), the matcher (/scan_match/odom) and the fusion (/odometry/filtered) against the
logs' corrected poses, and how many of the matcher's published steps are more than 1 m or
30 deg off the reference's motion. A log that cannot be converted or scored says why.

In local_map mode, the integrity's figures too: the matcher's claimed standard deviation over its
own error's (three-cornered hat over matcher, odometry and reference:
core/evaluation/consistency.py) per axis, and how many of the matches within 3x the reference's
own noise of the reference the fusion's gate refused.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import yaml
from numpy.typing import NDArray

from sensing_nodes.bags.storage import BagReader
from sensing_nodes.bench.icp import datasets
from sensing_nodes.core.evaluation.consistency import (
    consecutive_relations,
    informative,
    three_cornered_hat,
    within_reference_noise,
)
from sensing_nodes.core.evaluation.fusion import EVERY_OUTPUT, run_recorded
from sensing_nodes.core.evaluation.metrics import interpolate_poses
from sensing_nodes.core.fusion.config import default_config
from sensing_nodes.core.fusion.inputs import SCAN, WHEEL
from sensing_nodes.core.fusion.timeline import InputRecord
from sensing_nodes.core.geometry import se2
from sensing_nodes.paths import config_file
from sensing_nodes.ros.conversions import ScanMatchReferences, odometry_pose, stamp_to_ns
from sensing_nodes.ros.fusion_readings import ReadingConverter
from sensing_nodes.tools import carmen_to_bag, pipeline
from sensing_nodes.tools import eval as sensing_eval

MODES = ('local_map', 'keyframe')
TOPICS = ('/odom', '/scan_match/odom', '/odometry/filtered')
# docs/real-data.md's sensing_pipeline arguments (datasets.CARMEN_SETTINGS).
PIPELINE_ARGUMENTS = (
    '--nodes', 'icp_matcher,complementary_fusion', '--remap', '/odom:=/wheel/odom',
    '--param', 'icp_matcher:laser_x_m:=0.0',
    '--param', f'icp_matcher:max_gap_s:={datasets.CARMEN_MAX_GAP_S}',
    '--param', f'icp_matcher:odom_max_extrapolation_s:={datasets.CARMEN_EXTRAPOLATION_S}',
    '--params-file', str(config_file('fusion_carmen.yaml')), '--no-progress')
# ... and for a log whose time carmen_to_bag rebuilt from the line order (freiburg-campus):
# speed and yaw-rate limits measure nothing on an assumed time.
ASSUMED_TIME_ARGUMENTS = ('--param', 'icp_matcher:rate_limits:=false',
                          '--param', 'complementary_fusion:ekf.hold_back_max_s:=0.0')
FAR_M, FAR_RAD = 1.0, math.radians(30.0)
MATCHES, ODOMETRY, REFERENCE = '/scan_match/keyframe_odom', '/odom', '/ground_truth/odom'


def log_figures(bag: Path | None, modes: tuple[str, ...] = MODES) -> dict:
    """{mode: {topic: figures}} of one log's bag (datasets.carmen_bag), or {'error': why}."""
    if bag is None:
        return dict(datasets.NOT_CONVERTED)
    assumed = ASSUMED_TIME_ARGUMENTS \
        if carmen_to_bag.TIME_BASE_KEY in BagReader(bag).custom_data else ()
    figures: dict = {}
    for mode in modes:
        processed = bag.parent / f'{bag.name}-{mode}'
        shutil.rmtree(processed, ignore_errors=True)
        if pipeline.main([str(bag), str(processed), *PIPELINE_ARGUMENTS, *assumed,
                          '--param', f'icp_matcher:mode:={mode}']) != 0:
            figures[mode] = {'error': 'sensing_pipeline failed'}
            continue
        try:
            report = sensing_eval.evaluate(processed, list(TOPICS))
        except sensing_eval.EvalError as exc:
            figures[mode] = {'error': str(exc)}
            continue
        figures[mode] = {}
        for topic in TOPICS:
            entry = {k: v for k, v in report['estimates'][topic].items()}
            errors = report['_errors'][topic]
            entry['steps_beyond_1m_or_30deg'] = int(np.count_nonzero(
                (errors.translation_m > FAR_M) | (errors.rotation_rad > FAR_RAD)))
            figures[mode][topic] = entry
        if mode == 'local_map':
            figures[mode]['integrity'] = integrity_figures(processed, assumed)
    return figures


def _odometry_rows(bag: Path, topic: str):
    """(stamps ns, poses (N, 3), covariances (N, 3, 3), messages) of an Odometry topic."""
    t, p, c, m = [], [], [], []
    for _, _, msg in BagReader(bag).messages([topic]):
        pose, cov = odometry_pose(msg)
        t.append(stamp_to_ns(msg.header.stamp))
        p.append(pose)
        c.append(cov)
        m.append(msg)
    return np.array(t, dtype=np.int64), np.array(p), np.array(c), m


def _map_ids(messages) -> NDArray[np.int64]:
    """The local map each of the matcher's messages is a pose in (a match, or the map's origin
    at its first scan), named by its first scan's stamp (ns); -1 where it carries no pose in a
    map known from its start."""
    references = ScanMatchReferences()
    out = []
    for msg in messages:
        reference, _ = references.read(msg)
        known = reference is not None and reference.in_map and reference.reference_ns \
            is not None and (reference.matched or reference.starts)
        out.append(reference.reference_ns if known else -1)
    return np.array(out, dtype=np.int64)


def integrity_figures(processed: Path, assumed: tuple[str, ...] = ()) -> dict:
    """The matcher's claimed over own sigma per axis (x, y, yaw; inf where its own error is
    below what the hat resolves) on consecutive matches in one local map (those it calls
    uninformative, consistency.informative, counted apart), and the fusion's
    decisions, replayed over the processed bag as the node makes them with the benchmark's
    configuration: the matches refused among those whose relation lies within 3x the
    reference's own noise ('good'), and among all."""
    t, poses, covs, messages = _odometry_rows(processed, MATCHES)
    map_ids = _map_ids(messages)
    ref_t, ref_p, _, _ = _odometry_rows(processed, REFERENCE)
    odo_t, odo_p, _, _ = _odometry_rows(processed, ODOMETRY)
    matched = (map_ids >= 0) & np.all(np.isfinite(interpolate_poses(ref_t, ref_p, t)), axis=1)
    pairs, relations, relation_covs = consecutive_relations(
        t[matched], map_ids[matched], poses[matched], covs[matched])

    def motion(track_t, track_p):
        a = interpolate_poses(track_t, track_p, pairs[:, 0])
        b = interpolate_poses(track_t, track_p, pairs[:, 1])
        return np.array([se2.between(tuple(x), tuple(y)) for x, y in zip(a, b)]).reshape(-1, 3)

    reference = motion(ref_t, ref_p)
    told = informative(relation_covs)
    hat = three_cornered_hat(relations[told], motion(odo_t, odo_p)[told], reference[told],
                             relation_covs[told])
    good = within_reference_noise(relations, reference, hat.reference_own)
    # The fusion's decision on each match, as the node makes it over this bag.
    overrides = {name: yaml.safe_load(value) for name, value in (
        arg.split(':', 1)[1].split(':=') for arg in assumed[1::2]
        if arg.startswith('complementary_fusion:'))}
    config = default_config(config_file('fusion_carmen.yaml'),
                            overrides={**EVERY_OUTPUT, **overrides})
    converter = ReadingConverter.for_config(config)
    records = {WHEEL: InputRecord(WHEEL), SCAN: InputRecord(SCAN)}
    readings = []
    for topic, _, msg in BagReader(processed).messages([ODOMETRY, MATCHES]):
        source = WHEEL if topic == ODOMETRY else SCAN
        reading, _ = converter.reading(source, msg, converter.stamp_ns(source, msg),
                                       records[source])
        if reading is not None:
            readings.append((source, reading))
    refused = {stamp for name, stamp, outcome in run_recorded(config, readings).outcomes
               if name == SCAN and outcome.gated}
    refused_at_end = np.array([stamp in refused for stamp in pairs[:, 1]], dtype=bool)
    return {'relations': hat.relations, 'uninformative_relations': int(np.count_nonzero(~told)),
            **{f'claimed_over_own_{axis}': float(r) for axis, r in zip('xy', hat.ratio[:2])},
            'claimed_over_own_yaw': float(hat.ratio[2]),
            **{f'own_{axis}': float(v) for axis, v in zip(('x_m', 'y_m', 'yaw_rad'), hat.own)},
            **{f'claimed_{axis}': float(v)
               for axis, v in zip(('x_m', 'y_m', 'yaw_rad'), hat.claimed)},
            'good_matches': int(np.count_nonzero(good)),
            'good_matches_refused': int(np.count_nonzero(good & refused_at_end)),
            'matches_refused': len(refused)}


def table(results: dict) -> str:
    """docs/real-data.md's table: one row per log, mode and topic."""
    lines = ['| log | mode | estimate | ATE (m) | RPE mean (m / deg) | RPE median (m / deg) '
             '| steps > 1 m or 30 deg off |', '|---|---|---|---|---|---|---|']
    names = {'/odom': 'odometry', '/scan_match/odom': 'matcher',
             '/odometry/filtered': 'fusion (EKF)'}
    for log, modes in results.items():
        if 'error' in modes:
            lines.append(f"| {log} | | | cannot be scored: {modes['error']} | | | |")
            continue
        for mode, topics in modes.items():
            if 'error' in topics:
                lines.append(f"| {log} | {mode} | | cannot be scored: {topics['error']} | | | |")
                continue
            for topic, f in topics.items():
                if topic not in names or (topic == '/odom' and mode != next(iter(modes))):
                    continue                       # the same odometry for every mode
                lines.append(
                    f"| {log} | {'' if topic == '/odom' else mode} | {names[topic]} | "
                    f"{f['ate_rmse_m']:.3f} | {f['rpe_translation_mean_m']:.4f} / "
                    f"{f['rpe_rotation_mean_deg']:.3f} | {f['rpe_translation_median_m']:.4f} / "
                    f"{f['rpe_rotation_median_deg']:.3f} | {f['steps_beyond_1m_or_30deg']} |")
    return '\n'.join(lines)


def integrity_table(results: dict) -> str:
    """docs/real-data.md's integrity table: per log (local_map), the matcher's claimed over own
    sigma per axis (- where its own error is below what the hat resolves) and the gate's
    refusals among the good matches and among all."""
    lines = ['| log | relations (uninformative) | claimed / own sigma x, y, yaw | own sigma x, y '
             '(mm), yaw (deg) | good matches refused | matches refused |',
             '|---|---|---|---|---|---|']
    for log, modes in results.items():
        f = modes.get('local_map', {}).get('integrity') if 'error' not in modes else None
        if not f:
            continue
        ratios = ', '.join('-' if not math.isfinite(f[f'claimed_over_own_{a}']) else
                           f"{f[f'claimed_over_own_{a}']:.2f}" for a in ('x', 'y', 'yaw'))
        lines.append(
            f"| {log} | {f['relations']} ({f['uninformative_relations']}) | {ratios} | "
            f"{f['own_x_m'] * 1e3:.1f}, {f['own_y_m'] * 1e3:.1f}, "
            f"{math.degrees(f['own_yaw_rad']):.3f} | {f['good_matches_refused']} of "
            f"{f['good_matches']} | {f['matches_refused']} |")
    return '\n'.join(lines)
