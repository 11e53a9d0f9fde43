"""The bag fed to the graph and the bag written back: a whole rosbag2 bag loaded up front and
checked (sensing_replay, sensing_pipeline), its warm-up slice, and the output bag (the input
bag's topics plus what the graph published)."""

from __future__ import annotations

import shutil
from collections import defaultdict
from dataclasses import dataclass, field
from operator import itemgetter
from pathlib import Path

from sensing_nodes.bags.stamps import first_field_type, shifted_stamp
from sensing_nodes.topics import NODE_INPUT_TYPES


class InputBagError(Exception):
    """A bag that cannot be fed to the graph: the message names the file and topic."""


@dataclass
class InputBag:
    """Every message of a bag, loaded up front (so a truncated bag fails before any is sent)."""

    path: Path
    types: dict[str, str]
    messages: list[tuple[str, int, bytes]]  # (topic, bag time ns, CDR bytes), in bag order
    qos: dict[str, list] = field(default_factory=dict)  # topic -> offered QoS (rosbags records)
    custom_data: dict[str, str] = field(default_factory=dict)   # metadata.yaml's, carried on
    damage: str = ''   # what an unclosed recording lost (BagReader.damage; '' when closed)


@dataclass
class PassResult:
    """What one pass over the bag produced."""

    outputs: dict[str, list[tuple[int, bytes]]] = field(default_factory=lambda: defaultdict(list))
    inputs_published: int = 0
    missing: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    wall_s: float = 0.0
    wait_s: dict[str, float] = field(default_factory=lambda: defaultdict(float))  # per input topic



def load_bag(path: str | Path) -> InputBag:
    """Read a whole bag; InputBagError (naming the file) when it is missing or unreadable. A
    bag a recording did not close is read up to its last complete record (the reader warns)."""
    from sensing_nodes.bags.storage import BagError, BagReader, failure_reason

    path = Path(path)
    try:
        reader = BagReader(path)
        types = {t: i.msgtype for t, i in reader.topics.items()}
        expected = {t: i.count for t, i in reader.topics.items()}
        qos = {t: list(i.qos) for t, i in reader.topics.items()}
        messages = list(reader.raw())   # in stamp order, ties in the order the bag stores them
    except BagError as exc:
        raise InputBagError(str(exc)) from None
    except Exception as exc:  # rosbags raises several types for damaged files
        raise InputBagError(f'{path}: cannot read the bag ({failure_reason(exc)}); '
                          'truncated or damaged?') from None
    got = defaultdict(int)
    for topic, _, _ in messages:
        got[topic] += 1
    short = {t: (got[t], n) for t, n in expected.items() if got[t] != n}
    if short:
        detail = ', '.join(f'{t}: {g} of {n}' for t, (g, n) in sorted(short.items()))
        raise InputBagError(f'{path}: bag holds fewer messages than its metadata says ({detail}); '
                          'truncated?')
    return InputBag(path, types, messages, qos, dict(reader.custom_data), reader.damage)


def check_inputs(bag: InputBag, inputs: list[str], remaps: dict[str, str]) -> None:
    """Every input topic is in the bag with a type the receiving node takes."""
    for topic in inputs:
        if topic not in bag.types:
            raise InputBagError(f'{bag.path}: topic {topic} is not in the bag (it has: '
                              f'{", ".join(sorted(bag.types))})')
        published = remaps.get(topic, topic)
        wanted = NODE_INPUT_TYPES.get(published)
        if wanted is not None and bag.types[topic] != wanted:
            raise InputBagError(
                f'{bag.path}: topic {topic} holds {bag.types[topic]}, but the nodes '
                f'take {wanted} on {published}'
            )
        if not any(t == topic for t, _, _ in bag.messages):
            raise InputBagError(f'{bag.path}: topic {topic} has no messages')



def stamped_topics(bag: InputBag, topics) -> set[str]:
    """The topics among `topics` whose message type starts with a Header."""
    return {t for t in topics if first_field_type(bag.types[t]) == 'std_msgs/Header'}


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



def write_output_bag(path: Path, bag: InputBag, result: PassResult, output_types: dict[str, str],
                     outputs: set[str], compress: bool = False,
                     offered: dict[str, list] | None = None,
                     canonical_outputs: bool = False) -> dict[str, int]:
    """The input bag's topics (all but the graph's outputs) plus what the graph published, each
    with the QoS it was offered with (`offered`: topic -> profiles; else the input bag's).
    canonical_outputs: the outputs are canonical CDR already (sensing_pipeline's), stored as
    they are; so are the input bag's messages where its writer said they are canonical
    (metadata.yaml's custom_data, CANONICAL_KEY: BagWriter's bags)."""
    from sensing_nodes.bags.storage import CANONICAL_KEY, BagWriter

    offered = offered or {}
    # Written in one go from memory: 1 MiB chunks (a crash leaves no output anyway).
    with BagWriter(path, compress=compress, chunk_s=None) as out:
        for key, value in bag.custom_data.items():
            out.set_custom_data(key, value)
        for topic, msg_type in bag.types.items():
            if topic not in outputs:
                out.add_topic(topic, msg_type, offered.get(topic, bag.qos.get(topic)) or None)
        for topic in sorted(result.outputs):
            out.add_topic(topic, output_types[topic], offered.get(topic) or None)
        merged = [(s, 0, t, raw) for t, s, raw in bag.messages if t not in outputs]
        merged += [(s, 1, t, raw) for t in sorted(result.outputs) for s, raw in result.outputs[t]]
        # Outputs after the input of the same stamp; each topic keeps its arrival order.
        merged.sort(key=itemgetter(0, 1))
        canonical = set(result.outputs) if canonical_outputs else set()
        if bag.custom_data.get(CANONICAL_KEY) == 'canonical':
            canonical |= set(bag.types)
        out.write_raw_many(((topic, raw, stamp) for stamp, _, topic, raw in merged), canonical)
        return dict(out.counts)


def discard(path: Path) -> None:
    """Remove a folder (a partial bag), if there."""
    if path.exists():
        shutil.rmtree(path, ignore_errors=True)

