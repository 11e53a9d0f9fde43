"""carmen_to_bag: the shared CARMEN logs convert (scan geometry, no-return values, odometry,
reference poses); a bad line is reported with its number and the rest converts; a log whose
time is broken (all 0, six significant digits, a clock that stood still, backwards, negative,
wrapped) converts with a time base rebuilt from the line order, said so, or is refused naming
the problem."""

from __future__ import annotations

import gzip
import math
from pathlib import Path

import numpy as np
import pytest
from harness import run_to_exit

from sensing_nodes.bags.carmen import TimeCheck, check_time, read_carmen
from sensing_nodes.bags.storage import BagReader, read_messages, topic_counts
from sensing_nodes.ros.conversions import odometry_pose, scan_arrays
from sensing_nodes.tools import carmen_to_bag
from sensing_nodes.tools import eval as sensing_eval
from sensing_nodes.tools.carmen_to_bag import (
    NO_RETURN_MARGIN,
    TIME_BASE_KEY,
    ConvertOptions,
    convert,
    time_base,
)

CARMEN = Path(__file__).resolve().parents[2] / 'shared' / 'datasets' / 'carmen'
needs_logs = pytest.mark.skipif(not CARMEN.is_dir(), reason=f'CARMEN logs not found in {CARMEN}')

# file -> (scans, beams, no-return value) from ../shared/datasets/carmen/README.md
LOGS = {
    'aces-corrected.log.gz': (440, 180, 50.0),
    'freiburg-101-corrected.log.gz': (292, 360, 81.91),
}


@needs_logs
@pytest.mark.parametrize('name', sorted(LOGS))
def test_shared_log_converts(tmp_path, name):
    scans, beams, no_return = LOGS[name]
    out = tmp_path / 'bag'
    summary = convert(CARMEN / name, out)
    assert summary['errors'] == [] and summary['no_return_value'] == no_return
    counts = topic_counts(out)
    assert counts['/scan'] == ('sensor_msgs/msg/LaserScan', scans)
    assert counts['/ground_truth/odom'] == ('nav_msgs/msg/Odometry', scans)
    log = read_carmen(CARMEN / name)
    # Every ODOM line stamped 0 repeats the reference pose; the others are odometry.
    real_odometry = int(np.sum(log.odom_time_s > 0))
    assert 0 < counts['/odom'][1] <= real_odometry

    messages = list(read_messages(out, ['/scan', '/ground_truth/odom', '/odom']))
    stamps = [s for _, s, _ in messages]
    assert stamps == sorted(stamps)
    first_scan = next(m for t, _, m in messages if t == '/scan')
    ranges, angles = scan_arrays(first_scan)
    assert first_scan.header.frame_id == 'laser' and len(ranges) == beams
    # Beams at -90 deg + i * 180 deg / beams, counter-clockwise (the README's layout).
    np.testing.assert_allclose(angles, -math.pi / 2 + math.pi * np.arange(beams) / beams,
                               atol=1e-6)
    limit = no_return * (1.0 - NO_RETURN_MARGIN)
    assert first_scan.range_max == pytest.approx(limit)
    raw = log.scans[0].ranges
    np.testing.assert_array_equal(np.isinf(ranges), raw >= limit)
    np.testing.assert_allclose(ranges[np.isfinite(ranges)], raw[raw < limit], rtol=1e-6)
    assert first_scan.header.stamp.sec + first_scan.header.stamp.nanosec * 1e-9 == \
        pytest.approx(log.scans[0].time_s, abs=1e-6)

    truth = [m for t, _, m in messages if t == '/ground_truth/odom']
    for k in (0, len(truth) // 2, -1):
        pose, _ = odometry_pose(truth[k])
        np.testing.assert_allclose(pose, log.scans[k].pose, atol=1e-9)
    odom = [m for t, _, m in messages if t == '/odom']
    covariance = [odometry_pose(m)[1] for m in odom]
    # The fusion takes only odometry with a positive covariance after moving: it grows.
    assert np.all(np.diff([c[0, 0] for c in covariance]) >= 0) and covariance[-1][0, 0] > 0


@needs_logs
def test_laser_offset_moves_the_reference_back_to_base_link(tmp_path):
    out = tmp_path / 'bag'
    name = 'freiburg-101-corrected.log.gz'
    convert(CARMEN / name, out, laser_x_m=0.5)
    log = read_carmen(CARMEN / name)
    truth = next(m for t, _, m in read_messages(out, ['/ground_truth/odom']))
    (x, y, yaw), _ = odometry_pose(truth)
    lx, ly, lyaw = log.scans[0].pose
    assert (x, y, yaw) == pytest.approx(
        (lx - 0.5 * math.cos(lyaw), ly - 0.5 * math.sin(lyaw), lyaw)
    )


def _write_log(path: Path, lines: list[str]) -> Path:
    with gzip.open(path, 'wt') as handle:
        handle.write('\n'.join(lines) + '\n')
    return path


def test_odometry_reanchored_on_the_reference_is_chained_without_the_jump(tmp_path):
    """A "corrected" log: the odometry has drifted to (1, 0, 0) at the scan, the reference says
    (1.1, 0.1, 90 deg), the ODOM line stamped 0 repeats it and the next line continues from it
    by 1 m straight ahead. /odom continues from (1, 0, 0) by the same 1 m: (2, 0, 0), not the
    logged (1.1, 1.1, 90 deg)."""
    ranges = ' '.join(['2.0'] * 180)
    log = _write_log(tmp_path / 'anchored.log.gz', [
        'ODOM 0.0 0.0 0.0 0 0 0 1.0 host 1.0',
        'ODOM 1.0 0.0 0.0 0 0 0 2.0 host 2.0',
        f'FLASER 180 {ranges} 1.1 0.1 1.5707963267948966 1.1 0.1 1.5707963267948966 2.0 host 2.0',
        'ODOM 1.1 0.1 1.5707963267948966 0 0 0 0 host 0',
        'ODOM 1.1 1.1 1.5707963267948966 0 0 0 3.0 host 3.0',
        'ODOM 1.1 2.1 1.5707963267948966 0 0 0 4.0 host 4.0',
    ])
    out = tmp_path / 'bag'
    summary = convert(log, out)
    assert summary['skipped_odom']['reference_repeated'] == 1
    poses = [odometry_pose(m)[0] for _, _, m in read_messages(out, ['/odom'])]
    np.testing.assert_allclose(poses, [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (2.0, 0.0, 0.0),
                                       (3.0, 0.0, 0.0)], atol=1e-12)
    truth, _ = odometry_pose(next(m for _, _, m in read_messages(out, ['/ground_truth/odom'])))
    assert truth == pytest.approx((1.1, 0.1, math.pi / 2))


@needs_logs
def test_shared_logs_odometry_carries_no_reference(tmp_path):
    """Freiburg 101 re-anchors its ODOM on the reference after every scan: read as logged, the
    odometry at the last scan is 0.017 m from the last reference pose. Chained, it keeps its own
    drift: 65.6 m and 163 deg off at the last of its 292 scans (both in the reference's frame,
    where
    the log's odometry starts)."""
    out = tmp_path / 'bag'
    convert(CARMEN / 'freiburg-101-corrected.log.gz', out)
    odom = [(s, odometry_pose(m)[0]) for _, s, m in read_messages(out, ['/odom'])]
    last_truth = [(s, odometry_pose(m)[0]) for _, s, m in read_messages(
        out, ['/ground_truth/odom'])][-1]
    at_last_scan = [p for s, p in odom if s <= last_truth[0]][-1]
    assert math.hypot(at_last_scan[0] - last_truth[1][0], at_last_scan[1] - last_truth[1][1]) > 10


def test_bad_lines_are_reported_with_their_number_and_the_rest_converts(tmp_path):
    ranges = ' '.join(['2.0'] * 178 + ['50.0', '50.0'])
    log = _write_log(tmp_path / 'small.log.gz', [
        '# a comment',
        'ODOM 0.0 0.0 0.0 0 0 0 1.0 host 1.0',
        f'FLASER 180 {ranges} 1.0 2.0 0.5 1.0 2.0 0.5 1.1 host 1.1',
        'FLASER 180 1.0 2.0 garbage',
        'ODOM 0.1 0.0 0.0 0.2 0 0 1.5 host 1.5',
        'ODOM 1.0 2.0 0.5 0 0 0 0 host 0',
        f'FLASER 180 {ranges} 1.1 2.0 0.5 1.1 2.0 0.5 2.1 host 2.1',
        'BOGUS 1 2 3',
    ])
    out = tmp_path / 'bag'
    result = run_to_exit('carmen_to_bag', [str(log), str(out)])
    assert result.returncode == 0, result.stderr
    assert f'{log}:4: skipped: FLASER' in result.stderr
    assert f'{log}:8: skipped: BOGUS' in result.stderr
    assert '2 bad lines' in result.stdout and "1 repeating the scan's reference" in result.stdout
    counts = topic_counts(out)
    assert counts['/scan'][1] == 2 and counts['/ground_truth/odom'][1] == 2
    assert counts['/odom'][1] == 2
    scan = next(m for _, _, m in read_messages(out, ['/scan']))
    ranges_out, _ = scan_arrays(scan)
    assert np.isinf(ranges_out[-2:]).all() and np.all(ranges_out[:-2] == 2.0)


def test_a_scattered_no_return_value_and_a_stuck_beam_are_no_measurements(tmp_path):
    """As Edmonton and Acapulco: the sentinel 51.15 also read as 51.14 and, rarely, 51.16 (the
    largest value, too rare to be a sentinel on its own), and the last beam reading 50.0 in every
    scan. Every one of those is no return (+inf) or invalid (NaN); a far wall at 45 m stays."""
    lines = []
    for k in range(30):
        ranges = [2.0 + 0.01 * k] * 175 + [51.15, 51.14, 51.15, 45.0 - 0.1 * k, 50.0]
        if k == 3:
            ranges[0] = 51.16
        text = ' '.join(f'{r:g}' for r in ranges)
        lines += [f'ODOM {0.1 * k} 0 0 0 0 0 {1.0 + k} host {1.0 + k}',
                  f'FLASER 180 {text} {0.1 * k} 0 0 {0.1 * k} 0 0 {1.0 + k} host {1.0 + k}']
    out = tmp_path / 'bag'
    result = run_to_exit('carmen_to_bag', [str(_write_log(tmp_path / 'hall.log.gz', lines)),
                                           str(out)])
    assert result.returncode == 0, result.stderr
    assert 'no-return value 51.16' in result.stdout and 'beams [179]' in result.stdout
    scans = [scan_arrays(m)[0] for _, _, m in read_messages(out, ['/scan'])]
    for k, ranges in enumerate(scans):
        assert np.isinf(ranges[175:178]).all() and ranges[178] == pytest.approx(45.0 - 0.1 * k)
        assert np.isnan(ranges[179])
        assert np.isinf(ranges[0]) if k == 3 else ranges[0] == pytest.approx(2.0 + 0.01 * k)


def test_unusable_input_is_refused_without_output(tmp_path):
    out = tmp_path / 'bag'
    missing = run_to_exit('carmen_to_bag', [str(tmp_path / 'none.log'), str(out)])
    assert missing.returncode == 2 and 'none.log' in missing.stderr and not out.exists()
    empty = _write_log(tmp_path / 'empty.log.gz', ['ODOM 0 0 0 0 0 0 1.0 h 1.0', 'FLASER x'])
    result = run_to_exit('carmen_to_bag', [str(empty), str(out)])
    assert result.returncode == 2 and 'no FLASER line parsed' in result.stderr
    # The path is named once: 'carmen_to_bag: error: LOG: no FLASER line parsed (1 bad lines)'.
    assert result.stderr.strip() == \
        f'carmen_to_bag: error: {empty}: no FLASER line parsed (1 bad lines)', result.stderr
    assert not out.exists() and not list(tmp_path.glob('.bag*'))


def test_an_anchor_with_a_garbage_stamp_is_chained_like_a_zero_one(tmp_path):
    """acapulco and fhw stamp 8 and 3 of their re-anchoring lines with garbage (3.7, 9.98)
    instead of 0: they repeat the scan's pose and are chained through all the same (they
    were kept as odometry and skipped as 'not after the previous', which let the reference's
    jump into /odom)."""
    ranges = ' '.join(['2.0'] * 180)
    log = _write_log(tmp_path / 'garbage.log.gz', [
        'ODOM 0.0 0.0 0.0 0 0 0 11.0 host 11.0',
        'ODOM 1.0 0.0 0.0 0 0 0 12.0 host 12.0',
        f'FLASER 180 {ranges} 1.1 0.1 0 1.1 0.1 0 12.0 host 12.0',
        'ODOM 1.1 0.1 0 0 0 0 3.7 host 3.7',
        'ODOM 1.1 1.1 0 0 0 0 13.0 host 13.0',
    ])
    summary = convert(log, tmp_path / 'bag')
    assert summary['skipped_odom'] == {'reference_repeated': 1, 'not_after_previous': 0}
    poses = [odometry_pose(m)[0] for _, _, m in read_messages(tmp_path / 'bag', ['/odom'])]
    np.testing.assert_allclose(poses, [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (1.0, 1.0, 0.0)],
                               atol=1e-12)


# -- logs whose time is broken ----------------------------------------------------------------
SCANS, ODOM_PER_SCAN = 12, 4


def _timed_log(path: Path, stamp, scans: int = SCANS, odom_per_scan: int = ODOM_PER_SCAN,
               scan_stamp=None) -> Path:
    """A "corrected" log of `scans` scans, `odom_per_scan` odometry lines 0.1 m apart before
    each and the re-anchoring line after it (none without odometry lines); stamp(k) writes the
    stamp of the k-th odometry line, scan_stamp(j) that of the j-th scan (default: its
    preceding odometry line's; the re-anchoring line 0)."""
    ranges = ' '.join(['2.0'] * 180)
    lines, k, x = [], 0, 0.0
    for j in range(scans):
        for _ in range(odom_per_scan):
            x += 0.1
            lines.append(f'ODOM {x:.4f} 0 0 0 0 0 {stamp(k)} host {stamp(k)}')
            k += 1
        if odom_per_scan == 0:
            x += 0.1
        t = scan_stamp(j) if scan_stamp else stamp(k - 1)
        lines.append(f'FLASER 180 {ranges} {x + 0.01:.4f} 0.02 0 {x + 0.01:.4f} 0.02 0 '
                     f'{t} host {t}')
        if odom_per_scan:
            lines.append(f'ODOM {x + 0.01:.4f} 0.02 0 0 0 0 0 host 0')
    return _write_log(path, lines)


@pytest.mark.parametrize('kind, stamp, why', [
    ('all zero', lambda k: '0', 'stamped 0'),
    # six significant digits of a seconds-since-1970 stamp: 10^4 s resolution, so a few
    # distinct values over a long log, most consecutive stamps equal
    ('six significant digits', lambda k: f'{1.13486e9 + 500 * k:.6g}', 'too coarse'),
])
def test_a_log_without_time_converts_on_a_time_base_rebuilt_from_the_line_order(
        tmp_path, kind, stamp, why):
    log = _timed_log(tmp_path / 'log.gz', stamp)
    out = tmp_path / 'bag'
    result = run_to_exit('carmen_to_bag', [str(log), str(out), '--odom-rate', '5'])
    assert result.returncode == 0, result.stderr
    assert 'time base rebuilt from the order of the lines' in result.stdout, result.stdout
    assert why in result.stdout and 'assumed 5 Hz' in result.stdout
    assert 'run icp_matcher with rate_limits:=false' in result.stdout
    # Every odometry line kept (not 2), 0.2 s apart; each scan at its preceding line's time.
    odom = [s for _, s, _ in read_messages(out, ['/odom'])]
    assert len(odom) == SCANS * ODOM_PER_SCAN
    np.testing.assert_array_equal(np.diff(odom), 200_000_000)
    scans = [s for _, s, _ in read_messages(out, ['/scan'])]
    assert scans == odom[ODOM_PER_SCAN - 1::ODOM_PER_SCAN]
    metadata = BagReader(out).custom_data[TIME_BASE_KEY]
    assert metadata.startswith('rebuilt from the order of the lines') and '5 Hz' in metadata
    # sensing_eval scores every relation between the scans, and says which time base it used.
    scored = run_to_exit('sensing_eval', [str(out), '--topic', '/odom'])
    assert scored.returncode == 0, scored.stderr
    assert f'{SCANS - 1}/{SCANS - 1}' in scored.stdout
    assert 'time base: rebuilt from the order of the lines' in scored.stdout


@pytest.mark.parametrize('kind, stamp, words', [
    ('going backwards', lambda k: f'{100 + 0.1 * k - (5 if k >= 20 else 0):.3f}',
     ['go backwards', 'line 31: 97 after 101.9']),
    ('negative', lambda k: f'{-3 + 0.1 * k:.3f}', ['negative', 'line 1: -3']),
    # a 32-bit seconds clock that wrapped: 4294967290 s, then 0.x s
    ('wrapped', lambda k: f'{(4294967290 + 0.5 * k) % 2 ** 32:.3f}', ['wrapped', '4.295e+09']),
])
def test_a_log_whose_time_goes_wrong_is_refused_naming_the_problem(tmp_path, kind, stamp, words):
    log = _timed_log(tmp_path / 'log.gz', stamp)
    out = tmp_path / 'bag'
    result = run_to_exit('carmen_to_bag', [str(log), str(out)])
    assert result.returncode == 2, result.stdout + result.stderr
    assert "the log's time is broken" in result.stderr and '--time-base lines' in result.stderr
    for word in words:
        assert word in result.stderr, result.stderr
    assert 'Traceback' not in result.stderr and not out.exists()
    assert not list(tmp_path.glob('.bag*'))
    # Asked for, the line order gives a time base, said so.
    result = run_to_exit('carmen_to_bag', [str(log), str(out), '--time-base', 'lines'])
    assert result.returncode == 0, result.stderr
    assert 'time base rebuilt' in result.stdout
    assert topic_counts(out)['/odom'][1] == SCANS * ODOM_PER_SCAN


# -- coarse or repeated stamps: rebuilt where they carry no time, refused where part is sound ---
def _whole_seconds(interval_s: float):
    """Stamps of lines interval_s apart written to six significant digits (%g) of a six-digit
    count of seconds: whole seconds."""
    return lambda k: f'{975400 + interval_s * k:g}'


@pytest.mark.parametrize('kind, odom_stamp, scan_stamp, words', [
    ('odometry and scans on whole seconds', _whole_seconds(0.0365), None,
     'the 474 ODOM lines carry 18 distinct stamps'),
    # the odometry's stamps sound, the scans' coarse (which went unnoticed for the scans alone)
    ('scans on whole seconds', lambda k: f'{975400 + 0.0365 * k:.4f}', _whole_seconds(0.073),
     'the 237 FLASER lines carry 18 distinct stamps'),
])
def test_a_log_on_far_fewer_distinct_stamps_than_lines_is_rebuilt_and_said_so(
        tmp_path, capsys, kind, odom_stamp, scan_stamp, words):
    """237 scans at 18 distinct six-digit stamps (a log kept aside was converted on them without
    a word, and sensing_eval then refused to score it): rebuilt from the line order, said so
    with the matcher's setting for an assumed time, and every relation scored."""
    log = _timed_log(tmp_path / 'log.gz', odom_stamp, scans=237, odom_per_scan=2,
                     scan_stamp=scan_stamp)
    out = tmp_path / 'bag'
    assert carmen_to_bag.main([str(log), str(out)]) == 0
    printed = capsys.readouterr()
    assert 'time base rebuilt from the order of the lines' in printed.out, printed
    assert words in printed.out and 'too coarse' in printed.out, printed.out
    assert 'run icp_matcher with rate_limits:=false' in printed.out
    assert printed.err == ''
    scans = [s for _, s, _ in read_messages(out, ['/scan'])]
    assert len(scans) == 237 and np.all(np.diff(scans) > 0)
    assert BagReader(out).custom_data[TIME_BASE_KEY].startswith('rebuilt from the order')
    scored = sensing_eval.evaluate(out, ['/odom'])['estimates']['/odom']
    assert scored['relations'] == scored['relations_asked'] == 236, scored


def test_a_clock_that_stood_still_is_refused_naming_the_time_base_lines(tmp_path, capsys):
    """Sound stamps but for 6 odometry lines on one (the clock stood still for 0.6 s): rebuilding
    would throw the sound time away, so the tool refuses in one line naming the run and
    --time-base lines, which then converts it."""
    log = _timed_log(tmp_path / 'log.gz',
                     lambda k: f'{100 + 0.1 * (20 if 20 <= k < 26 else k):.3f}')
    out = tmp_path / 'bag'
    assert carmen_to_bag.main([str(log), str(out)]) == 2
    printed = capsys.readouterr()
    assert printed.out == '' and printed.err == (
        f"carmen_to_bag: error: {log}: the log's time is broken: 6 consecutive ODOM lines carry "
        'the same stamp 102 (lines 31 to 38): a clock that stood still; --time-base lines '
        'rebuilds a time base from the order of the lines\n'), printed
    assert not out.exists() and not list(tmp_path.glob('.bag*'))
    assert carmen_to_bag.main([str(log), str(out), '--time-base', 'lines']) == 0
    printed = capsys.readouterr().out
    assert 'time base rebuilt from the order of the lines (6 consecutive ODOM lines' in printed
    assert topic_counts(out)['/odom'][1] == SCANS * ODOM_PER_SCAN


def test_scans_on_one_stamp_are_found_in_the_flaser_lines(tmp_path):
    """The scans' own stamps are judged too: 5 FLASER lines on one stamp in a log of scans."""
    log = read_carmen(_timed_log(tmp_path / 'log.gz', None, odom_per_scan=0, scan_stamp=lambda j:
                                 f'{100.3 + 0.4 * (3 if 3 <= j < 8 else j):.3f}'))
    check = check_time(log, np.zeros(0, dtype=bool))
    assert check == TimeCheck('repeated', '5 consecutive FLASER lines carry the same stamp 101.5 '
                                          '(lines 4 to 8): a clock that stood still')


def test_a_few_repeated_stamps_convert_on_the_log_s_time_and_scans_sharing_one_are_said(
        tmp_path, capsys):
    """Runs of up to 4 equal stamps (the shared logs have runs of 2: Edmonton's odometry) are
    no broken clock: the log's stamps are kept. A scan on its predecessor's stamp is warned
    about, as the nodes skip it."""
    four = _timed_log(tmp_path / 'four.log.gz',
                      lambda k: f'{100 + 0.1 * (8 if 8 <= k < 12 else k):.3f}')
    assert carmen_to_bag.main([str(four), str(tmp_path / 'four')]) == 0
    printed = capsys.readouterr()
    assert 'time base' not in printed.out and 'rate_limits' not in printed.out
    assert '3 not after the previous' in printed.out and printed.err == '', printed
    assert TIME_BASE_KEY not in BagReader(tmp_path / 'four').custom_data
    # One odometry line per scan, the 6th on the 5th's stamp: scans 5 and 6 share it.
    shared = _timed_log(tmp_path / 'shared.log.gz', lambda k: f'{100 + 0.1 * (k - (k == 5)):.3f}',
                        odom_per_scan=1)
    assert carmen_to_bag.main([str(shared), str(tmp_path / 'shared')]) == 0
    printed = capsys.readouterr()
    assert 'time base' not in printed.out
    assert printed.err == ('carmen_to_bag: warning: 1 scans carry the stamp of the scan before '
                           'them: the nodes skip a repeated stamp and sensing_eval scores one '
                           'pose a stamp\n'), printed.err
    scans = [s for _, s, _ in read_messages(tmp_path / 'shared', ['/scan'])]
    assert scans[:6] == [100_000_000_000 + k * 100_000_000 for k in (0, 1, 2, 3, 4, 4)]


@pytest.mark.parametrize('time_base', ['auto', 'lines'])
def test_a_log_whose_line_order_cannot_time_the_scans_is_refused(tmp_path, capsys, time_base):
    """No ODOM line to carry a time (scans only, on whole seconds): a rebuilt time base would
    put every scan at 0, so neither time base is used, and both name the stamps' problem."""
    log = _timed_log(tmp_path / 'log.gz', None, scans=237, odom_per_scan=0,
                     scan_stamp=_whole_seconds(0.073))
    out = tmp_path / 'bag'
    assert carmen_to_bag.main([str(log), str(out), '--time-base', time_base]) == 2
    printed = capsys.readouterr()
    assert len(printed.err.splitlines()) == 1, printed.err
    assert 'cannot time the scans: its 237 FLASER lines get 1 distinct times from its 0 ODOM ' \
        'lines' in printed.err, printed.err
    assert 'the 237 FLASER lines carry 18 distinct stamps' in printed.err
    assert not out.exists()


@needs_logs
def test_the_shared_logs_keep_their_time_base():
    """No false alarm: six shared logs keep their own stamps, freiburg-campus (every stamp 0)
    is rebuilt as before."""
    for path in sorted(CARMEN.glob('*-corrected.log.gz')):
        log = read_carmen(path)
        time = time_base(log, ConvertOptions())
        if path.name.startswith('freiburg-campus'):
            assert time.rebuilt.startswith('rebuilt from the order of the lines (15683 of the '
                                           '15683 odometry lines are stamped 0)'), time.rebuilt
            continue
        assert time.rebuilt == '', (path.name, time.rebuilt)
        np.testing.assert_array_equal(time.odom_s, log.odom_time_s)
        np.testing.assert_array_equal(time.scan_s, [s.time_s for s in log.scans])


def test_a_time_offset_that_makes_stamps_negative_is_refused(tmp_path):
    log = _timed_log(tmp_path / 'log.gz', lambda k: f'{1 + 0.1 * k:.3f}')
    out = tmp_path / 'bag'
    result = run_to_exit('carmen_to_bag', [str(log), str(out), '--time-offset', '-5'])
    assert result.returncode == 2 and 'must not be negative' in result.stderr, result.stderr
    assert 'Traceback' not in result.stderr and not out.exists()


@needs_logs
def test_freiburg_campus_converts_on_a_rebuilt_time_base_and_scores(tmp_path):
    """Every stamp of freiburg-campus is 0: 2008 scans and 15683 odometry lines on a time base
    from the line order (it gave 2 odometry messages before), stated, and sensing_eval scores
    the odometry on all 2007 relations between consecutive scans."""
    out = tmp_path / 'campus'
    result = run_to_exit('carmen_to_bag', [str(CARMEN / 'freiburg-campus-corrected.log.gz'),
                                           str(out)], timeout=120)
    assert result.returncode == 0, result.stderr
    assert '15683 of the 15683 odometry lines are stamped 0' in result.stdout
    assert 'robot_max_t_vel 0.7' in result.stdout and '--odom-rate' in result.stderr
    counts = topic_counts(out)
    assert counts['/scan'][1] == counts['/ground_truth/odom'][1] == 2008
    assert counts['/odom'][1] == 15683
    stamps = [s for _, s, _ in read_messages(out, ['/ground_truth/odom'])]
    assert np.all(np.diff(stamps) > 0)
    scored = run_to_exit('sensing_eval', [str(out), '--topic', '/odom'], timeout=120)
    assert scored.returncode == 0, scored.stderr
    assert '2007/2007' in scored.stdout and 'shortfall' not in scored.stderr
