"""Timing of each input: rate, jitter, gaps, header stamps going backwards or repeated, header
stamp against record time (delay), and time offsets between sensors from their yaw motion.

Stamps int64 ns in bag (record) order; rates Hz; times s.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.diagnosis.check import OK, PROBLEM, WARNING, Check, graded, plural
from sensing_nodes.core.evaluation.calibration import grid_minimum

# Gap beyond which the nodes restart an integration (wheel_odometry, gyro_integrator,
# the fusion's IMU: max_gap_s 0.5; icp_matcher: 1.0) and the lowest useful rate, per kind.
GAP_LIMIT_S = {'imu': 0.5, 'joints': 0.5, 'odom': 0.5, 'scan': 1.0}
MIN_RATE_HZ = {'imu': 20.0, 'joints': 10.0, 'odom': 10.0, 'scan': 2.0}
DELAY_WARN_S, DELAY_PROBLEM_S = 0.1, 1.0
# A time offset errs the heading by (yaw rate) x offset while turning, without accumulating:
# 10 ms is 0.6 deg at 1 rad/s (a warning: the preset's delay_s corrects it), 50 ms 2.9 deg.
OFFSET_WARN_S, OFFSET_PROBLEM_S = 0.01, 0.05


def stream_checks(topic: str, kind: str, header_ns: NDArray[np.int64],
                  record_ns: NDArray[np.int64], has_header: bool = True) -> list[Check]:
    """Rate, jitter, gaps, backwards and repeated stamps, and delay of one topic."""
    t = np.asarray(header_ns, dtype=np.int64)
    if t.size < 3:
        return [Check('rate', topic, WARNING, float(t.size), 'messages',
                      f'{plural(int(t.size), "message")} only: too few to judge the timing')]
    step = np.diff(t) * 1e-9
    forward = step[step > 0]
    period = float(np.median(forward)) if forward.size else float('nan')
    checks = [_rate(topic, kind, t, period)]
    if forward.size > 2 and math.isfinite(period):
        checks.append(_jitter(topic, forward, period))
        checks.append(_gaps(topic, kind, forward, period))
    checks += _order(topic, step, has_header)
    if has_header:
        checks.append(_delay(topic, t, np.asarray(record_ns, dtype=np.int64)))
    return checks


def _rate(topic: str, kind: str, t: NDArray[np.int64], period: float) -> Check:
    rate = 1.0 / period if period > 0 else 0.0
    span = (t.max() - t.min()) * 1e-9
    minimum = MIN_RATE_HZ.get(kind)
    verdict = OK if minimum is None or rate >= minimum else WARNING
    advice = (f'{t.size} messages over {span:.1f} s' if verdict == OK else
              f'{rate:.1f} Hz is slow for this input (>= {minimum:g} Hz expected of {kind}): '
              'check the driver\'s rate or the recorder dropping messages' if rate > 0 else
              'the stamps never advance: no rate (stamps_repeated)')
    return Check('rate', topic, verdict, rate, 'Hz', advice,
                 f'>= {minimum:g} Hz' if minimum else '',
                 {'messages': int(t.size), 'span_s': span, 'median_period_s': period})


def _jitter(topic: str, forward: NDArray[np.float64], period: float) -> Check:
    regular = forward[forward < 5.0 * period]
    jitter = float(np.std(regular) / period) if regular.size else float('nan')
    verdict = graded(jitter, 0.25, float('inf'))
    advice = ('header stamps are regular' if verdict == OK else
              f'periods scatter by {100 * jitter:.0f} % of the median: a driver stamping at '
              'receipt (not at measurement) or a loaded machine; the nodes use the stamps as '
              'measurement times')
    return Check('jitter', topic, verdict, 100.0 * jitter, '% of period', advice, '< 25 %',
                 {'period_std_s': float(np.std(regular)) if regular.size else None})


def _gaps(topic: str, kind: str, forward: NDArray[np.float64], period: float) -> Check:
    limit = GAP_LIMIT_S.get(kind, max(10.0 * period, 0.5))
    gaps = forward[forward > limit]
    longest = float(forward.max())
    verdict = WARNING if gaps.size else OK
    advice = ('no gap' if verdict == OK else
              f'{plural(int(gaps.size), "gap")} longer than {limit:g} s (longest '
              f'{longest:.2f} s): the nodes restart their integration after one '
              '(max_gap_s); check the driver and the recorder (dropped messages, a paused '
              'recording)')
    return Check('gaps', topic, verdict, longest, 's', advice, f'<= {limit:g} s',
                 {'gaps': int(gaps.size)})


def _order(topic: str, step: NDArray[np.float64], has_header: bool) -> list[Check]:
    stamps = 'header stamps' if has_header else 'record times'
    back = int((step < 0).sum())
    same = int((step == 0).sum())
    back_check = Check(
        'stamps_backwards', topic, PROBLEM if back else OK, float(back), 'messages',
        f'{stamps} go backwards {plural(back, "time")} (largest step back '
        f'{-float(step.min()):.3f} s): nodes restart their estimates at each; fix the driver\'s '
        'clock or the bag (a looping or merged recording)' if back else f'{stamps} never go back',
        '0')
    share = same / max(step.size, 1)
    same_check = Check(
        'stamps_repeated', topic, OK if not same else (PROBLEM if share > 0.01 else WARNING),
        float(same), 'messages',
        f'{plural(same, "message repeats", "messages repeat")} the previous stamp '
        f'({100 * share:.2f} %): the nodes skip a '
        'repeated stamp (no time passed); the driver should stamp each measurement'
        if same else 'no repeated stamp', '0 (problem above 1 %)')
    return [back_check, same_check]


def _delay(topic: str, header_ns: NDArray[np.int64], record_ns: NDArray[np.int64]) -> Check:
    """How long after its header stamp each message was recorded."""
    delay = (record_ns - header_ns) * 1e-9
    median = float(np.median(delay))
    p5, p95 = (float(v) for v in np.percentile(delay, [5, 95]))
    details = {'median_s': median, 'p5_s': p5, 'p95_s': p95}
    if median < -0.005:
        return Check('delay', topic, WARNING if median > -DELAY_PROBLEM_S else PROBLEM, median,
                     's', 'header stamps lie after the time of recording: the driver\'s and the '
                     'recorder\'s clocks differ (or the stamps are not wall or sim time)',
                     f'|median| < {DELAY_WARN_S:g} s', details)
    verdict = graded(median, DELAY_WARN_S, DELAY_PROBLEM_S)
    advice = ('recorded within the tolerance of its stamp' if verdict == OK else
              f'messages reach the recorder {median:.3f} s after their stamps (p95 {p95:.3f} s): '
              'a slow link or a driver stamping late; nodes waiting on it (the fusion\'s '
              'reorder window) must hold inputs that long')
    return Check('delay', topic, verdict, median, 's', advice, f'< {DELAY_WARN_S:g} s', details)


def offset_cost(t_a: NDArray[np.int64], yaw_a: NDArray[np.float64], t_b: NDArray[np.int64],
                yaw_b: NDArray[np.float64], grid_s: NDArray[np.float64],
                trim: float = 0.1) -> NDArray[np.float64]:
    """For each offset d of the grid: the RMS (best 1 - trim share) of a's yaw increments read
    at (b's consecutive stamps + d), scaled by the gain that fits them best, minus b's own
    increments (rad). A gain is fitted at every d so that a scale error (a gyro's scale
    factor, a wheel geometry) does not pull the offset."""
    base = t_a[0]
    ta = (t_a - base) * 1e-9
    tb = (t_b - base) * 1e-9
    inc_b = np.diff(yaw_b)
    at = tb[None, :] + grid_s[:, None]
    a = np.interp(at.ravel(), ta, yaw_a).reshape(at.shape)
    inc_a = np.diff(a, axis=1)
    gain = (inc_a * inc_b).sum(axis=1) / np.maximum((inc_a * inc_a).sum(axis=1), 1e-300)
    residual = inc_a * gain[:, None] - inc_b[None, :]
    keep = max(1, int(math.floor((1.0 - trim) * inc_b.size)))
    part = np.partition(residual * residual, keep - 1, axis=1)[:, :keep]
    return np.sqrt(part.mean(axis=1))


def estimate_offset(t_a: NDArray[np.int64], yaw_a: NDArray[np.float64], t_b: NDArray[np.int64],
                    yaw_b: NDArray[np.float64], max_offset_s: float = 0.3,
                    step_s: float = 0.002) -> tuple[float, float, int]:
    """(offset s, turned rad, increments): a stamped t shows the motion b shows at t - offset.
    Stamps sorted and unique; ValueError when the streams cannot show an offset."""
    margin = max_offset_s + step_s
    inside = (t_b >= t_a[0] + margin * 1e9) & (t_b <= t_a[-1] - margin * 1e9)
    tb, yb = t_b[inside], yaw_b[inside]
    if tb.size < 11:
        raise ValueError(f'only {tb.size} samples of the second stream inside the first')
    turned = float(np.abs(np.diff(yb)).sum())
    if turned < math.radians(90.0):
        raise ValueError(f'they turn {math.degrees(turned):.0f} deg together: an offset needs '
                         'turning (>= 90 deg)')
    n = int(round(max_offset_s / step_s))
    grid = np.arange(-n, n + 1) * step_s
    offset = grid_minimum(grid, offset_cost(t_a, yaw_a, tb, yb, grid))
    if abs(offset) >= max_offset_s - step_s:
        raise ValueError(f'the best agreement lies at the edge of +-{max_offset_s:g} s')
    return offset, turned, int(tb.size - 1)


def pairwise_offset(t_a: NDArray[np.int64], yaw_a: NDArray[np.float64],
                    t_b: NDArray[np.int64], yaw_b: NDArray[np.float64],
                    max_rate_hz: float = 25.0) -> tuple[float, int]:
    """(offset of a against b in s, increments used): estimate_offset with the sparser stream
    as the increments' clock, thinned to max_rate_hz (memory: grid x increments)."""
    swap = t_a.size < t_b.size
    ta, ya, tb, yb = (t_b, yaw_b, t_a, yaw_a) if swap else (t_a, yaw_a, t_b, yaw_b)
    period = float(np.median(np.diff(tb))) * 1e-9 if tb.size > 1 else 1.0
    step = max(1, int(math.ceil(1.0 / (max_rate_hz * max(period, 1e-9)))))
    offset, _, count = estimate_offset(ta, ya, tb[::step], yb[::step])
    return (-offset if swap else offset), count


def solve_offsets(names: list[str], reference: str,
                  pairs: dict[tuple[str, str], tuple[float, float]]) -> dict[str, float]:
    """Each source's offset against the reference (s) from pairwise offsets
    {(a, b): (offset of a against b, weight)}: weighted least squares on o_a - o_b = d_ab with
    o_reference = 0; a source no pair connects to the reference is left out."""
    unknown = [n for n in names if n != reference]
    rows, rhs, weights = [], [], []
    for (a, b), (offset, weight) in pairs.items():
        row = np.zeros(len(unknown))
        for name, sign in ((a, 1.0), (b, -1.0)):
            if name != reference:
                row[unknown.index(name)] = sign
        rows.append(row)
        rhs.append(offset)
        weights.append(math.sqrt(weight))
    if not rows:
        return {reference: 0.0}
    design = np.array(rows) * np.array(weights)[:, None]
    solution, *_ = np.linalg.lstsq(design, np.array(rhs) * np.array(weights), rcond=None)
    linked = {reference}
    for _ in names:       # sources joined to the reference through measured pairs
        linked |= {x for a, b in pairs for x in (a, b) if a in linked or b in linked}
    out = {name: float(v) for name, v in zip(unknown, solution) if name in linked}
    out[reference] = 0.0
    return out


def offset_check(name: str, reference: str, offset: float,
                 pairs: dict[tuple[str, str], tuple[float, float]],
                 corrected: bool = True) -> Check:
    """The verdict on one source's offset against the reference, with the pairs behind it;
    corrected: the preset sets the fusion's delay_s from it (against an external reference,
    scan matching; between proprioceptive sources alone it cannot tell whose stamps to
    correct)."""
    verdict = graded(abs(offset), OFFSET_WARN_S, OFFSET_PROBLEM_S)
    advice = (f'{name} and {reference} agree in time' if verdict == OK else
              f'{name} shows the motion {1000 * abs(offset):.0f} ms '
              f'{"after" if offset > 0 else "before"} {reference} does: correct the driver '
              'stamping late (or early); ' + (
                  f'params.yaml sets the fusion\'s delay_s of {name} to {offset:.3f} s'
                  if corrected else
                  f'params.yaml sets no delay_s: without a laser it cannot tell whether {name} '
                  f'or {reference} is late' if reference != 'scan matching' else
                  f'the preset does not fuse {name}'))
    used = {f'{a} vs {b}': {'offset_s': o, 'increments': int(w)}
            for (a, b), (o, w) in pairs.items() if name in (a, b)}
    return Check('time_offset', f'{name} vs {reference}', verdict, offset, 's', advice,
                 f'|offset| < {1000 * OFFSET_WARN_S:g} ms', {'pairs': used})
