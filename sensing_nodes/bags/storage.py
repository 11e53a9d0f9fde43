"""rosbag2 bags of rclpy messages, written (MCAP, through the `mcap` package's writer) and read
(MCAP or sqlite3, and ROS 1 .bag files, with rosbags).

Every message is written in canonical CDR: the fields exactly as rclpy/DDS serialise them, but
with every alignment padding byte zero and no bytes after the last field (`canonical_cdr`).
rclpy's serialiser leaves padding uninitialised (process memory) and appends 4 alignment bytes
after a trailing empty sequence of 8-byte elements (JointState's `effort`), which rosbags'
strict reader rejects; canonical bytes make same-seed recordings byte-identical and decode with
rosbags, mcap-ros2-support and rclpy alike. Only public names of rosbags and mcap are used
(test_public_api.py).
"""

from __future__ import annotations

import array
import heapq
import importlib
import itertools
import os
import re
import signal
import sys
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.rosbag2 import Reader
from rosbags.serde import SerdeError
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
MCAP_CHUNK_BYTES = 2**20   # a chunk is closed past this size too (rosbag2's default)
# metadata.yaml's custom_data key by which BagWriter says every message is canonical CDR: a
# bag copied from such a bag (sensing_pipeline's inputs) need not be made canonical again.
CANONICAL_KEY = 'sensing_nodes.cdr'
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
    order and values, padding zero, nothing after the last field): what rosbags' typestore gives
    when it decodes the message and encodes it again. Bytes that are no message of the type
    raise what its decoder raises (ValueError for a wrong encapsulation header)."""
    if len(raw) < 4 or bytes(raw[:2]) not in (b'\x00\x00', b'\x00\x01'):
        raise ValueError(f'{msgtype}: not a CDR message (encapsulation header {bytes(raw[:4])!r})')
    message = _decode_cdr(raw, msgtype)
    return bytes(TYPESTORE.serialize_cdr(message, msgtype, little_endian=bool(raw[1])))


def message_cdr(msg: Any) -> bytes:
    """An rclpy message as canonical CDR (little endian), encoded by rosbags' typestore (padding
    zero by construction): the message itself where rosbags can read its fields (rosbags' encoder
    reads attributes; a type without numeric sequences), else its rosbags copy (to_rosbags: an
    rclpy numeric sequence is an array.array, which rosbags does not take); rclpy's serialiser
    and the round trip where neither will do (a byte field). The first that works for a type is
    remembered."""
    msgtype, kind = type_name(msg), type(msg)
    way = _ENCODING.get(kind, 0)
    while True:
        try:
            data = _ENCODINGS[way](msg, msgtype)
        except Exception:  # noqa: BLE001 - a field this way cannot encode: the next way
            if way == len(_ENCODINGS) - 1:
                raise
            way += 1
            continue
        _ENCODING[kind] = way
        return data


_ENCODINGS = (
    lambda msg, msgtype: bytes(TYPESTORE.serialize_cdr(msg, msgtype, little_endian=True)),
    lambda msg, msgtype: bytes(TYPESTORE.serialize_cdr(to_rosbags(msg), msgtype,
                                                       little_endian=True)),
    lambda msg, msgtype: canonical_cdr(serialize_message(msg), msgtype),
)
_ENCODING: dict[type, int] = {}   # per rclpy message class: the first of _ENCODINGS that works


# array.array type codes -> numpy dtypes (rosbags encodes numeric sequences from numpy arrays).
_ARRAY_DTYPES = {'b': 'int8', 'B': 'uint8', 'h': 'int16', 'H': 'uint16', 'i': 'int32',
                 'I': 'uint32', 'l': 'int64', 'L': 'uint64', 'q': 'int64', 'Q': 'uint64',
                 'f': 'float32', 'd': 'float64'}
_ROSBAGS_CLASSES: dict[type, tuple[type, tuple[str, ...]]] = {}


def to_rosbags(msg: Any) -> Any:
    """An rclpy message as rosbags' message of the same type, field by field (numeric sequences
    as numpy arrays over the same memory, no copy): what rosbags' typestore encodes."""
    entry = _ROSBAGS_CLASSES.get(type(msg))
    if entry is None:
        entry = _ROSBAGS_CLASSES[type(msg)] = (
            TYPESTORE.types[type_name(msg)], tuple(type(msg).get_fields_and_field_types()))
    cls, names = entry
    values = []
    for name in names:
        value = getattr(msg, name)
        if isinstance(value, array.array):
            value = np.frombuffer(value, _ARRAY_DTYPES[value.typecode])
        elif hasattr(value, 'get_fields_and_field_types'):
            value = to_rosbags(value)
        elif isinstance(value, list) and value and \
                hasattr(value[0], 'get_fields_and_field_types'):
            value = [to_rosbags(item) for item in value]
        values.append(value)
    return cls(*values)


def _decode_cdr(raw: bytes | memoryview, msgtype: str) -> object:
    """rosbags' message of CDR bytes, any bytes after the last field dropped.

    rosbags' decoder refuses more than 3 bytes after the last field, which rclpy's serialiser
    leaves (Fast-CDR aligns before the absent elements of a trailing empty sequence of doubles:
    an all-empty JointState ends in 8 such bytes): the message is decoded again without the last
    4, 8, ... bytes until no more than 3 are left over (a cut never reaches a field the decoder
    read). What the decoder raises for bytes it cannot read is raised as it is."""
    cut = 0
    while True:
        try:
            return TYPESTORE.deserialize_cdr(raw[:len(raw) - cut], msgtype)
        except SerdeError as error:
            if 'size mismatch' not in str(error):
                raise (error.__cause__ or error) from None
        cut += 4


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


def _qos_dicts(profiles: list) -> list[dict]:
    """rosbags QoS records -> offered_qos_profiles as rosbag2 (metadata version 9) writes them."""
    def time(t) -> dict:
        return {'sec': t.sec, 'nsec': t.nsec}

    return [{'history': q.history.name.lower(), 'depth': q.depth,
             'reliability': q.reliability.name.lower(),
             'durability': q.durability.name.lower(), 'deadline': time(q.deadline),
             'lifespan': time(q.lifespan), 'liveliness': q.liveliness.name.lower(),
             'liveliness_lease_duration': time(q.liveliness_lease_duration),
             'avoid_ros_namespace_conventions': q.avoid_ros_namespace_conventions}
            for q in profiles]


def _yaml(data: Any) -> str:
    return yaml.safe_dump(data, default_flow_style=False, sort_keys=False)


@dataclass
class _Topic:
    """A topic of a bag being written: its channel, type, offered QoS and message count."""

    channel: int
    msgtype: str
    qos: list
    count: int = 0


class BagWriter:
    """Writes rclpy messages to a new rosbag2 (format 9, MCAP storage) at `path`: the MCAP file
    through the `mcap` package's writer (profile ros2, each type's definition as its schema,
    each topic's offered QoS in its channel's metadata, the bag's metadata in a `rosbag2`
    record), and metadata.yaml; with `compress`, MCAP chunks are zstd-compressed (storage-level,
    as rosbag2's MCAP presets do).

    What a crash (power loss, kill -9) can take: the file holds every closed chunk, and its
    footer, summary and metadata.yaml are written at close, so an unclosed bag is read up to
    its last chunk (BagReader). With `chunk_s` (default 1 s) a chunk is closed once its
    messages span that much bag time, then handed to the operating system (fsync at most once
    per wall second), and whenever flush() is called (with an fsync; the live recorder: every
    wall second): a crash of the process loses at most the open chunk, a power cut at most the
    last wall second more. None: chunks of 1 MiB, the open one written at close (bags written
    in one go, where a crash leaves nothing to keep).
    """

    def __init__(self, path: str | Path, compress: bool = False,
                 chunk_s: float | None = CHUNK_S) -> None:
        self.path = Path(path)
        if self.path.exists():
            raise BagError(f'{self.path} exists already, not overwriting')
        self._compress = compress
        self._topics: dict[str, _Topic] = {}
        self._schemas: dict[str, int] = {}
        self._custom_data: dict[str, str] = {CANONICAL_KEY: 'canonical'}
        self._first_ns, self._last_ns = 2**63 - 1, 0
        self._chunk_ns = None if chunk_s is None else int(chunk_s * 1e9)
        self._chunk_first_ns: int | None = None   # bag time of the open chunk's first message
        self._synced = time.monotonic()
        self._file = None
        self._mcap: McapWriter | None = None

    @property
    def _storage(self) -> Path:
        return self.path / f'{self.path.name}.mcap'

    def __enter__(self) -> BagWriter:
        self.path.mkdir(mode=0o755, parents=True)
        self._file = self._storage.open('xb')
        self._mcap = McapWriter(self._file, chunk_size=MCAP_CHUNK_BYTES, compression=(
            CompressionType.ZSTD if self._compress else CompressionType.NONE))
        self._mcap.start(profile='ros2', library='sensing_nodes BagWriter')
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        with _signals_held():
            info = self._metadata()
            self._mcap.add_metadata('rosbag2', {'serialized_metadata': _yaml(info).strip()})
            self._mcap.finish()
            self._file.close()
            self._mcap = None
            metadata = self.path / 'metadata.yaml'
            staged = metadata.with_suffix('.yaml.tmp')
            staged.write_text(_yaml({'rosbag2_bagfile_information': info}))
            staged.replace(metadata)

    def _metadata(self) -> dict:
        """metadata.yaml's rosbag2_bagfile_information (version 9) of what was written."""
        start, duration = self._first_ns, max(0, self._last_ns - self._first_ns)
        count = sum(topic.count for topic in self._topics.values())

        def span() -> dict:    # a new dict per use: YAML writes no anchors
            return {'starting_time': {'nanoseconds_since_epoch': start},
                    'duration': {'nanoseconds': duration}}

        return {
            'version': 9, 'storage_identifier': 'mcap',
            'relative_file_paths': [self._storage.name], **span(), 'message_count': count,
            'topics_with_message_count': [
                {'topic_metadata': {'name': name, 'type': topic.msgtype,
                                    'serialization_format': 'cdr',
                                    'offered_qos_profiles': _qos_dicts(topic.qos),
                                    'type_description_hash': TYPESTORE.hash_rihs01(
                                        topic.msgtype)},
                 'message_count': topic.count} for name, topic in self._topics.items()],
            'compression_format': '', 'compression_mode': '',
            'files': [{'path': self._storage.name, **span(), 'message_count': count}],
            'custom_data': dict(self._custom_data) or None,
            'ros_distro': 'jazzy',
        }

    def set_custom_data(self, key: str, value: str) -> None:
        """A key of metadata.yaml's custom_data (what the bag's producer wants said)."""
        self._custom_data[key] = value

    def add_topic(self, topic: str, msg_type: str, qos: Any = None) -> None:
        """Register a topic up front, so it is in the bag even when no message arrives; `qos`
        (an rclpy QoSProfile, or a list of them) is stored as its offered QoS, which
        `ros2 bag play` publishes with."""
        if topic in self._topics:
            return
        if msg_type not in self._schemas:
            definition, _ = TYPESTORE.generate_msgdef(msg_type, ros_version=2)
            encoding = 'ros2idl' if definition.startswith('=' * 80 + '\nIDL: ') else 'ros2msg'
            self._schemas[msg_type] = self._mcap.register_schema(msg_type, encoding,
                                                                 definition.encode())
        profiles = [] if qos is None else [qos] if not isinstance(qos, (list, tuple)) else qos
        records = [bag_qos(p) for p in profiles]
        channel = self._mcap.register_channel(topic, 'cdr', self._schemas[msg_type], {
            'offered_qos_profiles': _yaml(_qos_dicts(records)).strip()})
        self._topics[topic] = _Topic(channel, msg_type, records)

    def write(self, topic: str, msg: Any, stamp_ns: int) -> None:
        """Append one rclpy message, with `stamp_ns` as its bag (receive) time."""
        self.add_topic(topic, type_name(msg))
        self.write_raw_many(((topic, message_cdr(msg), stamp_ns),), canonical_topics={topic})

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
                self._add(batch, canonical_topics)

    def _add(self, batch: list[tuple[str, bytes, int]], canonical_topics) -> None:
        add, topics, chunk_ns = self._mcap.add_message, self._topics, self._chunk_ns
        first, last = self._first_ns, self._last_ns
        for topic, data, stamp in batch:
            entry = topics[topic]
            if topic not in canonical_topics:
                data = canonical_cdr(data, entry.msgtype)
            stamp = int(stamp)
            add(entry.channel, stamp, data, stamp)
            entry.count += 1
            if stamp < first:
                first = stamp
            if stamp > last:
                last = stamp
            if chunk_ns is not None:
                # Close the open chunk once its messages span chunk_s of bag time.
                if self._chunk_first_ns is None:
                    self._chunk_first_ns = stamp
                elif abs(stamp - self._chunk_first_ns) >= chunk_ns:
                    self._close_chunk()
        self._first_ns, self._last_ns = first, last

    @property
    def counts(self) -> dict[str, int]:
        """Messages written per topic."""
        return {name: topic.count for name, topic in self._topics.items()}

    def flush(self) -> None:
        """Close the open chunk and hand the file to the disk (fsync): a crash or a power cut
        after this keeps every message written before it."""
        with _signals_held():
            self._close_chunk(sync=True)

    def _close_chunk(self, sync: bool = False) -> None:
        if self._mcap is None:
            return
        self._mcap.flush()     # the open chunk and its message indexes, into the file
        self._chunk_first_ns = None
        now = time.monotonic()
        if sync or now - self._synced >= FSYNC_INTERVAL_S:
            os.fsync(self._file.fileno())
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
        self.custom_data: dict[str, str] = {}   # metadata.yaml's custom_data (CANONICAL_KEY)
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
