"""The fusion's timeline: readings of its inputs in, fused outputs out, in stamp order.

FusionSession owns the filter (the EKF or the complementary filter, by SessionConfig.method),
the stamp-ordered reorder buffer, each input's record, the watermark, start gating (the filter
starts once every enabled input has spoken), the reset when an input's stamps go backwards,
input restarts and set_pose. The node's processor (nodes/complementary_fusion.py, which
sensing_pipeline drives too), the bag-fusing tool and the evaluation all run the fusion through
it. It reads no clock: `flush` processes what is held (the node after a wall-clock idle time,
the offline callers at the end of their input). Stamps in ns.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.fusion.complementary import ComplementaryMethod
from sensing_nodes.core.fusion.config import SessionConfig
from sensing_nodes.core.fusion.ekf import EkfFusion
from sensing_nodes.core.fusion.filter import FusedState, FusionFilter
from sensing_nodes.core.fusion.inputs import IMU, INPUTS, RANK, SCAN, WHEEL, Reading
from sensing_nodes.core.fusion.timeline import InputRecord, StampOrderedBuffer, watermark
from sensing_nodes.core.fusion.validation import pose_problem
from sensing_nodes.core.geometry.se2 import Pose2
from sensing_nodes.core.timing import StampRate

RESTART = 'restart'   # in the reorder buffer: the input restarts here (e.g. a new IMU mount)

FusedOutput = tuple[int, FusedState]   # (stamp ns the output is published at, the fused state)


@dataclass(frozen=True)
class Notice:
    """Something the session's user should be told (the node logs it): level 'info' or 'warn';
    notices with the same key (not None) are about one thing and may be throttled together."""

    level: str
    text: str
    key: str | None = None


def make_filter(config: SessionConfig) -> FusionFilter:
    """The filter config.method names, with its settings."""
    if config.method == 'ekf':
        return EkfFusion(config.inputs, config.ekf)
    return ComplementaryMethod(config.complementary)


class FusionSession:
    """Readings of the inputs (wheel_odom, imu, scan_match) -> fused outputs, in stamp order
    whatever the arrival order within the reorder window (ties: wheel, IMU, scan match).

    A message's life: `arrive(name, stamp)` (counted; time going backwards resets the timeline),
    then `add(name, reading)` or `reject(name, problem)`; `feed` does both for a reading in
    hand. Each returns the outputs it released. Every reading is filtered; the state is read
    once per stamp, after every reading of that stamp, where one of them is a wheel or
    scan-match reading (an IMU reading when the IMU is the only input); with publish_rate_hz 0
    every such state is an output; else each one with a scan match, and of the
    others the first in each period of 1/publish_rate_hz of stamp time (core/timing.py's
    StampRate), each with its stamp. Counts go to `counts` (the node's diagnostics counter),
    things to tell the user to `notices` (the caller drains them).
    """

    def __init__(self, config: SessionConfig, fusion: FusionFilter | None = None,
                 counts: Counter | None = None,
                 on_output: Callable[[int, FusedState], None] | None = None) -> None:
        self.config = config
        self.fusion = fusion if fusion is not None else make_filter(config)
        self.records = {name: InputRecord(name, config.enabled[name]) for name in INPUTS}
        self._record_list = list(self.records.values())
        self._enabled = [name for name in INPUTS if config.enabled[name]]
        # An IMU reading is published only when no input gives a position.
        self._imu_publishes = not (config.enabled[WHEEL] or config.enabled[SCAN])
        self.buffer = StampOrderedBuffer(int(config.reorder_window_s * 1e9))
        self.counts: Counter = counts if counts is not None else Counter()
        self.notices: list[Notice] = []
        self.resets = 0          # timelines ended by time going backwards
        self._rate = StampRate(config.publish_rate_hz)
        self.outputs = InputRecord('output')   # the outputs released (rate_hz: stamp time)
        self._lag_max_ns = 0
        self._on_output = on_output   # called with each output as it is made (evaluation)
        # Inputs told distrusted (a refused or blamed reading within DISTRUST_HOLD_S), and the
        # stamp of each input's last problem seen.
        self._distrusted: set[str] = set()
        self._problem_ns: dict[str, int | None] = {name: None for name in INPUTS}
        self._clear_timeline()

    def _clear_timeline(self) -> None:
        self._start_ns: int | None = None       # first stamp accepted
        # The filter starts at the first stamp by which every enabled input has spoken (or
        # when the reorder buffer stops waiting for a silent one): started on one input alone
        # it follows that input's start-up transients, e.g. gyro_integrator's heading before
        # its first bias estimate, which the wheels would have refused (a fusion subscribed a
        # moment after the wheels started ended 0.15 deg off and refused every scan match).
        self._first_ns: dict[str, int] = {}
        self._started = False
        self._waiting = False    # told that an input not heard yet is waited for
        self._rate.reset()
        self.outputs.clear()

    # -- input ---------------------------------------------------------------------------------
    def arrive(self, name: str, stamp_ns: int) -> list[FusedOutput]:
        """A message of input `name` stamped stamp_ns has arrived (before it is read: reading
        it uses the timeline's per-input state, a source's starting pose). An input's stamp
        more than reset_on_backwards_jump_s before its previous one means time went backwards
        (a looping bag, a restarted clock): what was held is processed (the old timeline's
        outputs, returned) and the session starts again."""
        record = self.records[name]
        record.received += 1
        if record.arrived_ns is None or \
                record.arrived_ns - stamp_ns <= self.config.reset_on_backwards_jump_s * 1e9:
            return []
        self.notices.append(Notice('warn', (
            f'{name} stamp {stamp_ns * 1e-9:.3f} s is {(record.arrived_ns - stamp_ns) * 1e-9:.3f} '
            's before its previous one: time went backwards (looping bag or restarted clock); '
            'resetting')))
        self.counts['resets'] += 1
        out = self._process(self.buffer.flush())   # what was held: the old timeline
        self.fusion.reset()
        self._distrusted.clear()
        self._problem_ns = dict.fromkeys(INPUTS)
        self.buffer.clear()
        for r in self._record_list:
            r.clear()
        self._clear_timeline()
        self.resets += 1
        return out

    def add(self, name: str, reading: Reading) -> list[FusedOutput]:
        """The arrived message's reading: into the reorder buffer (refused and counted when
        inputs after its stamp were already fused), then whatever is ready is fused."""
        stamp = reading.stamp_ns
        buffer = self.buffer
        record = self.records[name]
        if not buffer.push(stamp, RANK[name], (name, reading)):
            self.counts[f'{name}_dropped_late'] += 1
            self.notices.append(Notice('warn', (
                f'{name} message at {stamp * 1e-9:.3f} s arrived after inputs up to '
                f'{buffer.released_ns * 1e-9:.3f} s were fused: dropped ({buffer.late} so far)'),
                f'{name}_late'))
            # Still where the input has got to: an input that fell out of the watermark (silent
            # for input_timeout_s, e.g. a restarted matcher whose messages go out a sweep after
            # their stamps) is waited for again from its next message, instead of having every
            # later message dropped too.
            if record.arrived_ns is None or stamp > record.arrived_ns:
                record.arrived_ns = stamp
            return []
        if self._start_ns is None:
            self._start_ns = stamp
        first = self._first_ns.get(name)
        if first is None or stamp < first:
            self._first_ns[name] = stamp
        if record.arrived_ns is None or stamp > record.arrived_ns:
            record.arrived_ns = stamp
        if self._waiting_for_silent_input():
            return []
        out = self._process(buffer.pop_ready(watermark(
            self._record_list, buffer.newest_ns, self._start_ns, self.config.input_timeout_s,
            self.config.startup_timeout_s)))
        if self.outputs.last_ns is not None:
            self._lag_max_ns = max(self._lag_max_ns, buffer.newest_ns - self.outputs.last_ns)
        return out

    def reject(self, name: str, problem: str) -> None:
        """The arrived message could not be read (why: `problem`): counted, not fused."""
        self.counts[f'{name}_rejected'] += 1
        self.notices.append(Notice('warn', f'{name}: rejected a message ({problem})',
                                   f'{name}_rejected: {problem}'))

    def feed(self, name: str, reading: Reading) -> list[FusedOutput]:
        """arrive and add for a reading in hand."""
        return self.arrive(name, reading.stamp_ns) + self.add(name, reading)

    def restart(self, name: str, stamp_ns: int) -> None:
        """Input `name` starts again at stamp_ns, in stamp order (what it measures changed: a
        new IMU mount): its increments and its relative origin."""
        self.records[name].origin = None
        self.buffer.push(stamp_ns, RANK[name], (name, RESTART))

    def set_pose(self, pose: Pose2, covariance: NDArray[np.float64], problem: str = ''
                 ) -> list[FusedOutput]:
        """robot_localization's set_pose (m, rad, 3x3 in odom): what is held is fused first,
        then the pose is set. `problem`: why the caller could not read the pose ('' if it
        could); refused, counted and told then, or when the pose or covariance is unusable."""
        problem = problem or pose_problem(pose, covariance, None, True)
        if problem:
            self.counts['set_pose_rejected'] += 1
            self.notices.append(Notice('warn', f'set_pose rejected: {problem}'))
            return []
        out = self.flush()
        self.fusion.set_pose(pose, covariance)
        self.counts['set_pose'] += 1
        self.notices.append(Notice('info', 'pose set to x=%.3f m, y=%.3f m, yaw=%.3f rad'
                                   % tuple(pose)))
        return out

    def flush(self) -> list[FusedOutput]:
        """Process everything held (end of a stream, or no input for a while): an input not
        heard yet is no longer waited for."""
        return self._process(self.buffer.flush())

    def held(self) -> int:
        """How many readings the reorder buffer holds."""
        return len(self.buffer)

    def output_lag_s(self) -> tuple[float, float]:
        """How far the newest output trails the newest input, in stamp time (s): now, and the
        most after any input since the last call (the reorder buffer's hold, the output period,
        inputs that give no output); nan before the first output."""
        if self.outputs.last_ns is None or self.buffer.newest_ns is None:
            return math.nan, math.nan
        now = (self.buffer.newest_ns - self.outputs.last_ns) * 1e-9
        most, self._lag_max_ns = max(self._lag_max_ns * 1e-9, now), 0
        return now, most

    def take_notices(self) -> list[Notice]:
        """The notices since the last call (the caller tells them)."""
        notices, self.notices = self.notices, []
        return notices

    # -- fusion ----------------------------------------------------------------------------------
    def _process(self, ready: list[tuple[int, tuple[str, object]]]) -> list[FusedOutput]:
        out: list[FusedOutput] = []
        # The state is read once every reading of a stamp is in (a wheel message and an IMU
        # message stamped alike: the output at that stamp has both, instead of the heading
        # predicted over the IMU's last period), and only where one of them gives an output.
        wanted = match = False
        for index, (stamp, (name, reading)) in enumerate(ready):
            if reading is RESTART:
                self.fusion.restart(name)
            elif not self._started and self._before_every_input(stamp):
                self.counts['before_every_input'] += 1
            else:
                self.records[name].processed_at(stamp)
                self.fusion.update(name, reading)
                self._tell_episodes(stamp)
                # The IMU alone publishes only when no input gives a position.
                wanted = wanted or name != IMU or self._imu_publishes
                match = match or name == SCAN
            if index + 1 < len(ready) and ready[index + 1][0] == stamp:
                continue
            if wanted:
                self._output(stamp, match, out)
            wanted = match = False
        return out

    def _tell_episodes(self, stamp: int) -> None:
        """Once per episode: an input the filter starts to refuse or blame (a warning with
        why), and one it uses again (how many of its readings were refused and blamed)."""
        for name, health in self.fusion.health.items():
            if health.last_problem_ns != self._problem_ns[name]:
                self._problem_ns[name] = health.last_problem_ns
                if name not in self._distrusted:
                    self._distrusted.add(name)
                    self.notices.append(Notice('warn', (
                        f'{name} distrusted at {stamp * 1e-9:.3f} s: {health.last_problem}'),
                        f'{name}_distrusted'))
            elif name in self._distrusted and not health.distrusted(stamp):
                self._distrusted.discard(name)
                self.notices.append(Notice('info', (
                    f'{name} in use again at {stamp * 1e-9:.3f} s ({health.refused} of its '
                    f'readings refused, {health.blamed} blamed so far)')))

    def integrity(self) -> dict[str, dict[str, object]]:
        """Per input the filter gates: fused, refused and blamed readings, the share refused
        of its recent ones, its noise scale, whether it is distrusted now (a refused or blamed
        reading within the last second of stamps) and its last problem (/diagnostics)."""
        now = self.buffer.newest_ns or 0
        return {name: {'fused': h.fused, 'refused': h.refused, 'blamed': h.blamed,
                       'reacquired': h.reacquired, 'refused_share': h.refused_share,
                       'noise_scale': self.fusion.noise_scale.get(name, 1.0),
                       'distrusted': h.distrusted(now), 'last_problem': h.last_problem}
                for name, h in self.fusion.health.items()}

    def _output(self, stamp: int, match: bool, out: list[FusedOutput]) -> None:
        """The state after the readings at `stamp`, when the rate lets it out."""
        state = self.fusion.state     # read as at every rate: the filter runs the same
        if state is None:
            return
        # The first output in each period of the rate goes out (due() takes the period), and
        # every scan match's: the absolute correction, at once and at its own stamp (a
        # consumer, or sensing_demo's pacing, waits for the output at each scan's stamp).
        if not self._rate.due(stamp) and not match:
            return
        self.outputs.processed_at(stamp)
        out.append((stamp, state))
        if self._on_output is not None:
            self._on_output(stamp, state)

    def _waiting_for_silent_input(self) -> bool:
        """True while the filter has not started and an enabled input has not been heard yet,
        for up to startup_timeout_s of stamps since the first reading: what arrives is held, not
        fused (nodes started together come up and discover each other in any order; started
        without an input, the filter would then drop that input's first, late messages). Told
        once, naming the inputs, when it lasts longer than input_timeout_s."""
        if self._started:
            return False
        silent = [name for name in self._enabled if name not in self._first_ns]
        waited_ns = self.buffer.newest_ns - self._start_ns
        if not silent or waited_ns > self.config.startup_timeout_s * 1e9:
            return False
        # Told once the wait is longer than a silent input is waited for later on.
        if not self._waiting and waited_ns > self.config.input_timeout_s * 1e9:
            self._waiting = True
            self.notices.append(Notice('info', (
                f'waiting for {self._named(silent)}: not heard yet; fusing starts once every '
                f'enabled input has spoken (at most {self.config.startup_timeout_s:g} s of '
                'stamps)')))
        return True

    def _named(self, names: list[str]) -> str:
        return ', '.join(f'{name} ({self.config.topics[name]})' for name in names)

    def _before_every_input(self, stamp: int) -> bool:
        """True for a reading older than the first of some enabled input (not fused); the
        first reading that is not starts the filter (without the inputs still silent, once
        they are no longer waited for: startup_timeout_s, or a flush)."""
        if all(name in self._first_ns for name in self._enabled):
            start = max(self._first_ns[name] for name in self._enabled)
            if stamp < start:
                return True
            skipped = self.counts.get('before_every_input', 0)
            if skipped:
                self.notices.append(Notice('info', (
                    f'every input has spoken: fusing from {start * 1e-9:.3f} s; {skipped} '
                    'earlier readings not fused')))
        else:
            silent = [name for name in self._enabled if name not in self._first_ns]
            waited = (self.buffer.newest_ns - self._start_ns) * 1e-9
            self.notices.append(Notice('warn', (
                f'starting without {self._named(silent)} (not heard in {waited:.3g} s of '
                'stamps)')))
        self._started = True
        return False
