"""line_extractor: /scan (LaserScan) -> /scan/lines (MarkerArray) and /scan/lines/table
(PointCloud2).

The table is one PointCloud2 "point" per line with named fields (TABLE_FIELDS), so a consumer
reads it with numpy alone; header = the scan's stamp and frame. Layout documented in
docs/nodes/line_extractor.md. Each output is made and published only while a subscription
matches it (nothing in the graph takes them; a scan nobody's lines are wanted from is counted,
not extracted); sensing_pipeline makes both for every scan.
"""

from __future__ import annotations

import dataclasses
import math
import struct
import sys
from typing import Callable

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus
from sensor_msgs.msg import LaserScan, PointCloud2, PointField
from visualization_msgs.msg import MarkerArray

from sensing_nodes.core.config.line_extractor import LINE_EXTRACTOR_PARAMETERS
from sensing_nodes.core.geometry.scan import valid_ranges
from sensing_nodes.core.lines import Line, extract_lines
from sensing_nodes.core.timing import StampStep, classify_step
from sensing_nodes.ros.cdr import line_list_markers_cdr, point_cloud2_cdr
from sensing_nodes.ros.conversions import scan_arrays, stamp_to_ns
from sensing_nodes.ros.diagnostics import Diagnostics
from sensing_nodes.ros.logging import ThrottledWarnings
from sensing_nodes.ros.params import declare_config
from sensing_nodes.ros.processing_node import ProcessingNode
from sensing_nodes.ros.processor import Input, Output, Outputs, subscribed, wire
from sensing_nodes.ros.qos import ESTIMATE_QOS, SENSOR_QOS
from sensing_nodes.ros.run import run_node
from sensing_nodes.topics import SCAN, SCAN_LINES, SCAN_LINES_TABLE

# (name, PointField datatype, numpy type) of each table column, in order, little endian.
TABLE_FIELDS = (
    ('r', PointField.FLOAT64, '<f8'),
    ('alpha', PointField.FLOAT64, '<f8'),
    ('cov_rr', PointField.FLOAT64, '<f8'),
    ('cov_ra', PointField.FLOAT64, '<f8'),
    ('cov_aa', PointField.FLOAT64, '<f8'),
    ('x0', PointField.FLOAT64, '<f8'),
    ('y0', PointField.FLOAT64, '<f8'),
    ('x1', PointField.FLOAT64, '<f8'),
    ('y1', PointField.FLOAT64, '<f8'),
    ('first', PointField.UINT32, '<u4'),
    ('last', PointField.UINT32, '<u4'),
    ('point_count', PointField.UINT32, '<u4'),
)
TABLE_DTYPE = np.dtype([(name, np_type) for name, _, np_type in TABLE_FIELDS])
MARKER_NS = 'lines'


TABLE_COLUMNS = tuple((name, TABLE_DTYPE.fields[name][1], datatype)
                      for name, datatype, _ in TABLE_FIELDS)   # (name, offset, datatype)
MARKER_RGBA = (1.0, 0.45, 0.0, 1.0)
# One table row packed as TABLE_DTYPE lays it out (no padding, little endian): a struct per row
# costs a tenth of filling a numpy structured row.
_TABLE_ROW = struct.Struct('<' + ''.join(np.dtype(t).char for _, _, t in TABLE_FIELDS))
assert _TABLE_ROW.size == TABLE_DTYPE.itemsize


def lines_table_cdr(lines: list[Line], stamp_ns: int, frame_id: str) -> bytes:
    """The lines as a PointCloud2 (CDR bytes) with one point per line and the TABLE_FIELDS
    columns, stamped and framed as the scan."""
    rows = []
    for line in lines:
        (rr, ra), (_, aa) = line.covariance.tolist()
        rows.append(_TABLE_ROW.pack(line.r, line.alpha, rr, ra, aa, *line.start, *line.end,
                                    line.first, line.last, line.point_count))
    return point_cloud2_cdr(stamp_ns, frame_id, TABLE_COLUMNS, TABLE_DTYPE.itemsize, len(lines),
                            b''.join(rows))


def lines_markers_cdr(lines: list[Line], stamp_ns: int, frame_id: str, width_m: float) -> bytes:
    """MarkerArray (CDR bytes): DELETEALL (removes every earlier marker), then, if there are
    lines, one LINE_LIST of their end points."""
    return line_list_markers_cdr(stamp_ns, frame_id, MARKER_NS, width_m, MARKER_RGBA,
                                 [(*line.start, *line.end) for line in lines])


class LineExtractorNode(ProcessingNode):
    def __init__(self, **node_options) -> None:
        # node_options: rclpy Node keywords (sensing_pipeline passes this node's own cli_args)
        # and `lifecycle` (ros/processing_node.py)
        super().__init__('line_extractor', **node_options)

    def configure(self) -> None:
        parameters = declare_config(self, LINE_EXTRACTOR_PARAMETERS)
        self._options = dataclasses.asdict(parameters.lines)
        self._marker_width_m, self._max_gap_s = parameters.marker_width, parameters.max_gap_s
        self.diagnostics = Diagnostics(self)
        self.processor = LineExtractorProcessor(
            self._options, self._marker_width_m, self._max_gap_s, self.diagnostics,
            ThrottledWarnings(self, period_s=5.0))
        self.processor.listened = subscribed(
            wire(self, self.processor.inputs(), self.processor.outputs()))
        self.get_logger().info(
            'extracting lines from /scan with '
            + ', '.join(f'{k}={v}' for k, v in self._options.items())
        )


class LineExtractorProcessor:
    """line_extractor's per-message logic (ros/processor.py): /scan -> /scan/lines (markers)
    and /scan/lines/table (one PointCloud2 point per line), in the scan's frame and stamp; of
    them, those `listened` (topic -> bool) says someone takes: the node's matched subscriptions
    (ros/processor.subscribed), every output by default (sensing_pipeline)."""

    def __init__(self, options: dict, marker_width_m: float, max_gap_s: float,
                 diagnostics: Diagnostics, warnings: ThrottledWarnings) -> None:
        self._options = options
        self._marker_width_m = marker_width_m
        self._max_gap_s = max_gap_s
        self._diagnostics = diagnostics   # counted here, published by the node
        self._warnings = warnings
        self._last_stamp_ns: int | None = None
        self.listened: Callable[[str], bool] = lambda topic: True

    def inputs(self) -> list[Input]:
        return [Input(SCAN, LaserScan, SENSOR_QOS, self.on_scan, decoded=True)]

    def outputs(self) -> list[Output]:
        return [Output(SCAN_LINES, MarkerArray, ESTIMATE_QOS),
                Output(SCAN_LINES_TABLE, PointCloud2, ESTIMATE_QOS)]

    def on_scan(self, msg: LaserScan) -> Outputs:
        stamp_ns = stamp_to_ns(msg.header.stamp)
        self._diagnostics.last_stamp_ns = stamp_ns
        self._check_stamp(stamp_ns)
        wanted = [topic for topic in (SCAN_LINES, SCAN_LINES_TABLE) if self.listened(topic)]
        if not wanted:
            # Nobody takes the lines: the scan's ranges are neither checked nor extracted.
            self._diagnostics.count('scans_unsubscribed')
            return []
        self._diagnostics.count('scans')
        lines = self._lines(msg)
        self._diagnostics.count('lines', len(lines))
        if not lines:
            self._diagnostics.count('empty_results')
        # Packed straight into CDR bytes (ros/cdr.py): building the rclpy MarkerArray (a Point
        # object per end point) and PointCloud2 and serialising them cost more than the lines.
        frame_id = msg.header.frame_id
        pack = {SCAN_LINES: lambda: lines_markers_cdr(lines, stamp_ns, frame_id,
                                                      self._marker_width_m),
                SCAN_LINES_TABLE: lambda: lines_table_cdr(lines, stamp_ns, frame_id)}
        return [(topic, pack[topic]()) for topic in wanted]

    def _check_stamp(self, stamp_ns: int) -> None:
        # Extraction keeps no state, so an odd step is only reported, nothing is reset.
        step = classify_step(self._last_stamp_ns, stamp_ns, self._max_gap_s)
        self._last_stamp_ns = stamp_ns
        if step is StampStep.BACKWARDS:
            self._diagnostics.count('stamp_backwards')
            self._warnings.warn('backwards', 'scan stamp went backwards (looping bag or clock '
                                             'reset?); lines keep being extracted per scan')
        elif step is StampStep.REPEATED:
            self._diagnostics.count('stamp_repeated')
        elif step is StampStep.GAP:
            self._diagnostics.count('stamp_gaps')

    def _reject(self, key: str, message: str) -> list[Line]:
        self._diagnostics.count(f'rejected_{key}')
        self._diagnostics.level = DiagnosticStatus.WARN
        self._diagnostics.message = message
        self._warnings.warn(key, f'{message}; publishing no lines for this scan')
        return []

    def _lines(self, msg: LaserScan) -> list[Line]:
        """Lines of one scan, or [] (with a throttled warning) when the scan is unusable."""
        n = len(msg.ranges)
        if len(msg.intensities) not in (0, n):
            return self._reject('length_mismatch', f'scan has {n} ranges but '
                                f'{len(msg.intensities)} intensities')
        if not (math.isfinite(msg.angle_increment) and msg.angle_increment > 0.0):
            return self._reject('bad_increment', f'scan has angle_increment={msg.angle_increment} '
                                '(need a finite increment > 0)')
        if not math.isfinite(msg.angle_min):
            return self._reject('bad_angle_min', f'scan has angle_min={msg.angle_min}')
        if n == 0:
            return self._reject('empty', 'scan has no ranges')
        min_range, max_range = self._options['min_range'], self._options['max_range']
        if math.isfinite(msg.range_min) and math.isfinite(msg.range_max) \
                and 0.0 <= msg.range_min < msg.range_max:
            min_range, max_range = max(min_range, msg.range_min), min(max_range, msg.range_max)
        else:
            self._diagnostics.count('bad_range_limits')
            self._warnings.warn('range_limits', f'scan has range_min={msg.range_min}, '
                                f'range_max={msg.range_max}; using only the parameters '
                                f'min_range={min_range}, max_range={max_range}')
        if max_range <= min_range:
            return self._reject('range_limits', f'no range can be valid: limits '
                                f'[{min_range}, {max_range}] m')
        ranges, angles = scan_arrays(msg)
        nan_count = int(np.isnan(ranges).sum())
        if nan_count:
            # NaN is an invalid measurement (REP 117), unlike +-inf (no return / too close).
            self._diagnostics.count('nan_ranges', nan_count)
            self._warnings.warn('nan', f'scan has {nan_count} NaN ranges; they are ignored')
        valid = int(valid_ranges(ranges, min_range, max_range).sum())
        if valid == 0:
            return self._reject('no_valid_ranges', f'none of the {n} ranges is valid '
                                f'(finite, within [{min_range}, {max_range}] m)')
        if valid < self._options['min_line_points']:
            return self._reject('too_few_points', f'only {valid} valid ranges, fewer than '
                                f"min_line_points={self._options['min_line_points']}")
        options = {**self._options, 'min_range': min_range, 'max_range': max_range}
        self._diagnostics.level = DiagnosticStatus.OK
        self._diagnostics.message = 'ok'
        return extract_lines(ranges, angles, **options)


def main(args=None) -> None:
    sys.exit(run_node(LineExtractorNode, args))
