"""Per-scan CPU time of the scan matchers (`make bench` areas icp and icp_fast_lidar), from this
process's CPU time, methods interleaved pair by pair or pass by pass, best of `repeats`: only
ratios measured in one run mean much.

carmen-pairs: Freiburg 101's consecutive pairs (360 beams), every method given the same raw
(N, 2) arrays and the same initial guesses (the reference perturbed by sigma 0.10 m / 5 deg) and
doing all of its own preprocessing (k-d tree, normals or covariances) inside the timed region;
then streaming, as in the node (each scan prepared once, matched once). sim: the simulated
route's 360-beam scans at 10 Hz with the wheel odometry's guess. fast_lidar: a Hokuyo UTM-30LX
class stream (1081 beams over 270 deg, 40 Hz, 30 m) on the simulated route, the shared real
Hokuyo demo bag (681 beams, 10 Hz, hand-carried, no odometry), and the simulated stream through
the real nodes over DDS (as graph_cpu measures the graph). The % of one core at 1x is ms per scan
x scans per second / 10.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time

import numpy as np

from sensing_nodes.bench.icp import comparators as cmp
from sensing_nodes.bench.icp import datasets, scoring
from sensing_nodes.core import icp
from sensing_nodes.core.geometry.se2 import compose, inverse
from sensing_nodes.core.scan_matching import ScanMatcherSettings
from sensing_nodes.core.sim.inputs import matcher_settings, scan_inputs
from sensing_nodes.core.sim.simulator import SimParams, make_route


def _streaming_rates(points, guesses, repeats: int, search: str = 'bearing'
                     ) -> tuple[float, float]:
    """Scan after scan, as in the node: each scan prepared once (ours: bearing order or k-d tree,
    and normals, as the next keyframe; small_gicp: its preprocessing) and matched once as the
    source. Matches per second of ours and of small_gicp's GICP, interleaved scan by scan."""
    gicp = cmp.SmallGicp('GICP')
    best_ours = best_sg = math.inf
    for _ in range(repeats):
        start = time.process_time()
        ours_previous = icp.prepare_target(points[0], search=search)
        ours_spent = time.process_time() - start
        start = time.process_time()
        sg_previous = gicp.prepare(points[0])
        sg_spent = time.process_time() - start
        for k in range(1, len(points)):
            start = time.process_time()
            icp.match(points[k], ours_previous, guesses[k - 1])
            ours_previous = icp.prepare_target(points[k], search=search)
            ours_spent += time.process_time() - start
            start = time.process_time()
            current = gicp.prepare(points[k])
            gicp.align(sg_previous, current, guesses[k - 1])
            sg_previous = current
            sg_spent += time.process_time() - start
        best_ours, best_sg = min(best_ours, ours_spent), min(best_sg, sg_spent)
    return (len(points) - 1) / best_ours, (len(points) - 1) / best_sg


def carmen_pairs(quick: bool = False) -> dict:
    """Matches per second of each method on Freiburg 101's pairs and the ratios ours / other."""
    pairs = datasets.scan_pairs('freiburg-101')
    if quick:
        pairs = pairs[:40]
    guesses = datasets.initial_guesses(pairs, 'perturbed', seed=0)
    # Best of five interleaved passes: the shared machine's load swings within a run.
    repeats = 1 if quick else 5
    textbook_pairs = pairs[:3] if quick else pairs[:10]
    out: dict = {'pairs': len(pairs), 'beams': 360,
                 'source_points_mean': float(np.mean([len(p.source) for p in pairs]))}
    local = {'yaw_hypotheses': ()}          # the node's setting: odometry gives the guess
    methods = {'ours': cmp.ours(local), 'ours_hypotheses': cmp.ours()}
    methods.update({name: cmp.small_gicp_matcher(kind)
                    for name, kind in cmp.SMALL_GICP_TYPES.items()})
    for name, rate in scoring.pair_rates(methods, pairs, guesses, repeats).items():
        out[f'{name}_matches_per_s'] = rate
    textbook = {'textbook_loops': cmp.textbook_icp_loops, 'textbook_numpy': cmp.textbook_icp_numpy,
                'ours_on_textbook_pairs': cmp.ours(local)}
    for name, rate in scoring.pair_rates(textbook, textbook_pairs, guesses, 1).items():
        out[f'{name}_matches_per_s'] = rate
    ours = out['ours_matches_per_s']
    # Against the textbook on the same (first) pairs, measured in the same interleaved pass.
    ours_t = out['ours_on_textbook_pairs_matches_per_s']
    out['ratio_ours_vs_textbook_loops'] = ours_t / out['textbook_loops_matches_per_s']
    out['ratio_ours_vs_textbook_numpy'] = ours_t / out['textbook_numpy_matches_per_s']
    best_sg = max(out[f'{n}_matches_per_s'] for n in cmp.SMALL_GICP_TYPES)
    out['ratio_ours_vs_small_gicp_gicp'] = ours / out['small_gicp_gicp_matches_per_s']
    out['ratio_ours_vs_fastest_small_gicp'] = ours / best_sg
    out['ratio_ours_hypotheses_vs_small_gicp_gicp'] = (out['ours_hypotheses_matches_per_s']
                                                       / out['small_gicp_gicp_matches_per_s'])
    # Streaming, as in the node: each scan preprocessed once (keyframe), matched once (source).
    points = [pairs[0].target] + [p.source for p in pairs]
    out['streaming_ours_matches_per_s'], out['streaming_small_gicp_gicp_matches_per_s'] = \
        _streaming_rates(points, guesses, repeats)
    out['streaming_ratio_ours_vs_small_gicp_gicp'] = (
        out['streaming_ours_matches_per_s'] / out['streaming_small_gicp_gicp_matches_per_s']
    )
    # The local-map matcher over the same stream (each scan inserted: they are 1 m apart; the
    # guess as the odometry's motion, the laser at base_link, scans 1 s apart).
    stream = [(k * 1_000_000_000, scan, tuple(guesses[k - 1]) if k else None)
              for k, scan in enumerate(points)]
    settings = ScanMatcherSettings(laser_pose=(0.0, 0.0, 0.0), max_gap_s=10.0)
    out['streaming_local_map_matches_per_s'] = (
        1e3 * (len(points) - 1) / (cmp.local_map_ms(settings, stream, repeats) * len(stream)))
    out['streaming_ratio_local_map_vs_keyframe'] = (out['streaming_local_map_matches_per_s']
                                                    / out['streaming_ours_matches_per_s'])
    # The same with neighbours from a k-d tree (the same neighbours, found more slowly:
    # core/icp.prepare_target), against a second small_gicp pass.
    tree, sg_again = _streaming_rates(points, guesses, repeats, search='kd_tree')
    out['streaming_ours_kd_tree_matches_per_s'] = tree
    out['streaming_ratio_ours_kd_tree_vs_small_gicp_gicp'] = tree / sg_again
    return out


def sim(seconds: float = 60.0, repeats: int = 3) -> dict:
    """Per 360-beam scan of the simulated route (10 Hz, a 0.1 s sweep, the wheel odometry's
    guess and sweep motion, as the node runs): CPU ms per scan of each mode and of small_gicp's
    GICP on the same scans (scan to scan, the odometry's guess), interleaved pass by pass."""
    run = datasets.simulated_run(seed=0, laps=seconds / make_route(SimParams()).period_s)
    inputs = scan_inputs(run)
    gicp = cmp.SmallGicp('GICP')
    laser = matcher_settings(run.params).laser_pose
    best = {'local_map': math.inf, 'keyframe': math.inf, 'small_gicp_gicp': math.inf}
    for _ in range(repeats):
        for mode in ('local_map', 'keyframe'):
            best[mode] = min(best[mode], 1e-3 * len(inputs) * cmp.local_map_ms(
                matcher_settings(run.params, mode=mode), inputs))
        start = time.process_time()
        previous = None
        for stamp, scan, motion, _, _ in inputs:
            current = gicp.prepare(scan)
            if previous is not None:
                gicp.align(previous, current,
                           compose(compose(inverse(laser), motion or (0.0, 0.0, 0.0)), laser))
            previous = current
        best['small_gicp_gicp'] = min(best['small_gicp_gicp'], time.process_time() - start)
    return {f'simulated_{name}_ms_per_scan': 1e3 * spent / len(inputs)
            for name, spent in best.items()} | {'simulated_scans': len(inputs)}


def _stream_figures(name: str, inputs: list, convert_s: float, rate_hz: float,
                    settings: ScanMatcherSettings, repeats: int) -> dict:
    """Points per scan, CPU ms per scan of the matcher and of the scans' conversion, and the %
    of a core at 1x, of one stream."""
    ms = cmp.local_map_ms(settings, inputs, repeats)
    return {f'{name}_scans': len(inputs), f'{name}_rate_hz': rate_hz,
            f'{name}_points_mean': sum(len(i[1]) for i in inputs) / len(inputs),
            f'{name}_match_ms_per_scan': ms,
            f'{name}_inputs_ms_per_scan': 1e3 * convert_s / len(inputs),
            f'{name}_core_percent_at_1x': ms * rate_hz / 10.0}


def synthetic(seconds: float, repeats: int) -> dict:
    """The 1081-beam, 40 Hz stream over `seconds` of the default route (seed 0)."""
    params = dataclasses.replace(SimParams(), **datasets.FAST_LIDAR)
    run = datasets.simulated_run(seed=0, laps=seconds / make_route(params).period_s,
                                 params=params)
    start = time.process_time()
    inputs = scan_inputs(run)       # the points and the odometry's guess, as the node has them
    convert_s = time.process_time() - start
    return {'fast_lidar_beams': datasets.FAST_LIDAR['scan_beams'],
            **_stream_figures('fast_lidar', inputs, convert_s, datasets.FAST_LIDAR['scan_rate_hz'],
                              matcher_settings(run.params), repeats)}


def hokuyo_demo(repeats: int) -> dict:
    """The shared real Hokuyo bag's 360 scans (laser at base_link, the matcher's own
    constant-velocity prediction); a note without the bag."""
    bag = datasets.shared_dir('ros') / datasets.HOKUYO_DEMO
    if not bag.is_file():
        return {'hokuyo_demo': f'skipped: {bag} absent'}
    messages = datasets.bag_messages(bag)
    start = time.process_time()
    inputs = datasets.bag_inputs(messages)
    convert_s = time.process_time() - start
    rate = (len(inputs) - 1) / ((inputs[-1][0] - inputs[0][0]) * 1e-9)
    return {'hokuyo_demo_beams': len(messages[0][1].ranges),
            **_stream_figures('hokuyo_demo', inputs, convert_s, rate,
                              ScanMatcherSettings(laser_pose=(0.0, 0.0, 0.0)), repeats)}


def node(window_s: float) -> dict:
    """icp_matcher (and the wheel_odometry it takes its guess from) as processes on
    sensor_sim's 1081-beam, 40 Hz stream: CPU over window_s wall seconds, with its LaserScan
    decoding, the odometry's guess, DDS and publishing."""
    from sensing_nodes.bench.graph_cpu import measure

    processes = measure(('wheel_odometry', 'icp_matcher'), datasets.FAST_LIDAR,
                        window_s)['processes']
    matcher = processes['icp_matcher']
    return {'fast_lidar_node_core_percent_at_1x': matcher['core_percent_per_1x'],
            'fast_lidar_node_ms_per_scan': matcher['cpu_us_per_message'] / 1e3,
            'fast_lidar_node_rss_mb': matcher['rss_mb']}


def _with_load(figures) -> dict:
    """The figures with the 1-minute load average before and after them."""
    start = os.getloadavg()[0]
    return {'load_average_1min_start': start, **figures(),
            'load_average_1min_end': os.getloadavg()[0]}


def run(quick: bool = False) -> dict:
    """`make bench` area icp: carmen-pairs and the simulated route."""
    repeats = 1 if quick else 3
    return _with_load(lambda: carmen_pairs(quick) | sim(20.0 if quick else 60.0, repeats))


def run_fast_lidar(quick: bool = False) -> dict:
    """`make bench` area icp_fast_lidar."""
    repeats = 1 if quick else 3
    return _with_load(lambda: synthetic(20.0 if quick else 60.0, repeats) | hokuyo_demo(repeats)
                      | node(10.0 if quick else 30.0))
