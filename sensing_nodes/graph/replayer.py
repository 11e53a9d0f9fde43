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
from dataclasses import dataclass, field, replace
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
from sensing_nodes.bags.stamps import (
    SEQUENCE_OF_STAMPED,
    first_element_stamp_ns,
    leading_stamp_ns,
    stamp_reader,
)
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
# The warm-up (bag seconds) before a launched graph's pass, unless --warmup-s says otherwise; a
# graph already running gets one only when asked (its pass starts with time jumping back).
LAUNCHED_WARMUP_S = 2.0
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
        from sensing_nodes.ros.qos import CLOCK_QOS, topic_qos
        from sensing_nodes.ros.run import make_executor

        self._rclpy = rclpy
        rclpy.init(args=['sensing_replay'])  # never the tool's own argv (its ':=' are not ROS's)
        self.node = Node('sensing_replay')
        self.executor = make_executor()
        self.executor.add_node(self.node)
        self.expectations = expectations
        self.publishers = {}
        for topic, published in inputs.items():
            self.publishers[topic] = self.node.create_publisher(
                message_class(input_types[topic]), published, topic_qos(published))
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


@dataclass(frozen=True)
class PassSettings:
    """How a pass publishes the inputs and waits for the graph's answers (play_pass): 'lockstep'
    (each input's answers awaited, timeout_s at most) or 'timed' (the stamps' pace times rate),
    then quiet_s without arrivals ends the pass."""

    mode: str = 'lockstep'
    rate: float = 1.0
    timeout_s: float = 10.0
    quiet_s: float = 1.5
    settle_after: tuple[str, ...] = DEFAULT_SETTLE_AFTER
    settle_s: float = 0.002
    settle_before: tuple[tuple[str, float], ...] = tuple(DEFAULT_SETTLE_BEFORE.items())
    flush: FlushWait | None = None     # the fusion's end of pass, when it is launched


@dataclass(frozen=True)
class ReplayOptions:
    """What sensing_replay plays, launches and writes (replay)."""

    passes: PassSettings = PassSettings()
    expectations: dict[str, tuple[str, ...]] | None = None   # None: this package's graph
    extra_outputs: tuple[str, ...] = DEFAULT_EXTRA_OUTPUTS
    remaps: dict[str, str] = field(default_factory=dict)
    launch: bool = False
    nodes: tuple[str, ...] = PROCESSING_NODES
    node_params: dict[str, list[str]] = field(default_factory=dict)
    params_file: Path | None = None
    one_process: bool = False
    loops: int = 1
    startup_timeout_s: float = 60.0
    warmup_s: float | None = None   # None: LAUNCHED_WARMUP_S with launch, else none
    progress: bool = True
    logs: Path | None = None
    compress: bool = False


class _Pass:
    """One pass's bookkeeping: what was published, which answers are outstanding."""

    def __init__(self, replayer: Replayer, bag: InputBag, inputs: set[str],
                 settings: PassSettings, progress: str | None) -> None:
        self.replayer, self.settings, self.progress = replayer, settings, progress
        self.result = PassResult()
        self.started = time.monotonic()
        self.todo = [(t, s, raw) for t, s, raw in bag.messages if t in inputs]
        # The outputs carry the input's header stamp, which a bag recorded by ROS tools has
        # apart from its bag time (the time of receipt).
        self.stamped = stamped_topics(bag, inputs)
        self.published_as = {t: pub.topic_name for t, pub in replayer.publishers.items()}
        self.first_stamp = self.todo[0][1] if self.todo else 0
        self.next_report = self.next_discovery = self.started + 2.0
        self.later: list[tuple[str, int]] = []   # (output, stamp) of answers that come later
        replayer.current = self.result
        replayer.latest_stamp_ns = {}

    def publish(self, topic: str, bag_stamp: int, raw: bytes) -> int:
        """Publish one input (paced in timed mode); the stamp its answers carry."""
        replayer, settings = self.replayer, self.settings
        if settings.mode == 'timed':
            due = self.started + (bag_stamp - self.first_stamp) * 1e-9 / settings.rate
            while time.monotonic() < due:
                replayer.spin(min(0.005, max(0.0, due - time.monotonic())))
            replayer.publish_clock(bag_stamp)
        settle = dict(settings.settle_before).get(topic, 0.0)
        if settings.mode == 'lockstep' and settle > 0.0:
            replayer.spin(settle)
        replayer.publishers[topic].publish(raw)
        stamp = leading_stamp_ns(raw) if topic in self.stamped else bag_stamp
        replayer.input_stamp_ns = stamp
        published = self.published_as[topic]
        replayer.latest_stamp_ns[published] = max(stamp, replayer.latest_stamp_ns.get(published,
                                                                                   stamp))
        self.result.inputs_published += 1
        return stamp

    def await_answers(self, topic: str, stamp: int) -> None:
        """Lockstep: until every output expected of this input has come with its stamp (or it
        is taken to answer later), and the outstanding later answers are few enough."""
        replayer, settings = self.replayer, self.settings
        expected = replayer.expectations.get(topic, ())
        self.later += [(o, stamp) for o in expected if o in replayer.deferred]
        waited_from = time.monotonic()
        deadline = waited_from + settings.timeout_s
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
                self.later += [(o, stamp) for o in pending]
                print(f'sensing_replay: warning: no {", ".join(pending)} stamped {stamp} ns '
                      f'within {settings.timeout_s:g} s of publishing {topic}; taking it to '
                      'answer later (not waited for per input from now on, counted at the end '
                      'of the pass)', file=sys.stderr, flush=True)
                break
            replayer.executor.spin_once(timeout_sec=0.005)
        for o in expected:
            if o not in replayer.deferred:
                replayer.seen.pop((o, stamp), None)
        self.later = [k for k in self.later if replayer.seen[k] < 1]
        while len(self.later) > MAX_OUTSTANDING_LATER and time.monotonic() < deadline:
            replayer.executor.spin_once(timeout_sec=0.005)
            self.later = [k for k in self.later if replayer.seen[k] < 1]
        # Nothing to wait for when all its outputs answer later: let it land at least.
        if (topic in settings.settle_after or any(o in replayer.deferred for o in expected)) \
                and settings.settle_s > 0:
            replayer.spin(settings.settle_s)
        self.result.wait_s[topic] += time.monotonic() - waited_from

    def housekeeping(self, done: int, stamp: int) -> None:
        """Outputs whose publisher came late, and a progress line every 2 s."""
        now = time.monotonic()
        if now >= self.next_discovery:
            self.replayer.discover()
            self.next_discovery = now + 0.5
        if self.progress is not None and now >= self.next_report:
            self.next_report = now + 2.0
            outputs = sum(len(v) for v in self.result.outputs.values())
            print(f'  {self.progress}{done:6d} / {len(self.todo)} inputs '
                  f'({100 * done / len(self.todo):3.0f} %), '
                  f'{(stamp - self.first_stamp) * 1e-9:6.1f} s of bag time, {outputs} outputs',
                  file=sys.stderr, flush=True)

    def finish(self) -> PassResult:
        """The answers still outstanding, then quiet; what never came is counted missing."""
        replayer, settings = self.replayer, self.settings
        deadline = time.monotonic() + settings.timeout_s
        while any(replayer.seen[k] < 1 for k in self.later) and time.monotonic() < deadline:
            replayer.spin(0.02)
        if settings.flush is not None:
            replayer.wait_for_flush(settings.flush)
        replayer.drain(settings.quiet_s)
        for o, stamp in self.later:
            if replayer.seen[(o, stamp)] < 1:
                self.result.missing[o] += 1
        replayer.seen.clear()
        replayer.current = None
        self.result.wall_s = time.monotonic() - self.started
        return self.result


def play_pass(replayer: Replayer, bag: InputBag, inputs: set[str], settings: PassSettings,
              progress: str | None = None) -> PassResult:
    """One pass over the bag's inputs; returns what the graph published during it."""
    run = _Pass(replayer, bag, inputs, settings, progress)
    for i, (topic, bag_stamp, raw) in enumerate(run.todo):
        stamp = run.publish(topic, bag_stamp, raw)
        if settings.mode == 'lockstep':
            run.await_answers(topic, stamp)
        else:
            replayer.executor.spin_once(timeout_sec=0.0)
        run.housekeeping(i + 1, stamp)
    return run.finish()


def _stamp_span(bag: InputBag) -> tuple[int, int]:
    """The earliest and latest stamp (ns) the bag's messages carry (header, else bag time)."""
    readers = {topic: stamp_reader(kind) for topic, kind in bag.types.items()}
    stamps = [readers[topic](raw, stamp) for topic, stamp, raw in bag.messages]
    return min(stamps), max(stamps)


def _drop_stamped_within(result: PassResult, first_ns: int, last_ns: int) -> None:
    """Remove the pass's answers to inputs (every output but the timer-driven /diagnostics,
    stamped by a node's clock) stamped within [first_ns, last_ns]."""
    for topic, rows in result.outputs.items():
        if topic not in WALL_PERIODIC_TOPICS:
            rows[:] = [row for row in rows if not first_ns <= row[0] <= last_ns]


@dataclass(frozen=True)
class _Plan:
    """What a replay publishes (inputs: bag topic -> published name), expects and records."""

    expectations: dict[str, tuple[str, ...]]
    inputs: dict[str, str]
    outputs: set[str]
    required: set[str]      # outputs whose publisher must be there before the first input


def _plan(bag: InputBag, options: ReplayOptions) -> _Plan:
    """The expectation table (the default one names node inputs: a remapped bag topic feeds
    one), checked against the bag; the outputs to record and those to wait for."""
    remaps = options.remaps
    expectations = options.expectations
    if expectations is None:
        published_as = {dst: src for src, dst in remaps.items()}
        expectations = {published_as.get(t, t): o for t, o in DEFAULT_EXPECTATIONS.items()}
    check_inputs(bag, list(expectations), remaps)
    published_names = {remaps.get(t, t) for t in expectations}
    outputs = ({o for outs in expectations.values() for o in outs}
               | set(options.extra_outputs)) - published_names
    required = {o for outs in expectations.values() for o in outs}
    if options.launch:   # every output asked for that a launched node publishes
        required |= outputs & {o for n in options.nodes for o in NODES[n].outputs}
    return _Plan(dict(expectations), {t: remaps.get(t, t) for t in expectations}, outputs,
                 required)


def _launch(options: ReplayOptions, params_file: Path | None, log_dir: Path
            ) -> tuple[Graph, PassSettings]:
    """Start the processing nodes; the pass settings with the fusion's end of pass when it is
    launched in lockstep."""
    env = dict(os.environ)
    lockstep = options.passes.mode == 'lockstep'
    if lockstep:
        # Publish hands the message to every matched reader before it returns, so an output
        # the replay has received is already on its way to the other subscribers (asynchronous
        # publishing sends from a separate thread, later).
        env.setdefault('RMW_FASTRTPS_PUBLICATION_MODE', 'SYNCHRONOUS')
    graph = Graph(log_dir / 'logs', env)
    params_files = [params_file] if params_file else []
    settings = options.passes
    extras = {}
    for name in options.nodes:
        extra = list(options.node_params.get(name, []))
        if name == 'complementary_fusion' and lockstep \
                and not any(a.startswith('flush_after_s:=') for a in extra):
            # The fusion processes what it holds after flush_after_s of wall time without
            # input; a lockstep wait that long (a scan match on an overloaded machine) would
            # flush before the match arrives and change the outputs.
            extra = ['-p', f'flush_after_s:={LOCKSTEP_FUSION_FLUSH_S}', *extra]
            quiet_s = max(settings.quiet_s, 1.5 * LOCKSTEP_FUSION_FLUSH_S + 1.0)
            settings = replace(settings, flush=FlushWait(FUSED, FUSION_ANSWERED, quiet_s))
        extras[name] = extra
    if options.one_process:
        graph.start_one_process(options.nodes, extras, params_files=params_files)
    else:
        for name in options.nodes:
            graph.start(name, extras[name], params_files)
    return graph, settings


def _output_types(replayer: Replayer, results: list[PassResult]
                  ) -> tuple[dict[str, str], dict[str, list]]:
    """Each recorded output's type and the QoS its publishers offered (inputs: the replay's)."""
    output_types, offered = {}, {}
    for t in replayer.subscribed:
        infos = replayer.node.get_publishers_info_by_topic(t)
        if infos:
            output_types[t] = infos[0].topic_type
            offered[t] = [i.qos_profile for i in infos]
    for t, publisher in replayer.publishers.items():
        offered[t] = [publisher.qos_profile]
    for r in results:
        for t in r.outputs:
            if t not in output_types:
                raise ReplayError(f'output {t}: its publisher vanished before its type was read')
    return output_types, offered


def _write(partial: Path, bag: InputBag, results: list[PassResult], plan: _Plan,
           replayer: Replayer, compress: bool) -> None:
    """The output bag (one pass) or a folder of pass-K bags."""
    output_types, offered = _output_types(replayer, results)
    if len(results) == 1:
        write_output_bag(partial, bag, results[0], output_types, plan.outputs, compress, offered)
        return
    partial.mkdir(parents=True)
    for k, r in enumerate(results):
        write_output_bag(partial / f'pass-{k + 1}', bag, r, output_types, plan.outputs,
                         compress, offered)


def replay(bag_path: str | Path, out: str | Path | None,
           options: ReplayOptions = ReplayOptions()) -> list[PassResult]:
    """Replay a bag through the graph (started here with options.launch: with one_process, in
    one sensing_graph process), options.loops times back to back; writes `out` (one pass) or
    out/pass-K (several), complete or not at all."""
    bag = load_bag(bag_path)
    plan = _plan(bag, options)
    params_file = None
    if options.params_file is not None:
        try:
            params_file = params_file_path(options.params_file)
        except GraphArgumentError as exc:
            raise ReplayError(str(exc)) from None
    out = Path(out) if out is not None else None
    if out is not None and out.exists():
        raise ReplayError(f'{out}: already exists; choose a new output folder')
    # Written under a hidden sibling folder and moved into place only when complete (rosbag2
    # names the .mcap after its folder, so the folder already has its final name there).
    staging = out.with_name(f'.{out.name}.partial') if out is not None else None
    if staging is not None:
        discard(staging)
        staging.mkdir(parents=True)
    log_dir = Path(tempfile.mkdtemp(prefix='sensing_replay-')) if options.logs is None \
        else Path(options.logs)
    graph = replayer = None
    succeeded = False
    try:
        replayer = Replayer(plan.inputs, {t: bag.types[t] for t in plan.expectations},
                            plan.outputs, plan.expectations)
        settings = options.passes
        if options.launch:
            graph, settings = _launch(options, params_file, log_dir)
        _wait_for_graph(replayer, bag, plan, options, graph, log_dir)
        results = _play(replayer, bag, plan, options, settings, graph, log_dir)
        if staging is not None:
            _write(staging / out.name, bag, results, plan, replayer, options.compress)
            (staging / out.name).rename(out)
        succeeded = True
        return results
    finally:
        if staging is not None:
            discard(staging)   # empty after success; a partial bag after a failure
        if graph is not None:
            graph.stop()
        if replayer is not None:
            replayer.close()
        if options.logs is None and (graph is None or succeeded):
            shutil.rmtree(log_dir, ignore_errors=True)   # kept after a failure: it names them


def _wait_for_graph(replayer: Replayer, bag: InputBag, plan: _Plan, options: ReplayOptions,
                    graph: Graph | None, log_dir: Path) -> None:
    """Until the graph is up (Replayer.wait_for_graph); timed mode runs a lead-in /clock."""
    if options.passes.mode == 'timed':
        replayer.lead_in_clock_ns = next(s for t, s, _ in bag.messages
                                         if t in plan.expectations) \
            - int((options.startup_timeout_s + 1.0) * 1e9)
    try:
        replayer.wait_for_graph(
            plan.required, options.startup_timeout_s,
            failed=(graph.failed if graph is not None else lambda: []),
            nodes=options.nodes if options.launch and DIAGNOSTICS in plan.outputs else ())
    except (ReplayError, GraphArgumentError) as exc:
        raise ReplayError(f'{exc}; node logs in {log_dir / "logs"}' if options.launch
                          else str(exc)) from None


def _play(replayer: Replayer, bag: InputBag, plan: _Plan, options: ReplayOptions,
          settings: PassSettings, graph: Graph | None, log_dir: Path) -> list[PassResult]:
    """The warm-up (a launched graph's, or one asked for) and options.loops passes."""
    inputs = set(plan.expectations)
    warmup_s = options.warmup_s if options.warmup_s is not None else \
        LAUNCHED_WARMUP_S if options.launch else 0.0
    warm_up = warm_up_bag(bag, inputs, warmup_s) if warmup_s > 0 else None
    if warm_up is not None:
        warm_up_span = _stamp_span(warm_up)
        # Two nodes that have just discovered each other may still be matching: a message sent
        # then is lost. So the first warmup_s of the bag, and at least one message of every
        # input topic (a keyframe log may hold seconds between two scans), goes through first
        # and is discarded. Its stamps are moved after the bag's end, so the pass proper starts
        # with time jumping backwards on every input, which resets every node (the same path
        # every later loop takes), even an input whose first message the warm-up played.
        play_pass(replayer, warm_up, inputs, replace(settings, mode='lockstep'),
                  'warm-up: ' if options.progress else None)
    results = []
    for k in range(options.loops):
        label = f'pass {k + 1}/{options.loops}: ' if options.loops > 1 else ''
        results.append(play_pass(replayer, bag, inputs, settings,
                                 label if options.progress else None))
        if warm_up is not None:
            # What a node held at the warm-up's end (the fusion's reorder buffer) comes out as
            # the pass starts, stamped in the warm-up's moved span: the warm-up's, not the pass's.
            _drop_stamped_within(results[-1], *warm_up_span)
        if graph is not None and graph.failed():
            raise ReplayError(f'node(s) exited during the replay: {", ".join(graph.failed())}; '
                              f'logs in {log_dir / "logs"}')
    return results
