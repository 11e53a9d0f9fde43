"""Storage files a recording never closed (power loss, kill -9, a full disk): what they hold up
to their last complete record, and how they end.

MCAP: a file without its footer is read record by record from its start (the record layout of
the MCAP specification, parsed with the `mcap` package's record types), every record's length
checked against the bytes the file has: schemas, channels and messages inside chunks and out,
up to the last complete record; from a chunk the file cuts short, the complete messages of the
part that is there (plain or zstd chunks; an lz4 chunk only whole). The `mcap` package's
StreamReader cannot be used as it is: it hands on a record the file cuts short as if it were
whole (a message with part of its data), and a cut chunk fails whole.

sqlite3: SQLite refuses a database file cut short ("database disk image is malformed": its
header counts pages the file no longer has). A temporary copy cut to whole pages, its header
counting the pages present, reads its rows in id order up to the first page that is missing.
"""

from __future__ import annotations

import shutil
import sqlite3
import struct
import tempfile
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path

MCAP_MAGIC = b'\x89MCAP0\r\n'
_RECORD = struct.Struct('<BQ')        # opcode, body length
_MESSAGE = struct.Struct('<HIQQ')     # channel id, sequence, log time, publish time
_CHUNK = struct.Struct('<QQQI')       # message start/end time, uncompressed size and crc
_U32 = struct.Struct('<I')
_U64 = struct.Struct('<Q')
_SCHEMA, _CHANNEL, _MESSAGE_OP, _CHUNK_OP, _FOOTER, _DATA_END = 0x03, 0x04, 0x05, 0x06, 0x02, 0x0F
_SQLITE_MAGIC = b'SQLite format 3\x00'


class RecoveryError(Exception):
    """Nothing readable: the message says what the file holds and where it ends."""


@dataclass
class Recovered:
    """What one storage file still holds: its topics (type, offered QoS as rosbags records),
    its messages (bag time ns, topic, CDR bytes) in bag-time order, and how it ends."""

    path: Path
    types: dict[str, str] = field(default_factory=dict)
    qos: dict[str, list] = field(default_factory=dict)
    messages: list[tuple[int, str, bytes]] = field(default_factory=list)
    ending: str = ''   # how the file ends, after its name ('was not closed: ...'; '' when closed)
    lost_until_ns: int | None = None   # bag time the cut chunk reached: what lies beyond the
    #                                    last message read, up to it, is lost for certain
    data_whole: bool = False       # the cut is after the data section: no message is missing
    notes: list[str] = field(default_factory=list)


def mcap_closed(path: Path) -> bool:
    """Whether an MCAP file ends as a closed one does (footer, then the magic)."""
    size = path.stat().st_size
    if size < 2 * len(MCAP_MAGIC) + _RECORD.size:
        return False
    with path.open('rb') as handle:
        handle.seek(-len(MCAP_MAGIC), 2)
        return handle.read() == MCAP_MAGIC


@dataclass
class _Cut:
    """Where the record walk stopped short of a complete record."""

    at: int              # byte where the incomplete record starts
    opcode: int | None   # None: not even its 9-byte opening is there
    have: int            # bytes of its body in the file
    length: int          # bytes its opening declares


class _Damaged(Exception):
    """A complete record that cannot be what it claims (zeros, a chunk that does not unpack)."""


_NAMES = {0x01: 'header', 0x02: 'footer', 0x03: 'schema', 0x04: 'channel', 0x05: 'message',
          0x06: 'chunk', 0x07: 'message index', 0x08: 'chunk index', 0x09: 'attachment',
          0x0A: 'attachment index', 0x0B: 'statistics', 0x0C: 'metadata',
          0x0D: 'metadata index', 0x0E: 'summary offset', 0x0F: 'data end'}


def _walk(buf: memoryview, pos: int, on_record) -> tuple[int, _Cut | None]:
    """on_record(opcode, body) for every complete record from byte pos on; (end of the last
    complete record, the incomplete record after it or None). Stops after a footer."""
    size = len(buf)
    while pos < size:
        if size - pos < _RECORD.size:
            return pos, _Cut(pos, None, size - pos, _RECORD.size)
        opcode, length = _RECORD.unpack_from(buf, pos)
        if opcode == 0:
            raise _Damaged(f'byte {pos} starts no record (opcode 0: zeros, as a power cut can '
                           'leave where data was never written)')
        end = pos + _RECORD.size + length
        if end > size:
            return pos, _Cut(pos, opcode, size - pos - _RECORD.size, length)
        on_record(opcode, buf[pos + _RECORD.size:end])
        if opcode == _FOOTER:
            return end, None
        pos = end
    return pos, None


class _McapRecords:
    """Schemas, channels and messages collected from a walk."""

    def __init__(self) -> None:
        from mcap.data_stream import ReadDataStream
        from mcap.records import Channel, Schema

        self._stream = ReadDataStream
        self._schema, self._channel = Schema, Channel
        self.schemas: dict[int, object] = {}
        self.channels: dict[int, object] = {}
        self.messages: list[tuple[int, int, bytes]] = []    # (log time, channel id, data)
        self.data_ended = False
        self.footer = False

    def inner(self, opcode: int, body: memoryview) -> None:
        """A record inside a chunk, or outside chunks in the data section."""
        if opcode == _MESSAGE_OP:
            channel, _, log_time, _ = _MESSAGE.unpack_from(body)
            self.messages.append((log_time, channel, bytes(body[_MESSAGE.size:])))
        elif opcode == _SCHEMA:
            schema = self._schema.read(self._stream(BytesIO(bytes(body))))
            self.schemas[schema.id] = schema
        elif opcode == _CHANNEL:
            channel = self._channel.read(self._stream(BytesIO(bytes(body))))
            self.channels[channel.id] = channel

    def top(self, opcode: int, body: memoryview) -> None:
        """A record of the file itself."""
        if opcode == _CHUNK_OP:
            records = _chunk_records(body, whole=True)
            if _walk(records, 0, self.inner)[1] is not None:
                raise _Damaged('a chunk whose records do not fit in it')
        elif opcode == _DATA_END:
            self.data_ended = True
        elif opcode == _FOOTER:
            self.footer = True
        elif not self.data_ended:   # the summary repeats schemas and channels: nothing new
            self.inner(opcode, body)


def _chunk_records(body: memoryview, whole: bool) -> memoryview:
    """The records of a chunk record's body (decompressed); of the part present when not
    `whole` (what a decompressor gives from a cut stream; an lz4 chunk gives nothing)."""
    if len(body) < _CHUNK.size + 4:
        return memoryview(b'')
    _, _, size, crc = _CHUNK.unpack_from(body)
    (name_length,) = _U32.unpack_from(body, _CHUNK.size)
    start = _CHUNK.size + 4 + name_length + 8
    if len(body) < start:
        return memoryview(b'')
    compression = bytes(body[_CHUNK.size + 4:start - 8]).decode('ascii', 'replace')
    (length,) = _U64.unpack_from(body, start - 8)
    data = body[start:start + length]
    if whole and len(data) != length:
        raise _Damaged('a chunk whose data does not fit in it')
    try:
        if compression == '':
            records = data
        elif compression == 'zstd':
            import zstandard

            if whole:
                records = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
            else:
                records = zstandard.ZstdDecompressor().decompressobj().decompress(bytes(data))
        elif compression == 'lz4' and whole:
            import lz4.frame

            records = lz4.frame.decompress(bytes(data))
        elif compression == 'lz4':
            return memoryview(b'')
        else:
            raise _Damaged(f'a chunk compressed with {compression!r}, which is not read here')
    except _Damaged:
        raise
    except Exception as exc:    # zstandard and lz4 raise their own types for bad data
        if not whole:
            return memoryview(b'')
        raise _Damaged(f'a chunk that does not decompress ({exc})') from None
    if whole and (len(records) != size or (crc and _crc32(records) != crc)):
        raise _Damaged('a chunk whose size or checksum does not match its header')
    return memoryview(records)


def _crc32(data) -> int:
    import zlib

    return zlib.crc32(data)


def read_unclosed_mcap(path: Path) -> Recovered:
    """Every complete record of an MCAP file (closed or not) and the complete messages of a
    chunk it cuts short; RecoveryError when it holds no message."""
    buf = memoryview(path.read_bytes())
    if bytes(buf[:len(MCAP_MAGIC)]) != MCAP_MAGIC:
        raise RecoveryError(f'{path.name} is not an MCAP file (no MCAP magic at its start)')
    records = _McapRecords()
    try:
        cut, damage = _walk(buf, len(MCAP_MAGIC), records.top)[1], ''
    except _Damaged as exc:
        cut, damage = None, str(exc)
    result = Recovered(path)
    partial = 0
    if cut is not None and cut.opcode == _CHUNK_OP and not records.data_ended:
        body = buf[cut.at + _RECORD.size:]
        before = len(records.messages)
        _walk(_chunk_records(body, whole=False), 0, records.inner)
        partial = len(records.messages) - before
        if len(body) >= _CHUNK.size:
            result.lost_until_ns = _CHUNK.unpack_from(body)[1]
    result.data_whole = records.data_ended and not damage
    result.ending = _mcap_ending(len(buf), records, cut, damage, partial)
    _mcap_topics(records, result)
    if not result.messages:
        raise RecoveryError(f'{path.name} {result.ending}: no complete message in it')
    return result


def _mcap_ending(size: int, records: _McapRecords, cut: _Cut | None, damage: str,
                 partial: int) -> str:
    """How the file ends, in words."""
    if damage:
        return f'is damaged: {damage}; read up to there'
    if records.footer:
        return ''
    if cut is None:
        where = 'after its data, in its summary' if records.data_ended else \
            'between two records' if records.messages else 'before its first chunk or message'
        return f'was not closed: it ends {where} ({size} bytes, no footer)'
    if cut.opcode is None:
        return (f'was not closed: it ends {cut.have} bytes into the opening of a record at '
                f'byte {cut.at}')
    what = _NAMES.get(cut.opcode, f'opcode 0x{cut.opcode:02x}')
    text = (f'was not closed: it ends inside a {what} record at byte {cut.at} ({cut.have} of its '
            f'{cut.length} bytes)' + (', after its data' if records.data_ended else ''))
    if cut.opcode == _CHUNK_OP:
        text += f'; {partial} complete messages read from the part of it that is there'
    return text


def _mcap_topics(records: _McapRecords, result: Recovered) -> None:
    """Topics (type, QoS) of the channels and the messages, sorted by bag time."""
    from rosbags.rosbag2.metadata import parse_qos

    topics: dict[int, str] = {}
    for channel in records.channels.values():
        schema = records.schemas.get(channel.schema_id)
        if schema is None or channel.message_encoding != 'cdr':
            result.notes.append(f'channel {channel.topic}: no ROS 2 schema or not CDR: skipped')
            continue
        topics[channel.id] = channel.topic
        result.types.setdefault(channel.topic, schema.name)
        qos = channel.metadata.get('offered_qos_profiles', '')
        result.qos.setdefault(channel.topic, parse_qos(qos) if qos else [])
    orphans = sum(1 for _, channel, _ in records.messages if channel not in topics)
    if orphans:
        result.notes.append(f'{orphans} messages of channels the file does not declare: skipped')
    rows = [(t, topics[c], data) for t, c, data in records.messages if c in topics]
    rows.sort(key=lambda row: row[0])     # stable: ties keep the order the file has them in
    result.messages = rows


def sqlite_cut_short(path: Path) -> bool:
    """Whether a file is an SQLite database shorter than the pages its header counts."""
    with path.open('rb') as handle:
        header = handle.read(100)
    if len(header) < 100 or not header.startswith(_SQLITE_MAGIC):
        return len(header) < 100        # cut inside its header: nothing to tell it by
    page = struct.unpack_from('>H', header, 16)[0]
    page = 65536 if page == 1 else page
    return path.stat().st_size < struct.unpack_from('>I', header, 28)[0] * page


def read_cut_sqlite(path: Path) -> Recovered:
    """The rows of a rosbag2 sqlite3 file SQLite refuses (cut short): read from a copy cut to
    whole pages whose header counts them, in id order up to the first missing page."""
    from rosbags.rosbag2.metadata import parse_qos

    result = Recovered(path)
    size = path.stat().st_size
    with path.open('rb') as handle:
        header = handle.read(100)
    if len(header) < 100 or not header.startswith(_SQLITE_MAGIC):
        raise RecoveryError(f'{path.name} is not an SQLite database ({size} bytes)')
    page = struct.unpack_from('>H', header, 16)[0]
    page = 65536 if page == 1 else page
    counted = struct.unpack_from('>I', header, 28)[0]
    pages = size // page
    with tempfile.TemporaryDirectory(prefix='sensing_bag_recovery-') as tmp:
        copy = Path(tmp) / path.name
        shutil.copyfile(path, copy)
        with copy.open('r+b') as handle:
            handle.truncate(pages * page)
            handle.seek(28)
            handle.write(struct.pack('>I', pages))
        connection = sqlite3.connect(f'file:{copy}?mode=ro', uri=True)
        try:
            try:
                columns = {row[1] for row in connection.execute('PRAGMA table_info(topics)')}
                qos_column = 'offered_qos_profiles' if 'offered_qos_profiles' in columns \
                    else "''"
                topics = {i: (name, kind, qos) for i, name, kind, qos in connection.execute(
                    f'SELECT id, name, type, {qos_column} FROM topics')}
            except sqlite3.DatabaseError as exc:
                raise RecoveryError(f'{path.name}: SQLite cannot read its topics ({exc}; '
                                    f'{size} bytes, {pages} of {counted} pages)') from None
            rows = []
            try:
                for topic_id, stamp, data in connection.execute(
                        'SELECT topic_id, timestamp, data FROM messages ORDER BY id'):
                    rows.append((int(stamp), topics[topic_id][0], bytes(data)))
                stopped = ''
            except (sqlite3.DatabaseError, KeyError) as exc:
                stopped = f' up to a missing page ({exc})'
        finally:
            connection.close()
    for name, kind, qos in topics.values():
        result.types.setdefault(name, kind)
        result.qos.setdefault(name, parse_qos(qos) if qos else [])
    rows.sort(key=lambda row: row[0])
    result.messages = rows
    result.ending = (f'is cut short: SQLite calls it malformed; it has {pages} whole pages of '
                     f'the {counted} its header counts; {len(rows)} rows read in id '
                     f'order{stopped}')
    if not rows:
        raise RecoveryError(f'{path.name} {result.ending}: no readable message in it')
    return result
