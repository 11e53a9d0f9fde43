"""The simulated differential-drive robot: truth, LaserScan, IMU and wheel encoders as arrays.

One engine, `SensorSim`, advances simulated time in fixed blocks of physics ticks and returns
each block's sensor samples; `simulate` drives it for a batch run, the `sensor_sim` node drives
the same engine and publishes each sample as a message, so both give the same numbers.

Frames and units: the truth is base_link in the map frame (x, y in m, yaw in rad); ranges in m
in the `laser` frame (mounted at laser_x_m, laser_y_m, laser_yaw_rad in base_link, plus the
laser_*_error injected mount error: the nodes are told the former); IMU in
`imu_link`, which coincides with base_link; wheel joint angles in rad. Every time is int64
nanoseconds of simulated time, starting at start_time_s (a fixed epoch).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.geometry.se2 import wrap_angle
from sensing_nodes.core.sim.route import Motion, Route
from sensing_nodes.core.sim.world import World, raycast
from sensing_nodes.parameters import Param, ParameterError, ParameterTable

NS_PER_S = 1_000_000_000

# Rounds the central table of the default world (2 x 1.5 m at the origin) counter-clockwise on a
# 5 x 4 m rectangle, >= 1.25 m from the table and >= 0.4 m from everything: a still start for
# gyro bias calibration, straights, fast and slow (5 deg/s) turns in place, a full turn the other
# way, a stop mid-route, an arc, and back to the start pose. About 124 s.
DEFAULT_ROUTE = (
    'wait 6',
    'straight 5.0 0.25',
    'turn 90 30',
    'straight 4.0 0.25',
    'turn 90 5',
    'wait 4',
    'turn -360 45',
    'straight 4.5 0.25',
    'arc 90 0.5 0.25',
    'straight 3.5 0.25',
    'turn 90 30',
    'wait 5',
)


def _p(default: Any, doc: str, minimum: float | None = None, maximum: float | None = None,
       **options):
    """A SimParams field: its default and, as a parameter of sensor_sim, what it means and its
    inclusive range."""
    return field(default=default, metadata={'param': Param(doc, minimum, maximum, **options)})


def _legs(value: Any) -> tuple[str, ...]:
    """The route parameter (a list of leg strings) as SimParams.route."""
    if isinstance(value, str) or not isinstance(value, (list, tuple)):
        raise ValueError('must be a list of leg strings')
    return tuple(value)


@dataclass(frozen=True)
class SimParams:
    """Every number of the simulation; defaults equal config/sensor_sim.yaml."""

    # Time
    physics_rate_hz: int = _p(1000, 'physics ticks per simulated second; every sensor period '
                              'must be a whole number of ticks', 1, 1_000_000)
    start_time_s: int = _p(1_700_000_000, 'simulated time of the first sample (s since the '
                           'epoch); stamps are start_time_s + elapsed', 0)
    # Route (truth)
    route: tuple[str, ...] = _p(DEFAULT_ROUTE, "scripted legs: 'wait S', 'straight M SPEED', "
                                "'turn DEG DEG_PER_S', 'arc DEG RADIUS_M SPEED'; repeats",
                                from_value=_legs)
    start_x_m: float = _p(-2.5, 'start x of base_link in the map frame (m)')
    start_y_m: float = _p(-2.0, 'start y of base_link in the map frame (m)')
    start_yaw_rad: float = _p(0.0, 'start yaw of base_link in the map frame (rad)')
    max_linear_accel_m_s2: float = _p(0.5, 'linear acceleration of route ramps and /cmd_vel '
                                      'following (m/s^2)', 1e-6)
    max_angular_accel_rad_s2: float = _p(1.0, 'angular acceleration of route ramps and /cmd_vel '
                                         'following (rad/s^2)', 1e-6)
    cmd_vel_timeout_s: float = _p(0.5, 'with use_cmd_vel: stop when no command came for this '
                                  'long (simulated s)', 1e-3)
    # Wheels and encoders
    wheel_radius_m: float = _p(0.05, 'nominal wheel radius (m)', 1e-6)
    wheel_separation_m: float = _p(0.30, 'distance between the wheels (m)', 1e-6)
    left_radius_error: float = _p(0.0, 'systematic: true left radius = wheel_radius_m * '
                                  '(1 + this)', -0.5, 0.5)
    right_radius_error: float = _p(0.01, 'systematic: true right radius = wheel_radius_m * '
                                   '(1 + this)', -0.5, 0.5)
    left_slip: float = _p(0.0, 'systematic slip: the left wheel turns (1 + this) times what '
                          'its travel needs', -0.5, 0.5)
    right_slip: float = _p(0.0, 'systematic slip of the right wheel, as left_slip', -0.5, 0.5)
    wheel_separation_error: float = _p(0.0, 'systematic: true wheel separation = '
                                       'wheel_separation_m * (1 + this)', -0.5, 0.5)
    slip_noise_sqrt_m: float = _p(0.002, 'random slip: each wheel travel increment d gets an '
                                  'error of std this * sqrt(|d|) (m^0.5)', 0.0, 1.0)
    encoder_counts_per_rev: int = _p(2000, 'encoder lines per wheel revolution', 1, 10_000_000)
    encoder_quadrature: int = _p(4, 'edges counted per line (1, 2 or 4)', 1, 4)
    joint_rate_hz: float = _p(50.0, '/joint_states rate (Hz)', 1e-3)
    # IMU
    imu_rate_hz: float = _p(200.0, '/imu/data_raw rate (Hz)', 1e-3)
    gyro_bias_rad_s: float = _p(math.radians(0.5), 'constant bias of the yaw rate (rad/s)')
    gyro_noise_std_rad_s: float = _p(0.001, 'white noise std of each gyro sample, all axes '
                                     '(rad/s)', 0.0)
    gyro_scale_error: float = _p(0.0, 'scale factor error: the gyro reads (1 + this) x the '
                                 'true rate, all axes', -0.5, 0.5)
    gyro_bias_random_walk: float = _p(0.0, 'rate random walk K of the bias, all axes '
                                      '(rad/s/sqrt(s)); 0 = none', 0.0)
    gyro_bias_instability_rad_s: float = _p(0.0, 'bias instability B, all axes (rad/s): '
                                            'flicker-like bias whose Allan deviation is flat at '
                                            '0.664 B from ~3 s to ~3000 s; 0 = none', 0.0)
    accel_bias_x_m_s2: float = _p(0.02, 'accelerometer bias, x (m/s^2)')
    accel_bias_y_m_s2: float = _p(-0.02, 'accelerometer bias, y (m/s^2)')
    accel_bias_z_m_s2: float = _p(0.0, 'accelerometer bias, z (m/s^2)')
    accel_noise_std_m_s2: float = _p(0.02, 'white noise std of each accelerometer sample, all '
                                     'axes (m/s^2)', 0.0)
    gravity_m_s2: float = _p(9.81, 'gravity; the accelerometer reads +this on z at rest '
                             '(m/s^2)', 0.0)
    # LiDAR
    scan_rate_hz: float = _p(10.0, '/scan rate (Hz)', 1e-3)
    scan_beams: int = _p(360, 'beams per scan', 1, 100_000)
    scan_fov_rad: float = _p(2.0 * math.pi, 'field of view, centred on the laser x axis; beams '
                             'at -fov/2 + i * fov/beams (rad)', 1e-6, 2.0 * math.pi)
    scan_sweep_fraction: float = _p(1.0, 'share of the scan period over which the beams are '
                                    'taken in order, as a spinning laser does: beam i at stamp + '
                                    'i x this / (scan_rate_hz x scan_beams), the scan published '
                                    'when the sweep ends (stamp + this / scan_rate_hz); 0 = every '
                                    'beam at the stamp', 0.0, 1.0)
    range_min_m: float = _p(0.12, 'returns shorter than this read -inf (m)', 0.0)
    range_max_m: float = _p(8.0, 'returns longer than this, and no hit, read +inf (m)', 1e-6)
    range_noise_std_m: float = _p(0.01, 'Gaussian range noise std (m)', 0.0)
    range_bias_m: float = _p(0.0, 'range bias added to every return (m)')
    laser_x_m: float = _p(0.10, 'laser mount x in base_link (m)')
    laser_y_m: float = _p(0.0, 'laser mount y in base_link (m)')
    laser_yaw_rad: float = _p(0.0, 'laser mount yaw in base_link (rad)')
    laser_x_error_m: float = _p(0.0, 'mount error: the laser truly sits at laser_x_m + this '
                                '(laser_x_m is what the nodes are told) (m)', -1.0, 1.0)
    laser_y_error_m: float = _p(0.0, 'mount error on y, as laser_x_error_m (m)', -1.0, 1.0)
    laser_yaw_error_rad: float = _p(0.0, 'mount error on yaw, as laser_x_error_m (rad)',
                                    -math.pi, math.pi)
    # Truth and clock
    truth_rate_hz: float = _p(100.0, '/ground_truth/odom rate (Hz)', 1e-3)
    clock_rate_hz: float = _p(100.0, '/clock rate (Hz of simulated time)', 1e-3)

    def problems(self) -> list[tuple[str, str, object]]:
        """(field, problem, value) for each number the simulation cannot run with (types and
        ranges checked: SIM_PARAMETERS)."""
        out: list[tuple[str, str, object]] = [
            (f.name, 'must be finite', getattr(self, f.name)) for f in dataclasses.fields(self)
            if f.name != 'route' and not math.isfinite(getattr(self, f.name))]
        if out:
            return out
        if NS_PER_S % self.physics_rate_hz:
            out.append(('physics_rate_hz', 'must divide 1e9 (whole nanoseconds per tick)',
                        self.physics_rate_hz))
        if self.encoder_quadrature not in (1, 2, 4):
            out.append(('encoder_quadrature', 'must be 1, 2 or 4', self.encoder_quadrature))
        if self.range_min_m >= self.range_max_m:
            out.append(('range_min_m', f'must be < range_max_m ({self.range_max_m})',
                        self.range_min_m))
        for name in ('joint_rate_hz', 'imu_rate_hz', 'scan_rate_hz', 'truth_rate_hz',
                     'clock_rate_hz'):
            try:
                period_ticks(self, name)
            except ParameterError as error:
                out.append((name, error.problem, error.value))
        try:
            make_route(self)
        except ValueError as error:
            out.append(('route', str(error), None))
        return out

    @property
    def count_angle_rad(self) -> float:
        """Joint angle of one encoder count (rad)."""
        return 2.0 * math.pi / (self.encoder_counts_per_rev * self.encoder_quadrature)

    @property
    def scan_angle_min_rad(self) -> float:
        """Angle of the first beam in the laser frame (rad)."""
        return -0.5 * self.scan_fov_rad

    @property
    def scan_angle_increment_rad(self) -> float:
        """Angle between neighbouring beams (rad)."""
        return self.scan_fov_rad / self.scan_beams

    @property
    def scan_time_increment_s(self) -> float:
        """Time between two beams of a scan (s; LaserScan.time_increment)."""
        return self.scan_sweep_fraction / (self.scan_rate_hz * self.scan_beams)

    @property
    def start_ns(self) -> int:
        """Stamp of the first sample (ns)."""
        return int(self.start_time_s) * NS_PER_S

    @property
    def true_wheel_separation_m(self) -> float:
        """Distance between the wheels the robot really has (m)."""
        return self.wheel_separation_m * (1.0 + self.wheel_separation_error)

    @property
    def true_laser_pose(self) -> tuple[float, float, float]:
        """Where the laser really sits in base_link (x m, y m, yaw rad): told mount + error."""
        return (self.laser_x_m + self.laser_x_error_m, self.laser_y_m + self.laser_y_error_m,
                self.laser_yaw_rad + self.laser_yaw_error_rad)


# SimParams' fields as sensor_sim's parameters (each field's Param in its metadata).
SIM_PARAMETERS = ParameterTable(SimParams())


def validate(params: SimParams) -> None:
    """Raise ParameterError naming the first parameter the simulation cannot run with."""
    SIM_PARAMETERS.check(params)


def period_ticks(params: SimParams, rate_name: str) -> int:
    """Physics ticks between two samples of the sensor whose rate parameter is rate_name."""
    rate = getattr(params, rate_name)
    ticks = params.physics_rate_hz / rate
    if abs(ticks - round(ticks)) > 1e-9 * ticks or round(ticks) < 1:
        raise ParameterError(rate_name, f'must divide physics_rate_hz '
                             f'({params.physics_rate_hz}) into a whole number of ticks', rate)
    return int(round(ticks))


def make_route(params: SimParams) -> Route:
    """The scripted route of the parameters (ValueError naming the faulty leg)."""
    legs = list(params.route)
    for i, text in enumerate(legs):
        if not isinstance(text, str):
            raise ValueError(f'route[{i}] must be a string, got {text!r}')
    try:
        return Route(legs, params.max_linear_accel_m_s2, params.max_angular_accel_rad_s2)
    except ValueError as exc:
        raise ValueError(f'has a bad leg: {exc}') from None


def params_from_dict(values: dict[str, Any]) -> SimParams:
    """SimParams from a dict of parameter values (other keys ignored), unchecked; ints given
    for float fields are accepted. ParameterError for a route that is no list of legs."""
    return SIM_PARAMETERS.build(values)


class CommandedMotion:
    """Motion that follows velocity commands (v m/s, w rad/s) within the acceleration limits,
    stopping when commands time out. Advanced block by block with increasing times."""

    def __init__(self, params: SimParams) -> None:
        self._accel = (params.max_linear_accel_m_s2, params.max_angular_accel_rad_s2)
        self._timeout_s = params.cmd_vel_timeout_s
        self._target = (0.0, 0.0)
        self._command_s = -math.inf
        self._t = 0.0
        self._distance = 0.0
        self._heading = 0.0
        self._rates = (0.0, 0.0)

    def command(self, speed: float, yaw_rate: float, time_s: float) -> None:
        """A new command, received at route time time_s (s). Non-finite values are refused."""
        if not (math.isfinite(speed) and math.isfinite(yaw_rate)):
            raise ValueError(f'command ({speed}, {yaw_rate}) is not finite')
        self._target = (float(speed), float(yaw_rate))
        self._command_s = float(time_s)

    def motion(self, t: NDArray[np.float64]) -> Motion:
        """Motion at increasing times t (s) after the previous call's last time."""
        target = self._target if self._t - self._command_s <= self._timeout_s else (0.0, 0.0)
        dt = np.asarray(t, dtype=float) - self._t
        outputs = []
        for axis in range(2):
            rate0, accel = self._rates[axis], self._accel[axis]
            delta = target[axis] - rate0
            ramp_s = abs(delta) / accel
            slope = math.copysign(accel, delta)
            on_ramp = dt < ramp_s
            rate = np.where(on_ramp, rate0 + slope * dt, target[axis])
            moved = np.where(on_ramp, rate0 * dt + 0.5 * slope * dt * dt,
                             rate0 * ramp_s + 0.5 * slope * ramp_s ** 2
                             + target[axis] * (dt - ramp_s))
            outputs.append((rate, moved, np.where(on_ramp, slope, 0.0)))
        (speed, ds, accel_v), (yaw_rate, dtheta, _) = outputs
        distance, heading = self._distance + ds, self._heading + dtheta
        if dt.size:
            self._t = float(t[-1])
            self._distance, self._heading = float(distance[-1]), float(heading[-1])
            self._rates = (float(speed[-1]), float(yaw_rate[-1]))
        return Motion(distance, heading, speed, yaw_rate, accel_v)


# Correlation times (s) of the first-order Gauss-Markov processes whose sum imitates flicker
# bias noise: half a decade apart, their Allan deviations add up to a flat floor from ~3 s to
# ~3000 s; each has std BIAS_INSTABILITY_STD_PER_B x B so that the floor is 0.664 B.
BIAS_CORRELATION_TIMES_S = tuple(10.0 ** (k / 2.0) for k in range(-2, 9))
BIAS_INSTABILITY_STD_PER_B = 0.664 / 1.0893


class GyroBiasProcess:
    """The time-varying part of the gyro bias (rad/s, 3 axes): a random walk of density
    `random_walk` (rad/s/sqrt(s)) plus flicker-like bias instability `instability` (rad/s),
    sampled every `period_s`. Stateful: successive calls continue the same process."""

    def __init__(self, random_walk: float, instability: float, period_s: float,
                 rng: np.random.Generator) -> None:
        self.random_walk, self.instability, self.period_s = random_walk, instability, period_s
        self._rng = rng
        self._walk = np.zeros(3)
        self._decay = np.exp(-period_s / np.asarray(BIAS_CORRELATION_TIMES_S))
        self._state = np.zeros((len(BIAS_CORRELATION_TIMES_S), 3))

    @property
    def active(self) -> bool:
        """False when both parts are zero (the bias stays constant and no numbers are drawn)."""
        return self.random_walk > 0.0 or self.instability > 0.0

    def sample(self, n: int) -> NDArray[np.float64]:
        """The next n samples (n, 3) of the varying bias (rad/s)."""
        from scipy.signal import lfilter

        out = np.zeros((n, 3))
        if n == 0 or not self.active:
            return out
        if self.random_walk > 0.0:
            steps = self._rng.standard_normal((n, 3)) * (
                self.random_walk * math.sqrt(self.period_s)
            )
            out += self._walk + np.cumsum(steps, axis=0)
            self._walk = out[-1].copy()
        if self.instability > 0.0:
            std = BIAS_INSTABILITY_STD_PER_B * self.instability
            for i, a in enumerate(self._decay):
                # Exact AR(1) discretisation of a Gauss-Markov process with stationary std `std`.
                drive = self._rng.standard_normal((n, 3)) * (std * math.sqrt(1.0 - a * a))
                values, _ = lfilter([1.0], [1.0, -a], drive, axis=0, zi=(a * self._state[i])[None])
                out += values
                self._state[i] = values[-1]
        return out


@dataclass
class SimBlock:
    """The samples of one block of simulated time (times int64 ns, see SimRun for the rest)."""

    truth_t: NDArray[np.int64]
    truth_pose: NDArray[np.float64]
    truth_twist: NDArray[np.float64]
    scan_t: NDArray[np.int64]                # stamp: the first beam's time
    scan_ranges: NDArray[np.float32]
    imu_t: NDArray[np.int64]
    imu_gyro: NDArray[np.float64]
    imu_accel: NDArray[np.float64]
    joint_t: NDArray[np.int64]
    joint_position: NDArray[np.float64]
    joint_velocity: NDArray[np.float64]
    clock_t: NDArray[np.int64]
    scan_publish_t: NDArray[np.int64]        # when the sweep has ended and the scan goes out


# Kinds of events, in the order they are published when they share a stamp.
CLOCK, TRUTH, IMU, JOINTS, SCAN = range(5)
_KIND_TIMES = ((CLOCK, 'clock_t'), (TRUTH, 'truth_t'), (IMU, 'imu_t'), (JOINTS, 'joint_t'),
               (SCAN, 'scan_publish_t'))


def block_events(
    block: SimBlock,
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """(time ns, kind, index into that kind's arrays) of every sample of a block, in publishing
    order: by time, then by kind (CLOCK, TRUTH, IMU, JOINTS, SCAN). A scan's time is when it is
    published (scan_publish_t, its sweep ended), not its stamp (scan_t, its first beam)."""
    times = [getattr(block, name) for _, name in _KIND_TIMES]
    t = np.concatenate(times)
    kind = np.concatenate([np.full(len(x), k, dtype=np.int64)
                           for (k, _), x in zip(_KIND_TIMES, times)])
    index = np.concatenate([np.arange(len(x), dtype=np.int64) for x in times])
    order = np.lexsort((kind, t))
    return t[order], kind[order], index[order]


class SensorSim:
    """The simulation engine: call advance() for the next block of samples.

    Each sensor draws from its own random stream (SeedSequence(seed).spawn), so changing one
    sensor's settings leaves the other sensors' noise unchanged. Blocks have a fixed length, so
    the numbers do not depend on how fast or in what portions a consumer pulls them.
    """

    def __init__(self, params: SimParams, world: World, seed: int,
                 commands: CommandedMotion | None = None) -> None:
        validate(params)
        self.params = params
        self.world = world
        self.seed = int(seed)
        self.route = None if commands is not None else make_route(params)
        self._source = commands if commands is not None else self.route
        self.tick_ns = NS_PER_S // params.physics_rate_hz
        self.block_ticks = max(1, params.physics_rate_hz // 10)
        self.periods = {name: period_ticks(params, name + '_rate_hz')
                        for name in ('scan', 'imu', 'joint', 'truth', 'clock')}
        # A fourth stream for the varying gyro bias: spawn(4) leaves the first three as they were.
        scan_seq, imu_seq, wheel_seq, bias_seq = np.random.SeedSequence(self.seed).spawn(4)
        self._rng_scan = np.random.Generator(np.random.PCG64(scan_seq))
        self._rng_imu = np.random.Generator(np.random.PCG64(imu_seq))
        self._rng_wheels = np.random.Generator(np.random.PCG64(wheel_seq))
        self.beam_angles = (params.scan_angle_min_rad
                            + params.scan_angle_increment_rad * np.arange(params.scan_beams))
        p = params
        self._gyro_bias = GyroBiasProcess(
            p.gyro_bias_random_walk, p.gyro_bias_instability_rad_s,
            self.periods['imu'] * self.tick_ns / NS_PER_S,
            np.random.Generator(np.random.PCG64(bias_seq)))
        self._laser_pose = p.true_laser_pose
        self._true_radius = p.wheel_radius_m * np.array([1.0 + p.left_radius_error,
                                                         1.0 + p.right_radius_error])
        self._slip = np.array([1.0 + p.left_slip, 1.0 + p.right_slip])
        # State at the last computed tick.
        self.tick = 0
        m0 = self._source.motion(np.zeros(1))
        self._motion_last = np.array([m0.distance[0], m0.heading[0], m0.speed[0],
                                      m0.yaw_rate[0], m0.accel[0]])
        self._xy_last = np.array([p.start_x_m, p.start_y_m])
        self._imu_last = self._motion_last[[1, 2]].copy()          # heading, speed
        self._wheel_travel_last = self._wheel_travel(self._motion_last[:1],
                                                     self._motion_last[1:2])[0]
        self._wheel_angle_last = np.zeros(2)
        self._counts_last = np.zeros(2, dtype=np.int64)
        # A scan is published this many ticks after its stamp (its sweep: the first tick at or
        # after the last beam's time + one beam interval); the truth poses of the ticks since
        # then are kept (ticks, x, y, unwrapped yaw), the robot at its start pose before tick 0.
        self.scan_publish_ticks = math.ceil(p.scan_sweep_fraction * self.periods['scan']
                                            - 1e-9)
        self._history = np.array([[0.0], [p.start_x_m], [p.start_y_m],
                                  [p.start_yaw_rad + self._motion_last[1]]])

    @property
    def time_ns(self) -> int:
        """Simulated time (ns) of the last computed tick."""
        return self.params.start_ns + self.tick * self.tick_ns

    @property
    def block_ns(self) -> int:
        """Simulated time covered by one advance() (ns)."""
        return self.block_ticks * self.tick_ns

    def _wheel_travel(self, distance: NDArray, heading: NDArray) -> NDArray[np.float64]:
        half = 0.5 * self.params.true_wheel_separation_m
        return np.column_stack((distance - half * heading, distance + half * heading))

    # long: one block of the simulation in the order the samples depend on each other (motion,
    # wheels, IMU, scans, clock), vectorised over the block.
    def advance(self) -> SimBlock:
        """Simulate the next block of ticks and return the samples that fall in it."""
        p, first = self.params, self.tick == 0
        ticks = self.tick + np.arange(self.block_ticks + 1, dtype=np.int64)
        new = self._source.motion(ticks[1:] * (self.tick_ns / NS_PER_S))
        cols = [np.concatenate(([self._motion_last[i]], x)) for i, x in
                enumerate((new.distance, new.heading, new.speed, new.yaw_rate, new.accel))]
        distance, heading, speed, yaw_rate, _ = cols
        yaw = p.start_yaw_rad + heading
        ds, dtheta = np.diff(distance), np.diff(heading)
        # Exact arc per tick: the motion within a tick has constant curvature.
        chord = ds * np.sinc(dtheta / (2.0 * np.pi))
        mid = yaw[:-1] + 0.5 * dtheta
        x = self._xy_last[0] + np.concatenate(([0.0], np.cumsum(chord * np.cos(mid))))
        y = self._xy_last[1] + np.concatenate(([0.0], np.cumsum(chord * np.sin(mid))))

        def samples(name: str) -> NDArray[np.intp]:
            """Local indices (into ticks) of this block's samples of one sensor."""
            local = np.flatnonzero(ticks % self.periods[name] == 0)
            return local if first else local[local > 0]

        def stamps(local: NDArray[np.intp]) -> NDArray[np.int64]:
            return p.start_ns + ticks[local] * self.tick_ns

        k = samples('truth')
        truth_t = stamps(k)
        truth_pose = np.column_stack((x[k], y[k], np.asarray(wrap_angle(yaw[k])).reshape(-1)))
        truth_twist = np.column_stack((speed[k], yaw_rate[k]))

        # IMU: the mean rate and acceleration over each sample interval (an integrating sensor),
        # so summing rate x period gives the true heading change exactly.
        k = samples('imu')
        imu_t = stamps(k)
        imu_gyro, imu_accel = self._imu(heading[k], speed[k], yaw_rate[k])

        # Encoders: wheel rotation = travel x slip / true radius, plus random slip ~
        # sqrt(|travel|).
        k = samples('joint')
        joint_t = stamps(k)
        joint_position, joint_velocity = self._encoders(distance[k], heading[k])

        # Scans: published scan_publish_ticks after their stamp (the sweep), each beam ranged
        # from where the laser was at its own time.
        offset, period = self.scan_publish_ticks, self.periods['scan']
        k = np.flatnonzero(((ticks - offset) % period == 0) & (ticks >= offset))
        k = k if first else k[k > 0]
        scan_publish_t = stamps(k)
        scan_t = scan_publish_t - offset * self.tick_ns
        if p.scan_sweep_fraction > 0.0:
            history = np.concatenate((self._history[:, :-1],
                                      np.vstack((ticks, x, y, yaw))), axis=1)
            self._history = history[:, -(offset + 1):]
            scan_ranges = self._swept_scans(ticks[k] - offset, history)
        else:
            scan_ranges = self._scans(x[k], y[k], yaw[k])

        clock_t = stamps(samples('clock'))

        self.tick = int(ticks[-1])
        self._xy_last = np.array([x[-1], y[-1]])
        self._motion_last = np.array([c[-1] for c in cols])
        return SimBlock(truth_t, truth_pose, truth_twist, scan_t, scan_ranges, imu_t, imu_gyro,
                        imu_accel, joint_t, joint_position, joint_velocity, clock_t,
                        scan_publish_t)

    def _imu(self, heading: NDArray, speed: NDArray, yaw_rate: NDArray
             ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Gyro (rad/s) and accelerometer (m/s^2) samples, body frame, at the IMU samples with
        the given true heading (rad, since the start), speed (m/s) and yaw rate (rad/s)."""
        p = self.params
        n = heading.size
        period_s = self.periods['imu'] * self.tick_ns / NS_PER_S
        head = np.concatenate(([self._imu_last[0]], heading))
        vel = np.concatenate(([self._imu_last[1]], speed))
        noise = self._rng_imu.standard_normal((n, 6))
        imu_gyro = p.gyro_noise_std_rad_s * noise[:, :3]
        true_rate = np.diff(head) / period_s
        if p.gyro_scale_error:
            true_rate = true_rate * (1.0 + p.gyro_scale_error)
        imu_gyro[:, 2] += true_rate + p.gyro_bias_rad_s
        if self._gyro_bias.active:
            imu_gyro += self._gyro_bias.sample(n)
        imu_accel = p.accel_noise_std_m_s2 * noise[:, 3:]
        imu_accel += np.column_stack((np.diff(vel) / period_s, speed * yaw_rate,
                                      np.full(n, p.gravity_m_s2)))
        imu_accel += (p.accel_bias_x_m_s2, p.accel_bias_y_m_s2, p.accel_bias_z_m_s2)
        if n:
            self._imu_last = np.array([head[-1], vel[-1]])
        return imu_gyro, imu_accel

    def _encoders(self, distance: NDArray, heading: NDArray
                  ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Wheel positions (rad, whole encoder counts) and velocities (rad/s) [left, right] at
        the encoder samples with the given true distance (m) and heading (rad)."""
        p = self.params
        travel = self._wheel_travel(distance, heading)
        step = np.diff(np.vstack((self._wheel_travel_last, travel)), axis=0)
        slip_noise = (p.slip_noise_sqrt_m * np.sqrt(np.abs(step))
                      * self._rng_wheels.standard_normal(step.shape))
        angle = self._wheel_angle_last + np.cumsum(
            (step * self._slip + slip_noise) / self._true_radius, axis=0)
        counts = np.floor(angle / p.count_angle_rad).astype(np.int64)
        joint_position = counts * p.count_angle_rad
        joint_period_s = self.periods['joint'] * self.tick_ns / NS_PER_S
        joint_velocity = np.diff(np.vstack((self._counts_last, counts)), axis=0) \
            * (p.count_angle_rad / joint_period_s)
        if travel.shape[0]:
            self._wheel_travel_last, self._wheel_angle_last = travel[-1], angle[-1]
            self._counts_last = counts[-1]
        return joint_position, joint_velocity

    def _scans(self, x: NDArray, y: NDArray, yaw: NDArray) -> NDArray[np.float32]:
        """Noisy ranges (m, float32 as published) of scans taken at base poses (x, y, yaw)."""
        p = self.params
        laser_x, laser_y, laser_yaw = self._laser_pose
        out = np.empty((x.size, p.scan_beams), dtype=np.float32)
        noise = self._rng_scan.standard_normal((x.size, p.scan_beams))
        for i in range(x.size):
            c, s = math.cos(yaw[i]), math.sin(yaw[i])
            origin = (x[i] + c * laser_x - s * laser_y, y[i] + s * laser_x + c * laser_y)
            true = raycast(self.world.segments, origin, yaw[i] + laser_yaw + self.beam_angles)
            out[i] = measured_ranges(true, noise[i], p)
        return out


    def _swept_scans(self, stamp_ticks: NDArray, history: NDArray) -> NDArray[np.float32]:
        """Noisy ranges (m, float32) of scans stamped at stamp_ticks whose beams are taken in
        turn over the sweep, each from the laser's pose at its own time (the truth interpolated
        linearly between ticks: history rows tick, x, y, unwrapped yaw)."""
        p = self.params
        laser_x, laser_y, laser_yaw = self._laser_pose
        beam_ticks = np.arange(p.scan_beams) * (p.scan_time_increment_s * p.physics_rate_hz)
        out = np.empty((stamp_ticks.size, p.scan_beams), dtype=np.float32)
        noise = self._rng_scan.standard_normal((stamp_ticks.size, p.scan_beams))
        for i, stamp_tick in enumerate(stamp_ticks):
            at = stamp_tick + beam_ticks
            bx, by, byaw = (np.interp(at, history[0], row) for row in history[1:])
            c, s = np.cos(byaw), np.sin(byaw)
            origins = np.column_stack((bx + c * laser_x - s * laser_y,
                                       by + s * laser_x + c * laser_y))
            true = raycast(self.world.segments, origins, byaw + laser_yaw + self.beam_angles)
            out[i] = measured_ranges(true, noise[i], p)
        return out


def measured_ranges(
    true_ranges: NDArray, noise: NDArray, params: SimParams
) -> NDArray[np.float64]:
    """What the laser reports for true ranges (m), given standard-normal draws: true + bias +
    sigma * noise; +inf beyond range_max or with no hit, -inf below range_min (REP 117)."""
    with np.errstate(invalid='ignore'):
        measured = true_ranges + params.range_bias_m + params.range_noise_std_m * noise
        measured = np.where(measured > params.range_max_m, np.inf, measured)
        measured = np.where(measured < params.range_min_m, -np.inf, measured)
    return np.where(np.isfinite(true_ranges), measured, np.inf)


@dataclass
class SimRun(SimBlock):
    """A batch simulation: every sample as arrays (SimBlock's, over the whole run), with the
    parameters, seed and scan geometry it ran with. Times int64 ns of simulated time.

    truth_pose (N, 3) [x, y, yaw] of base_link in the map frame, truth_twist (N, 2) [v, w];
    scan_ranges (S, B) float32 in m (+inf no return, -inf too close) in the `laser` frame;
    imu_gyro (K, 3) rad/s and imu_accel (K, 3) m/s^2 specific force in imu_link;
    joint_position (J, 2) [left, right] rad, whole encoder counts; joint_velocity (J, 2) rad/s.
    """

    params: SimParams
    seed: int
    scan_angle_min: float
    scan_angle_increment: float
    scan_range_min: float
    scan_range_max: float
    scan_time_increment: float = 0.0      # s between two beams (0: every beam at the stamp)

    @property
    def scan_angles(self) -> NDArray[np.float64]:
        """Beam angles (rad) in the laser frame."""
        beams = np.arange(self.scan_ranges.shape[1])
        return self.scan_angle_min + self.scan_angle_increment * beams

    def truth_at(self, t_ns: NDArray[np.int64] | int) -> NDArray[np.float64]:
        """Truth pose(s) [x, y, yaw] interpolated at time(s) t_ns (linear; yaw unwrapped)."""
        t = np.asarray(t_ns, dtype=np.int64) - self.truth_t[0]
        base = (self.truth_t - self.truth_t[0]).astype(float)
        yaw = np.unwrap(self.truth_pose[:, 2])
        out = np.stack([np.interp(t.astype(float), base, col)
                        for col in (self.truth_pose[:, 0], self.truth_pose[:, 1], yaw)], axis=-1)
        out[..., 2] = wrap_angle(out[..., 2])
        return out


_ARRAYS = [f.name for f in dataclasses.fields(SimBlock)]


def simulate(params: SimParams, world: World, duration_s: float, seed: int) -> SimRun:
    """Run the simulation for duration_s simulated seconds (samples at times start .. start +
    duration inclusive), without ROS."""
    if not (math.isfinite(duration_s) and duration_s >= 0.0):
        raise ParameterError('duration_s', 'must be finite and >= 0', duration_s)
    sim = SensorSim(params, world, seed)
    end_ns = params.start_ns + int(round(duration_s * NS_PER_S))
    blocks = [sim.advance()]
    while sim.time_ns < end_ns:
        blocks.append(sim.advance())
    arrays: dict[str, Any] = {}
    for name in _ARRAYS:
        arrays[name] = np.concatenate([getattr(b, name) for b in blocks])
    for prefix in ('truth', 'scan', 'imu', 'joint', 'clock'):
        keep = arrays[f'{prefix}_t'] <= end_ns
        for name in _ARRAYS:
            if name.startswith(prefix + '_'):
                arrays[name] = arrays[name][keep]
    return SimRun(params=params, seed=int(seed), **arrays,
                  scan_angle_min=params.scan_angle_min_rad,
                  scan_angle_increment=params.scan_angle_increment_rad,
                  scan_range_min=params.range_min_m, scan_range_max=params.range_max_m,
                  scan_time_increment=params.scan_time_increment_s)
