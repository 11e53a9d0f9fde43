"""Faults injected into a simulated run, for the fusion's integrity checks: where the sensors or
the estimators they feed go wrong for a while, in the middle of a run.

Sensor faults change the raw samples (SimRun) before the package's estimators run over them, so
the wheel odometry, the gyro integrator and the scan matcher see them as they would: a scan
from another place, a full wheel slip, an IMU rate spike, a stuck IMU. Matcher faults change the
scan matcher's output (FusionInputs): a sideways slip and a symmetric-corridor jump. A delayed
burst changes when one input's readings arrive. Times in s after the run's first sample.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.geometry import se2
from sensing_nodes.core.sim.inputs import FusionInputs
from sensing_nodes.core.sim.simulator import SimRun

SENSOR_FAULTS = ('foreign_scan', 'wheel_slip', 'imu_spike', 'imu_stuck')
MATCHER_FAULTS = ('matcher_slip', 'corridor_jump')
ARRIVAL_FAULTS = ('delayed_burst',)
KINDS = SENSOR_FAULTS + MATCHER_FAULTS + ARRIVAL_FAULTS
# The input each fault makes wrong (the fusion should name it).
FAULTY_INPUT = {'foreign_scan': 'scan_match', 'wheel_slip': 'wheel_odom', 'imu_spike': 'imu',
                'imu_stuck': 'imu', 'matcher_slip': 'scan_match', 'corridor_jump': 'scan_match',
                'delayed_burst': 'scan_match'}


@dataclass(frozen=True)
class Fault:
    """One fault: its kind (KINDS), when it starts (s after the run's first sample) and how
    long it lasts (s), and its size where it has one (m, rad/s: the matcher faults' offset, the
    spike's rate)."""

    kind: str
    start_s: float
    duration_s: float
    size: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f'fault kind must be one of {KINDS}, got {self.kind!r}')
        if not (self.start_s >= 0.0 and self.duration_s > 0.0):
            raise ValueError('a fault needs start_s >= 0 and duration_s > 0')

    @property
    def input(self) -> str:
        """The fusion input the fault makes wrong."""
        return FAULTY_INPUT[self.kind]

    def window_ns(self, first_ns: int) -> tuple[int, int]:
        """[start, end) of the fault in stamps (ns) of a run whose first sample is first_ns."""
        start = first_ns + int(round(self.start_s * 1e9))
        return start, start + int(round(self.duration_s * 1e9))


def _during(t: NDArray[np.int64], window: tuple[int, int]) -> NDArray[np.bool_]:
    return (t >= window[0]) & (t < window[1])


def inject_sensors(run: SimRun, fault: Fault) -> SimRun:
    """The run with a sensor fault in its raw samples (a copy; other kinds: unchanged).

    foreign_scan: the scans in the window replaced by the scans taken half a run later (another
    place); wheel_slip: both wheels spin freely, their encoders turning a second time as far as
    the robot travels (a full slip: the odometry reports twice the motion) and keeping the extra
    turns; imu_spike: the gyro's z rate plus `size` rad/s (default 5) in the window; imu_stuck:
    the gyro's z rate stuck at zero in the window."""
    first = int(run.truth_t[0])
    if fault.kind == 'foreign_scan':
        during = np.flatnonzero(_during(run.scan_t, fault.window_ns(first)))
        ranges = run.scan_ranges.copy()
        ranges[during] = run.scan_ranges[(during + len(run.scan_t) // 2) % len(run.scan_t)]
        return dataclasses.replace(run, scan_ranges=ranges)
    if fault.kind == 'wheel_slip':
        start, end = fault.window_ns(first)
        t = run.joint_t
        seconds = (np.clip(t, start, end) - start) * 1e-9
        dt = np.diff(seconds, prepend=0.0)
        spinning = run.joint_velocity * _during(t, (start, end))[:, None]
        extra = np.cumsum(spinning * dt[:, None], axis=0)
        return dataclasses.replace(run, joint_position=run.joint_position + extra,
                                   joint_velocity=run.joint_velocity + spinning)
    if fault.kind in ('imu_spike', 'imu_stuck'):
        during = _during(run.imu_t, fault.window_ns(first))
        gyro = run.imu_gyro.copy()
        if fault.kind == 'imu_spike':
            gyro[during, 2] += fault.size or 5.0
        else:
            gyro[during, 2] = 0.0
        return dataclasses.replace(run, imu_gyro=gyro)
    return run


def inject_matches(inputs: FusionInputs, fault: Fault) -> FusionInputs:
    """The streams with a matcher fault in the scan matcher's poses in its map (a copy; other
    kinds: unchanged). matcher_slip: every match in the window `size` m (default 1) to the
    robot's left; corridor_jump: every match in the window `size` m (default 1) ahead along the
    robot's heading, as a matcher that locked onto the next section of a symmetric corridor."""
    if fault.kind not in MATCHER_FAULTS:
        return inputs
    during = np.flatnonzero(_during(inputs.scan_map_t, fault.window_ns(int(inputs.truth_t[0])))
                            & (inputs.scan_map_id >= 0)
                            & (inputs.scan_map_id != inputs.scan_map_t))
    offset = (0.0, fault.size or 1.0) if fault.kind == 'matcher_slip' else (fault.size or 1.0,
                                                                             0.0)
    poses = inputs.scan_map_pose.copy()
    for i in during:
        poses[i] = se2.compose(tuple(poses[i]), (offset[0], offset[1], 0.0))
    return dataclasses.replace(inputs, scan_map_pose=poses)


def wrong_matches(inputs: FusionInputs, fault: Fault) -> NDArray[np.int64]:
    """The stamps (ns) of the matches a matcher fault made wrong (empty for other kinds)."""
    if fault.kind not in MATCHER_FAULTS:
        return np.zeros(0, dtype=np.int64)
    during = _during(inputs.scan_map_t, fault.window_ns(int(inputs.truth_t[0]))) \
        & (inputs.scan_map_id >= 0) & (inputs.scan_map_id != inputs.scan_map_t)
    return inputs.scan_map_t[during]


def arrival_order(readings: list[tuple[str, object]], first_ns: int,
                  fault: Fault) -> list[tuple[str, object]]:
    """(input, reading) pairs in the order they arrive: for a delayed_burst, the faulty
    input's readings stamped in the window held back and delivered together with the first
    reading stamped at the window's end (a link that stalls for the window, then flushes: the
    first held reading arrives duration_s late); others unchanged."""
    if fault.kind != 'delayed_burst':
        return readings
    start, end = fault.window_ns(first_ns)
    release = end
    held = [(n, r) for n, r in readings if n == fault.input and start <= r.stamp_ns < end]
    rest = [(n, r) for n, r in readings if not (n == fault.input and start <= r.stamp_ns < end)]
    at = next((i for i, (_, r) in enumerate(rest) if r.stamp_ns >= release), len(rest))
    return rest[:at] + held + rest[at:]
