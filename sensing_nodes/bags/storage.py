"""rosbag2 bags of rclpy messages, written (MCAP) and read (MCAP or sqlite3, and ROS 1 .bag
files) with rosbags.

Every message is written in canonical CDR: the fields exactly as rclpy/DDS serialise them, but
with every alignment padding byte zero and no bytes after the last field (`canonical_cdr`).
rclpy's serialiser leaves padding uninitialised (process memory) and appends 4 alignment bytes
after a trailing empty sequence of 8-byte elements (JointState's `effort`), which rosbags'
strict reader rejects; canonical bytes make same-seed recordings byte-identical and decode with
rosbags, mcap-ros2-support and rclpy alike.
"""

from __future__ import annotations

import heapq
import importlib
import itertools
import os
import re
import signal
import struct
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.rosbag2 import (
    CompressionFormat,
    CompressionMode,
    Reader,
    StoragePlugin,
    Writer,
    WriterError,
)
from rosbags.typesys import Stores, get_typestore

from sensing_nodes.bags.recovery import (
    Recovered,
    RecoveryError,
    mcap_closed,
    read_cut_sqlite,
    read_unclosed_mcap,
    sqlite_cut_short,
)

_DEFERRED_SIGNALS = {signal.SIGINT, signal.SIGTERM}
_SIGNAL_BATCH = 5000   # messages written with the signals held off (a few ms)
CHUNK_S = 1.0          # bag time an MCAP chunk spans at most: what a crash can lose
# rosbags' MCAP writer (pinned in requirements.txt): a Message record (opcode, record length,
# channel id, sequence, log time, publish time, then the data) and the chunk size past which it
# closes a chunk; BagWriter._append writes what its write() writes.
_MESSAGE_RECORD = struct.Struct('<BQHIQQ')
_MCAP_CHUNK_BYTES = 2**20
FSYNC_INTERVAL_S = 1.0  # wall time between two fsyncs at most: what a power cut can lose more

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


class BagError(Exception):
    """A bag that cannot be read: the message names the file and what is wrong."""


def failure_reason(exc: BaseException) -> str:
    """Why a reader failed, in words: no Python class names, no tuple reprs."""
    if isinstance(exc, KeyError):
        return f'the field {exc.args[0]} is missing' if exc.args else 'a field is missing'
    if isinstance(exc, UnicodeDecodeError):
        return 'bytes that are not text where the format wants text'
    args = exc.args
    while len(args) == 1 and isinstance(args[0], tuple):     # a tuple of reasons, once or twice
        args = args[0]
    parts = [str(a) for a in args if str(a)] or [str(exc)]
    text = '; '.join(parts)
    # Messages that embed a tuple repr of one string: "damaged: ('Header ...',)".
    text = re.sub(r"\(\s*['\"]([^'\"]*)['\"]\s*,?\s*\)", r'\1', text)
    return text.strip().rstrip('.') or 'an unreadable record'



def canonical_cdr(raw: bytes | memoryview, msgtype: str) -> bytes:
    """CDR bytes of a 'pkg/msg/Name' message -> the same message in canonical CDR (same byte
    order and values, padding zero, nothing after the last field): what rosbags' typestore
    gives when it decodes and encodes the message again, found by walking the bytes instead
    (`_padding_walker`), with the round trip itself for what the walk does not vouch for."""
    msgdef = TYPESTORE.get_msgdef(msgtype)
    if len(raw) < 4 or bytes(raw[:2]) not in (b'\x00\x00', b'\x00\x01'):
        raise ValueError(f'{msgtype}: not a CDR message (encapsulation header {bytes(raw[:4])!r})')
    little_endian = bool(raw[1])
    walk = _WALKERS.get((msgtype, little_endian))
    if walk is None:
        walk = _WALKERS[msgtype, little_endian] = _padding_walker(msgtype, little_endian)
    body = memoryview(raw)[4:]
    try:
        end, gaps = walk(body)
    except (_NotPlain, IndexError, struct.error, UnicodeDecodeError):
        end = -1   # rosbags decides (and raises for what it cannot read)
    if 0 <= end <= len(body):
        out = bytearray(raw[:4 + end])
        out[2:4] = b'\x00\x00'     # rosbags writes no encapsulation options
        for i in range(0, len(gaps), 2):
            out[4 + gaps[i]:4 + gaps[i + 1]] = _ZEROS[:gaps[i + 1] - gaps[i]]
        return bytes(out)
    decode = msgdef.deserialize_cdr_le if little_endian else msgdef.deserialize_cdr_be
    # Bytes after the last field are dropped: Fast-CDR aligns before the (absent) elements of
    # each empty sequence of doubles, so an all-empty JointState ends in 8 such bytes.
    message, _ = decode(body, 0, msgdef.cls, TYPESTORE)
    return bytes(TYPESTORE.serialize_cdr(message, msgtype, little_endian=little_endian))


class _NotPlain(Exception):
    """A message whose bytes rosbags' round trip would change (or refuse) beyond its padding."""


_WALKERS: dict[tuple[str, bool], Callable] = {}
_ZEROS = bytes(16)


def _padding_walker(msgtype: str, little_endian: bool) -> Callable:
    """A function of a CDR message body (bytes after the encapsulation header) -> (end of its
    last field, [start, end, start, end, ...] of its alignment padding), positions from the
    body's start, as rosbags' generated CDR decoder reads the body and its encoder writes it
    back (rosbags.serde.cdr: the same alignment decisions, field by field, so the canonical
    message is the body up to `end` with the padding zeroed). It raises _NotPlain where the
    round trip would change a value's bytes or fail: a bool byte other than 0 or 1, a float32
    NaN (widened to a Python float: a signalling NaN comes back quiet), a string without its
    terminator, a sequence longer than the bytes left."""
    source = _WalkerSource()
    try:
        source.fields(TYPESTORE.get_msgdef(msgtype).fields, ' ')
    except _NotPlain:   # a type the walk does not cover (float128): always the round trip
        return _never_plain
    return source.compile(msgtype, little_endian)


def _never_plain(raw):
    raise _NotPlain


class _WalkerSource:
    """The Python source of a padding walker, generated field by field as rosbags generates its
    CDR decoder (rosbags.serde.cdr: the same branches, in the same order, with the same
    alignment decisions); `aligned` is the alignment known at the current position."""

    def __init__(self) -> None:
        from rosbags.interfaces import Nodetype
        from rosbags.serde.utils import SIZEMAP, align, align_after

        self._node, self._size = Nodetype, SIZEMAP
        self._align = lambda desc: align(desc, TYPESTORE)
        self._align_after = lambda desc: align_after(desc, TYPESTORE)
        self.lines = ['def walk(raw):', ' size = len(raw)', ' pos = 0', ' gaps = []']
        self._names = itertools.count()

    def compile(self, msgtype: str, little_endian: bool) -> Callable:
        """The walker function of the lines so far."""
        order = '<' if little_endian else '>'
        scope = {'_NotPlain': _NotPlain, 'u32': struct.Struct(order + 'I').unpack_from,
                 'f32': struct.Struct(order + 'f').unpack_from}
        source = '\n'.join([*self.lines, ' return pos, gaps'])
        exec(compile(source, f'<canonical_cdr walker of {msgtype}>', 'exec'), scope)
        return scope['walk']

    def fields(self, desc_fields, indent: str) -> None:
        """Lines reading a message's fields, each followed by the padding up to the next."""
        for current, following in zip(desc_fields, [*desc_fields[1:], None]):
            aligned = self._field(current[1], indent)
            if following is not None and aligned < (before := self._align(following[1])):
                self.pad(before, indent)

    def _field(self, desc, indent: str) -> int:
        """Lines reading one field; the alignment known after it."""
        if desc[0] == self._node.NAME:
            self.fields(TYPESTORE.get_msgdef(desc[1]).fields, indent)
            return self._align_after(desc)
        if desc[0] == self._node.BASE:
            return self._base(desc[1][0], indent)
        if desc[0] == self._node.ARRAY:
            return self._array(*desc[1], indent)
        return self._sequence(desc[1][0], indent)

    def _base(self, kind: str, indent: str) -> int:
        if kind == 'string':
            self.string(indent)
            return 1
        self.scalar(kind, indent)
        return self._size[kind]

    def _array(self, sub, length: int, indent: str) -> int:
        """A fixed-size array: strings, plain values, or messages."""
        if sub[0] == self._node.BASE and sub[1][0] == 'string':
            for index in range(length):
                if index:
                    self.pad(4, indent)
                self.string(indent)
            return 1
        if sub[0] == self._node.BASE:
            self._check_plain(sub[1][0])
            # numpy arrays in the round trip: their bytes come back as they were
            self.lines.append(f'{indent}pos += {length * self._size[sub[1][0]]}')
            return self._size[sub[1][0]]
        before, after = self._align(sub), self._align_after(sub)
        for _ in range(length):
            if before > after:
                self.pad(before, indent)
            self.fields(TYPESTORE.get_msgdef(sub[1]).fields, indent)
        return after

    def _sequence(self, sub, indent: str) -> int:
        """A sequence: its count, checked against the bytes left, then its elements."""
        count = f'n{next(self._names)}'
        self.lines.extend([f'{indent}{count} = u32(raw, pos)[0]', f'{indent}pos += 4'])
        string = sub[0] == self._node.BASE and sub[1][0] == 'string'
        least = 5 if string else self._size.get(sub[1][0], 16) if sub[0] == self._node.BASE \
            else 1
        most = TYPESTORE.max_sequence_length
        self.lines.extend([f'{indent}if pos + {count} * {least} > size or {count} > {most}:',
                           f'{indent} raise _NotPlain'])
        if string:
            self.lines.append(f'{indent}for _ in range({count}):')
            self.pad(4, indent + ' ')
            self.string(indent + ' ')
            return 1
        if sub[0] == self._node.BASE:
            self._check_plain(sub[1][0])
            before = self._align(sub)
            if 4 < before:     # the count leaves the position 4-aligned
                self.lines.append(f'{indent}if {count}:')
                self.pad(before, indent + ' ')
            self.lines.append(f'{indent}pos += {count} * {self._size[sub[1][0]]}')
            return min(4, before)
        self.lines.append(f'{indent}for _ in range({count}):')
        self.pad(self._align(sub), indent + ' ')
        self.fields(TYPESTORE.get_msgdef(sub[1]).fields, indent + ' ')
        return min(4, self._align_after(sub))

    def _check_plain(self, kind: str) -> None:
        if kind not in self._size or kind == 'float128':
            raise _NotPlain

    def pad(self, to: int, indent: str) -> None:
        """Lines moving pos to the next multiple of `to`, recording the gap."""
        self.lines.extend([f'{indent}new = (pos + {to - 1}) & -{to}',
                           f'{indent}if new != pos:',
                           f'{indent} gaps.append(pos)', f'{indent} gaps.append(new)',
                           f'{indent} pos = new'])

    def string(self, indent: str) -> None:
        """Lines reading a string: its length, its bytes (UTF-8), its terminator."""
        self.lines.extend([f'{indent}n = u32(raw, pos)[0]',
                           f'{indent}if n < 1 or pos + 4 + n > size or raw[pos + 3 + n]:',
                           f'{indent} raise _NotPlain',
                           f'{indent}str(raw[pos + 4:pos + 3 + n], "utf-8")',
                           f'{indent}pos += 4 + n'])

    def scalar(self, kind: str, indent: str) -> None:
        """Lines reading a plain value: a bool 0 or 1, a float32 not NaN."""
        if kind == 'bool':
            self.lines.extend([f'{indent}if raw[pos] > 1:', f'{indent} raise _NotPlain'])
        elif kind == 'float32':
            self.lines.extend([f'{indent}v = f32(raw, pos)[0]',
                               f'{indent}if v != v:', f'{indent} raise _NotPlain'])
        else:
            self._check_plain(kind)
        self.lines.append(f'{indent}pos += {self._size[kind]}')


def type_name(msg_or_class: Any) -> str:
    """rclpy message (or class) -> 'pkg/msg/Name'."""
    cls = msg_or_class if isinstance(msg_or_class, type) else type(msg_or_class)
    return f"{cls.__module__.split('.')[0]}/msg/{cls.__name__}"


def message_class(name: str) -> type:
    """'pkg/msg/Name' -> the rclpy message class."""
    package, _, cls = name.split('/')
    return getattr(importlib.import_module(f'{package}.msg'), cls)


def bag_qos(profile: Any) -> Any:
    """rclpy QoSProfile -> the rosbags QoS record of a bag's offered_qos_profiles (a rosbags
    record, e.g. read from another bag, is kept as it is)."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    if isinstance(profile, Qos):
        return profile

    def duration(d) -> QosTime:
        sec, nsec = divmod(int(d.nanoseconds), 1_000_000_000)
        return QosTime(sec, nsec)

    return Qos(QosHistory(int(profile.history)), int(profile.depth),
               QosReliability(int(profile.reliability)), QosDurability(int(profile.durability)),
               duration(profile.deadline), duration(profile.lifespan),
               QosLiveliness(int(profile.liveliness)), duration(profile.liveliness_lease_duration),
               bool(profile.avoid_ros_namespace_conventions))


class BagWriter:
    """Writes rclpy messages to a new rosbag2 (format 9, MCAP storage) at `path`; with
    `compress`, MCAP chunks are zstd-compressed (storage-level, as rosbag2's MCAP presets do).

    What a crash (power loss, kill -9) can take: the file holds every closed chunk, and its
    footer, summary and metadata.yaml are written at close, so an unclosed bag is read up to
    its last chunk (BagReader). With `chunk_s` (default 1 s) a chunk is closed once its
    messages span that much bag time, then handed to the operating system (fsync at most once
    per wall second), and whenever flush() is called (with an fsync; the live recorder: every
    wall second): a crash of the process loses at most the open chunk, a power cut at most the
    last wall second more. None: rosbags' own chunks of 1 MiB, all written at close (bags
    written in one go, where a crash leaves nothing to keep).
    """

    def __init__(self, path: str | Path, compress: bool = False,
                 chunk_s: float | None = CHUNK_S) -> None:
        self.path = Path(path)
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        if compress:
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._connections: dict[str, Any] = {}
        self.counts: dict[str, int] = {}
        self._chunk_ns = None if chunk_s is None else int(chunk_s * 1e9)
        self._chunk_first_ns: int | None = None   # bag time of the open chunk's first message
        self._synced = time.monotonic()

    def __enter__(self) -> BagWriter:
        self._writer.open()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self._writer.close()

    def set_custom_data(self, key: str, value: str) -> None:
        """A key of metadata.yaml's custom_data (what the bag's producer wants said)."""
        self._writer.set_custom_data(key, value)

    def add_topic(self, topic: str, msg_type: str, qos: Any = None) -> None:
        """Register a topic up front, so it is in the bag even when no message arrives; `qos`
        (an rclpy QoSProfile, or a list of them) is stored as its offered QoS, which
        `ros2 bag play` publishes with."""
        if topic not in self._connections:
            profiles = [] if qos is None else [qos] if not isinstance(qos, (list, tuple)) else qos
            self._connections[topic] = self._writer.add_connection(
                topic, msg_type, typestore=TYPESTORE,
                offered_qos_profiles=[bag_qos(p) for p in profiles])
            self.counts[topic] = 0

    def write(self, topic: str, msg: Any, stamp_ns: int) -> None:
        """Append one message, with `stamp_ns` as its bag (receive) time."""
        self.add_topic(topic, type_name(msg))
        self.write_raw(topic, serialize_message(msg), stamp_ns)

    def write_raw(self, topic: str, data: bytes, stamp_ns: int) -> None:
        """Append one CDR-serialised message (as rclpy or DDS gave it) of a topic registered
        with add_topic; it is stored in canonical CDR."""
        self.write_raw_many(((topic, data, stamp_ns),))

    def write_raw_many(self, rows: Iterable[tuple[str, bytes, int]],
                       canonical_topics: frozenset[str] | set[str] = frozenset()) -> None:
        """write_raw of each (topic, CDR bytes, bag time ns), in order. Messages of
        `canonical_topics` are already canonical CDR (ros/cdr.py's encoders write nothing else;
        sensing_pipeline canonicalises what rclpy serialised) and are stored as they are."""
        rows = iter(rows)
        while True:
            batch = list(itertools.islice(rows, _SIGNAL_BATCH))
            if not batch:
                return
            with _signals_held():
                self._append(batch, canonical_topics)

    def _append(self, batch: list[tuple[str, bytes, int]], canonical_topics) -> None:
        """Store messages as rosbags' Writer.write and its MCAP storage's write do, message by
        message (the same records, indexes, statistics and chunk closes: test_storage compares
        the files byte for byte), without their per-call checks and record buffers: their
        ~4 us per message were most of sensing_pipeline's writing. The connections are this
        writer's own and compression is per chunk (never per message), which the checks were
        for."""
        writer, connections, counts = self._writer, self._connections, self.counts
        storage = writer.storage
        if storage is None:
            raise WriterError('Bag was not opened.')
        written, stats, record = writer.counts, storage.channel_stats, _MESSAGE_RECORD.pack
        chunk = storage.chunk
        for topic, data, stamp_ns in batch:
            connection = connections[topic]
            if topic not in canonical_topics:
                data = canonical_cdr(data, connection.msgtype)
            stamp, cid = int(stamp_ns), connection.id
            if stamp < writer.min_timestamp:
                writer.min_timestamp = stamp
            if stamp > writer.max_timestamp:
                writer.max_timestamp = stamp
            if stamp < storage.message_start_time:
                storage.message_start_time = stamp
            if stamp > storage.message_end_time:
                storage.message_end_time = stamp
            stats[cid] += 1
            if stamp < chunk.message_start_time:
                chunk.message_start_time = stamp
            if stamp > chunk.message_end_time:
                chunk.message_end_time = stamp
            bio = chunk.bio
            chunk.msgs[cid].append((stamp, bio.tell()))
            bio.write(record(0x05, 22 + len(data), cid, 0, stamp, stamp))
            bio.write(data)
            if bio.tell() > _MCAP_CHUNK_BYTES:
                storage.close_chunk()
                chunk = storage.chunk
            written[cid] += 1
            counts[topic] += 1
            if self._chunk_ns is not None:
                self._chunk_after(stamp)
                chunk = storage.chunk

    def _chunk_after(self, stamp_ns: int) -> None:
        """Close the open chunk once its messages span chunk_s of bag time."""
        if self._chunk_first_ns is None:
            self._chunk_first_ns = stamp_ns
        elif abs(stamp_ns - self._chunk_first_ns) >= self._chunk_ns:
            self._close_chunk()

    def flush(self) -> None:
        """Close the open chunk and hand the file to the disk (fsync): a crash or a power cut
        after this keeps every message written before it."""
        with _signals_held():
            self._close_chunk(sync=True)

    def _close_chunk(self, sync: bool = False) -> None:
        # rosbags' MCAP writer (pinned in requirements.txt) keeps the open chunk in memory
        # (storage.chunk) and closes it only at 1 MiB: its close_chunk() writes the chunk and its
        # message indexes to storage.bio, the file.
        storage = self._writer.storage
        if storage is None:
            return
        if storage.chunk.bio.tell():
            storage.close_chunk()
        storage.bio.flush()
        self._chunk_first_ns = None
        now = time.monotonic()
        if sync or now - self._synced >= FSYNC_INTERVAL_S:
            os.fsync(storage.bio.fileno())
            self._synced = now


@contextmanager
def _signals_held():
    """SIGINT/SIGTERM held off while messages are stored: raised inside the writer, after it
    counted a message and before it stored it, the bag's metadata counted one message more than
    it held (seen: 4471 counted, 4470 read back after a SIGINT). Held per batch of messages:
    twice per message, the mask cost as much as the writing."""
    held = signal.pthread_sigmask(signal.SIG_BLOCK, _DEFERRED_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)


@dataclass(frozen=True)
class TopicInfo:
    """One topic of a bag: message type, message count, offered QoS (rosbags records)."""

    msgtype: str
    count: int
    qos: tuple


class _ClosedFile:
    """A storage file rosbags reads (or the bag folder, for file-compressed bags): its
    connections up front, its messages on demand."""

    def __init__(self, path: Path) -> None:
        self.path = path
        with Reader(path) as reader:
            self.connections = [
                (c.topic, c.msgtype, c.msgcount,
                 tuple(getattr(c.ext, 'offered_qos_profiles', None) or ()))
                for c in reader.connections]

    def rows(self, topics: set[str] | None) -> Iterator[tuple[int, str, Any]]:
        """(bag time ns, topic, CDR bytes) of the file's messages (of `topics`), in time order."""
        with Reader(self.path) as reader:
            wanted = [c for c in reader.connections if topics is None or c.topic in topics]
            if not wanted:   # rosbags reads every connection when given none
                return
            for connection, stamp, raw in reader.messages(connections=wanted):
                yield stamp, connection.topic, raw


class _RecoveredFile:
    """A storage file a recording did not close, as bags/recovery.py read it (in memory)."""

    def __init__(self, recovered: Recovered) -> None:
        self.path = recovered.path
        self.recovered = recovered
        counts: dict[str, int] = dict.fromkeys(recovered.types, 0)
        for _, topic, _ in recovered.messages:
            counts[topic] += 1
        self.connections = [(t, kind, counts[t], tuple(recovered.qos.get(t, ())))
                            for t, kind in recovered.types.items()]

    def rows(self, topics: set[str] | None) -> Iterator[tuple[int, str, Any]]:
        for stamp, topic, raw in self.recovered.messages:
            if topics is None or topic in topics:
                yield stamp, topic, raw


_WARNED: set[tuple[str, str]] = set()


def _warn_once(path: Path, text: str) -> None:
    """A reader's warning on stderr, once per bag and text in a process (a tool may open the
    same bag several times)."""
    key = (str(path.resolve()), text)
    if key not in _WARNED:
        _WARNED.add(key)
        program = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else 'sensing_nodes'
        print(f'{program}: warning: {path}: {text}', file=sys.stderr, flush=True)


class BagReader:
    """Reads a rosbag2 bag folder (metadata.yaml + MCAP or sqlite3 storage, metadata versions 4
    to 9, as written by rosbag2 itself or by BagWriter), a single .mcap or .db3 file, or a ROS 1
    .bag file; BagError when it cannot.

    Each storage file is opened with the topics it declares itself: rosbags' folder reader
    matches them against metadata.yaml's QoS and silently yields nothing when the two disagree
    (rosbag2's own test bags store 'infinite' deadlines in the file, zero in metadata.yaml).

    A bag a recording did not close (power loss, kill -9: an MCAP file without its footer, often
    no metadata.yaml; a sqlite3 file cut short) is read up to its last complete record
    (bags/recovery.py); `damage` then says what was read and what was lost, and the reader
    prints it once as a warning on stderr. Without metadata.yaml the storage files in the
    folder are read: they hold the topics, types and QoS themselves.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise BagError(f'{self.path}: no such bag')
        self._ros1: Ros1Bag | None = None
        self.damage = ''              # what an unclosed recording lost ('' for a closed bag)
        self.custom_data: dict[str, str] = {}   # metadata.yaml's custom_data
        if self.path.is_file() and self.path.suffix not in STORAGE_SUFFIXES:
            self._ros1 = Ros1Bag(self.path)
            self.topics = self._ros1.topics
            return
        try:
            metadata = self._metadata()
            self._sources = self._open_sources(metadata)
        except BagError:
            raise
        except RecoveryError as exc:
            raise BagError(f'{self.path}: nothing readable: {exc}') from None
        except Exception as exc:  # rosbags raises several types for damaged files
            raise BagError(f'{self.path}: cannot read the bag ({failure_reason(exc)}); '
                           'truncated or damaged?') from None
        self.topics: dict[str, TopicInfo] = {}
        for source in self._sources:
            for topic, msgtype, count, qos in source.connections:
                known = self.topics.get(topic)
                self.topics[topic] = TopicInfo(msgtype, count, qos) if known is None else \
                    TopicInfo(known.msgtype, known.count + count, known.qos)
        self.damage = self._damage(metadata)
        if self.damage:
            _warn_once(self.path, self.damage)

    def _metadata(self) -> dict | None:
        """metadata.yaml's rosbag2_bagfile_information, None when there is none."""
        file = self.path / 'metadata.yaml'
        if self.path.is_file() or not file.is_file():
            return None
        info = yaml.safe_load(file.read_text())['rosbag2_bagfile_information']
        self.custom_data = dict(info.get('custom_data') or {})
        return info

    def _open_sources(self, metadata: dict | None) -> list:
        """The storage files, each read by rosbags when it was closed, else recovered."""
        if self.path.is_file():
            files = [self.path]
        elif metadata is not None:
            files = [self.path / Path(p).name for p in metadata['relative_file_paths']]
            if metadata.get('compression_mode'):  # file- or message-compressed: only rosbags'
                with Reader(self.path):           # folder reader unpacks it
                    pass
                return [_ClosedFile(self.path)]
        else:
            files = sorted((p for p in self.path.iterdir() if p.suffix in STORAGE_SUFFIXES),
                           key=_split_index)
            if not files:
                raise BagError(f'{self.path}: not a rosbag2 bag (no metadata.yaml, no .mcap or '
                               '.db3 file)')
        missing = [f.name for f in files if not f.is_file()]
        if missing:
            raise BagError(f'{self.path}: storage file(s) {", ".join(missing)} named in '
                           'metadata.yaml are missing')
        sources = [self._open_file(f) for f in files]
        if metadata is not None and not any(isinstance(s, _RecoveredFile) for s in sources):
            with Reader(self.path):   # checks metadata.yaml against the storage files
                pass
        return sources

    @staticmethod
    def _open_file(file: Path):
        if file.suffix == '.mcap':
            return _ClosedFile(file) if mcap_closed(file) else \
                _RecoveredFile(read_unclosed_mcap(file))
        try:
            return _ClosedFile(file)
        except Exception:
            if not sqlite_cut_short(file):
                raise
            # SQLite refuses a file cut short: read the rows that are there
            return _RecoveredFile(read_cut_sqlite(file))

    def _damage(self, metadata: dict | None) -> str:
        """What an unclosed recording lost, in words ('' when nothing is missing)."""
        recovered = [s.recovered for s in self._sources if isinstance(s, _RecoveredFile)]
        no_metadata = metadata is None and self.path.is_dir()
        if not recovered and not no_metadata:
            return ''
        parts = ['no metadata.yaml (the recording did not finish): read from its storage '
                 'files'] if no_metadata else []
        for r in recovered:
            parts.append(f'{r.path.name} {r.ending}'
                         + ''.join(f'; {note}' for note in r.notes))
        if recovered:
            parts.append(self._lost(recovered, metadata))
        return '; '.join(parts)

    def _lost(self, recovered: list[Recovered], metadata: dict | None) -> str:
        """How much was read from the recovered files, and what is known to be lost."""
        start = min(r.messages[0][0] for r in recovered)
        end = max(r.messages[-1][0] for r in recovered)
        total = sum(info.count for info in self.topics.values())
        text = f'read {total} messages, bag time up to {(end - start) * 1e-9:.3f} s from the first'
        expected = {} if metadata is None else {
            entry['topic_metadata']['name']: int(entry['message_count'])
            for entry in metadata.get('topics_with_message_count') or []}
        if expected:
            got = {t: self.topics[t].count if t in self.topics else 0 for t in expected}
            lost = {t: (n - got[t], n) for t, n in sorted(expected.items()) if got[t] < n}
            if not lost:
                return f'{text}: every message metadata.yaml counts'
            return (f'{text}; lost {sum(n for n, _ in lost.values())} of the '
                    f'{sum(expected.values())} messages metadata.yaml counts: '
                    + ', '.join(f'{t} {n} of {of}' for t, (n, of) in lost.items()))
        if all(r.data_whole for r in recovered):
            return f'{text}: every message (the files end after their data)'
        text += ('; how much was recorded after that is unknown (nothing that counts the '
                 'messages was written)')
        until = [r.lost_until_ns for r in recovered if r.lost_until_ns is not None]
        if until:
            text += f'; the cut chunk held messages up to {(max(until) - start) * 1e-9:.3f} s'
        return text

    def raw(self, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, bytes]]:
        """(topic, bag time ns, CDR bytes) of every message (of `topics`), in bag-time order."""
        wanted = None if topics is None else set(topics)
        if self._ros1 is not None:
            for topic, stamp, msg in self._ros1.messages(wanted):
                yield topic, stamp, serialize_message(msg)
            return
        streams = [source.rows(wanted) for source in self._sources]
        for stamp, topic, raw in heapq.merge(*streams, key=lambda row: row[0]):
            yield topic, stamp, bytes(raw)

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, Any]]:
        """(topic, bag time ns, rclpy message) for every message (of `topics`)."""
        wanted = None if topics is None else set(topics)
        if self._ros1 is not None:
            yield from self._ros1.messages(wanted)
            return
        classes = {t: message_class(i.msgtype) for t, i in self.topics.items()
                   if wanted is None or t in wanted}
        for topic, stamp, raw in self.raw(classes):
            yield topic, stamp, deserialize_message(raw, classes[topic])


STORAGE_SUFFIXES = ('.mcap', '.db3')


def _split_index(path: Path) -> tuple[str, int]:
    """bag_10.mcap after bag_9.mcap (rosbag2 numbers its split files)."""
    stem, _, number = path.stem.rpartition('_')
    return (stem, int(number)) if number.isdigit() else (path.stem, -1)


class Ros1Bag:
    """A ROS 1 bag (v2.0 .bag file) read with rosbags, its messages as the ROS 2 Jazzy rclpy
    messages of the same name, field by field (ROS 1's header.seq has no ROS 2 field: dropped)."""

    def __init__(self, path: Path) -> None:
        from rosbags.highlevel import AnyReader

        self.path = path
        try:
            with AnyReader([path], default_typestore=TYPESTORE) as reader:
                connections = list(reader.connections)
        except Exception as exc:  # rosbags raises several types for damaged or foreign files
            raise BagError(f'{path}: cannot read the bag ({failure_reason(exc)}); a '
                           'rosbag2 folder or a ROS 1 .bag file expected') from None
        self.topics: dict[str, TopicInfo] = {}
        for c in connections:
            count = self.topics[c.topic].count if c.topic in self.topics else 0
            self.topics[c.topic] = TopicInfo(c.msgtype, count + c.msgcount, ())

    def messages(self, topics: set[str] | None) -> Iterator[tuple[str, int, Any]]:
        """(topic, bag time ns, rclpy message), in bag-time order."""
        from rosbags.highlevel import AnyReader

        with AnyReader([self.path], default_typestore=TYPESTORE) as reader:
            wanted = [c for c in reader.connections if topics is None or c.topic in topics]
            if not wanted:   # rosbags reads every connection when given none
                return
            classes = {c.msgtype: message_class(c.msgtype) for c in wanted}
            for connection, stamp, raw in reader.messages(connections=wanted):
                msg = reader.deserialize(raw, connection.msgtype)
                yield connection.topic, stamp, to_rclpy(msg, classes[connection.msgtype])


def to_rclpy(value: Any, cls: type) -> Any:
    """A rosbags message object -> an instance of the rclpy message class cls, copying the
    fields cls has (a field cls lacks, e.g. ROS 1's header.seq, is dropped)."""
    out = cls()
    for name, kind in cls.get_fields_and_field_types().items():
        field = getattr(value, name)
        element = _message_element(kind)
        if element is not None and isinstance(field, list):
            setattr(out, name, [to_rclpy(item, element) for item in field])
        elif hasattr(field, '__msgtype__'):
            setattr(out, name, to_rclpy(field, type(getattr(out, name))))
        else:
            setattr(out, name, field)      # numbers, strings, numpy arrays of numbers
    return out


def _message_element(kind: str) -> type | None:
    """The rclpy class of a sequence or array field of messages ('sequence<pkg/Name>',
    'pkg/Name[3]'), None for any other field."""
    if not (kind.startswith('sequence<') or kind.endswith(']')) or '/' not in kind:
        return None
    package, name = kind.removeprefix('sequence<').split('[')[0].rstrip('>').split('/')
    return message_class(f'{package}/msg/{name.split(",")[0]}')


def read_messages(
    path: str | Path, topics: Iterable[str] | None = None
) -> Iterator[tuple[str, int, Any]]:
    """(topic, bag time ns, rclpy message) for every message in the bag, in bag-time order."""
    yield from BagReader(path).messages(topics)


def topic_counts(path: str | Path) -> dict[str, tuple[str, int]]:
    """topic -> (type, message count) of every topic in the bag."""
    return {t: (i.msgtype, i.count) for t, i in BagReader(path).topics.items()}
