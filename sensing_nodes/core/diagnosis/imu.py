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


# A MEMS accelerometer's zero-g offset (typically +-20 mg): a bias the still data cannot tell
# from a tilt, so the tilt from gravity is never known better than atan(0.2 / g) = 1.2 deg.
ACCEL_BIAS_M_S2 = 0.2
TILT_FLOOR_RAD = math.atan2(ACCEL_BIAS_M_S2, GRAVITY)


def gravity_check(subject: str, accel: NDArray[np.float64], still: Stillness,
                  declared: NDArray[np.float64]
                  ) -> tuple[Check, NDArray[np.float64] | None, float | None]:
    """REP 103/145: the specific force while still against +g along the up axis the declared
    mount predicts; returns the measured up axis (IMU frame) and its standard deviation (rad:
    the scatter of 0.5 s means while still, and the accelerometer's unknown bias), None when
    the accelerometer shows no gravity or the IMU is never still (not judged: the motion's
    accelerations would pass for a tilt)."""
    if still.still.sum() < 20:
        mean = accel.mean(axis=0)
        return Check('imu_gravity', subject, SKIPPED, None, 'deg',
                     'not judged: the IMU never stands still, and while it moves its '
                     f'accelerations mix with gravity (the mean over the bag, '
                     f'{float(np.linalg.norm(mean)):.2f} m/s^2, is no reading of g)', '',
                     {'mean_m_s2': mean, 'basis': 'never still'}), None, None
    samples = accel[still.still]
    mean = samples.mean(axis=0)
    norm = float(np.linalg.norm(mean))
    if norm < 0.5 * GRAVITY or norm > 1.5 * GRAVITY:
        return Check('imu_gravity', subject, PROBLEM, norm, 'm/s^2',
                     f'the accelerometer reads {norm:.2f} m/s^2 while still, not g: REP 145 '
                     'wants the specific force with gravity (+9.81 up when level); a driver '
                     'removing gravity, or zeros from a simulator: tilt and stillness cannot '
                     'be read', '|a| = 9.81 +- 50 %', {'mean_m_s2': mean}), None, None
    up = mean / norm
    chunks = [c.mean(axis=0) for c in np.array_split(samples, max(1, len(samples) // 50))]
    deviation = [math.acos(float(np.clip(c @ up / np.linalg.norm(c), -1.0, 1.0)))
                 for c in chunks]
    scatter = math.sqrt(float(np.mean(np.square(deviation))) / max(len(chunks), 1))
    up_std = math.hypot(scatter, TILT_FLOOR_RAD)
    expected = declared.T @ np.array([0.0, 0.0, 1.0])
    angle = math.degrees(math.acos(float(np.clip(up @ expected, -1.0, 1.0))))
    verdict = graded(angle, 3.0, 10.0)
    seen = up_axis_name(up)
    advice = (f'gravity as declared ({seen})' if verdict == OK else
              f'gravity shows the IMU {seen}, {angle:.1f} deg from what the declared mount '
              'predicts: the mount differs from the declared one (imu_mount below)')
    return Check('imu_gravity', subject, verdict, angle, 'deg', advice, '< 3 deg',
                 {'gravity_m_s2': norm, 'up_in_imu': up, 'seen': seen, 'basis': 'while still',
                  'up_std_deg': math.degrees(up_std)}), up, up_std


def rate_axis(t: NDArray[np.int64], gyro: NDArray[np.float64], ref_t: NDArray[np.int64],
              ref_rate: NDArray[np.float64]
              ) -> tuple[NDArray[np.float64], float, float] | None:
    """base_link's z in the IMU frame from gyro = axis x (yaw rate) + bias, least squares over
    the samples where the reference turns (its unit vector, the fitted gain and the axis's
    standard deviation in rad, at least 0.5 deg); None when the reference hardly turns."""
    w = np.interp((t - t[0]) * 1e-9, (ref_t - t[0]) * 1e-9, ref_rate)
    inside = (t >= ref_t[0]) & (t <= ref_t[-1])
    if inside.sum() < 50 or np.sum(np.abs(w[inside]) > 0.1) < 20:
        return None
    design = np.column_stack((w[inside], np.ones(int(inside.sum()))))
    coef, *_ = np.linalg.lstsq(design, gyro[inside], rcond=None)
    axis = coef[0]
    gain = float(np.linalg.norm(axis))
    residual = gyro[inside] - design @ coef
    # Samples at 100 Hz and more are not independent: count one per 0.1 s.
    span_s = (t[inside][-1] - t[inside][0]) * 1e-9
    effective = max(3.0, min(float(inside.sum()), 10.0 * span_s))
    xtx = float(np.linalg.inv(design.T @ design)[0, 0]) * inside.sum() / effective
    std = math.sqrt(float((residual ** 2).sum(axis=0).sum()) / max(inside.sum() - 2, 1) * xtx)
    return axis / gain, gain, max(std / gain, math.radians(0.5))


def horizontal_yaw(t: NDArray[np.int64], accel: NDArray[np.float64], roll: float, pitch: float,
                   ref_t: NDArray[np.int64], ref_v: NDArray[np.float64],
                   ref_w: NDArray[np.float64], bin_s: float = 0.05
                   ) -> tuple[float, float, float] | None:
    """Mount yaw (rad) from the levelled horizontal accelerations against base_link's (dv/dt,
    v w), both averaged over bin_s bins, with a constant bias fitted; the RMS of the
    reference acceleration it rests on (m/s^2), and the yaw's standard deviation (rad, from
    the residuals, at least 0.1 deg). None when the robot hardly accelerates."""
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
    f, s, x, y = forward[use], lateral[use], ax[use], ay[use]
    one, zero = np.ones(f.size), np.zeros(f.size)
    # a_lev = Rz(-yaw) a_base + bias: x = c f + s' l + bx, y = -s' f + c l + by
    design = np.vstack((np.column_stack((f, s, one, zero)), np.column_stack((s, -f, zero, one))))
    target = np.concatenate((x, y))
    coef, *_ = np.linalg.lstsq(design, target, rcond=None)
    yaw = math.atan2(float(coef[1]), float(coef[0]))
    # The angle's standard deviation from the residuals, their correlation from bin to bin
    # (vibration, the reference's own errors) counted: (1 + rho) / (1 - rho) samples per one.
    residual = target - design @ coef
    dof = max(target.size - 4, 1)
    rho = float(np.clip(np.mean([np.corrcoef(r[:-1], r[1:])[0, 1] for r in
                                 (residual[:f.size], residual[f.size:])]), 0.0, 0.95))
    inflate = (1.0 + rho) / (1.0 - rho)
    cov = float((residual ** 2).sum()) / dof * np.linalg.inv(design.T @ design) * inflate
    std = math.sqrt(0.5 * float(cov[0, 0] + cov[1, 1])) / max(float(np.hypot(*coef[:2])), 1e-9)
    return yaw, ref_rms, max(std, math.radians(0.1))


def rotation_angle_deg(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    """The angle (deg) of the rotation taking b to a."""
    c = (np.trace(a @ b.T) - 1.0) / 2.0
    return math.degrees(math.acos(float(np.clip(c, -1.0, 1.0))))


RIGHT_ANGLE = math.pi / 2


def snap(angle: float, std: float | None) -> float:
    """The nearest multiple of 90 deg when it lies within 2 standard deviations of the
    measured angle (a bracket's right angle), else the measured angle (rad)."""
    if std is None:
        return angle
    right = RIGHT_ANGLE * round(angle / RIGHT_ANGLE)
    return math.remainder(right, math.tau) if abs(angle - right) <= 2.0 * std else angle


@dataclass(frozen=True)
class MountEstimate:
    """The IMU mount (rad, ZYX) the preset takes: each measured angle snapped to the nearest
    right angle within 2 standard deviations (`measured` and `std` keep what the data
    showed); yaw None when the horizontal accelerations cannot show it; up_from 'gravity',
    'rotation' or 'declared' (not judged: the declared mount)."""

    roll: float
    pitch: float
    yaw: float | None
    up_from: str
    yaw_note: str
    measured: tuple[float, float, float | None] | None = None
    std: tuple[float | None, float | None, float | None] = (None, None, None)

    @staticmethod
    def snapped(roll: float, pitch: float, yaw: float | None, stds, up_from: str,
                yaw_note: str) -> 'MountEstimate':
        return MountEstimate(snap(roll, stds[0]), snap(pitch, stds[1]),
                             None if yaw is None else snap(yaw, stds[2]), up_from, yaw_note,
                             (roll, pitch, yaw), tuple(stds))

    def rotation(self) -> NDArray[np.float64]:
        return mount_rotation(self.roll, self.pitch, self.yaw or 0.0)


def axis_phrase(v: NDArray[np.float64]) -> str:
    """An IMU axis in words: 'its +z axis', or 'an axis 4.2 deg from its +z axis'."""
    axis = int(np.argmax(np.abs(v)))
    sign = '+' if v[axis] > 0 else '-'
    tilt = math.degrees(math.acos(min(1.0, abs(float(v[axis])) / float(np.linalg.norm(v)))))
    name = f'its {sign}{"xyz"[axis]} axis'
    return name if tilt < 3.0 else f'an axis {tilt:.1f} deg from {name}'


def rate_axis_check(subject: str, reference: str, axis: NDArray[np.float64], gain: float,
                    up: NDArray[np.float64] | None) -> Check:
    """The IMU axis that turns with base_link (from the rates) against the up axis from
    gravity: they must agree (a left-handed frame or swapped axes do not)."""
    seen = up_axis_name(axis)
    details = {'axis_in_imu': axis, 'gain': gain, 'reference': reference, 'seen': seen}
    turns = f'the IMU turns with {reference} about {axis_phrase(axis)}'
    if up is None:
        return Check('imu_rate_axis', subject, OK, None, 'deg',
                     f'{turns} (no gravity reading to compare with)', '', details)
    angle = math.degrees(math.acos(float(np.clip(axis @ up, -1.0, 1.0))))
    verdict = graded(angle, 5.0, 20.0)
    advice = (f'{turns}, as gravity shows it' if verdict == OK else
              f'{turns}, {angle:.0f} deg from the up axis gravity shows: the gyro and '
              'accelerometer axes disagree (swapped or mirrored axes in the driver: REP 103 '
              'wants one right-handed frame), or the reference turns the robot about '
              'another axis (a ramp, a bank)')
    return Check('imu_rate_axis', subject, verdict, angle, 'deg', advice, '< 5 deg', details)


def _angle_text(measured: float | None, std: float | None, used: float | None) -> str:
    """'-90.3 +- 0.4 -> -90' (snapped), '2.1 +- 0.2' (kept), in degrees."""
    if measured is None:
        return 'unknown'
    text = f'{math.degrees(measured):.1f}' + (
        f' +- {math.degrees(std):.1f}' if std is not None else '')
    if used is not None and abs(used - measured) > 1e-12:
        text += f' -> {math.degrees(used):.0f}'
    return text


def mount_check(subject: str, found: MountEstimate, declared: NDArray[np.float64],
                declared_from: str, frame_is_base: bool = False) -> Check:
    """The mount the preset takes (each angle snapped to a right angle within 2 sigma) against
    the declared one: the full rotation when the yaw was found, else the tilt (up axis)
    alone. frame_is_base: the Imu's frame_id is the base frame, which declares it aligned (the
    nodes then ignore their mount parameters)."""
    measured = found.measured or (found.roll, found.pitch, found.yaw)
    std = found.std
    details = {'roll_deg': math.degrees(found.roll), 'pitch_deg': math.degrees(found.pitch),
               'yaw_deg': None if found.yaw is None else math.degrees(found.yaw),
               'measured_deg': [None if v is None else math.degrees(v) for v in measured],
               'std_deg': [None if v is None else math.degrees(v) for v in std],
               'up_from': found.up_from, 'yaw_note': found.yaw_note,
               'declared_from': declared_from}
    if found.yaw is not None:
        angle = rotation_angle_deg(found.rotation(), declared)
    else:
        up_found = found.rotation().T @ np.array([0.0, 0.0, 1.0])
        up_declared = declared.T @ np.array([0.0, 0.0, 1.0])
        angle = math.degrees(math.acos(float(np.clip(up_found @ up_declared, -1.0, 1.0))))
    verdict = graded(angle, 3.0, 10.0)
    shown = ', '.join(f'{axis} {_angle_text(m, s, u)}' for axis, m, s, u in zip(
        ('roll', 'pitch', 'yaw'), measured, std, (found.roll, found.pitch, found.yaw))) + ' deg'
    basis = (f'tilt from {"gravity" if found.up_from == "gravity" else "the rotation axis"}'
             + (f'; yaw {found.yaw_note}' if found.yaw is not None else
                f'; yaw not judged ({found.yaw_note}): the declared one kept'))
    if found.yaw is not None and abs(math.cos(found.roll) * math.cos(found.pitch)) < 0.5:
        basis += ('; the IMU lies on its side: its rotation about the vertical is only as '
                  'good as the accelerations that show it')
    fix = ('the Imu\'s frame_id is the base frame, which declares it aligned (the nodes '
           'ignore mount_*_rad then): publish the IMU in a frame of its own with its mount on '
           '/tf_static' if frame_is_base else
           'correct /tf_static (the nodes take it over the mount_*_rad of params.yaml)'
           if declared_from == '/tf_static' else
           'params.yaml sets the nodes\' mount_*_rad to it (or declare it on /tf_static)')
    advice = (f'the mount found ({shown}; {basis}) is the one declared ({declared_from})'
              if verdict == OK else
              f'the IMU sits at {shown} in base_link ({basis}), {angle:.1f} deg from the mount '
              f'declared ({declared_from}): {fix}')
    return Check('imu_mount', subject, verdict, angle, 'deg', advice,
                 '< 3 deg; a right angle within 2 sigma taken', details)


def gyro_noise_checks(subject: str, t: NDArray[np.int64], gyro_z: NDArray[np.float64],
                      still: Stillness) -> list[Check]:
    """Gyro bias about base_link's z while still, white noise and bias instability from the
    Allan deviation of the longest still stretch (when it lasts MIN_ALLAN_S)."""
    if still.still.sum() < 20:
        return [Check('gyro_bias', subject, SKIPPED, None, 'deg/s',
                      'not judged: the IMU never stands still: no bias to read (params.yaml '
                      'sets none; gyro_integrator learns it whenever the robot stops)')]
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
