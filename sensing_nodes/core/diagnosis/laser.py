"""The laser's ranges against REP 117 (+inf no return, -inf too close, NaN invalid; finite
values inside [range_min, range_max]) and its declared limits. Ranges (S, B) m."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.diagnosis.check import OK, PROBLEM, WARNING, Check


def range_checks(topic: str, ranges: NDArray[np.float64], range_min: float,
                 range_max: float) -> list[Check]:
    """NaN share, finite readings outside the declared limits (REP 117 wants +-inf), readings
    at exactly range_max or 0 (no-return written as a number), and the limits themselves."""
    r = np.asarray(ranges, dtype=float)
    total = r.size
    nan = int(np.isnan(r).sum())
    whole = int(np.isnan(r).all(axis=1).sum()) if r.ndim == 2 else 0
    share = nan / max(total, 1)
    scans_with_nan = int(np.isnan(r).any(axis=1).sum()) if r.ndim == 2 else 0
    if not nan:
        nan_check = Check('laser_nan', topic, OK, 0.0, 'beams', 'no NaN range', '0')
    else:
        verdict = PROBLEM if whole or share > 0.1 else WARNING
        nan_check = Check(
            'laser_nan', topic, verdict, float(nan), 'beams',
            f'{nan} NaN ranges ({100 * share:.2f} % of beams, in {scans_with_nan} scans; '
            f'{whole} scans all NaN): REP 117 reads NaN as an invalid measurement and '
            'the nodes skip those beams; many point at a driver fault or a dirty window',
            '0 (problem above 10 % or a scan all NaN)',
            {'share': share, 'scans_with_nan': scans_with_nan,
             'scans_all_nan': whole})
    finite = np.isfinite(r)
    with np.errstate(invalid='ignore'):
        below = int((finite & (r < range_min)).sum())
        above = int((finite & (r > range_max)).sum())
        at_max = int((finite & (np.abs(r - range_max) < 1e-3)).sum())
        zero = int((finite & (r == 0.0)).sum())
    outside = below + above
    notes = []
    if outside:
        notes.append(f'{below} finite readings below range_min and {above} above range_max '
                     '(REP 117: -inf too close, +inf no return)')
    if at_max > 0.05 * total:
        notes.append(f'{100 * at_max / total:.0f} % of readings equal range_max: no return '
                     'written as range_max, not +inf (REP 117)')
    if zero > 0.05 * total and range_min > 0:
        notes.append(f'{100 * zero / total:.0f} % of readings are 0: no return written as 0')
    conv = Check('laser_rep117', topic, WARNING if notes else OK, float(outside), 'readings',
                 '; '.join(notes) + ': the nodes drop them as invalid, so it costs nothing but '
                 'other consumers may take them as obstacles' if notes else
                 'finite ranges lie within the declared limits (REP 117)', '0 outside limits',
                 {'below_min': below, 'above_max': above, 'at_max': at_max, 'zero': zero})
    bad_limits = not (0.0 <= range_min < range_max) or not np.isfinite(range_max)
    limits = Check('laser_limits', topic, PROBLEM if bad_limits else OK, range_max, 'm',
                   f'range_min {range_min:g} m, range_max {range_max:g} m' + (
                       ': invalid limits (the nodes would refuse every beam)' if bad_limits
                       else ''), '0 <= range_min < range_max', {'range_min_m': range_min})
    return [nan_check, conv, limits]
