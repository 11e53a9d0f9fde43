"""Playing a bag's input topics into the running nodes over DDS and recording what they publish
(sensing_replay; docs/tools.md).

Lockstep (default): publish one input message, wait until the nodes have published what it
causes (the expectation table: input topic -> output topics, each carrying the input's stamp),
then the next; deterministic. Timed: respects the stamps, scaled by rate, and publishes /clock.
With launch the package's processing nodes are started (graph/processes.py) and stopped here.
"""

from __future__ import annotations

import math
import os
import shutil
import sys
import tempfile
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

from sensing_nodes.bags.input_bag import (
    InputBag,
    InputBagError,
    PassResult,
    check_inputs,
    discard,
    load_bag,
    stamped_topics,
    warm_up_bag,
    write_output_bag,
)
from sensing_nodes.bags.stamps import SEQUENCE_OF_STAMPED, first_element_stamp_ns, leading_stamp_ns
from sensing_nodes.graph.cli import GraphArgumentError, params_file_path
from sensing_nodes.graph.processes import Graph
from sensing_nodes.topics import (
    ANSWERS,
    CLOCK,
    DIAGNOSTICS,
    FUSED,
    JOINT_STATES,
    NODES,
    PROCESSING_NODES,
    SCAN,
    SCAN_MATCH,
    SENSOR_TOPICS,
    TF,
    WALL_PERIODIC_TOPICS,
    WHEEL_ODOM,
)

# Input topic -> output topics that carry its stamp (one message each), for this package's graph.
DEFAULT_EXPECTATIONS: dict[str, tuple[str, ...]] = dict(ANSWERS)
# Inputs whose outputs feed another node that acts on them at its next input without ordering
# by stamp (/wheel/odom: the gyro's stillness veto, the scan matcher's initial guess). Their
# outputs reach the replay and those nodes over separate DDS paths, so after them the replay
# lets the fan-out land (settle) before it publishes the next input.
DEFAULT_SETTLE_AFTER = (JOINT_STATES,)
# ... and before these inputs it lets everything published so far land (the scan matcher acts on
# the odometry it holds when a scan arrives).
DEFAULT_SETTLE_BEFORE = {SCAN: 0.010}
# Outputs of nodes that buffer their inputs (the fusion's reorder window: it answers an input
# once the other inputs have caught up, or after its idle flush): an expectation naming one is
# not waited for per input; the end of the pass checks that every stamp came.
ANSWERS_LATER = (FUSED,)
# ... but at most this many of their answers may be outstanding: a node that releases a burst of
# held outputs must not overrun the recording subscription (reliable, keep last 100).
MAX_OUTSTANDING_LATER = 50
# Lockstep with --launch: the fusion's idle flush (wall time without input), unless --param sets
# it; the end of a pass then waits for quiet a second longer than the flush can take (its
# timer looks every flush_after_s / 2).
LOCKSTEP_FUSION_FLUSH_S = 2.0
# The fusion answers each of these inputs with a message carrying its stamp, in stamp order, and
# its idle flush answers everything it holds at once: once the answer to the latest of them is
# in, no flush is still to come and the end of a pass needs only the ordinary quiet.
FUSION_ANSWERED = (WHEEL_ODOM, SCAN_MATCH)
# Outputs that are not 1:1 with an input: recorded as they come.
DEFAULT_EXTRA_OUTPUTS = (FUSED, DIAGNOSTICS, TF)


class ReplayError(InputBagError):
    """Bad input or a graph that did not come up: the message names the file and topic."""


@dataclass(frozen=True)
class FlushWait:
    """The end of a lockstep pass through a node that buffers its inputs: `output` answers each
    of `sources` with its stamp once flushed; without the answer to the latest, wait until
    nothing has arrived for quiet_s (longer than the node's idle flush can take)."""

    output: str
    sources: tuple[str, ...]
    quiet_s: float


class Replayer:
    """One rclpy node publishing a bag's inputs and recording the graph's outputs."""

    def __init__(self, inputs: dict[str, str], input_types: dict[str, str],
                 outputs: set[str], expectations: dict[str, tuple[str, ...]]) -> None:
        import rclpy
        from rclpy.node import Node

        from sensing_nodes.bags.storage import message_class
        from sensing_nodes.graph.recorder import TopicRecorder
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
        # Latest stamp (ns) per topic in this pass, published or received (see flush_wait).
        self.latest_stamp_ns: dict[str, int] = {}
        self.current: PassResult | None = None
        listeners = {t: (lambda raw, stamp, wall, t=t: self._on_output(t, raw, stamp))
                     for t in outputs}
        self.recorder = TopicRecorder(self.node, None, listeners, only=outputs)
        self.diagnostics_seen: dict[str, float] = {}  # node name -> wall time of its last status
        # Outputs that are a sequence of stamped messages (MarkerArray, TFMessage): their bag
        # time is their first element's stamp.
        self.sequence_topics: set[str] = set()
        self.input_stamp_ns = 0
        self.subscribed: set[str] = set()
        self.deferred: set[str] = set(ANSWERS_LATER)   # expected outputs that come later
        # Timed mode: while the graph comes up, /clock runs at wall speed from this stamp (so far
        # before the bag's first that it never reaches it), so nodes with use_sim_time have a
        # time that advances (their timers, diagnostics included, run on it) and never see it
        # go backwards when the pass starts.
        self.lead_in_clock_ns: int | None = None

    def _on_output(self, topic: str, raw: bytes, stamp: int) -> None:
        if topic in self.sequence_topics:
            stamp = first_element_stamp_ns(raw, self.input_stamp_ns)
        if topic == DIAGNOSTICS:
            from diagnostic_msgs.msg import DiagnosticArray
            from rclpy.serialization import deserialize_message

            now = time.monotonic()
            for status in deserialize_message(raw, DiagnosticArray).status:
                self.diagnostics_seen[status.name] = now
        if topic not in WALL_PERIODIC_TOPICS:
            self.arrivals += 1
        self.seen[(topic, stamp)] += 1
        self.latest_stamp_ns[topic] = max(stamp, self.latest_stamp_ns.get(topic, stamp))
        if self.current is not None:
            self.current.outputs[topic].append((stamp, bytes(raw)))

    def discover(self) -> None:
        """Subscribe to outputs whose publisher appeared since the last call."""
        for topic in self.recorder.discover():
            self.subscribed.add(topic)
            types = [p.topic_type for p in self.node.get_publishers_info_by_topic(topic)]
            if SEQUENCE_OF_STAMPED & set(types):
                self.sequence_topics.add(topic)

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
                self._clock_class, CLOCK, self._clock_qos)
        msg = self._clock_class()
        msg.clock.sec, msg.clock.nanosec = divmod(stamp_ns, 1_000_000_000)
        self.clock_publisher.publish(msg)

    def drain(self, quiet_s: float, timeout_s: float = 60.0) -> None:
        """Until nothing has arrived for quiet_s (the fusion's idle flush included)."""
        from sensing_nodes.ros.run import spin_until_quiet

        spin_until_quiet(self.executor, lambda: self.arrivals, quiet_s, timeout_s)

    def wait_for_flush(self, wait: FlushWait, timeout_s: float = 60.0) -> None:
        """Until wait.output carries a stamp at least the latest of wait.sources (the buffering
        node has answered everything it holds), or nothing has arrived for wait.quiet_s."""
        from sensing_nodes.ros.run import spin_until_quiet

        latest = [self.latest_stamp_ns[t] for t in wait.sources if t in self.latest_stamp_ns]
        target = max(latest) if latest else math.inf
        spin_until_quiet(self.executor, lambda: self.arrivals, wait.quiet_s, timeout_s,
                         done=lambda: self.latest_stamp_ns.get(wait.output, -1) >= target)

    def close(self) -> None:
        self.node.destroy_node()
        self._rclpy.try_shutdown()


def play_pass(replayer: Replayer, bag: InputBag, inputs: set[str], mode: str, rate: float,
              timeout_s: float, quiet_s: float, progress: str | None,
              settle_after: tuple[str, ...] = DEFAULT_SETTLE_AFTER,
              settle_s: float = 0.002,
              settle_before: dict[str, float] | None = None,
              flush: FlushWait | None = None) -> PassResult:
    """One pass over the bag's inputs; returns what the graph published during it."""
    settle_before = DEFAULT_SETTLE_BEFORE if settle_before is None else settle_before
    result = PassResult()
    replayer.current = result
    replayer.latest_stamp_ns = {}
    started = time.monotonic()
    todo = [(t, s, raw) for t, s, raw in bag.messages if t in inputs]
    # The outputs carry the input's header stamp, which a bag recorded by ROS tools has apart
    # from its bag time (the time of receipt).
    stamped = stamped_topics(bag, inputs)
    published_as = {t: publisher.topic_name for t, publisher in replayer.publishers.items()}
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
        stamp = leading_stamp_ns(raw) if topic in stamped else stamp   # what the outputs carry
        replayer.input_stamp_ns = stamp
        published = published_as[topic]
        replayer.latest_stamp_ns[published] = max(stamp, replayer.latest_stamp_ns.get(published,
                                                                                   stamp))
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
            print(
                f'  {progress}{i + 1:6d} / {len(todo)} inputs '
                f'({100 * (i + 1) / len(todo):3.0f} %), '
                f'{(stamp - first_stamp) * 1e-9:6.1f} s of bag time, {outputs} outputs',
                file=sys.stderr,
                flush=True,
            )
    deadline = time.monotonic() + timeout_s   # the answers still outstanding, then quiet
    while any(replayer.seen[k] < 1 for k in deferred_pending) and time.monotonic() < deadline:
        replayer.spin(0.02)
    if flush is not None:
        replayer.wait_for_flush(flush)
    replayer.drain(quiet_s)
    for o, stamp in deferred_pending:
        if replayer.seen[(o, stamp)] < 1:
            result.missing[o] += 1
    replayer.seen.clear()
    replayer.current = None
    result.wall_s = time.monotonic() - started
    return result



def replay(
    bag_path: str | Path,
    out: str | Path | None,
    *,
    mode: str = 'lockstep',
    rate: float = 1.0,
    expectations: dict[str, tuple[str, ...]] | None = None,
    extra_outputs: tuple[str, ...] = DEFAULT_EXTRA_OUTPUTS,
    remaps: dict[str, str] | None = None,
    launch: bool = False,
    nodes: tuple[str, ...] = PROCESSING_NODES,
    node_params: dict[str, list[str]] | None = None,
    loops: int = 1,
    timeout_s: float = 10.0,
    quiet_s: float = 1.5,
    startup_timeout_s: float = 60.0,
    progress: bool = True,
    logs: Path | None = None,
    compress: bool = False,
    settle_after: tuple[str, ...] = DEFAULT_SETTLE_AFTER,
    settle_s: float = 0.002,
    warmup_s: float = 2.0,
    settle_before: dict[str, float] | None = None,
    params_file: Path | None = None,
    one_process: bool = False,
) -> list[PassResult]:
    """Replay a bag through the graph (started here when `launch`: with one_process, in one
    sensing_graph process), `loops` times back to back; writes `out` (one pass) or out/pass-K
    (several), complete or not at all."""
    remaps = dict(remaps or {})
    # the default table names node inputs: a remapped bag topic feeds one
    if expectations is None:
        published_as = {dst: src for src, dst in remaps.items()}
        expectations = {published_as.get(t, t): o for t, o in DEFAULT_EXPECTATIONS.items()}
    expectations = dict(expectations)
    bag = load_bag(bag_path)
    check_inputs(bag, list(expectations), remaps)
    if params_file is not None:
        try:
            params_file = params_file_path(params_file)
        except GraphArgumentError as exc:
            raise ReplayError(str(exc)) from None
    published_names = {remaps.get(t, t) for t in expectations}
    outputs = ({o for outs in expectations.values() for o in outs} | set(extra_outputs)) \
        - published_names
    required = {o for outs in expectations.values() for o in outs}
    if launch:   # every output asked for that a launched node publishes
        required |= outputs & {o for n in nodes for o in NODES[n].outputs}
    out = Path(out) if out is not None else None
    if out is not None and out.exists():
        raise ReplayError(f'{out}: already exists; choose a new output folder')
    # Written under a hidden sibling folder and moved into place only when complete (rosbag2
    # names the .mcap after its folder, so the folder already has its final name there).
    staging = out.with_name(f'.{out.name}.partial') if out is not None else None
    partial = staging / out.name if staging is not None else None
    if staging is not None:
        discard(staging)
        staging.mkdir(parents=True)

    graph = None
    flush = None       # the fusion's end of pass, when it is launched in lockstep
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
                    flush = FlushWait(FUSED, FUSION_ANSWERED,
                                      max(quiet_s, 1.5 * LOCKSTEP_FUSION_FLUSH_S + 1.0))
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
                nodes=nodes if launch and DIAGNOSTICS in outputs else ())
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
                      'warm-up: ' if progress else None, settle_after, settle_s, settle_before,
                      flush)
        results = []
        for k in range(loops):
            label = f'pass {k + 1}/{loops}: ' if loops > 1 else ''
            results.append(play_pass(replayer, bag, set(expectations), mode, rate, timeout_s,
                                     quiet_s, label if progress else None, settle_after,
                                     settle_s, settle_before, flush))
            if graph is not None and graph.failed():
                raise ReplayError(
                    f'node(s) exited during the replay: {", ".join(graph.failed())}; '
                    f'logs in {log_dir / "logs"}'
                )
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
                    raise ReplayError(
                        f'output {t}: its publisher vanished before its type was read'
                    )
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
            discard(staging)   # empty after success; a partial bag after a failure
        if graph is not None:
            graph.stop()
        if replayer is not None:
            replayer.close()
        if logs is None and (graph is None or succeeded):
            shutil.rmtree(log_dir, ignore_errors=True)   # kept after a failure: it names them
