"""icp_matcher: /scan -> /scan_match/odom (base_link pose from point-to-line ICP of each deskewed
scan against a local map of the recent surroundings, or against one keyframe), with the
initial guess from an odometry topic or a constant-velocity model; each match also in the map's
frame or against its keyframe on /scan_match/keyframe_odom, for the fusion."""

from __future__ import annotations

import dataclasses
import math
import sys

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus
from nav_msgs.msg import Odometry
from sensor_msgs.msg import LaserScan
from tf2_msgs.msg import TFMessage

from sensing_nodes.core.config.icp_matcher import ICP_MATCHER_PARAMETERS
from sensing_nodes.core.geometry.scan import scan_to_points
from sensing_nodes.core.geometry.transform import Transform
from sensing_nodes.core.scan_matching import (
    ZERO,
    OdometryBuffer,
    ScanEvent,
    ScanMatcherSettings,
    ScanStatus,
    ScanStep,
    make_scan_matcher,
    odometry_guidance,
)
from sensing_nodes.ros.cdr import odometry_cdr, transform_cdr
from sensing_nodes.ros.conversions import (
    NOT_MATCHED,
    SCAN_MATCH_KEYFRAME_FRAME,
    SCAN_MATCH_MAP_FRAME,
    odometry_pose,
    scan_arrays,
    stamp_to_ns,
)
from sensing_nodes.ros.diagnostics import Diagnostics
from sensing_nodes.ros.logging import ThrottledWarnings
from sensing_nodes.ros.params import declare_config
from sensing_nodes.ros.processing_node import ProcessingNode
from sensing_nodes.ros.processor import Input, Output, Outputs, wire
from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS, TF_QOS
from sensing_nodes.ros.run import run_node
from sensing_nodes.ros.tf import TF_TOPIC, SensorMount, StaticTransformBuffer
from sensing_nodes.topics import SCAN, SCAN_MATCH, SCAN_MATCH_KEYFRAME

# Scan time (s) a never-heard odometry topic is information, before it is warned about.
ODOM_START_GRACE_S = 5.0


# A match's covariance where the message carries none (ros/conversions.NOT_MATCHED).
_NOT_MATCHED = np.diag([NOT_MATCHED, 0.0, 0.0])


def keyframe_odometry(step: ScanStep, base_frame: str) -> bytes:
    """A scan step as /scan_match/keyframe_odom, the fusion's input, packed into CDR bytes
    (ros/cdr.py; docs/fusion.md, "The scan matcher's input").

    local_map mode: header.frame_id scan_match_map, stamped at the middle of the scan's sweep
    (MapPose.time_ns), the pose base_link then in the map with the registration's covariance,
    or zero with covariance[0] = -1 when nothing was matched. The scan that starts a map is its
    origin: stamped at the scan, child_frame_id scan_match_map too, the pose zero and exact.
    keyframe mode: header.frame_id scan_match_keyframe, stamped at the scan, the pose base_link
    at the scan in base_link at the keyframe with the match's covariance (or zero with
    covariance[0] = -1: no match); child_frame_id scan_match_keyframe when this scan becomes the
    next keyframe, else the base frame."""
    in_map = step.local_map
    if in_map is not None:
        if in_map.origin:
            return odometry_cdr(step.stamp_ns, SCAN_MATCH_MAP_FRAME, SCAN_MATCH_MAP_FRAME, ZERO,
                                np.zeros((3, 3)))
        if in_map.pose is None:
            return odometry_cdr(in_map.time_ns, SCAN_MATCH_MAP_FRAME, base_frame, ZERO,
                                _NOT_MATCHED)
        return odometry_cdr(in_map.time_ns, SCAN_MATCH_MAP_FRAME, base_frame, in_map.pose,
                            in_map.covariance)
    child = SCAN_MATCH_KEYFRAME_FRAME if step.new_keyframe else base_frame
    if step.keyframe is None:
        return odometry_cdr(step.stamp_ns, SCAN_MATCH_KEYFRAME_FRAME, child, ZERO, _NOT_MATCHED)
    return odometry_cdr(step.stamp_ns, SCAN_MATCH_KEYFRAME_FRAME, child, step.keyframe.pose,
                        step.keyframe.covariance)


class IcpMatcherNode(ProcessingNode):
    def __init__(self, **node_options) -> None:
        # node_options: rclpy Node keywords (sensing_pipeline passes this node's own cli_args)
        # and `lifecycle` (ros/processing_node.py)
        super().__init__('icp_matcher', **node_options)

    def configure(self) -> None:
        parameters = declare_config(self, ICP_MATCHER_PARAMETERS)
        settings, odom_topic = parameters.matcher, parameters.odom_topic
        self._base_frame, self._deskew = parameters.base_frame, parameters.deskew
        # The laser mount: /tf_static's base_frame -> <scan frame> where it is published, else
        # the laser_* parameters.
        mount = SensorMount(self, StaticTransformBuffer(self), self._base_frame,
                            Transform.from_planar(*settings.laser_pose), 'laser')
        self.diagnostics = Diagnostics(self)
        self.processor = IcpMatcherProcessor(
            settings, odom_topic, parameters.odom_max_extrapolation_s, parameters.min_points,
            parameters.odom_frame, self._base_frame, parameters.publish_tf, mount,
            self.diagnostics, ThrottledWarnings(self), parameters.odom_delay_s, self._deskew,
            self.get_logger())
        wire(self, self.processor.inputs(), self.processor.outputs())
        self.diagnostics.values['prediction'] = odom_topic or 'constant_velocity'
        laser, options = settings.laser_pose, settings.icp_options
        self.diagnostics.values['mode'] = settings.mode
        against = (f'a local map ({settings.local_map.cell_m} m cells within '
                   f'{settings.local_map.radius_m} m)' if settings.mode == 'local_map' else
                   f'keyframes every {settings.keyframe_distance_m} m / '
                   f'{math.degrees(settings.keyframe_angle_rad):.1f} deg')
        self.get_logger().info(
            f"initial guess from {odom_topic or 'a constant-velocity model'}; laser at "
            f'({laser[0]}, {laser[1]}, {laser[2]}) in {self._base_frame}; each scan against '
            f'{against}; {options.method}, robust {options.correspondences.robust}; '
            f"deskewing {'on' if self._deskew else 'off'}")
        if not settings.rate_limits:
            self.get_logger().info(
                'rate limits off (rate_limits: false): max_speed_m_s and max_yaw_rate_rad_s do '
                "not bound the matches, as the stamps' time is assumed (e.g. rebuilt from a "
                "log's line order)")


class IcpMatcherProcessor:
    """icp_matcher's per-message logic (ros/processor.py): /scan (and an odometry topic for the
    initial guess) -> /scan_match/keyframe_odom, then /scan_match/odom (odom_frame ->
    base_frame, m and rad) and, with publish_tf, the same pose on /tf."""

    def __init__(self, settings: ScanMatcherSettings, odom_topic: str,
                 odom_extrapolation_s: float, min_points: int, odom_frame: str, base_frame: str,
                 publish_tf: bool, mount: SensorMount, diagnostics: Diagnostics,
                 warnings: ThrottledWarnings, odom_delay_s: float = 0.0,
                 deskew: bool = True, logger=None) -> None:
        self._settings = settings
        self._matcher = make_scan_matcher(settings)
        self._deskew = deskew
        self._odom_topic = odom_topic
        # Odometry history must reach back to the previous scan, however far apart scans may be
        # (max_gap_s): a real log's keyframes can be tens of seconds apart.
        self._odometry = OdometryBuffer(max_age_s=max(10.0, 2.0 * settings.max_gap_s),
                                        max_extrapolation_s=odom_extrapolation_s) \
            if odom_topic else None
        # The odometry's poses are read as the robot's at stamp - odom_delay_s (a lagging source).
        self._odom_delay_ns = round(odom_delay_s * 1e9)
        self._odom_heard = False   # any message of odom_topic since the node started
        self._odom_unheard_since_ns: int | None = None   # first scan matched before that
        self._min_points = min_points
        self._odom_frame, self._base_frame = odom_frame, base_frame
        self._publish_tf = publish_tf
        self._last_scan_ns: int | None = None
        self._laser_parameters = settings.laser_pose
        self._mount = mount
        self.diagnostics = diagnostics   # counted here, published by the node
        self._warnings = warnings
        self._logger = logger            # the node's (one-off information)

    def inputs(self) -> list[Input]:
        return [Input(SCAN, LaserScan, SENSOR_QOS, self.on_scan)] + \
            ([Input(self._odom_topic, Odometry, ESTIMATE_QOS, self.on_odometry, decoded=True)]
             if self._odom_topic else [])

    def outputs(self) -> list[Output]:
        # Each match in its local map or relative to its keyframe, for a fusion that keeps the
        # map's origin or the keyframe's pose in its state
        # (docs/fusion.md, "The scan matcher's input").
        return [Output(SCAN_MATCH_KEYFRAME, Odometry, ESTIMATE_QOS),
                Output(SCAN_MATCH, Odometry, ESTIMATE_QOS)] + \
            ([Output(TF_TOPIC, TFMessage, TF_QOS)] if self._publish_tf else [])

    def on_odometry(self, msg: Odometry) -> Outputs:
        self._odom_heard = True
        stamp = stamp_to_ns(msg.header.stamp) - self._odom_delay_ns
        pose, _ = odometry_pose(msg)
        if not all(math.isfinite(v) for v in pose):
            self.diagnostics.count('odom_not_finite')
            self._warnings.warn(
                'odom_nan', f'odometry at {stamp * 1e-9:.3f} s is not finite: ignored'
            )
            return []
        if not self._odometry.add(stamp, pose):
            self.diagnostics.count('odom_backwards')
            self._warnings.warn('odom_backwards', f'odometry stamp {stamp * 1e-9:.3f} s went '
                                'backwards: odometry buffer cleared')
        return []

    def _odom_not_heard(self, stamp: int) -> None:
        """A scan matched without odometry because odom_topic has not been heard yet: said
        once (information: nodes launched together come up in any order), and warned about
        once it lasts ODOM_START_GRACE_S of scan stamps. Not waited for: every scan is
        answered (a lockstep replay or the fusion's pacing waits for one answer per scan), and
        odometry published before this node's subscription matched never arrives
        (docs/nodes/icp_matcher.md, "Start-up")."""
        if self._odom_unheard_since_ns is None:
            self._odom_unheard_since_ns = stamp
            text = (f'no odometry from {self._odom_topic} yet (scan at {stamp * 1e-9:.3f} s): '
                    'matching with the constant-velocity prediction until it comes')
            if self._logger is not None:
                self._logger.info(text)
            else:
                self._warnings.warn('odom', text)
        elif stamp - self._odom_unheard_since_ns > ODOM_START_GRACE_S * 1e9:
            self._warnings.warn('odom', (
                f'no odometry from {self._odom_topic} in '
                f'{(stamp - self._odom_unheard_since_ns) * 1e-9:.1f} s of scans: constant '
                'velocity prediction instead (is odom_topic right?)'))

    def _beam_times(self, msg: LaserScan, beams, stamp: int):
        """Each valid point's time after the stamp (s) from the scan's time_increment, or None
        (deskewing off, every beam at the stamp, or an unusable increment: counted)."""
        increment = float(msg.time_increment)
        if not self._deskew or increment == 0.0:
            return None
        if not (math.isfinite(increment) and increment > 0.0):
            self.diagnostics.count('time_increment_unusable')
            self._warnings.warn('time_increment', f'scan at {stamp * 1e-9:.3f} s has '
                                f'time_increment {increment}: not deskewed')
            return None
        return beams * increment

    def _use_mount(self, laser_pose: tuple[float, float, float]) -> None:
        """Match with this laser mount; a new mount (a late /tf_static) restarts the keyframe."""
        if laser_pose == self._settings.laser_pose:
            return
        self._settings = dataclasses.replace(self._settings, laser_pose=laser_pose)
        self._matcher = make_scan_matcher(self._settings)
        self.diagnostics.count('mount_changes')
        self.diagnostics.values['laser_mount'] = '%.4f %.4f %.4f' % laser_pose

    # long: a scan's path through the node (mount, conversion, validation, guess, match,
    # diagnostics, outputs) in order: each step reads what the previous one set.
    def _match_quality(self, step) -> None:
        """The last match's quality on /diagnostics: its mean alignment error and
        iterations, the share of its points paired (inliers), the residuals' standard deviation
        behind its covariance (m), whether a direction was unconstrained, and the recent RMS
        deviation of matches from their predictions (m at the scan's reach) its covariance and
        the doubt test are scaled by."""
        result, values = step.result, self.diagnostics.values
        values['last_error_m'] = f'{result.error:.4f}'
        values['last_iterations'] = str(result.iterations)
        values['last_inlier_share'] = \
            f'{result.inliers / result.source_points if result.source_points else 0.0:.3f}'
        values['last_residual_std_m'] = f'{math.sqrt(result.residual_variance):.4f}' \
            if math.isfinite(result.residual_variance) else 'nan'
        values['last_degenerate'] = str(result.degenerate).lower()
        errors = self._matcher.model_errors
        values['model_error_rms_m'] = f'{errors.rms if errors else 0.0:.4f}'

    def on_scan(self, msg: LaserScan) -> Outputs:
        stamp = stamp_to_ns(msg.header.stamp)
        diag = self.diagnostics
        diag.count('scans')
        mount = self._mount.from_tf(msg.header.frame_id)
        self._use_mount(mount.planar() if mount is not None else self._laser_parameters)
        ranges, angles = scan_arrays(msg)
        points, beams = scan_to_points(ranges, angles, msg.range_min, msg.range_max)
        if points.shape[0] < self._min_points:
            diag.count('too_few_points')
            self._warnings.warn('few', f'scan at {stamp * 1e-9:.3f} s has {points.shape[0]} valid '
                                f'points (< {self._min_points}): falling back to the prediction')
        beam_times = self._beam_times(msg, beams, stamp)
        prediction = sweep = None
        if self._odometry is not None:
            prediction, sweep = odometry_guidance(self._odometry, self._last_scan_ns, stamp,
                                                  beam_times)
            if prediction is None and self._last_scan_ns is not None \
                    and stamp > self._last_scan_ns:
                diag.count('odom_unavailable')
                if self._odom_heard:
                    self._warnings.warn('odom', f'no odometry around {stamp * 1e-9:.3f} s: '
                                        'constant velocity prediction instead')
                else:
                    self._odom_not_heard(stamp)
        step = self._matcher.process(stamp, points, prediction, beam_times, sweep)
        if ScanEvent.GAP in step.events:
            self._warnings.warn('gap', f'scan at {stamp * 1e-9:.3f} s: '
                                f'{(stamp - self._last_scan_ns) * 1e-9:.2f} s since the previous '
                                'scan: the velocity restarts at zero, the map stays')
        if step.status is not ScanStatus.REPEATED:
            self._last_scan_ns = stamp
        diag.count(step.status)
        for event in step.events:
            diag.count(event)
        if step.prediction:
            diag.count(f'predicted_by_{step.prediction}')
        if step.new_keyframe:
            diag.count('keyframes')
        if step.status is ScanStatus.FALLBACK:
            diag.values['last_fallback'] = step.reason
            self._warnings.warn('fallback', f'scan at {stamp * 1e-9:.3f} s: match failed '
                                f'({step.reason}); using the {step.prediction} prediction')
        elif step.status in (ScanStatus.REPEATED, ScanStatus.RESET_BACKWARDS, ScanStatus.GAP):
            self._warnings.warn(step.status, f'scan at {stamp * 1e-9:.3f} s: {step.reason}')
        if step.result is not None and step.status is ScanStatus.MATCHED:
            self._match_quality(step)
        if self._settings.mode == 'local_map':
            diag.values['map_cells'] = str(len(self._matcher.map))
            diag.values['gate_m'] = f'{self._matcher.gate_m:.3f}'
            matched = diag.counts['matched']
            diag.values['not_inserted_share'] = \
                f"{diag.counts['not_inserted'] / matched if matched else 0.0:.3f}"
            doubt = step.local_map.doubt if step.local_map is not None else ''
            if doubt:
                diag.values['last_not_inserted'] = f'{stamp * 1e-9:.3f} s: {doubt}'
                self._warnings.warn('not_inserted', f'scan at {stamp * 1e-9:.3f} s: matched but '
                                    f'kept out of the map ({doubt})')
        if not step.publish:
            return []
        # The fusion's input first: a consumer waiting for /scan_match/odom (a lockstep replay)
        # then knows the fusion's input for this scan is already on its way.
        out: Outputs = [
            (SCAN_MATCH_KEYFRAME, keyframe_odometry(step, self._base_frame)),
            (SCAN_MATCH, odometry_cdr(
                stamp, self._odom_frame, self._base_frame, step.pose, step.covariance,
                step.twist, step.twist_covariance))]
        if self._publish_tf:
            out.append((TF_TOPIC, transform_cdr(stamp, self._odom_frame, self._base_frame,
                                                Transform.from_planar(*step.pose))))
        diag.count('published')
        # The newest scan stamp, until time goes back (a looping bag, a replay's warm-up): a
        # kept maximum stamped every later status with the old timeline's time.
        diag.last_stamp_ns = stamp if step.status is ScanStatus.RESET_BACKWARDS \
            else max(diag.last_stamp_ns, stamp)
        diag.values['pose'] = '%.4f %.4f %.4f' % step.pose
        failures = diag.counts['fallback']
        failed = step.status is ScanStatus.FALLBACK
        diag.level = DiagnosticStatus.WARN if failed else DiagnosticStatus.OK
        diag.message = (f'last match failed ({failures} in all): {step.reason}'
                        if failed else f'ok ({failures} failed matches)')
        return out


def main(args: list[str] | None = None) -> None:
    sys.exit(run_node(IcpMatcherNode, args))
