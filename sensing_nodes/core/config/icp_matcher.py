"""icp_matcher's configuration: the scan matcher (core/scan_matching.py: its mode, laser mount,
local map or keyframes, ICP and gates), where its initial guess comes from, and its frames; and
its parameters."""

from __future__ import annotations

import math
from dataclasses import dataclass

from sensing_nodes.core.icp import Correspondences, IcpOptions
from sensing_nodes.core.scan_matching import ScanMatcherSettings
from sensing_nodes.parameters import Param, ParameterTable


@dataclass(frozen=True)
class IcpMatcherParameters:
    """The matcher's settings (as sensor_sim mounts the laser: 0.10 m ahead of base_link; a
    match needs 30 % of a scan's points and scans need 20 points), the odometry topic of the
    initial guess ('' = constant velocity), how far past its newest message it is used and how
    far its stamps lag the robot (s), deskewing, frames and /tf."""

    odom_topic: str = ''
    odom_frame: str = 'odom'
    base_frame: str = 'base_link'
    matcher: ScanMatcherSettings = ScanMatcherSettings(
        laser_pose=(0.10, 0.0, 0.0),
        icp_options=IcpOptions(correspondences=Correspondences(min_points=20,
                                                               min_inlier_fraction=0.3)))
    deskew: bool = True
    odom_max_extrapolation_s: float = 0.1
    odom_delay_s: float = 0.0
    publish_tf: bool = False

    def problems(self) -> list[tuple[str, str, object]]:
        """(field, problem, value) for each setting the node cannot run with."""
        out = [(f'matcher.{name}', problem, value)
               for name, problem, value in self.matcher.problems()]
        if not (self.odom_frame and self.base_frame):
            out.append(('odom_frame/base_frame', 'must not be empty', None))
        if not math.isfinite(self.odom_delay_s):
            out.append(('odom_delay_s', 'must be finite', self.odom_delay_s))
        return out

    @property
    def min_points(self) -> int:
        """Scans with fewer valid points are not matched."""
        return self.matcher.icp_options.correspondences.min_points


def _laser(name: str, axis: str, unit: str, limit: float | None = None) -> Param:
    return Param(f'laser mount {axis} in base_link ({unit})',
                 None if limit is None else -limit, limit, name=name)


ICP_MATCHER_PARAMETERS = ParameterTable(IcpMatcherParameters(), described={
    'odom_topic': Param("odometry for the initial guess (e.g. /wheel/odom); '' = constant "
                        'velocity model'),
    'odom_frame': Param('frame of the published pose'),
    'base_frame': Param('child frame (robot base)'),
    'matcher.mode': Param("'local_map': each scan against a map of the recent surroundings; "
                          "'keyframe': each scan against one keyframe"),
    'matcher.laser_pose': Param(elements=(
        _laser('laser_x_m', 'x', 'm'), _laser('laser_y_m', 'y', 'm'),
        _laser('laser_yaw_rad', 'yaw', 'rad', math.pi))),
    'matcher.keyframe_distance_m': Param(
        'new keyframe after moving this far from the last one (m)', 0.0, 10.0),
    'matcher.keyframe_angle_rad': Param(
        'new keyframe after turning this much from the last one (rad)', 0.0, math.pi),
    'matcher.max_error_m': Param('mean alignment error above this: failed match (m)', 0.0),
    'matcher.max_jump_m': Param('a match further than this from the prediction is rejected (m)',
                                0.0),
    'matcher.max_jump_rad': Param(
        'a match turned further than this from the prediction is rejected', 0.0, math.pi),
    'matcher.fallback_std_m': Param('std added to x and y per fallback step (m)', 0.0),
    'matcher.fallback_std_rad': Param('std added to yaw per fallback step (rad)', 0.0),
    'matcher.max_gap_s': Param('scans further apart than this restart the keyframe (s)', 0.0),
    'matcher.search': Param(
        "nearest neighbours from the scan's bearing order ('bearing') or a k-d tree "
        "('kd_tree'): the same neighbours, the bearing order faster"),
    'matcher.icp_options.method': Param("'point_to_line' or 'point_to_point'"),
    'matcher.icp_options.voxel_size': Param(
        'downsample each scan to one point per voxel of this size (m); 0 = off', 0.0, 1.0,
        name='voxel_size_m'),
    'matcher.icp_options.convergence.max_iterations': Param('ICP iterations at most', 1, 1000),
    'matcher.icp_options.correspondences.max_correspondence_distance': Param(
        'initial correspondence gate (m); shrinks with the residuals', 0.01, 10.0,
        name='max_correspondence_distance_m'),
    'matcher.icp_options.correspondences.robust': Param(
        "outlier rule: 'adaptive' (3 x robust std of residuals), 'trim', 'none'"),
    'matcher.icp_options.correspondences.min_points': Param(
        'scans with fewer valid points are not matched', 3),
    'matcher.icp_options.correspondences.min_inlier_fraction': Param(
        'fewer matched points than this fraction: failed match', 0.0, 1.0),
    'matcher.local_map.cell_m': Param('local map: side of its cells (m)', 0.01, 1.0),
    'matcher.local_map.max_points_per_cell': Param(
        'local map: points a cell takes before it is full', 1, 10_000,
        name='map_points_per_cell'),
    'matcher.local_map.radius_m': Param(
        'local map: cells further than this from the robot are dropped (m)', 0.1, 1000.0),
    'matcher.local_map.radius_per_range': Param(
        "local map: ... or than this x the recent scans' 90th-percentile range where that is "
        'further (0: off)', 0.0, 100.0),
    'matcher.map_restart_reach': Param(
        'local map: while matches fail, the map restarts from the scan once the prediction is '
        "this x the scan's median range from the last match (0: never)", 0.0, 100.0),
    'matcher.local_map.max_cells': Param(
        'local map: at most this many cells (the furthest dropped)', 1, 10_000_000),
    'matcher.max_speed_m_s': Param(
        "no published step further from the odometry's motion than this x the time since the "
        'previous scan (m/s; without odometry, no step faster)', 1e-3),
    'matcher.max_yaw_rate_rad_s': Param(
        "no published step turned further from the odometry's motion than this x that time "
        '(rad/s)', 1e-3),
    'matcher.rate_limits': Param(
        'false: the two limits above are off, for stamps whose time is assumed (rebuilt from '
        "a log's line order), where a rate measures nothing"),
    'matcher.anchor_distance_m': Param(
        "local map: /scan_match/odom's covariance is built from an anchor renewed after the "
        'robot moved this far from it (m)', 0.0, 1000.0),
    'matcher.max_error_ratio': Param(
        'local map: a mean alignment error above this many times the recent median fails the '
        'match', 1.0),
    'matcher.map_degeneracy_ratio': Param(
        'local map: a direction whose information is below this share of the strongest is '
        'degenerate (kept from the prediction, variance inflated)', 0.0, 1.0),
    'matcher.min_gate_m': Param(
        'local map: the correspondence gate (3 x the recent RMS model error) is at least this '
        '(m)', 0.01, 10.0),
    'matcher.insert_distance_m': Param(
        'local map: insert a matched scan after moving this far (m)', 0.0, 10.0),
    'matcher.insert_angle_rad': Param('... or turning this much (rad) since the last insertion',
                                      0.0, math.pi),
    'matcher.velocity_decay_s': Param(
        'without odometry, a failed match leaves the velocity decaying with this time constant '
        '(s)', 1e-3),
    'matcher.reacquire_after': Param(
        'local map: failed matches in a row after which a scan is searched for over a wide '
        'window', 1, 1000),
    'matcher.reacquire_window_m': Param('local map: that window, x and y each way (m)', 0.0,
                                        10.0),
    'matcher.reacquire_window_rad': Param('... and yaw each way (rad)', 0.0, math.pi),
    'matcher.doubt_deviations': Param(
        'local map: a match further from its prediction than this many x the recent RMS model '
        'error does not join the map until the next one agrees (0: no such test; a re-acquired '
        'match waits too)', 0.0, 100.0),
    'matcher.doubt_streak': Param('local map: ... this many doubted matches in a row join it',
                                  1, 1000),
    'matcher.prediction_error_share': Param(
        "a match's covariance keeps this share of its prediction's error: plus (this x the "
        'recent RMS deviation between prediction and match)^2 in x and y, over the scan\'s '
        'median range^2 in yaw', 0.0, 1.0),
    'deskew': Param("move each beam to the scan's stamp by the motion during the sweep, where "
                    'the scan gives time_increment'),
    'odom_max_extrapolation_s': Param('use odometry up to this far past its newest message (s)',
                                      0.0, 1.0),
    'odom_delay_s': Param(
        "how far the odometry's stamps lag the robot (s): a message stamped t is read as the "
        'pose at t - this (< 0: stamps early)', -1.0, 1.0),
    'publish_tf': Param('broadcast odom_frame -> base_frame on /tf (one owner per tree: the '
                        'fusion broadcasts it by default)'),
}, prefixes={'matcher': '', 'matcher.icp_options': '', 'matcher.icp_options.convergence': '',
             'matcher.icp_options.correspondences': '', 'matcher.local_map': 'map_'},
    # What the node does not expose: the ICP loop's and pairing's finer settings, the yaw
    # search, the map's planarity and the model error's window keep the core's values.
    internal={'matcher.icp_options.degeneracy_ratio', 'matcher.icp_options.min_residual_std',
              'matcher.icp_options.convergence.tolerance',
              'matcher.icp_options.convergence.error_tolerance',
              'matcher.icp_options.convergence.stall_iterations',
              'matcher.icp_options.correspondences.min_correspondence_distance',
              'matcher.icp_options.correspondences.trim_fraction',
              'matcher.icp_options.correspondences.adaptive_factor',
              'matcher.icp_options.yaw_search', 'matcher.local_map.min_planarity',
              'matcher.model_error_window'})
