"""Fast paths between the nodes' high-rate messages and their CDR bytes (what DDS carries).

Decoding: subscriptions whose messages are decoded here instead of by rclpy. rclpy turns every
received message into Python objects through each field's generated Python setter (a Python
__init__ per sub-message, a numpy array per covariance): ~100 us for an Imu and ~270 us for an
Odometry on the development machine, more than the nodes' own work. A decoder generated per
type from rosbags' definitions (`_DecoderSource`: one struct read per run of fixed fields, the
messages named tuples built in C) reads little-endian bytes into a message with the same fields,
read the same way (attribute access; fixed and numeric arrays as numpy arrays, strings as str):
2.3 us for an Imu, 3.4 us for an Odometry, where rosbags' own decoder took 6.0 and 9.2 us
(test_cdr checks it gives rosbags' messages, field by field). Callbacks written for rclpy
messages read these alike. They are for reading only: copy fields out (numbers, strings,
arrays), never assign a decoded sub-message into an rclpy message (rclpy's converter expects
its own classes).

Encoding: publishing an rclpy message converts it field by field back into C and serialises it
(~80 us for an Odometry). The stamped outputs published per input message (Imu, Odometry, a
TFMessage) are a header, strings and a fixed block of float64 fields, so they are packed here
directly into little-endian CDR (XCDR1, as rmw_fastrtps writes, with zero padding: canonical
CDR) by one cached struct per frame-id layout, and published as bytes: the same message on the
wire, checked against rclpy's serialiser in test/test_cdr.py. The line extractor's MarkerArray
and PointCloud2 are built from a layout made once per frame and style, with the stamps, counts
and points patched in.
"""

from __future__ import annotations

import collections
import functools
import itertools
import struct
from typing import Any, Callable, Sequence

import numpy as np
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.serialization import deserialize_message
from rosbags.typesys.base import normalize_fieldname

from sensing_nodes.bags.storage import TYPESTORE, type_name
from sensing_nodes.core.geometry import quaternion
from sensing_nodes.core.geometry.se2 import Pose2
from sensing_nodes.core.geometry.transform import Transform

_CDR_LE = b'\x00\x01\x00\x00'   # encapsulation: plain CDR, little endian, no options
_LENGTH = struct.Struct('<I')
_ONE = _LENGTH.pack(1)
_ZEROS_36 = (0.0,) * 36


def cdr_decoder(msg_class: type) -> Callable[[bytes], Any]:
    """A function decoding serialized (CDR) bytes of msg_class into a message with its fields.

    Little-endian CDR (what DDS and the bags here carry) is decoded by a decoder generated for
    the type (`_DecoderSource`), into read-only messages (tuples with named fields); whatever it
    does not take (big-endian CDR, bytes it finds malformed) goes to rosbags' decoder, then to
    rclpy's own deserializer, which decides (and says why). Bytes after the last field (Fast-CDR's
    padding before an empty sequence of doubles) are ignored, as rclpy does.
    """
    msgtype = type_name(msg_class)
    fast = _fast_decoder(msgtype)

    def decode(raw: bytes) -> Any:
        if fast is not None and len(raw) >= 4 and raw[0] == 0 and raw[1] == 1:
            try:
                return fast(raw)
            except Exception:   # noqa: BLE001 - malformed here: rosbags and rclpy decide
                pass
        if len(raw) >= 4 and raw[0] == 0 and raw[1] in (0, 1):
            # rosbags' message definition (13 generated functions for the type and each type
            # in it: 0.28 MB for Imu and Odometry) only for bytes that need it.
            msgdef = TYPESTORE.get_msgdef(msgtype)
            decode_body = msgdef.deserialize_cdr_le if raw[1] else msgdef.deserialize_cdr_be
            try:
                return decode_body(memoryview(raw)[4:], 0, msgdef.cls, TYPESTORE)[0]
            except Exception:   # noqa: BLE001 - rclpy's deserializer decides (and says why)
                pass
        return deserialize_message(raw, msg_class)

    return decode


def _fields(msgtype: str) -> list[tuple[str, Any]]:
    """(name, rosbags field description) of a type's fields, names as rosbags' message classes
    have them, read from the typestore's definitions without generating its serializers."""
    return [(normalize_fieldname(name), desc) for name, desc in TYPESTORE.fielddefs[msgtype][1]]


class _Malformed(Exception):
    """Bytes the generated decoder does not vouch for (rosbags' decoder decides)."""


_MESSAGE_CLASSES: dict[str, type] = {}
_FAST_DECODERS: dict[str, Callable[[bytes], Any] | None] = {}


def message_tuple_class(msgtype: str) -> type:
    """The read-only message class of a 'pkg/msg/Name' type the generated decoders build: a
    named tuple of its fields (attribute access as on rclpy's and rosbags' messages, built in C,
    no Python __init__ per sub-message), with __msgtype__ as rosbags' classes have."""
    cls = _MESSAGE_CLASSES.get(msgtype)
    if cls is None:
        fields = [name for name, _ in _fields(msgtype)]
        cls = collections.namedtuple(msgtype.rsplit('/', 1)[-1], fields)
        cls.__msgtype__ = msgtype
        _MESSAGE_CLASSES[msgtype] = cls
    return cls


def _fast_decoder(msgtype: str) -> Callable[[bytes], Any] | None:
    """The generated little-endian decoder of a type (None for a type it does not cover)."""
    if msgtype not in _FAST_DECODERS:
        try:
            _FAST_DECODERS[msgtype] = _DecoderSource.build(msgtype)
        except _Malformed:
            _FAST_DECODERS[msgtype] = None
    return _FAST_DECODERS[msgtype]


# struct format and numpy dtype of each CDR primitive, as rosbags reads them (rosbags.serde:
# 'byte' is signed, 'char' unsigned).
_PRIMITIVES = {'bool': ('?', 'bool_'), 'byte': ('b', 'int8'), 'char': ('B', 'uint8'),
               'int8': ('b', 'int8'), 'uint8': ('B', 'uint8'), 'int16': ('h', 'int16'),
               'uint16': ('H', 'uint16'), 'int32': ('i', 'int32'), 'uint32': ('I', 'uint32'),
               'int64': ('q', 'int64'), 'uint64': ('Q', 'uint64'), 'float32': ('f', 'float32'),
               'float64': ('d', 'float64')}


class _DecoderSource:
    """The Python source of one type's little-endian CDR decoder, generated from its rosbags
    definition: every field at its natural alignment from the body's start (what rosbags'
    generated decoder does, field by field), consecutive fixed-size fields (a Header's stamp, a
    pose, covariances) read by one struct.unpack_from with the padding between them known in
    advance, fixed numeric arrays and numeric sequences as read-only numpy arrays over the
    bytes (as rosbags gives them), strings and sequence lengths checked as rosbags checks them
    (_Malformed otherwise). `pos` is the offset in the whole message, the body starting at 4;
    (mod, rem): pos - 4 is rem modulo mod where known."""

    def __init__(self, scope: dict, element: int | None = None) -> None:
        self.scope = scope
        self.names = scope['_names']
        head = ('def decode(raw):', ' size = len(raw)', ' pos = 4') if element is None else \
            ('def decode(raw, pos, size):',)
        self.lines = list(head)
        self.mod, self.rem = (8, 0) if element is None else (element, 0)
        self._run: list[str] = []        # struct format of the pending fixed-size fields
        self._run_size = 0
        self._run_var = ''
        self._arrays: list[tuple[str, str, int, int]] = []   # (name, dtype, count, offset)

    @classmethod
    def build(cls, msgtype: str) -> Callable[[bytes], Any]:
        scope = {'_new': tuple.__new__, 'u32': _LENGTH.unpack_from,
                 'frombuffer': np.frombuffer, '_Malformed': _Malformed,
                 '_names': itertools.count()}
        source = cls(scope)
        expression = source.message(msgtype)
        return source.compile(f'return {expression}', msgtype)

    def compile(self, result: str, msgtype: str) -> Callable:
        self.flush()
        source = '\n'.join([*self.lines, f' {result}'])
        name = f'decode{next(self.names)}'
        local: dict = {}
        exec(compile(source, f'<CDR decoder of {msgtype}>', 'exec'), self.scope, local)
        self.scope[name] = local['decode']
        return local['decode']

    def _name(self, prefix: str) -> str:
        return f'{prefix}{next(self.names)}'

    def message(self, msgtype: str) -> str:
        """Lines reading a message's fields; the expression that builds it."""
        parts = [self.field(desc) for _, desc in _fields(msgtype)]
        cls_name = self._name('M')
        self.scope[cls_name] = message_tuple_class(msgtype)
        return f'_new({cls_name}, ({", ".join(parts)}{"," if len(parts) == 1 else ""}))'

    def field(self, desc) -> str:
        """Lines reading one field; the expression of its value."""
        from rosbags.interfaces import Nodetype

        if desc[0] == Nodetype.NAME:
            return self.message(desc[1])
        if desc[0] == Nodetype.BASE:
            kind = desc[1][0]
            return self.string() if kind == 'string' else self.scalar(kind)
        sub = desc[1][0]
        if desc[0] == Nodetype.ARRAY:
            length = desc[1][1]
            if sub[0] == Nodetype.BASE and sub[1][0] != 'string':
                return self.array(sub[1][0], length)
            return '[' + ', '.join(self.field(sub) for _ in range(length)) + ']'
        return self.sequence(sub)

    # -- fixed-size fields, gathered into runs ----------------------------------------------
    def _fixed(self, kind: str, count: int) -> tuple[str, int]:
        """Append a fixed-size field (count primitives) to the run; its format and offset."""
        if kind not in _PRIMITIVES:
            raise _Malformed(kind)            # float128: rosbags reads it
        code, _ = _PRIMITIVES[kind]
        size = struct.calcsize(code)
        if size > self.mod:                   # alignment not known here: a new run
            self.flush()
            self.lines.append(f' pos = ((pos + {size - 5}) & -{size}) + 4')
            self.mod, self.rem = size, 0
        pad = -self.rem % size
        if pad:
            self._run.append(f'{pad}x')
        offset = self._run_size + pad
        self._run_size = offset + size * count
        self.rem = (self.rem + pad + size * count) % self.mod
        if not self._run_var:
            self._run_var = self._name('v')
        return code, offset

    def scalar(self, kind: str) -> str:
        code, _ = self._fixed(kind, 1)
        index = sum(1 for part in self._run if not part.endswith('x'))
        self._run.append(code)
        return f'{self._run_var}[{index}]'

    def array(self, kind: str, length: int) -> str:
        _, offset = self._fixed(kind, length)
        size = struct.calcsize(_PRIMITIVES[kind][0]) * length
        self._run.append(f'{size}x')          # checked by unpack_from, read by frombuffer
        name = self._name('a')
        self._arrays.append((name, _PRIMITIVES[kind][1], length, offset))
        return name

    def flush(self) -> None:
        """Lines reading the pending run; pos moves past it."""
        if not self._run_var:
            return
        reader = self._name('S')
        self.scope[reader] = struct.Struct('<' + ''.join(self._run)).unpack_from
        self.lines.append(f' {self._run_var} = {reader}(raw, pos)')
        for name, dtype, count, offset in self._arrays:
            self.lines.append(f' {name} = frombuffer(raw, "{dtype}", {count}, pos + {offset})')
        self.lines.append(f' pos += {self._run_size}')
        self._run, self._run_size, self._run_var, self._arrays = [], 0, '', []

    # -- variable-size fields --------------------------------------------------------------
    def _count(self) -> str:
        """A string's or sequence's uint32 length, read with the run; the run ends there."""
        expression = self.scalar('uint32')
        self.flush()
        name = self._name('n')
        self.lines.append(f' {name} = {expression}')
        return name

    def string(self, indent: str = ' ', length: str | None = None) -> str:
        """Lines reading a string (after its length): UTF-8, terminator checked."""
        length = length or self._count()
        name = self._name('s')
        self.lines.extend([
            f'{indent}end = pos + {length}',
            f'{indent}if {length} < 1 or end > size or raw[end - 1]:',
            f'{indent} raise _Malformed',
            f'{indent}{name} = str(raw[pos:end - 1], "utf-8")',
            f'{indent}pos = end'])
        self.mod, self.rem = 1, 0
        return name

    def sequence(self, sub) -> str:
        from rosbags.interfaces import Nodetype

        count = self._count()
        name = self._name('q')
        if sub[0] == Nodetype.BASE and sub[1][0] == 'string':
            self.lines.extend([f' if pos + {count} * 5 > size:', '  raise _Malformed',
                               f' {name} = []', f' for _ in range({count}):',
                               '  pos = ((pos - 1) & -4) + 4',
                               '  n = u32(raw, pos)[0]', '  pos += 4'])
            element = self.string('  ', 'n')
            self.lines.append(f'  {name}.append({element})')
        elif sub[0] == Nodetype.BASE:
            kind = sub[1][0]
            if kind not in _PRIMITIVES:
                raise _Malformed(kind)
            code, dtype = _PRIMITIVES[kind]
            size = struct.calcsize(code)
            self.lines.append(f' if pos + {count} * {size} > size:')
            self.lines.append('  raise _Malformed')
            if size > 4:     # the length left pos 4-aligned; an empty sequence is not aligned
                self.lines.append(f' if {count}:')
                self.lines.append(f'  pos = ((pos + {size - 5}) & -{size}) + 4')
            self.lines.extend([f' {name} = frombuffer(raw, "{dtype}", {count}, pos)',
                               f' pos += {count} * {size}'])
            self.mod, self.rem = min(4, size), 0
        else:
            element = _DecoderSource(self.scope, _first_alignment(sub[1]))
            function = element.compile(f'return {element.message(sub[1])}, pos', sub[1])
            call = self._name('f')
            self.scope[call] = function
            first = _first_alignment(sub[1])
            self.lines.extend([f' if pos + {count} > size:', '  raise _Malformed',
                               f' {name} = []', f' for _ in range({count}):',
                               f'  pos = ((pos + {first - 5}) & -{first}) + 4',
                               f'  element, pos = {call}(raw, pos, size)',
                               f'  {name}.append(element)'])
        self.mod, self.rem = (self.mod, self.rem) if sub[0] == Nodetype.BASE and \
            sub[1][0] != 'string' else (1, 0)
        return name


def _first_alignment(msgtype: str) -> int:
    """Alignment of a message's first field (where an element of a sequence of it starts), as
    rosbags aligns it: its first primitive's size (a string's or sequence's length: 4)."""
    from rosbags.interfaces import Nodetype

    desc = _fields(msgtype)[0][1]
    while True:
        if desc[0] == Nodetype.NAME:
            desc = _fields(desc[1])[0][1]
        elif desc[0] == Nodetype.ARRAY:
            desc = desc[1][0]
        elif desc[0] == Nodetype.SEQUENCE or desc[1][0] == 'string':
            return 4
        elif desc[1][0] not in _PRIMITIVES:
            raise _Malformed(desc[1][0])      # float128: rosbags reads it
        else:
            return struct.calcsize(_PRIMITIVES[desc[1][0]][0])


def create_decoded_subscription(node: Node, msg_class: type, topic: str,
                                callback: Callable[[Any], None], qos: QoSProfile | int,
                                on_error: Callable[[Exception], None] | None = None):
    """node.create_subscription(msg_class, topic, callback, qos), with messages decoded by
    cdr_decoder. A message neither decoder can read is passed to on_error (default: a warning
    in the node's log) and dropped; the node keeps running."""
    decode = cdr_decoder(msg_class)

    def report(error: Exception) -> None:
        node.get_logger().warn(f'{topic}: undecodable {msg_class.__name__} message dropped '
                               f'({error})', throttle_duration_sec=5.0)

    handle_error = on_error or report

    def on_raw(raw: bytes) -> None:
        try:
            msg = decode(raw)
        except Exception as error:  # noqa: BLE001 - bad input is reported, not fatal
            handle_error(error)
            return
        callback(msg)

    return node.create_subscription(msg_class, topic, on_raw, qos, raw=True)


@functools.lru_cache(maxsize=64)
def _stamped_layout(strings: tuple[str, ...], lead: bytes, doubles: int):
    """(pack, head, tail) of a message that is `lead` (4-byte fields before the header: a
    sequence's length), a header stamp, strings (frame ids) and `doubles` float64 fields:
    pack(head, sec, nanosec, tail, *doubles) gives its CDR bytes. head is the encapsulation and
    lead, tail the strings padded so the float64 fields start 8-aligned (CDR aligns relative to
    the encapsulation's end); the same few frame ids in every message of a node: built once."""
    size = len(lead) + 8
    parts = []
    for text in strings:
        data = text.encode() + b'\x00'
        pad = -size % 4
        parts += [b'\x00' * pad, _LENGTH.pack(len(data)), data]
        size += pad + 4 + len(data)
    parts.append(b'\x00' * (-size % 8))
    head, tail = _CDR_LE + lead, b''.join(parts)
    return struct.Struct(f'<{len(head)}siI{len(tail)}s{doubles}d').pack, head, tail


def imu_cdr(stamp_ns: int, frame_id: str, orientation: Sequence[float],
            orientation_covariance: Sequence[float], angular_velocity: Sequence[float],
            angular_velocity_covariance: Sequence[float], linear_acceleration: Sequence[float],
            linear_acceleration_covariance: Sequence[float]) -> bytes:
    """sensor_msgs/Imu as CDR bytes: quaternion (x, y, z, w), rates (rad/s), accelerations
    (m/s^2) and their 9-element row-major covariances."""
    pack, head, tail = _stamped_layout((frame_id,), b'', 37)
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return pack(head, sec, nanosec, tail, *orientation, *orientation_covariance,
                *angular_velocity, *angular_velocity_covariance, *linear_acceleration,
                *linear_acceleration_covariance)


_ZEROS_18 = (0.0,) * 18


def _planar_36(cov3) -> tuple[float, ...]:
    """3x3 covariance over (x, y, yaw) -> 36 values of a 6x6 ROS covariance (rest zero), its
    entries at conversions.PLANAR_IN_36 (test_cdr compares with make_odometry)."""
    xx, xy, xt, yx, yy, yt, tx, ty, tt = np.asarray(cov3, dtype=float).ravel().tolist()
    return (xx, xy, 0.0, 0.0, 0.0, xt, yx, yy, 0.0, 0.0, 0.0, yt, *_ZEROS_18,
            tx, ty, 0.0, 0.0, 0.0, tt)


def odometry_cdr(stamp_ns: int, frame_id: str, child_frame_id: str, pose: Pose2,
                 pose_covariance, twist: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 twist_covariance=None) -> bytes:
    """nav_msgs/Odometry as CDR bytes, the same message as conversions.make_odometry with the
    same arguments: planar pose (x, y, yaw) in frame_id with its 3x3 covariance, twist (vx, vy,
    wz) in child_frame_id with its 3x3 covariance (None: zero)."""
    pack, head, tail = _stamped_layout((frame_id, child_frame_id), b'', 85)
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return pack(head, sec, nanosec, tail,
                float(pose[0]), float(pose[1]), 0.0, *quaternion.from_yaw(float(pose[2])),
                *_planar_36(pose_covariance),
                float(twist[0]), float(twist[1]), 0.0, 0.0, 0.0, float(twist[2]),
                *(_ZEROS_36 if twist_covariance is None else _planar_36(twist_covariance)))


def transform_cdr(stamp_ns: int, parent: str, child: str, transform: Transform) -> bytes:
    """tf2_msgs/TFMessage of one transform as CDR bytes, the same message as
    tf.transform_message with the same arguments: the child frame's pose in the parent frame."""
    pack, head, tail = _stamped_layout((parent, child), _ONE, 7)
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return pack(head, sec, nanosec, tail, *(float(v) for v in transform.translation),
                *(float(v) for v in transform.rotation))


class _CdrBody:
    """A little-endian CDR message written field by field: each value at its natural alignment
    from the body's start, padding zero (canonical CDR, as bags/storage.canonical_cdr makes
    rclpy's bytes). Used once per layout for the outputs made of sequences and strings
    (markers, point clouds: `_line_list_layout`, `_point_cloud_layout`), whose messages then
    differ only in a few fields at offsets `mark` noted."""

    def __init__(self) -> None:
        self.parts = [_CDR_LE]
        self.size = 0              # bytes of the body so far (alignment is relative to it)
        self.marks: list[int] = []

    def mark(self) -> _CdrBody:
        """Note where the next value goes (its offset in the message), once it is aligned."""
        self.marks.append(4 + self.size)
        return self

    def values(self, code: str, *values) -> _CdrBody:
        """Values of one struct code ('i', 'I', 'd', 'f', '?', 'B'), or one value per code of
        codes of one size ('iI': a Time), aligned to that size."""
        pad = -self.size % struct.calcsize(code[0])
        if self.marks and self.marks[-1] == 4 + self.size:
            self.marks[-1] += pad
        data = struct.pack(f'<{pad}x{len(values)}{code}' if len(code) == 1 else f'<{pad}x{code}',
                           *values)
        self.parts.append(data)
        self.size += len(data)
        return self

    def string(self, text: str) -> _CdrBody:
        data = text.encode() + b'\x00'
        self.values('I', len(data))
        self.parts.append(data)
        self.size += len(data)
        return self

    def header(self, stamp_ns: int, frame_id: str) -> _CdrBody:
        return self.values('iI', *divmod(int(stamp_ns), 1_000_000_000)).string(frame_id)

    def raw(self, data: bytes) -> _CdrBody:
        """A uint8[] sequence."""
        self.values('I', len(data))
        self.parts.append(data)
        self.size += len(data)
        return self

    def bytes(self) -> bytes:
        return b''.join(self.parts)


# Marker.type and Marker.action values (visualization_msgs/Marker).
_LINE_LIST, _ADD, _DELETEALL = 5, 0, 3
_TIME = struct.Struct('<iI')


def _marker(body: _CdrBody, frame_id: str, ns: str, kind: int, action: int, scale_x: float,
            rgba: tuple[float, float, float, float], points: bool) -> None:
    """One visualization_msgs/Marker (id 0, identity pose, no lifetime, no texture, mesh or
    text); its stamp and (with points) its points' count are marked, the points left out."""
    body.mark().header(0, frame_id).string(ns).values('iii', 0, kind, action)
    body.values('d', 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, scale_x, 0.0, 0.0)   # pose, scale
    body.values('f', *rgba).values('iI', 0, 0).values('?', False)          # colour, lifetime
    if points:
        body.mark().values('I', 0)
        pad = -body.size % 8                              # the points (x, y, z), 8-aligned
        body.parts.append(bytes(pad))
        body.size += pad
        body.mark()
    else:
        body.values('I', 0)
    body.values('I', 0).string('')                        # colors, texture_resource
    body.header(0, '').string('').raw(b'')                # texture (CompressedImage)
    body.values('I', 0).string('').string('')             # uv_coordinates, text, mesh_resource
    body.string('').raw(b'').values('?', False)           # mesh_file, mesh_use_embedded_...


@functools.lru_cache(maxsize=16)
def _line_list_layout(frame_id: str, ns: str, width_m: float,
                      rgba: tuple[float, float, float, float], empty: bool):
    """The MarkerArray of line_list_markers_cdr for stamp 0: (the bytes before and after the
    LINE_LIST's points (with `empty`: the whole array of the DELETEALL marker alone), the
    offsets of the stamps and of the points' count)."""
    body = _CdrBody().values('I', 1 if empty else 2)
    _marker(body, frame_id, ns, 0, _DELETEALL, 0.0, (0.0, 0.0, 0.0, 0.0), False)
    if not empty:
        _marker(body, frame_id, ns, _LINE_LIST, _ADD, width_m, rgba, True)
    data = body.bytes()
    if empty:
        return data, b'', body.marks
    points_at = body.marks.pop()
    return data[:points_at], data[points_at:], body.marks


def line_list_markers_cdr(stamp_ns: int, frame_id: str, ns: str, width_m: float,
                          rgba: tuple[float, float, float, float],
                          segments: Sequence[tuple[float, float, float, float]]) -> bytes:
    """visualization_msgs/MarkerArray as CDR bytes: a DELETEALL marker (clears what an earlier
    array showed), then, if there are segments, one LINE_LIST marker (id 0 in `ns`, width_m
    wide (m), colour rgba) with each segment (x0, y0, x1, y1) (m, z = 0) as a pair of points.
    The layout is built once per frame, namespace and style; a message patches in its stamps
    and appends its points."""
    head, tail, marks = _line_list_layout(frame_id, ns, width_m, tuple(rgba), not segments)
    out = bytearray(head)
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    if not segments:
        _TIME.pack_into(out, marks[0], sec, nanosec)
        return bytes(out)
    _TIME.pack_into(out, marks[0], sec, nanosec)
    _TIME.pack_into(out, marks[1], sec, nanosec)
    _LENGTH.pack_into(out, marks[2], 2 * len(segments))
    out += struct.pack(f'<{6 * len(segments)}d', *[
        v for x0, y0, x1, y1 in segments for v in (x0, y0, 0.0, x1, y1, 0.0)])
    out += tail
    return bytes(out)


@functools.lru_cache(maxsize=16)
def _point_cloud_layout(frame_id: str, fields: tuple[tuple[str, int, int], ...],
                        point_step: int):
    """point_cloud2_cdr's message for stamp 0 and no points: its bytes up to the data and the
    offsets of the stamp, width, row_step and data length."""
    body = _CdrBody().mark().header(0, frame_id).values('I', 1).mark().values('I', 0)
    body.values('I', len(fields))
    for name, offset, datatype in fields:
        body.string(name).values('I', offset).values('B', datatype).values('I', 1)
    body.values('?', False).values('I', point_step).mark().values('I', 0).mark().values('I', 0)
    return body.bytes(), body.marks


def point_cloud2_cdr(stamp_ns: int, frame_id: str, fields: Sequence[tuple[str, int, int]],
                     point_step: int, width: int, data: bytes) -> bytes:
    """sensor_msgs/PointCloud2 as CDR bytes: one row (height 1) of `width` points of
    point_step bytes each (little endian, dense), with `fields` as (name, offset, datatype),
    count 1 each."""
    head, (stamp_at, width_at, row_step_at, length_at) = _point_cloud_layout(
        frame_id, tuple(fields), point_step)
    out = bytearray(head)
    _TIME.pack_into(out, stamp_at, *divmod(int(stamp_ns), 1_000_000_000))
    _LENGTH.pack_into(out, width_at, width)
    _LENGTH.pack_into(out, row_step_at, point_step * width)
    _LENGTH.pack_into(out, length_at, len(data))
    out += data
    out.append(1)                 # is_dense
    return bytes(out)
