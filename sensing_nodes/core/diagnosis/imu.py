"""The IMU against REP 103/145 and its mount in base_link, from the data alone.

Gravity: an accelerometer reports specific force, +g along the up axis when still (REP 145):
the mean while still gives the IMU's up axis (a level IMU: +z; upside down: -z). The rate axis:
the gyro vector regressed on base_link's yaw rate (wheels, odometry or scan matching) gives the
same up axis from the rotation. Roll and pitch of the mount follow from the up axis; its yaw
about the vertical shows only in the horizontal accelerations, matched against base_link's
(dv/dt along x, v w along y). Mount: the IMU frame's orientation in base_link, ZYX roll, pitch,
yaw (core/geometry/imu_mount.py); vectors in the IMU frame, rad, s, m/s^2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.diagnosis.check import OK, PROBLEM, SKIPPED, Check, graded
from sensing_nodes.core.evaluation.characterization import allan_deviation, fit_noise_terms
from sensing_nodes.core.geometry.imu_mount import mount_rotation

GRAVITY = 9.80665
WINDOW_S = 0.5
MIN_ALLAN_S = 10.0          # stillness needed for an Allan deviation worth reporting


@dataclass(frozen=True)
class Stillness:
    """Still samples (mask over the IMU samples) and the longest still stretch (s)."""

    still: NDArray[np.bool_]
    longest_s: float
    longest: slice


def stillness(t: NDArray[np.int64], gyro: NDArray[np.float64], accel: NDArray[np.float64],
              moving_ref: NDArray[np.bool_] | None = None) -> Stillness:
    """Samples in 0.5 s windows whose gyro and accelerometer scatter stays near the quietest
    windows' (3x, with floors 2e-3 rad/s and 0.05 m/s^2) and whose rate is below 0.05 rad/s;
    moving_ref (per sample, from wheels or odometry) vetoes a window."""
    ts = (t - t[0]) * 1e-9
    win = np.floor(ts / WINDOW_S).astype(np.int64)
    n = int(win[-1]) + 1
    count = np.maximum(np.bincount(win, minlength=n), 1)

    def scatter(x: NDArray[np.float64]) -> NDArray[np.float64]:
        mean = np.stack([np.bincount(win, x[:, i], n) for i in range(3)], 1) / count[:, None]
        sq = np.stack([np.bincount(win, x[:, i] ** 2, n) for i in range(3)], 1) / count[:, None]
        return np.sqrt(np.maximum(sq - mean ** 2, 0.0).sum(axis=1)), mean

    g_std, g_mean = scatter(gyro)
    a_std, _ = scatter(accel)
    full = np.bincount(win, minlength=n) >= 3
    if not full.any():
        return Stillness(np.zeros(t.size, bool), 0.0, slice(0, 0))
    g_lim = max(3.0 * float(np.percentile(g_std[full], 10)), 2e-3)
    a_lim = max(3.0 * float(np.percentile(a_std[full], 10)), 0.05)
    still_win = full & (g_std < g_lim) & (a_std < a_lim) & (np.linalg.norm(g_mean, axis=1) < 0.05)
    if moving_ref is not None:
        moving_win = np.bincount(win, moving_ref.astype(float), n) > 0
        still_win &= ~moving_win
    still = still_win[win]
    edges = np.flatnonzero(np.diff(np.concatenate(([0], still.astype(np.int8), [0]))))
    best, best_s = slice(0, 0), 0.0
    for a, b in zip(edges[::2], edges[1::2]):
        span = (t[b - 1] - t[a]) * 1e-9
        if span > best_s:
            best, best_s = slice(int(a), int(b)), span
    return Stillness(still, best_s, best)


def up_axis_name(up: NDArray[np.float64]) -> str:
    """'level', 'upside down', or the IMU axis nearest to up with the tilt from it."""
    axis = int(np.argmax(np.abs(up)))
    sign = '+' if up[axis] > 0 else '-'
    tilt = math.degrees(math.acos(min(1.0, abs(float(up[axis])))))
    if axis == 2:
        name = 'level' if up[2] > 0 else 'upside down'
    else:
        name = f'on its side: up is {sign}{"xyz"[axis]}'
    return name if tilt < 3.0 else f'{name}, tilted {tilt:.1f} deg'


def roll_pitch_of(up: NDArray[np.float64]) -> tuple[float, float]:
    """Mount roll and pitch (rad) that bring the IMU's up axis onto base_link's z."""
    u = up / np.linalg.norm(up)
    return math.atan2(float(u[1]), float(u[2])), -math.asin(float(np.clip(u[0], -1.0, 1.0)))


def gravity_check(subject: str, accel: NDArray[np.float64], still: Stillness,
                  declared: NDArray[np.float64]) -> tuple[Check, NDArray[np.float64] | None]:
    """REP 103/145: the specific force while still (or over the whole bag of a planar robot
    when never still) against +g along the up axis the declared mount predicts; returns the
    measured up axis (IMU frame) too, None when the accelerometer shows no gravity."""
    use = still.still if still.still.sum() >= 20 else np.ones(len(accel), bool)
    mean = accel[use].mean(axis=0)
    norm = float(np.linalg.norm(mean))
    basis = 'while still' if use is still.still else 'over the whole bag (never still)'
    if norm < 0.5 * GRAVITY or norm > 1.5 * GRAVITY:
        return Check('imu_gravity', subject, PROBLEM, norm, 'm/s^2',
                     f'the accelerometer reads {norm:.2f} m/s^2 {basis}, not g: REP 145 wants '
                     'the specific force with gravity (+9.81 up when level); a driver removing '
                     'gravity, or zeros from a simulator: tilt and stillness cannot be read',
                     '|a| = 9.81 +- 50 %', {'mean_m_s2': mean}), None
    up = mean / norm
    expected = declared.T @ np.array([0.0, 0.0, 1.0])
    angle = math.degrees(math.acos(float(np.clip(up @ expected, -1.0, 1.0))))
    verdict = graded(angle, 3.0, 10.0)
    seen = up_axis_name(up)
    advice = (f'gravity as declared ({seen})' if verdict == OK else
              f'the IMU reads gravity {seen} ({angle:.1f} deg from what the declared mount '
              'predicts): declare the mount (/tf_static base_link -> the IMU frame, or the '
              'nodes\' mount_roll/pitch/yaw_rad: params.yaml carries the measured one)')
    return Check('imu_gravity', subject, verdict, angle, 'deg', advice, '< 3 deg',
                 {'gravity_m_s2': norm, 'up_in_imu': up, 'seen': seen, 'basis': basis}), up


def rate_axis(t: NDArray[np.int64], gyro: NDArray[np.float64], ref_t: NDArray[np.int64],
              ref_rate: NDArray[np.float64]) -> tuple[NDArray[np.float64], float] | None:
    """base_link's z in the IMU frame from gyro = axis x (yaw rate) + bias, least squares over
    the samples where the reference turns (its unit vector, and the fitted gain); None when
    the reference hardly turns."""
    w = np.interp((t - t[0]) * 1e-9, (ref_t - t[0]) * 1e-9, ref_rate)
    inside = (t >= ref_t[0]) & (t <= ref_t[-1])
    if inside.sum() < 50 or np.sum(np.abs(w[inside]) > 0.1) < 20:
        return None
    design = np.column_stack((w[inside], np.ones(int(inside.sum()))))
    coef, *_ = np.linalg.lstsq(design, gyro[inside], rcond=None)
    axis = coef[0]
    gain = float(np.linalg.norm(axis))
    return axis / gain, gain


def horizontal_yaw(t: NDArray[np.int64], accel: NDArray[np.float64], roll: float, pitch: float,
                   ref_t: NDArray[np.int64], ref_v: NDArray[np.float64],
                   ref_w: NDArray[np.float64], bin_s: float = 0.05) -> tuple[float, float] | None:
    """Mount yaw (rad) from the levelled horizontal accelerations against base_link's (dv/dt,
    v w), both averaged over bin_s bins, with a constant bias fitted; and the RMS of the
    reference acceleration it rests on (m/s^2). None when the robot hardly accelerates."""
    level = mount_rotation(roll, pitch, 0.0)
    a = accel @ level.T
    t0 = max(t[0], ref_t[0])
    edges = np.arange(t0, min(t[-1], ref_t[-1]), int(bin_s * 1e9))
    if edges.size < 20:
        return None
    idx = np.searchsorted(edges, t, side='right') - 1
    ok = (idx >= 0) & (idx < edges.size - 1)
    n = edges.size - 1
    count = np.bincount(idx[ok], minlength=n)
    ax = np.bincount(idx[ok], a[ok, 0], n) / np.maximum(count, 1)
    ay = np.bincount(idx[ok], a[ok, 1], n) / np.maximum(count, 1)
    mid = (edges[:-1] + edges[1:]) // 2
    rt = (ref_t - t0) * 1e-9
    v_edges = np.interp((edges - t0) * 1e-9, rt, ref_v)
    forward = np.diff(v_edges) / bin_s
    lateral = np.interp((mid - t0) * 1e-9, rt, ref_v) * np.interp((mid - t0) * 1e-9, rt, ref_w)
    use = count > 0
    ref_rms = float(np.sqrt(np.mean(forward[use] ** 2 + lateral[use] ** 2)))
    if use.sum() < 20 or np.sum(np.hypot(forward[use], lateral[use]) > 0.1) < 10:
        return None
    f, s, one, zero = forward[use], lateral[use], np.ones(int(use.sum())), np.zeros(int(use.sum()))
    # a_lev = Rz(-yaw) a_base + bias: x = c f + s' l + bx, y = -s' f + c l + by
    design = np.vstack((np.column_stack((f, s, one, zero)), np.column_stack((s, -f, zero, one))))
    coef, *_ = np.linalg.lstsq(design, np.concatenate((ax[use], ay[use])), rcond=None)
    return math.atan2(float(coef[1]), float(coef[0])), ref_rms


def rotation_angle_deg(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    """The angle (deg) of the rotation taking b to a."""
    c = (np.trace(a @ b.T) - 1.0) / 2.0
    return math.degrees(math.acos(float(np.clip(c, -1.0, 1.0))))


@dataclass(frozen=True)
class MountEstimate:
    """The IMU mount found in the data (rad, ZYX) and what each angle rests on; yaw None when
    the horizontal accelerations cannot show it."""

    roll: float
    pitch: float
    yaw: float | None
    up_from: str                 # 'gravity' or 'rotation'
    yaw_note: str

    def rotation(self) -> NDArray[np.float64]:
        return mount_rotation(self.roll, self.pitch, self.yaw or 0.0)


def rate_axis_check(subject: str, reference: str, axis: NDArray[np.float64], gain: float,
                    up: NDArray[np.float64] | None) -> Check:
    """The IMU axis that turns with base_link (from the rates) against the up axis from
    gravity: they must agree (a left-handed frame or swapped axes do not)."""
    seen = up_axis_name(axis)
    details = {'axis_in_imu': axis, 'gain': gain, 'reference': reference, 'seen': seen}
    if up is None:
        return Check('imu_rate_axis', subject, OK, None, 'deg',
                     f'the yaw rate of {reference} shows on the IMU {seen} (no gravity to '
                     'compare with)', '', details)
    angle = math.degrees(math.acos(float(np.clip(axis @ up, -1.0, 1.0))))
    verdict = graded(angle, 5.0, 20.0)
    advice = (f'the rate axis agrees with gravity ({seen}); gyro gain {gain:.4f} against '
              f'{reference}' if verdict == OK else
              f'the IMU turns about its {seen} axis with {reference} while gravity points '
              f'{angle:.0f} deg away from it: the gyro and accelerometer axes disagree '
              '(swapped or mirrored axes in the driver: REP 103 wants one right-handed frame)')
    return Check('imu_rate_axis', subject, verdict, angle, 'deg', advice, '< 5 deg', details)


def mount_check(subject: str, found: MountEstimate, declared: NDArray[np.float64],
                declared_from: str, frame_is_base: bool = False) -> Check:
    """The mount found against the declared one: the full rotation when the yaw was found,
    else the tilt (up axis) alone. frame_is_base: the Imu's frame_id is the base frame, which
    declares it aligned (the nodes then ignore their mount parameters)."""
    details = {'roll_deg': math.degrees(found.roll), 'pitch_deg': math.degrees(found.pitch),
               'yaw_deg': None if found.yaw is None else math.degrees(found.yaw),
               'up_from': found.up_from, 'yaw_note': found.yaw_note,
               'declared_from': declared_from}
    if found.yaw is not None:
        angle = rotation_angle_deg(found.rotation(), declared)
    else:
        up_found = found.rotation().T @ np.array([0.0, 0.0, 1.0])
        up_declared = declared.T @ np.array([0.0, 0.0, 1.0])
        angle = math.degrees(math.acos(float(np.clip(up_found @ up_declared, -1.0, 1.0))))
    verdict = graded(angle, 3.0, 10.0)
    shown = (f'roll {details["roll_deg"]:.1f}, pitch {details["pitch_deg"]:.1f}, yaw '
             + (f'{details["yaw_deg"]:.1f} deg' if found.yaw is not None else
                f'unknown ({found.yaw_note})'))
    fix = ('the Imu\'s frame_id is the base frame, which declares it aligned (the nodes '
           'ignore mount_*_rad then): publish the IMU in a frame of its own with its mount on '
           '/tf_static' if frame_is_base else
           'correct /tf_static (the nodes take it over their mount_*_rad)'
           if declared_from == '/tf_static' else
           'declare it on /tf_static or in the nodes\' mount_*_rad (params.yaml has it)')
    advice = (f'the mount found ({shown}) is the one declared ({declared_from})'
              if verdict == OK else
              f'the IMU sits at {shown} in base_link, {angle:.1f} deg from the mount declared '
              f'({declared_from}): {fix}')
    return Check('imu_mount', subject, verdict, angle, 'deg', advice, '< 3 deg', details)


def gyro_noise_checks(subject: str, t: NDArray[np.int64], gyro_z: NDArray[np.float64],
                      still: Stillness) -> list[Check]:
    """Gyro bias about base_link's z while still, white noise and bias instability from the
    Allan deviation of the longest still stretch (when it lasts MIN_ALLAN_S)."""
    if still.still.sum() < 20:
        return [Check('gyro_bias', subject, SKIPPED, None, 'deg/s',
                      'the robot never stands still: no bias to read')]
    bias = float(gyro_z[still.still].mean())
    verdict = graded(abs(bias), math.radians(1.0), 0.05)
    checks = [Check('gyro_bias', subject, verdict, math.degrees(bias), 'deg/s',
                    f'bias {math.degrees(bias):+.3f} deg/s while still: gyro_integrator learns '
                    'it while still (initial_bias_z_rad_s in params.yaml)' if verdict == OK else
                    f'bias {math.degrees(bias):+.3f} deg/s: large (gyro_integrator refuses '
                    'estimates beyond max_gyro_bias_rad_s 0.05); calibrate the gyro',
                    '< 1 deg/s', {'bias_rad_s': bias,
                                  'still_s': float(still.still.sum()) / max(
                                      1, len(t)) * (t[-1] - t[0]) * 1e-9})]
    stretch = still.longest
    if still.longest_s < MIN_ALLAN_S:
        checks.append(Check('gyro_noise', subject, SKIPPED, None, 'rad/s/sqrt(Hz)',
                            f'the longest still stretch is {still.longest_s:.1f} s: an Allan '
                            f'deviation needs {MIN_ALLAN_S:g} s'))
        return checks
    seg_t, seg = t[stretch], gyro_z[stretch]
    rate = (seg_t.size - 1) / ((seg_t[-1] - seg_t[0]) * 1e-9)
    ad = allan_deviation(seg, rate)
    terms = fit_noise_terms(ad)
    white = terms.n if terms.n is not None else float(np.std(seg) / math.sqrt(rate / 2.0))
    checks.append(Check('gyro_noise', subject, OK, white, 'rad/s/sqrt(Hz)',
                        f'white noise {white:.2g} rad/s/sqrt(Hz) over {still.longest_s:.0f} s '
                        'still (gyro_integrator gyro_noise_density in params.yaml)', '',
                        {'bias_instability_rad_s': terms.b, 'rate_random_walk': terms.k,
                         'allan_tau_s': ad.tau, 'allan_dev_rad_s': ad.adev,
                         'notes': list(terms.notes)}))
    return checks
