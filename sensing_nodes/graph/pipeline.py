"""The processing nodes driven over a bag without DDS (sensing_pipeline's work), written into a new
bag.

Each node is built as its executable builds it (its class, with config/<node>.yaml, then
--params-file files, then --param overrides: the same defaults and validation), but never spun:
the pipeline drives the node's per-message processor (ros/processor.py) itself, in bag order,
one input at a time, and hands every output at once to the processors that take its topic
(depth first), as a lockstep `sensing_replay --launch` does over DDS. Outputs are written with
the bag's other topics, as the replay writes them. Documented in docs/pipeline.md.
"""

from __future__ import annotations

import os
import shutil
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

EXIT_BAD_INPUT = 2

DISCOVERY_RANGE = 'ROS_AUTOMATIC_DISCOVERY_RANGE'
PROGRESS_AFTER_S = 1.0   # no progress display for bags done sooner


class PipelineError(Exception):
    """Bad input or parameters: the message names the file, topic or parameter."""


def build_nodes(names: tuple[str, ...], params_files: list[Path],
                node_params: dict[str, list[str]]) -> dict[str, Any]:
    """The named nodes, each constructed with the arguments its executable gets from a launch
    (--params-file config/<node>.yaml, then `params_files`, then its `-p NAME:=VALUE`
    overrides, as its own cli_args: the same precedence and parsing as a separate process),
    in one rclpy context that is never spun, with discovery off: nothing goes over DDS; every
    output is made, those a running node makes only while subscribed too. PipelineError on a
    bad parameter."""
    import rclpy

    from sensing_nodes.graph.cli import node_arguments
    from sensing_nodes.nodes.registry import make_node
    from sensing_nodes.ros.run import _PARAMETER_ERRORS

    # The nodes exist only to hold their parameters, logger and diagnostics: no peer should
    # ever see them (a robot's graph on the same domain has nodes of the same names).
    # Only while the context and nodes are made: the caller's environment (a test session
    # that starts graphs afterwards) keeps its own discovery range.
    previous = os.environ.get(DISCOVERY_RANGE)
    os.environ[DISCOVERY_RANGE] = 'OFF'
    try:
        # A context of its own: a caller that already has rclpy running (a test session)
        # keeps its default context.
        context = rclpy.Context()
        rclpy.init(args=['sensing_pipeline'], context=context)   # never the tool's own argv
        nodes = {}
        for name in names:
            try:
                # Plain whatever a parameter file says: the pipeline calls the processors.
                nodes[name] = make_node(name, node_arguments(name, params_files,
                                                             node_params.get(name, [])),
                                        context, lifecycle=False)
                if hasattr(nodes[name].processor, 'listened'):
                    # Outputs a running node makes only while subscribed (ON_DEMAND_TOPICS):
                    # whoever drives the processor here takes every output.
                    nodes[name].processor.listened = _every_output
            except _PARAMETER_ERRORS as exc:
                close(nodes, context)
                raise PipelineError(f'{name}: invalid parameter: {exc}') from None
    finally:
        if previous is None:
            os.environ.pop(DISCOVERY_RANGE, None)
        else:
            os.environ[DISCOVERY_RANGE] = previous
    return nodes


def _every_output(topic: str) -> bool:
    return True


def close(nodes: dict[str, Any], context=None) -> None:
    """Destroy the nodes and shut their context down."""
    import rclpy

    for node in nodes.values():
        context = node.context
        node.destroy_node()
    if context is not None:
        rclpy.try_shutdown(context=context)


class Progress:
    """A progress bar with the bag time done, the speed and an ETA, on stderr (a line every
    5 s when stderr is not a terminal); nothing for bags done within PROGRESS_AFTER_S."""

    def __init__(self, first_ns: int, last_ns: int, enabled: bool) -> None:
        self.first_ns, self.span_ns = first_ns, max(last_ns - first_ns, 1)
        self.enabled = enabled
        self.tty = sys.stderr.isatty()
        self.started = time.monotonic()
        self.next_s = self.started + PROGRESS_AFTER_S
        self.shown = False

    def update(self, stamp_ns: int, force: bool = False) -> None:
        now = time.monotonic()
        if not self.enabled or (now < self.next_s and not force) or (force and not self.shown):
            return
        self.next_s = now + (0.25 if self.tty else 5.0)
        self.shown = True
        done = min(max((stamp_ns - self.first_ns) / self.span_ns, 0.0), 1.0)
        elapsed = now - self.started
        bag_s = (stamp_ns - self.first_ns) * 1e-9
        speed = bag_s / elapsed if elapsed > 0 else 0.0
        eta = elapsed * (1.0 - done) / done if done > 0 else float('inf')
        bar = '#' * int(30 * done) + '.' * (30 - int(30 * done))
        text = (f'[{bar}] {100 * done:3.0f} % {bag_s:8.1f} / {self.span_ns * 1e-9:.1f} s of bag, '
                f'{speed:6.1f}x real time, ETA {eta:5.0f} s')
        print(('\r' + text) if self.tty else ('sensing_pipeline: ' + text), file=sys.stderr,
              end='' if self.tty else '\n', flush=True)

    def finish(self, stamp_ns: int) -> None:
        self.update(stamp_ns, force=True)
        if self.enabled and self.shown and self.tty:
            print(file=sys.stderr, flush=True)


class Wiring:
    """The nodes' processors as the pipeline drives them: topic -> handlers (in node order)
    with the decoding each expects, and the outputs they publish."""

    def __init__(self, built: dict[str, Any], nodes: tuple[str, ...]) -> None:
        from rclpy.serialization import deserialize_message

        from sensing_nodes.bags.stamps import stamp_reader
        from sensing_nodes.bags.storage import type_name
        from sensing_nodes.ros.cdr import cdr_decoder

        self.handlers: dict[str, list] = defaultdict(list)
        self.input_types: dict[str, type] = {}
        self.decoders: dict[tuple[str, bool], Any] = {}    # (topic, decoded) -> bytes -> msg
        self.outputs: dict[str, Any] = {}                   # topic -> Output
        self.flushes = []                                   # what a node holds at the end
        for name in nodes:
            processor = built[name].processor
            for i in processor.inputs():
                # What the node's subscription gives it: a `decoded` input a rosbags-decoded
                # message (ros/cdr.py), any other an rclpy message.
                self.handlers[i.topic].append((i.handler, i.decoded))
                self.input_types[i.topic] = i.msg_type
                self.decoders[i.topic, i.decoded] = cdr_decoder(i.msg_type) if i.decoded else \
                    (lambda raw, cls=i.msg_type: deserialize_message(raw, cls))
            for o in processor.outputs():
                self.outputs[o.topic] = o
            if hasattr(processor, 'flush'):
                self.flushes.append(processor.flush)
        self.output_types = {t: type_name(o.msg_type) for t, o in self.outputs.items()}
        self.stamp_of = {t: stamp_reader(kind) for t, kind in self.output_types.items()}

    def feeds(self, bag, remaps: dict[str, str]) -> dict[str, str]:
        """Bag topic -> the node input it feeds: those a node takes (after --remap) and no node
        produces; PipelineError when none, or a type does not match."""
        from sensing_nodes.bags.storage import type_name
        from sensing_nodes.topics import NODE_INPUT_TYPES

        feeds = {t: remaps.get(t, t) for t in bag.types
                 if remaps.get(t, t) in self.handlers and remaps.get(t, t) not in self.outputs}
        if not feeds:
            raise PipelineError(f'{bag.path}: no topic the nodes take (' + ', '.join(sorted(
                t for t in self.handlers if t not in self.outputs)) + '); it has: '
                + ', '.join(sorted(bag.types)) + ' (--remap BAG_TOPIC:=TOPIC)')
        for topic, fed in feeds.items():
            wanted = type_name(self.input_types[fed])
            if bag.types[topic] != wanted:
                raise PipelineError(f'{bag.path}: topic {topic} holds {bag.types[topic]}, but the '
                                    f'nodes take {wanted} on {fed}')
        fed = set(feeds.values())
        unused = sorted(t for t in NODE_INPUT_TYPES
                        if t in self.handlers and t not in self.outputs and t not in fed)
        if unused:
            print(f'sensing_pipeline: warning: nothing in {bag.path} feeds {", ".join(unused)} '
                  f'(bag topics: {", ".join(sorted(bag.types))}; --remap BAG_TOPIC:=TOPIC)',
                  file=sys.stderr)
        return feeds


class Driver:
    """The one driver of the nodes' processors without DDS (sensing_pipeline's, and the
    benchmarks'): hands each input to its handlers and every output at once to the handlers of
    its topic (depth first), recording the outputs: (bag time, CDR bytes) per topic."""

    def __init__(self, wiring: Wiring) -> None:
        from sensing_nodes.bags.input_bag import PassResult

        self.wiring = wiring
        self.result = PassResult()

    def receive(self, topic: str, raw: bytes, stamp_ns: int) -> None:
        """CDR bytes on a topic to each of its handlers, decoded once per kind of decoding."""
        handlers = self.wiring.handlers[topic]
        if len(handlers) == 1:
            handler, kind = handlers[0]
            self.deliver(handler(self.wiring.decoders[topic, kind](raw)), stamp_ns)
            return
        decoded: dict[bool, Any] = {}
        for handler, kind in handlers:
            msg = decoded.get(kind)
            if msg is None:
                msg = decoded[kind] = self.wiring.decoders[topic, kind](raw)
            self.deliver(handler(msg), stamp_ns)

    def decoded(self, rows) -> list[tuple[str, int, Any]]:
        """(topic, bag time, CDR bytes) rows of the topics the nodes take, each decoded as its
        handlers take it (one kind of decoding per topic): a benchmark's inputs, decoded
        beforehand and handed over by take()."""
        decoders = {}
        for topic, handlers in self.wiring.handlers.items():
            kinds = {kind for _, kind in handlers}
            assert len(kinds) == 1, f'{topic}: its handlers decode it {len(kinds)} ways'
            decoders[topic] = self.wiring.decoders[topic, kinds.pop()]
        return [(topic, stamp_ns, decoders[topic](raw)) for topic, stamp_ns, raw in rows
                if topic in decoders]

    def take(self, topic: str, msg, stamp_ns: int) -> None:
        """A message decoded as decoded() decodes it to each of the topic's handlers."""
        for handler, _ in self.wiring.handlers[topic]:
            self.deliver(handler(msg), stamp_ns)

    def finish(self, last_ns: int) -> None:
        """The end of the input: what the nodes hold (the fusion's reorder buffer), delivered
        at the last input's bag time."""
        for flush in self.wiring.flushes:
            self.deliver(flush(), last_ns)

    def deliver(self, produced, stamp_ns: int) -> None:
        """Depth first: an output reaches its consumers before the next output, as a lockstep
        replay waits for one input's outputs (and lets them land) first. Outputs are recorded
        in canonical CDR: the nodes' own packing (ros/cdr.py) writes nothing else, an rclpy
        message is encoded here as the bag writer encodes one (message_cdr)."""
        recorded, wiring = self.result.outputs, self.wiring
        for topic, msg in produced:
            if isinstance(msg, bytes):     # packed by the node itself (ros/cdr.py)
                recorded[topic].append((wiring.stamp_of[topic](msg, stamp_ns), msg))
                if topic in wiring.handlers:
                    self.receive(topic, msg, stamp_ns)
                continue
            from sensing_nodes.bags.storage import message_cdr

            raw = message_cdr(msg)     # now: a node may refill its message in place
            recorded[topic].append((wiring.stamp_of[topic](raw, stamp_ns), raw))
            for handler, _ in wiring.handlers.get(topic, ()):
                self.deliver(handler(msg), stamp_ns)

    def run(self, bag, feeds: dict[str, str], progress: bool):
        """Every fed input in bag order, then what the nodes hold; each output topic sorted
        by bag time, ties in production order (as the replay's recorder stamps them)."""
        inputs = [(t, s, raw) for t, s, raw in bag.messages if t in feeds]
        bar = Progress(inputs[0][1] if inputs else 0, inputs[-1][1] if inputs else 0, progress)
        for topic, stamp_ns, raw in inputs:
            self.receive(feeds[topic], raw, stamp_ns)
            self.result.inputs_published += 1
            bar.update(stamp_ns)
        last_ns = inputs[-1][1] if inputs else 0
        self.finish(last_ns)
        bar.finish(last_ns)
        for rows in self.result.outputs.values():
            rows.sort(key=lambda row: row[0])
        return self.result


def node_driver(name: str) -> tuple[dict[str, Any], Driver]:
    """The node built as sensing_pipeline builds it (config/<node>.yaml) and its Driver; close()
    the first when done."""
    built = build_nodes((name,), [], {})
    return built, Driver(Wiring(built, (name,)))


def _write(out: Path, bag, result, wiring: Wiring, compress: bool) -> None:
    """The output bag, complete or not at all: the bag's topics with the nodes' outputs in place
    of earlier copies. /diagnostics is published by every node on a wall-clock timer, not
    produced here (docs/pipeline.md); the input bag's copy is dropped (it describes another
    run)."""
    from sensing_nodes.bags.input_bag import write_output_bag
    from sensing_nodes.topics import DIAGNOSTICS

    replaced = set(wiring.outputs) | {DIAGNOSTICS}
    staging = out.with_name(f'.{out.name}.partial')
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    try:
        write_output_bag(staging / out.name, bag, result, wiring.output_types, replaced, compress,
                         {t: [o.qos] for t, o in wiring.outputs.items()}, canonical_outputs=True)
        (staging / out.name).rename(out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def run(bag_path: str | Path, out: str | Path, nodes: tuple[str, ...], *,
        params_files: list[Path] | None = None,
        node_params: dict[str, list[str]] | None = None,
        remaps: dict[str, str] | None = None, progress: bool = True,
        compress: bool = False) -> dict[str, int]:
    """Run the nodes over the bag and write OUT (the bag's topics, with the nodes' outputs in
    place of earlier copies); returns the number of messages per output topic."""
    from sensing_nodes.bags.input_bag import InputBagError, load_bag

    out = Path(out)
    if out.exists():
        raise PipelineError(f'{out}: already exists; choose a new output folder')
    try:
        bag = load_bag(bag_path)
    except InputBagError as exc:
        raise PipelineError(str(exc)) from None
    built = build_nodes(nodes, list(params_files or []), dict(node_params or {}))
    try:
        wiring = Wiring(built, nodes)
        feeds = wiring.feeds(bag, dict(remaps or {}))
        result = Driver(wiring).run(bag, feeds, progress)
        _write(out, bag, result, wiring, compress)
        return {t: len(v) for t, v in sorted(result.outputs.items())}
    finally:
        close(built)
