"""sensing_replay: play a bag's input topics into the running nodes over DDS and record what
they publish into a new bag.

Lockstep (default): publish one input message, wait until the nodes have published what it
causes (the expectation table: input topic -> output topics, each carrying the input's stamp),
then the next; deterministic. Timed: respects the stamps, scaled by --rate, and publishes /clock.
With --launch the package's processing nodes are started (with their config/ parameter files)
and stopped by the tool itself; --make-bags DIR regenerates the project's bags in bags/.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

from sensing_nodes.ros.graph import (
    PROCESSING_NODES, Graph, GraphArgumentError, executable, parse_node_params, parse_nodes,
    parse_remaps,
)

# Input topic -> output topics that carry its stamp (one message each), for this package's graph.
DEFAULT_EXPECTATIONS: dict[str, tuple[str, ...]] = {
    '/joint_states': ('/wheel/odom',),
    '/imu/data_raw': ('/imu/data',),
    '/scan': ('/scan/lines', '/scan/lines/table', '/scan_match/odom'),
}
# Inputs whose outputs feed another node that acts on them at its next input without ordering
# by stamp (/wheel/odom: the gyro's stillness veto, the scan matcher's initial guess). Their
# outputs reach the replay and those nodes over separate DDS paths, so after them the replay
# lets the fan-out land (settle) before it publishes the next input.
DEFAULT_SETTLE_AFTER = ('/joint_states',)
# ... and before these inputs it lets everything published so far land (the scan matcher acts on
# the odometry it holds when a scan arrives).
DEFAULT_SETTLE_BEFORE = {'/scan': 0.010}
# Outputs of nodes that buffer their inputs (the fusion's reorder window: it answers an input
# once the other inputs have caught up, or after its idle flush): an expectation naming one is
# not waited for per input; the end of the pass checks that every stamp came.
ANSWERS_LATER = ('/odometry/filtered',)
# ... but at most this many of their answers may be outstanding: a node that releases a burst of
# held outputs must not overrun the recording subscription (reliable, keep last 100).
MAX_OUTSTANDING_LATER = 50
# Lockstep with --launch: the fusion's idle flush (wall time without input), unless --param sets
# it; the end of a pass then waits for quiet a second longer than the flush can take (its
# timer looks every flush_after_s / 2).
LOCKSTEP_FUSION_FLUSH_S = 2.0
# Outputs that are not 1:1 with an input: recorded as they come.
DEFAULT_EXTRA_OUTPUTS = ('/odometry/filtered', '/diagnostics')
# Message type each node input takes (a bag topic of another type is refused).
NODE_INPUT_TYPES = {
    '/joint_states': 'sensor_msgs/msg/JointState',
    '/imu/data_raw': 'sensor_msgs/msg/Imu',
    '/scan': 'sensor_msgs/msg/LaserScan',
    '/wheel/odom': 'nav_msgs/msg/Odometry',
    '/imu/data': 'sensor_msgs/msg/Imu',
    '/scan_match/odom': 'nav_msgs/msg/Odometry',
    '/cmd_vel': 'geometry_msgs/msg/Twist',
}
# Raw sensor streams: published best effort, as a driver would (SENSOR_QOS); the rest reliable.
SENSOR_TOPICS = {'/joint_states', '/imu/data_raw', '/scan'}
# Published on a wall-clock timer whatever the input: never waited for, not part of "quiet".
WALL_PERIODIC_TOPICS = {'/diagnostics'}
# What each processing node publishes (so a launched graph is only used once each requested
# output has a publisher).
NODE_OUTPUTS = {
    'wheel_odometry': ('/wheel/odom', '/diagnostics'),
    'gyro_integrator': ('/imu/data', '/diagnostics'),
    'line_extractor': ('/scan/lines', '/scan/lines/table', '/diagnostics'),
    'icp_matcher': ('/scan_match/odom', '/diagnostics'),
    'complementary_fusion': ('/odometry/filtered', '/diagnostics'),
}

# The project's bags: name -> (sensor_sim parameter file in config/, seed, simulated seconds).
BAG_SPECS = {
    'nominal': ('bags_nominal.yaml', 1, 22.0),
    'strong_errors': ('bags_strong_errors.yaml', 2, 22.0),
}

EXIT_BAD_INPUT = 2
EXIT_FAILED = 1


class ReplayError(Exception):
    """Bad input or a graph that did not come up: the message names the file and topic."""


@dataclass
class InputBag:
    """Every message of a bag, loaded up front (so a truncated bag fails before any is sent)."""

    path: Path
    types: dict[str, str]
    messages: list[tuple[str, int, bytes]]  # (topic, bag time ns, CDR bytes), in bag order
    qos: dict[str, list] = field(default_factory=dict)  # topic -> offered QoS (rosbags records)


@dataclass
class PassResult:
    """What one pass over the bag produced."""

    outputs: dict[str, list[tuple[int, bytes]]] = field(default_factory=lambda: defaultdict(list))
    inputs_published: int = 0
    missing: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    wall_s: float = 0.0
    wait_s: dict[str, float] = field(default_factory=lambda: defaultdict(float))  # per input topic


def load_bag(path: str | Path) -> InputBag:
    """Read a whole rosbag2 bag; ReplayError (naming the file) when it is missing or unreadable."""
    from sensing_nodes.bag import BagError, BagReader

    path = Path(path)
    try:
        reader = BagReader(path)
        types = {t: i.msgtype for t, i in reader.topics.items()}
        expected = {t: i.count for t, i in reader.topics.items()}
        qos = {t: list(i.qos) for t, i in reader.topics.items()}
        messages = list(reader.raw())   # in stamp order, ties in the order the bag stores them
    except BagError as exc:
        raise ReplayError(str(exc)) from None
    except Exception as exc:  # rosbags raises several types for damaged files
        raise ReplayError(f'{path}: cannot read the bag ({type(exc).__name__}: {exc}); '
                          'truncated or damaged?') from None
    got = defaultdict(int)
    for topic, _, _ in messages:
        got[topic] += 1
    short = {t: (got[t], n) for t, n in expected.items() if got[t] != n}
    if short:
        detail = ', '.join(f'{t}: {g} of {n}' for t, (g, n) in sorted(short.items()))
        raise ReplayError(f'{path}: bag holds fewer messages than its metadata says ({detail}); '
                          'truncated?')
    return InputBag(path, types, messages, qos)


def check_inputs(bag: InputBag, inputs: list[str], remaps: dict[str, str]) -> None:
    """Every input topic is in the bag with a type the receiving node takes."""
    for topic in inputs:
        if topic not in bag.types:
            raise ReplayError(f'{bag.path}: topic {topic} is not in the bag (it has: '
                              f'{", ".join(sorted(bag.types))})')
        published = remaps.get(topic, topic)
        wanted = NODE_INPUT_TYPES.get(published)
        if wanted is not None and bag.types[topic] != wanted:
            raise ReplayError(f'{bag.path}: topic {topic} holds {bag.types[topic]}, but the nodes '
                              f'take {wanted} on {published}')
        if not any(t == topic for t, _, _ in bag.messages):
            raise ReplayError(f'{bag.path}: topic {topic} has no messages')


def parse_expectations(specs: list[str]) -> dict[str, tuple[str, ...]]:
    """['/scan=/a,/b', '/odom='] -> {'/scan': ('/a', '/b'), '/odom': ()}."""
    table = {}
    for spec in specs:
        topic, sep, outputs = spec.partition('=')
        if not sep or not topic.startswith('/'):
            raise ReplayError(f"--expect {spec!r}: write INPUT=OUTPUT[,OUTPUT...] (OUTPUT may be "
                              "empty), e.g. /scan=/scan_match/odom")
        table[topic] = tuple(o for o in outputs.split(',') if o)
    return table


def shifted_stamp(raw: bytes, offset_ns: int) -> bytes:
    """A CDR message whose first field is a Header, with its stamp moved by offset_ns."""
    order = '<' if raw[1] == 1 else '>'
    sec, nanosec = struct.unpack_from(order + 'iI', raw, 4)
    sec, nanosec = divmod(sec * 1_000_000_000 + nanosec + offset_ns, 1_000_000_000)
    out = bytearray(raw)
    struct.pack_into(order + 'iI', out, 4, sec, nanosec)
    return bytes(out)


def header_stamp_ns(raw: bytes) -> int:
    """Stamp of a CDR message whose first field is a Header."""
    order = '<' if raw[1] == 1 else '>'
    sec, nanosec = struct.unpack_from(order + 'iI', raw, 4)
    return sec * 1_000_000_000 + nanosec


def stamped_topics(bag: InputBag, topics) -> set[str]:
    """The topics among `topics` whose message type starts with a Header."""
    from sensing_nodes.bag import message_class

    return {t for t in topics if next(iter(message_class(bag.types[t])
                                           .get_fields_and_field_types().values()), '')
            == 'std_msgs/Header'}


def warm_up_bag(bag: InputBag, inputs: set[str], warmup_s: float) -> InputBag:
    """The inputs of the bag's first warmup_s, and at least the first message of every input
    topic, with stamps (header and bag time) moved to 1 s after the bag's last message."""
    firsts: dict[str, int] = {}
    for topic, stamp, _ in bag.messages:
        if topic in inputs:
            firsts.setdefault(topic, stamp)
    start = min(firsts.values())
    end = max(start + int(warmup_s * 1e9), max(firsts.values()))
    offset = bag.messages[-1][1] - start + 1_000_000_000
    stamped = stamped_topics(bag, firsts)
    return InputBag(bag.path, bag.types, [
        (t, s + offset, shifted_stamp(raw, offset) if t in stamped else raw)
        for t, s, raw in bag.messages if t in inputs and s <= end])


def marker_array_stamp_ns(raw: bytes, fallback_ns: int) -> int:
    """Stamp of a CDR MarkerArray: its first marker's header (after the encapsulation header and
    the sequence length), or fallback_ns when it has no marker."""
    order = '<' if raw[1] == 1 else '>'
    (count,) = struct.unpack_from(order + 'I', raw, 4)
    if count == 0:
        return fallback_ns
    sec, nanosec = struct.unpack_from(order + 'iI', raw, 8)
    return sec * 1_000_000_000 + nanosec


class Replayer:
    """One rclpy node publishing a bag's inputs and recording the graph's outputs."""

    def __init__(self, inputs: dict[str, str], input_types: dict[str, str],
                 outputs: set[str], expectations: dict[str, tuple[str, ...]]) -> None:
        import rclpy
        from rclpy.node import Node

        from sensing_nodes.bag import message_class
        from sensing_nodes.recorder import TopicRecorder
        from sensing_nodes.ros.qos import CLOCK_QOS, ESTIMATE_QOS, SENSOR_QOS
        from sensing_nodes.ros.run import make_executor

        self._rclpy = rclpy
        rclpy.init(args=['sensing_replay'])  # never the tool's own argv (its ':=' are not ROS's)
        self.node = Node('sensing_replay')
        self.executor = make_executor()
        self.executor.add_node(self.node)
        self.expectations = expectations
        self.publishers = {}
        for topic, published in inputs.items():
            qos = SENSOR_QOS if published in SENSOR_TOPICS else ESTIMATE_QOS
            self.publishers[topic] = self.node.create_publisher(
                message_class(input_types[topic]), published, qos)
        from rosgraph_msgs.msg import Clock
        self.clock_publisher = None
        self._clock_class = Clock
        self._clock_qos = CLOCK_QOS
        self.outputs = outputs
        self.seen: dict[tuple[str, int], int] = defaultdict(int)
        self.arrivals = 0
        self.current: PassResult | None = None
        listeners = {t: (lambda raw, stamp, wall, t=t: self._on_output(t, raw, stamp))
                     for t in outputs}
        self.recorder = TopicRecorder(self.node, None, listeners, only=outputs)
        self.diagnostics_seen: dict[str, float] = {}  # node name -> wall time of its last status
        self.marker_topics: set[str] = set()   # MarkerArray outputs: stamp of their first marker
        self.input_stamp_ns = 0
        self.subscribed: set[str] = set()
        self.deferred: set[str] = set(ANSWERS_LATER)   # expected outputs that come later
        # Timed mode: while the graph comes up, /clock runs at wall speed from this stamp (so far
        # before the bag's first that it never reaches it), so nodes with use_sim_time have a
        # time that advances (their timers, diagnostics included, run on it) and never see it
        # go backwards when the pass starts.
        self.lead_in_clock_ns: int | None = None

    def _on_output(self, topic: str, raw: bytes, stamp: int) -> None:
        if topic in self.marker_topics:
            stamp = marker_array_stamp_ns(raw, self.input_stamp_ns)
        if topic == '/diagnostics':
            from diagnostic_msgs.msg import DiagnosticArray
            from rclpy.serialization import deserialize_message

            now = time.monotonic()
            for status in deserialize_message(raw, DiagnosticArray).status:
                self.diagnostics_seen[status.name] = now
        if topic not in WALL_PERIODIC_TOPICS:
            self.arrivals += 1
        self.seen[(topic, stamp)] += 1
        if self.current is not None:
            self.current.outputs[topic].append((stamp, bytes(raw)))

    def discover(self) -> None:
        """Subscribe to outputs whose publisher appeared since the last call."""
        for topic in self.recorder.discover():
            self.subscribed.add(topic)
            types = [p.topic_type for p in self.node.get_publishers_info_by_topic(topic)]
            if 'visualization_msgs/msg/MarkerArray' in types:
                self.marker_topics.add(topic)

    def spin(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while True:
            self.executor.spin_once(timeout_sec=min(0.01, max(0.0, deadline - time.monotonic())))
            if time.monotonic() >= deadline:
                return

    def wait_for_graph(self, required_outputs: set[str], timeout_s: float,
                       failed=lambda: [], nodes: tuple[str, ...] = ()) -> None:
        """Until every required output is subscribed, every input publisher is matched, the
        graph has been stable (no new subscriptions or publishers) for a second and each of
        `nodes` has published diagnostics since (so its executor runs and has had time to match
        its own subscriptions; a message sent before two nodes match is lost)."""
        started = time.monotonic()
        deadline = started + timeout_s
        stable_since, last = time.monotonic(), None
        while time.monotonic() < deadline:
            if self.lead_in_clock_ns is not None:
                self.publish_clock(self.lead_in_clock_ns + int((time.monotonic() - started) * 1e9))
            self.spin(0.1)
            if failed():
                raise ReplayError(f'node(s) exited at start-up: {", ".join(failed())}')
            self.discover()
            subscribed = self.subscribed
            matched = all(p.get_subscription_count() > 0 for t, p in self.publishers.items()
                          if self.expectations.get(t))
            graph = tuple(sorted((t, len(self.node.get_publishers_info_by_topic(t)),
                                  len(self.node.get_subscriptions_info_by_topic(t)))
                                 for t, _ in self.node.get_topic_names_and_types()))
            if graph != last:
                stable_since, last = time.monotonic(), graph
            spoken = all(self.diagnostics_seen.get(n, -math.inf) > stable_since for n in nodes)
            if required_outputs <= subscribed and matched and spoken \
                    and time.monotonic() - stable_since >= 1.0:
                return
        missing = sorted(required_outputs - self.subscribed)
        unmatched = sorted(t for t, p in self.publishers.items()
                           if self.expectations.get(t) and p.get_subscription_count() == 0)
        silent = sorted(n for n in nodes if n not in self.diagnostics_seen)
        raise ReplayError(f'the graph did not come up within {timeout_s:g} s: no publisher of '
                          f'{missing or "-"}; no subscriber of {unmatched or "-"}; no diagnostics '
                          f'from {silent or "-"}')

    def publish_clock(self, stamp_ns: int) -> None:
        if self.clock_publisher is None:
            self.clock_publisher = self.node.create_publisher(
                self._clock_class, '/clock', self._clock_qos)
        msg = self._clock_class()
        msg.clock.sec, msg.clock.nanosec = divmod(stamp_ns, 1_000_000_000)
        self.clock_publisher.publish(msg)

    def drain(self, quiet_s: float, timeout_s: float = 60.0) -> None:
        """Until nothing has arrived for quiet_s (the fusion's idle flush included)."""
        deadline = time.monotonic() + timeout_s
        quiet_since, seen = time.monotonic(), self.arrivals
        while time.monotonic() - quiet_since < quiet_s and time.monotonic() < deadline:
            self.spin(0.02)
            if self.arrivals != seen:
                quiet_since, seen = time.monotonic(), self.arrivals

    def close(self) -> None:
        self.node.destroy_node()
        self._rclpy.try_shutdown()


def play_pass(replayer: Replayer, bag: InputBag, inputs: set[str], mode: str, rate: float,
              timeout_s: float, quiet_s: float, progress: str | None,
              settle_after: tuple[str, ...] = DEFAULT_SETTLE_AFTER,
              settle_s: float = 0.002,
              settle_before: dict[str, float] | None = None) -> PassResult:
    """One pass over the bag's inputs; returns what the graph published during it."""
    settle_before = DEFAULT_SETTLE_BEFORE if settle_before is None else settle_before
    result = PassResult()
    replayer.current = result
    started = time.monotonic()
    todo = [(t, s, raw) for t, s, raw in bag.messages if t in inputs]
    # The outputs carry the input's header stamp, which a bag recorded by ROS tools has apart
    # from its bag time (the time of receipt).
    stamped = stamped_topics(bag, inputs)
    first_stamp = todo[0][1] if todo else 0
    next_report = next_discovery = started + 2.0
    deferred_pending: list[tuple[str, int]] = []   # (output, stamp) of outputs that answer later
    for i, (topic, stamp, raw) in enumerate(todo):
        if mode == 'timed':
            due = started + (stamp - first_stamp) * 1e-9 / rate
            while time.monotonic() < due:
                replayer.spin(min(0.005, max(0.0, due - time.monotonic())))
            replayer.publish_clock(stamp)
        if mode == 'lockstep' and settle_before.get(topic, 0.0) > 0.0:
            replayer.spin(settle_before[topic])
        replayer.publishers[topic].publish(raw)
        stamp = header_stamp_ns(raw) if topic in stamped else stamp   # what the outputs carry
        replayer.input_stamp_ns = stamp
        result.inputs_published += 1
        if mode == 'lockstep':
            expected = replayer.expectations.get(topic, ())
            deferred_pending += [(o, stamp) for o in expected if o in replayer.deferred]
            waited_from = time.monotonic()
            deadline = waited_from + timeout_s
            while True:
                pending = [o for o in expected
                           if o not in replayer.deferred and replayer.seen[(o, stamp)] < 1]
                if not pending:
                    break
                if time.monotonic() >= deadline:
                    # A node that buffers (the fusion's reorder window) answers only after later
                    # inputs: from now on that output is not waited for per input; whether every
                    # stamp came is checked at the end of the pass.
                    replayer.deferred.update(pending)
                    deferred_pending += [(o, stamp) for o in pending]
                    print(f'sensing_replay: warning: no {", ".join(pending)} stamped {stamp} ns '
                          f'within {timeout_s:g} s of publishing {topic}; taking it to answer '
                          'later (not waited for per input from now on, counted at the end of '
                          'the pass)', file=sys.stderr, flush=True)
                    break
                replayer.executor.spin_once(timeout_sec=0.005)
            for o in expected:
                if o not in replayer.deferred:
                    replayer.seen.pop((o, stamp), None)
            deferred_pending = [k for k in deferred_pending if replayer.seen[k] < 1]
            while len(deferred_pending) > MAX_OUTSTANDING_LATER \
                    and time.monotonic() < deadline:
                replayer.executor.spin_once(timeout_sec=0.005)
                deferred_pending = [k for k in deferred_pending if replayer.seen[k] < 1]
            # Nothing to wait for when all its outputs answer later: let it land at least.
            if (topic in settle_after or any(o in replayer.deferred for o in expected)) \
                    and settle_s > 0:
                replayer.spin(settle_s)
            result.wait_s[topic] += time.monotonic() - waited_from
        else:
            replayer.executor.spin_once(timeout_sec=0.0)
        now = time.monotonic()
        if now >= next_discovery:   # outputs whose publisher came late
            replayer.discover()
            next_discovery = now + 0.5
        if progress is not None and now >= next_report:
            next_report = now + 2.0
            outputs = sum(len(v) for v in result.outputs.values())
            print(f'  {progress}{i + 1:6d} / {len(todo)} inputs ({100 * (i + 1) / len(todo):3.0f} %), '
                  f'{(stamp - first_stamp) * 1e-9:6.1f} s of bag time, {outputs} outputs',
                  file=sys.stderr, flush=True)
    deadline = time.monotonic() + timeout_s   # the answers still outstanding, then quiet
    while any(replayer.seen[k] < 1 for k in deferred_pending) and time.monotonic() < deadline:
        replayer.spin(0.02)
    replayer.drain(quiet_s)
    for o, stamp in deferred_pending:
        if replayer.seen[(o, stamp)] < 1:
            result.missing[o] += 1
    replayer.seen.clear()
    replayer.current = None
    result.wall_s = time.monotonic() - started
    return result


def write_output_bag(path: Path, bag: InputBag, result: PassResult, output_types: dict[str, str],
                     outputs: set[str], compress: bool = False,
                     offered: dict[str, list] | None = None) -> dict[str, int]:
    """The input bag's topics (all but the graph's outputs) plus what the graph published, each
    with the QoS it was offered with (`offered`: topic -> profiles; else the input bag's)."""
    from sensing_nodes.bag import BagWriter

    offered = offered or {}
    with BagWriter(path, compress=compress) as out:
        for topic, msg_type in bag.types.items():
            if topic not in outputs:
                out.add_topic(topic, msg_type, offered.get(topic, bag.qos.get(topic)) or None)
        for topic in sorted(result.outputs):
            out.add_topic(topic, output_types[topic], offered.get(topic) or None)
        merged = [(s, 0, t, raw) for t, s, raw in bag.messages if t not in outputs]
        merged += [(s, 1, t, raw) for t in sorted(result.outputs) for s, raw in result.outputs[t]]
        # Outputs after the input of the same stamp; each topic keeps its arrival order.
        merged.sort(key=lambda row: (row[0], row[1]))
        for stamp, _, topic, raw in merged:
            out.write_raw(topic, raw, stamp)
        return dict(out.counts)


def _discard(path: Path) -> None:
    if path.exists():
        shutil.rmtree(path, ignore_errors=True)


def replay(bag_path: str | Path, out: str | Path | None, *, mode: str = 'lockstep',
           rate: float = 1.0, expectations: dict[str, tuple[str, ...]] | None = None,
           extra_outputs: tuple[str, ...] = DEFAULT_EXTRA_OUTPUTS, remaps: dict[str, str] | None = None,
           launch: bool = False, nodes: tuple[str, ...] = PROCESSING_NODES,
           node_params: dict[str, list[str]] | None = None, loops: int = 1,
           timeout_s: float = 10.0, quiet_s: float = 1.5, startup_timeout_s: float = 60.0,
           progress: bool = True, logs: Path | None = None,
           compress: bool = False, settle_after: tuple[str, ...] = DEFAULT_SETTLE_AFTER,
           settle_s: float = 0.002, warmup_s: float = 2.0,
           settle_before: dict[str, float] | None = None,
           params_file: Path | None = None, one_process: bool = False) -> list[PassResult]:
    """Replay a bag through the graph (started here when `launch`: with one_process, in one
    sensing_graph process), `loops` times back to back; writes `out` (one pass) or out/pass-K
    (several), complete or not at all."""
    remaps = dict(remaps or {})
    if expectations is None:   # the default table names node inputs: a remapped bag topic feeds one
        published_as = {dst: src for src, dst in remaps.items()}
        expectations = {published_as.get(t, t): o for t, o in DEFAULT_EXPECTATIONS.items()}
    expectations = dict(expectations)
    bag = load_bag(bag_path)
    check_inputs(bag, list(expectations), remaps)
    if params_file is not None and not Path(params_file).is_file():
        from sensing_nodes.paths import config_file

        preset = config_file(f'robots/{params_file}.yaml')    # a preset by name: turtlebot3
        if not preset.is_file():
            raise ReplayError(f'--params-file {params_file}: no such file, and no preset '
                              f'{preset}')
        params_file = preset
    published_names = {remaps.get(t, t) for t in expectations}
    outputs = ({o for outs in expectations.values() for o in outs} | set(extra_outputs)) \
        - published_names
    required = {o for outs in expectations.values() for o in outs}
    if launch:   # every output asked for that a launched node publishes
        required |= outputs & {o for n in nodes for o in NODE_OUTPUTS.get(n, ())}
    out = Path(out) if out is not None else None
    if out is not None and out.exists():
        raise ReplayError(f'{out}: already exists; choose a new output folder')
    # Written under a hidden sibling folder and moved into place only when complete (rosbag2
    # names the .mcap after its folder, so the folder already has its final name there).
    staging = out.with_name(f'.{out.name}.partial') if out is not None else None
    partial = staging / out.name if staging is not None else None
    if staging is not None:
        _discard(staging)
        staging.mkdir(parents=True)

    graph = None
    succeeded = False
    log_dir = Path(tempfile.mkdtemp(prefix='sensing_replay-')) if logs is None else Path(logs)
    replayer = None
    try:
        replayer = Replayer({t: remaps.get(t, t) for t in expectations},
                            {t: bag.types[t] for t in expectations}, outputs, expectations)
        if launch:
            (log_dir / 'logs').mkdir(parents=True, exist_ok=True)
            env = dict(os.environ)
            if mode == 'lockstep':
                # Publish hands the message to every matched reader before it returns, so an
                # output the replay has received is already on its way to the other subscribers
                # (asynchronous publishing sends from a separate thread, later).
                env.setdefault('RMW_FASTRTPS_PUBLICATION_MODE', 'SYNCHRONOUS')
            graph = Graph(log_dir, env, params_file)
            extras = {}
            for name in nodes:
                extra = list((node_params or {}).get(name, []))
                if name == 'complementary_fusion' and mode == 'lockstep' \
                        and not any(a.startswith('flush_after_s:=') for a in extra):
                    # The fusion processes what it holds after flush_after_s of wall time
                    # without input; a lockstep wait that long (a scan match on an overloaded
                    # machine) would flush before the match arrives and change the outputs.
                    extra = ['-p', f'flush_after_s:={LOCKSTEP_FUSION_FLUSH_S}', *extra]
                    quiet_s = max(quiet_s, 1.5 * LOCKSTEP_FUSION_FLUSH_S + 1.0)
                extras[name] = extra
            if one_process:
                graph.start_one_process(nodes, extras)
            else:
                for name in nodes:
                    graph.start(name, extras[name])
        if mode == 'timed':
            replayer.lead_in_clock_ns = next(s for t, s, _ in bag.messages if t in expectations) \
                - int((startup_timeout_s + 1.0) * 1e9)
        try:
            replayer.wait_for_graph(
                required, startup_timeout_s,
                failed=(graph.failed if graph is not None else lambda: []),
                nodes=nodes if launch and '/diagnostics' in outputs else ())
        except (ReplayError, GraphArgumentError) as exc:
            raise ReplayError(f'{exc}; node logs in {log_dir / "logs"}' if launch else str(exc)) \
                from None
        if warmup_s > 0 and launch:
            # Two nodes that have just discovered each other may still be matching: a message
            # sent then is lost. So the first warmup_s of the bag, and at least one message of
            # every input topic (a keyframe log may hold seconds between two scans), goes
            # through first and is discarded. Its stamps are moved after the bag's end, so the
            # pass proper starts with time jumping backwards on every input, which resets every
            # node (the same path every later loop takes), even an input whose first message
            # the warm-up played.
            play_pass(replayer, warm_up_bag(bag, set(expectations), warmup_s),
                      set(expectations), 'lockstep', rate, timeout_s, quiet_s,
                      'warm-up: ' if progress else None, settle_after, settle_s, settle_before)
        results = []
        for k in range(loops):
            label = f'pass {k + 1}/{loops}: ' if loops > 1 else ''
            results.append(play_pass(replayer, bag, set(expectations), mode, rate, timeout_s,
                                     quiet_s, label if progress else None, settle_after,
                                     settle_s, settle_before))
            if graph is not None and graph.failed():
                raise ReplayError(f'node(s) exited during the replay: {", ".join(graph.failed())}; '
                                  f'logs in {log_dir / "logs"}')
        output_types, offered = {}, {}
        for t in replayer.subscribed:
            infos = replayer.node.get_publishers_info_by_topic(t)
            if infos:
                output_types[t] = infos[0].topic_type
                offered[t] = [i.qos_profile for i in infos]
        for t, publisher in replayer.publishers.items():   # the inputs, as the replay offered them
            offered[t] = [publisher.qos_profile]
        for r in results:
            for t in r.outputs:
                if t not in output_types:
                    raise ReplayError(f'output {t}: its publisher vanished before its type was read')
        if partial is not None:
            if loops == 1:
                write_output_bag(partial, bag, results[0], output_types, outputs, compress,
                                 offered)
            else:
                partial.mkdir(parents=True)
                for k, r in enumerate(results):
                    write_output_bag(partial / f'pass-{k + 1}', bag, r, output_types, outputs,
                                     compress, offered)
            partial.rename(out)
        succeeded = True
        return results
    finally:
        if staging is not None:
            _discard(staging)   # empty after success; a partial bag after a failure
        if graph is not None:
            graph.stop()
        if replayer is not None:
            replayer.close()
        if logs is None and (graph is None or succeeded):
            shutil.rmtree(log_dir, ignore_errors=True)   # kept after a failure: it names them


# -- comparing outputs ----------------------------------------------------------------------
# A replay on another CPU (another OpenBLAS kernel: OPENBLAS_CORETYPE) sums in another order, so
# its floats may differ from the recording's in the last bits, and a difference can grow through
# the graph's feedback (fusion, the matcher's initial guess). Floats therefore count as
# reproduced when |a - b| <= ATOL + RTOL * max(|a|, |b|); integers, strings, lengths and bag
# times must be equal. Measured (docs/reproducibility.md): between the SkylakeX, Haswell,
# Sandybridge, Nehalem and Prescott kernels the largest difference was 1.1e-14 absolute, and
# 9.7e-10 relative only on values near zero (covariance cross terms); the worst field used
# 1/1000 of this tolerance, which is still far below what a change of behaviour gives (>= 1e-6).
REPRODUCE_RTOL = 1e-9
REPRODUCE_ATOL = 1e-11


def output_messages(path: str | Path, topics: set[str]) -> dict[str, list[tuple[int, bytes]]]:
    """topic -> [(bag time ns, CDR bytes)] in bag order, for the given topics."""
    from sensing_nodes.bag import BagReader

    out: dict[str, list[tuple[int, bytes]]] = {t: [] for t in topics}
    for topic, stamp, raw in BagReader(path).raw(topics):
        out[topic].append((stamp, raw))
    return out


@dataclass
class Difference:
    """The worst field of a comparison: its path, the absolute difference, and that difference
    over the tolerance at its magnitude (> 1: not reproduced; inf: not a float, or a length)."""

    where: str = ''
    absolute: float = 0.0
    excess: float = 0.0

    def worse(self, other: Difference) -> Difference:
        return other if (other.excess, other.absolute) > (self.excess, self.absolute) else self


def _float_difference(x, y, path: str, rtol: float, atol: float) -> Difference:
    """Element-wise comparison of two float arrays (NaN equals NaN, infinities equal only with
    the same sign)."""
    import numpy as np

    x, y = np.asarray(x, dtype=float).ravel(), np.asarray(y, dtype=float).ravel()
    same = (x == y) | (np.isnan(x) & np.isnan(y))
    if same.all():
        return Difference()
    with np.errstate(invalid='ignore', over='ignore'):
        absolute = np.where(same, 0.0, np.abs(x - y))
        absolute = np.where(np.isnan(absolute), np.inf, absolute)
        excess = absolute / (atol + rtol * np.maximum(np.abs(x), np.abs(y)))
        excess = np.where(np.isnan(excess), np.inf, excess)
    i = int(np.argmax(excess))
    return Difference(f'{path}[{i}]' if x.size > 1 else path, float(absolute[i]), float(excess[i]))


def _cloud_columns(msg) -> dict[str, object] | None:
    """A PointCloud2's data as its declared fields (name -> numpy column), or None when its
    layout is not one numpy can describe."""
    import numpy as np

    kinds = {1: 'i1', 2: 'u1', 3: 'i2', 4: 'u2', 5: 'i4', 6: 'u4', 7: 'f4', 8: 'f8'}
    try:
        dtype = np.dtype({'names': [f.name for f in msg.fields],
                          'formats': [('>' if msg.is_bigendian else '<') + kinds[f.datatype]
                                      + ('' if f.count == 1 else f'({f.count},)')
                                      for f in msg.fields],
                          'offsets': [f.offset for f in msg.fields], 'itemsize': msg.point_step})
        points = np.frombuffer(bytes(msg.data), dtype=dtype, count=msg.width * msg.height)
    except (KeyError, ValueError, TypeError):
        return None
    return {name: points[name] for name in dtype.names}


def message_difference(a, b, path: str = '', rtol: float = REPRODUCE_RTOL,
                       atol: float = REPRODUCE_ATOL) -> Difference:
    """Worst difference between two decoded rclpy messages, every field compared: floats within
    the tolerance, everything else exactly (a PointCloud2's data as its declared fields)."""
    import numpy as np

    if hasattr(a, 'get_fields_and_field_types'):
        worst = Difference()
        fields = a.get_fields_and_field_types()
        columns = None
        if type(a).__name__ == 'PointCloud2' and fields.get('data') == 'sequence<uint8>':
            columns = (_cloud_columns(a), _cloud_columns(b))
        for name in fields:
            if name == 'data' and columns is not None and None not in columns:
                ca, cb = columns
                if list(ca) != list(cb) or any(ca[k].shape != cb[k].shape for k in ca):
                    worst = worst.worse(Difference(f'{path}.data (layout)', math.inf, math.inf))
                    continue
                for k in ca:
                    sub = f'{path}.data.{k}'
                    if ca[k].dtype.kind == 'f':
                        worst = worst.worse(_float_difference(ca[k], cb[k], sub, rtol, atol))
                    elif not np.array_equal(ca[k], cb[k]):
                        worst = worst.worse(Difference(sub, math.inf, math.inf))
                continue
            worst = worst.worse(message_difference(getattr(a, name), getattr(b, name),
                                                   f'{path}.{name}', rtol, atol))
        return worst
    if isinstance(a, (bytes, str, bool, int)) or a is None:
        return Difference() if type(a) is type(b) and a == b else \
            Difference(path, math.inf, math.inf)
    if isinstance(a, float):
        return _float_difference(a, b, path, rtol, atol)
    # Sequences and arrays: array.array, numpy arrays, lists of messages or strings.
    if len(a) != len(b):
        return Difference(f'{path} (length {len(a)} vs {len(b)})', math.inf, math.inf)
    if len(a) == 0:
        return Difference()
    kind = np.asarray(a).dtype.kind if not hasattr(a[0], 'get_fields_and_field_types') else 'O'
    if kind == 'f':
        return _float_difference(a, b, path, rtol, atol)
    if kind in 'iub':
        x, y = np.asarray(a), np.asarray(b)
        if np.array_equal(x, y):
            return Difference()
        i = int(np.argmax(x != y))
        return Difference(f'{path}[{i}]', math.inf, math.inf)
    worst = Difference()
    for i, (u, v) in enumerate(zip(a, b)):
        worst = worst.worse(message_difference(u, v, f'{path}[{i}]', rtol, atol))
    return worst


def compare_outputs(expected: dict[str, list[tuple[int, bytes]]],
                    actual: dict[str, list[tuple[int, bytes]]],
                    types: dict[str, str]) -> dict[str, dict]:
    """Per topic: message counts, how many are byte-identical (in canonical CDR), the worst
    difference among the others (absolute, and relative to the tolerance: 'excess' <= 1 is
    reproduced) and whether the topic is reproduced (same count, every message within it)."""
    from rclpy.serialization import deserialize_message

    from sensing_nodes.bag import canonical_cdr, message_class

    report = {}
    for topic in sorted(set(expected) | set(actual)):
        a, b = expected.get(topic, []), actual.get(topic, [])
        entry = {'expected': len(a), 'actual': len(b), 'identical': 0, 'max_difference': 0.0,
                 'excess': 0.0, 'where': ''}
        cls = message_class(types[topic])
        worst = Difference()
        for (sa, ra), (sb, rb) in zip(a, b):
            if sa == sb and (ra == rb or canonical_cdr(ra, types[topic])
                             == canonical_cdr(rb, types[topic])):
                entry['identical'] += 1
                continue
            if sa != sb:
                d = Difference(f'bag time {sa} vs {sb}', math.inf, math.inf)
            else:
                d = message_difference(deserialize_message(ra, cls), deserialize_message(rb, cls))
            d.where = f'stamp {sa}: {d.where}'
            worst = worst.worse(d)
        entry.update(max_difference=worst.absolute, excess=worst.excess, where=worst.where)
        entry['reproduced'] = len(a) == len(b) and worst.excess <= 1.0
        entry['byte_identical'] = len(a) == len(b) == entry['identical']
        report[topic] = entry
    return report


def _find_executables_next_to_python() -> None:
    """`python -m sensing_nodes.tools.replay` from a venv: its bin/ holds the node executables
    (ros.graph.executable looks next to sys.argv[0], then on PATH)."""
    bin_dir = Path(sys.executable).parent
    if (bin_dir / 'wheel_odometry').is_file() and str(bin_dir) not in os.environ['PATH'].split(os.pathsep):
        os.environ['PATH'] = str(bin_dir) + os.pathsep + os.environ.get('PATH', '')


# -- the project's bags ---------------------------------------------------------------------
def make_bags(folder: str | Path, names: list[str] | None = None, progress: bool = True) -> None:
    """Regenerate bags/<name>: inputs recorded with `sensor_sim --record`, outputs by a lockstep
    replay through the real node processes."""
    from sensing_nodes.paths import config_file

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for name in names or list(BAG_SPECS):
        params_file, seed, duration = BAG_SPECS[name]
        with tempfile.TemporaryDirectory(prefix='sensing_bags-') as tmp:
            inputs = Path(tmp) / 'inputs'
            subprocess.run([executable('sensor_sim'), '--record', str(inputs), '--duration',
                            str(duration), '--seed', str(seed), '--params-file',
                            str(config_file(params_file)), '--quiet'], check=True)
            target = folder / name
            _discard(target)
            results = replay(inputs, target, launch=True, progress=progress, compress=True)
            missing = dict(results[0].missing)
            if missing:
                _discard(target)
                raise ReplayError(f'{name}: outputs missing in the lockstep replay: {missing}')
        size = sum(p.stat().st_size for p in target.iterdir())
        print(f'sensing_replay: wrote {target} ({size / 1e6:.2f} MB)')


# -- command line ---------------------------------------------------------------------------
def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog='sensing_replay', description=__doc__.split('\n\n')[0])
    parser.add_argument('bag', nargs='?', help='input bag: a rosbag2 folder (MCAP or sqlite3) or a '
                        'ROS 1 .bag file')
    parser.add_argument('out', nargs='?', help='output bag folder to create (inputs + outputs)')
    parser.add_argument('--mode', choices=('lockstep', 'timed'), default='lockstep')
    parser.add_argument('--rate', type=float, default=1.0,
                        help='timed mode: bag seconds per wall second (default 1)')
    parser.add_argument('--expect', action='append', default=[], metavar='IN=OUT[,OUT]',
                        help='expectation table entry (replaces the default table when given): '
                             'an input topic and the outputs carrying its stamp; OUT may be empty')
    parser.add_argument('--record', action='append', default=None, metavar='TOPIC',
                        help='further outputs recorded as they come (default: '
                             + ' '.join(DEFAULT_EXTRA_OUTPUTS) + ')')
    parser.add_argument('--remap', action='append', default=[], metavar='BAG_TOPIC:=TOPIC',
                        help='publish a bag topic under another name (the default expectation '
                             'table then applies to it, e.g. /imu:=/imu/data_raw)')
    parser.add_argument('--launch', action='store_true',
                        help="start the package's processing nodes (config/ parameter files)")
    parser.add_argument('--nodes', default=','.join(PROCESSING_NODES),
                        help='with --launch: which nodes (comma separated)')
    parser.add_argument('--one-process', action='store_true',
                        help='with --launch: the nodes in one process (sensing_graph)')
    parser.add_argument('--param', action='append', default=[], metavar='NODE:NAME:=VALUE',
                        help='with --launch: a parameter override for one node')
    parser.add_argument('--params-file', type=Path, default=None,
                        help='with --launch: a parameter file read after each node\'s own in '
                             'config/, e.g. a robot preset: config/robots/turtlebot3.yaml, or '
                             'its name, turtlebot3')
    parser.add_argument('--loops', type=int, default=1,
                        help='play the bag this many times back to back (time jumps backwards); '
                             'outputs go to OUT/pass-K')
    parser.add_argument('--timeout', type=float, default=10.0,
                        help='lockstep: wall seconds to wait for an input\'s outputs (default 10)')
    parser.add_argument('--quiet-s', type=float, default=1.5,
                        help='end of a pass: wall seconds without output before it is over '
                             '(longer than the fusion\'s flush_after_s)')
    parser.add_argument('--settle-ms', type=float, default=2.0,
                        help='lockstep: wall ms to spin after the outputs of a --settle-after '
                             'input arrived (default 2)')
    parser.add_argument('--settle-after', action='append', default=None, metavar='TOPIC',
                        help='inputs followed by the settle time (default: '
                             + ' '.join(DEFAULT_SETTLE_AFTER) + ')')
    parser.add_argument('--settle-before', action='append', default=None, metavar='TOPIC=MS',
                        help='lockstep: wall ms to spin before publishing that input (default: '
                             + ' '.join(f'{t}={1e3 * v:g}' for t, v in DEFAULT_SETTLE_BEFORE.items())
                             + '); TOPIC=0 turns one off')
    parser.add_argument('--warmup-s', type=float, default=2.0,
                        help='with --launch: first play this much of the bag (bag seconds) and '
                             'discard the outputs, so every link of the graph is matched before '
                             'the pass that counts (0: no warm-up)')
    parser.add_argument('--logs', type=Path, default=None, help='with --launch: keep node logs here')
    parser.add_argument('--make-bags', metavar='DIR', default=None,
                        help="regenerate the project's bags (" + ', '.join(BAG_SPECS) + ') in DIR')
    parser.add_argument('--check', action='store_true',
                        help='compare the outputs with those recorded in BAG; exit 1 if any differ')
    parser.add_argument('--compress', action='store_true',
                        help='zstd-compress the output bag\'s MCAP chunks')
    parser.add_argument('--no-progress', action='store_true')
    args = parser.parse_args(argv)
    if args.make_bags is None and (args.bag is None or args.out is None):
        parser.error('give BAG and OUT (or --make-bags DIR)')
    if not (args.rate > 0 and args.timeout > 0 and args.loops >= 1 and args.quiet_s > 0):
        parser.error('--rate, --timeout and --quiet-s must be > 0 and --loops >= 1')
    return args


def _settle_before(specs: list[str] | None) -> dict[str, float] | None:
    if specs is None:
        return None
    table = dict(DEFAULT_SETTLE_BEFORE)
    for spec in specs:
        topic, sep, ms = spec.partition('=')
        try:
            table[topic] = float(ms) * 1e-3
        except ValueError:
            raise ReplayError(f'--settle-before {spec!r}: write TOPIC=MS') from None
        if not sep or table[topic] < 0:
            raise ReplayError(f'--settle-before {spec!r}: write TOPIC=MS with MS >= 0')
    return table


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    _find_executables_next_to_python()
    signal.signal(signal.SIGTERM, _interrupt)  # a killed replay still stops its nodes
    try:
        if args.make_bags is not None:
            make_bags(args.make_bags, progress=not args.no_progress)
            return 0
        remaps = parse_remaps(args.remap)
        nodes = parse_nodes(args.nodes)
        results = replay(
            args.bag, args.out, mode=args.mode, rate=args.rate,
            expectations=parse_expectations(args.expect) if args.expect else None,
            extra_outputs=tuple(args.record) if args.record is not None else DEFAULT_EXTRA_OUTPUTS,
            remaps=remaps, launch=args.launch, nodes=nodes,
            node_params=parse_node_params(args.param), loops=args.loops, timeout_s=args.timeout,
            quiet_s=args.quiet_s, progress=not args.no_progress, logs=args.logs,
            compress=args.compress, settle_s=args.settle_ms * 1e-3, warmup_s=args.warmup_s,
            settle_before=_settle_before(args.settle_before), params_file=args.params_file,
            one_process=args.one_process,
            settle_after=(tuple(args.settle_after) if args.settle_after is not None
                          else DEFAULT_SETTLE_AFTER))
    except (ReplayError, GraphArgumentError) as exc:
        print(f'sensing_replay: error: {exc}', file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print('sensing_replay: interrupted; no output written', file=sys.stderr)
        return 130
    for k, r in enumerate(results):
        counts = ', '.join(f'{t} {len(v)}' for t, v in sorted(r.outputs.items()))
        missing = sum(r.missing.values())
        print(f'sensing_replay: pass {k + 1}: {r.inputs_published} inputs in {r.wall_s:.1f} s; '
              f'outputs: {counts}' + (f'; MISSING {dict(r.missing)}' if missing else ''))
        print('  waiting for outputs per input topic: ' + ', '.join(
            f'{t} {s:.1f} s' for t, s in sorted(r.wait_s.items())))
    print(f'sensing_replay: wrote {args.out}')
    failed = any(r.missing for r in results)
    if args.check:
        failed |= not check_against(Path(args.bag), results)
    return EXIT_FAILED if failed else 0


def check_against(recorded: Path, results: list[PassResult]) -> bool:
    """Print, per pass and output topic, whether the replay reproduced the bag's recorded
    outputs (the topics both have, /diagnostics aside): floats within the tolerance (the bag may
    come from another CPU), the rest exactly. Passes after the first must equal the first byte
    for byte (canonical CDR): one process on one CPU is deterministic. True when all hold."""
    from sensing_nodes.bag import topic_counts

    types = {t: v[0] for t, v in topic_counts(recorded).items()}
    topics = {t for r in results for t in r.outputs} & set(types) - WALL_PERIODIC_TOPICS
    expected = output_messages(recorded, topics)
    ok = True
    for k, r in enumerate(results):
        report = compare_outputs(expected, {t: r.outputs.get(t, []) for t in topics}, types)
        for topic, e in report.items():
            ok &= e['reproduced']
            print(f"  check pass {k + 1} {topic:<22} "
                  f"{'reproduced' if e['reproduced'] else 'DIFFERS'}: "
                  f"{e['identical']} of {e['expected']} byte-identical"
                  + (f", {e['actual']} replayed" if e['actual'] != e['expected'] else '')
                  + (f", largest difference {e['max_difference']:.3g} "
                     f"({e['excess']:.3g} x tolerance) at {e['where']}"
                     if e['identical'] != e['expected'] else ''))
        if k > 0:
            same = compare_outputs({t: results[0].outputs.get(t, []) for t in topics},
                                   {t: r.outputs.get(t, []) for t in topics}, types)
            for topic, e in same.items():
                ok &= e['byte_identical']
                print(f"  check pass {k + 1} {topic:<22} "
                      f"{'identical to pass 1' if e['byte_identical'] else 'DIFFERS FROM PASS 1'}"
                      + ('' if e['byte_identical'] else
                         f": {e['identical']} of {e['expected']} byte-identical, "
                         f"largest difference {e['max_difference']:.3g} at {e['where']}"))
    return ok


if __name__ == '__main__':
    sys.exit(main())
