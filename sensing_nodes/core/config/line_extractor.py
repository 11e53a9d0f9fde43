"""line_extractor's configuration: the extraction (core/lines.py), the marker's width and the
gap it reports; and its parameters."""

from __future__ import annotations

from dataclasses import dataclass

from sensing_nodes.core.lines import LineOptions
from sensing_nodes.parameters import Param, ParameterTable


@dataclass(frozen=True)
class LineExtractorParameters:
    """extract_lines' options (ranges up to 100 m unless a scan says less), the LINE_LIST
    marker's width (m) and the stamp gap reported in the diagnostics (s)."""

    lines: LineOptions = LineOptions(max_range=100.0)
    marker_width: float = 0.03
    max_gap_s: float = 1.0

    def problems(self) -> list[tuple[str, str, object]]:
        """(field, problem, value) for each setting the node cannot run with."""
        return [(f'lines.{name}', problem, value)
                for name, problem, value in self.lines.problems()]


LINE_EXTRACTOR_PARAMETERS = ParameterTable(LineExtractorParameters(), described={
    'lines.split_distance': Param(
        'a segment is split while one of its points is farther than this from its '
        'least-squares line (m)', 1e-6, 100.0),
    'lines.max_line_gap': Param(
        'no line spans two consecutive valid points farther apart than this (m)', 1e-6, 1000.0),
    'lines.min_line_points': Param('lines fitted to fewer beams are dropped', 2, 100000),
    'lines.min_line_length': Param('shorter lines (endpoint distance) are dropped (m)', 0.0,
                                   1000.0),
    'lines.min_range': Param("shorter ranges are invalid (m); the scan's range_min also applies",
                             0.0, 1000.0),
    'lines.max_range': Param("longer ranges are invalid (m); the scan's range_max also applies",
                             1e-3, 1e6),
    'lines.range_sigma': Param(
        'standard deviation of the range noise (m): weights the fit, scales covariances', 1e-6,
        10.0),
    'lines.merge_chi2': Param(
        'neighbouring segments merge when chi-square of (dr, dalpha) over their summed '
        'covariance is at most this (2 dof; 9.21 = 99 %)', 1e-6, 1e6),
    'marker_width': Param('line width of the LINE_LIST marker (m)', 1e-4, 10.0),
    'max_gap_s': Param('scans further apart (stamp time) are reported as a gap', 1e-3, 3600.0),
}, prefixes={'lines': ''})
