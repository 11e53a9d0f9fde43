"""ros/cdr.py: the fast encoders write the same messages as rclpy's serialiser, and the rosbags
decoder reads what rclpy wrote (and falls back to rclpy for what rosbags does not take)."""

from __future__ import annotations

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Imu, JointState

from sensing_nodes.bags.storage import canonical_cdr, type_name
from sensing_nodes.ros.cdr import cdr_decoder, imu_cdr, odometry_cdr
from sensing_nodes.ros.conversions import make_odometry, ros_covariance_to_planar

FRAME_IDS = ['', 'a', 'abc', 'abcd', 'odom', 'base_link', 'scan_match_keyframe', 'ünï']


@pytest.mark.parametrize('frame_id', FRAME_IDS)
@pytest.mark.parametrize('child_frame_id', ['', 'base_link', 'scan_match_map', 'abcde'])
def test_odometry_cdr_is_rclpys_odometry(frame_id, child_frame_id):
    rng = np.random.default_rng(len(frame_id) + 10 * len(child_frame_id))
    pose = tuple(rng.normal(size=3).tolist())
    cov, twist_cov = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
    twist = tuple(rng.normal(size=3).tolist())
    stamp = 1_700_000_000_123_456_789
    for tc in (twist_cov, None):
        expected = make_odometry(stamp, frame_id, child_frame_id, pose, cov, twist, tc)
        raw = odometry_cdr(stamp, frame_id, child_frame_id, pose, cov, twist, tc)
        assert raw == canonical_cdr(serialize_message(expected), 'nav_msgs/msg/Odometry')
        back = deserialize_message(raw, Odometry)
        assert (back.header.frame_id, back.child_frame_id) == (frame_id, child_frame_id)
        np.testing.assert_array_equal(ros_covariance_to_planar(back.pose.covariance), cov)


@pytest.mark.parametrize('frame_id', FRAME_IDS)
def test_imu_cdr_is_rclpys_imu(frame_id):
    v = np.random.default_rng(len(frame_id)).normal(size=37).tolist()
    msg = Imu()
    msg.header.frame_id = frame_id
    msg.header.stamp.sec, msg.header.stamp.nanosec = 1_700_000_000, 5_000_000
    o, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
    o.x, o.y, o.z, o.w = v[0:4]
    w.x, w.y, w.z = v[13:16]
    a.x, a.y, a.z = v[25:28]
    msg.orientation_covariance, msg.angular_velocity_covariance = v[4:13], v[16:25]
    msg.linear_acceleration_covariance = v[28:37]
    raw = imu_cdr(1_700_000_000_005_000_000, frame_id, v[0:4], v[4:13], v[13:16], v[16:25],
                  v[25:28], v[28:37])
    assert raw == canonical_cdr(serialize_message(msg), 'sensor_msgs/msg/Imu')


def test_decoder_reads_what_rclpy_wrote():
    msg = Imu()
    msg.header.frame_id = 'imu_link'
    msg.header.stamp.sec, msg.header.stamp.nanosec = 12, 345
    msg.angular_velocity.z = 0.25
    msg.linear_acceleration_covariance = [float(i) for i in range(9)]
    got = cdr_decoder(Imu)(serialize_message(msg))
    assert (got.header.stamp.sec, got.header.stamp.nanosec, got.header.frame_id) == (
        12, 345, 'imu_link')
    assert got.angular_velocity.z == 0.25
    np.testing.assert_array_equal(got.linear_acceleration_covariance, np.arange(9.0))
    # Fast-CDR pads before the (absent) elements of empty sequences: still decoded.
    joints = JointState(name=['left', 'right'], position=[1.5, -2.0])
    got = cdr_decoder(JointState)(serialize_message(joints))
    assert list(got.name) == ['left', 'right'] and list(got.position) == [1.5, -2.0]
    assert len(got.velocity) == 0 and len(cdr_decoder(JointState)(
        serialize_message(JointState())).name) == 0


def test_decoder_big_endian_and_bad_bytes():
    msg = make_odometry(1_000_000_123, 'odom', 'base_link', (1.0, 2.0, 0.5), np.eye(3))
    raw = serialize_message(msg)
    decode = cdr_decoder(Odometry)
    little = decode(raw)
    from sensing_nodes.bags.storage import TYPESTORE
    big = TYPESTORE.serialize_cdr(TYPESTORE.deserialize_cdr(raw, 'nav_msgs/msg/Odometry'),
                                  'nav_msgs/msg/Odometry', little_endian=False)
    assert bytes(big[:2]) == b'\x00\x00'
    got = decode(bytes(big))
    assert got.pose.pose.position.x == little.pose.pose.position.x == 1.0
    assert got.header.stamp.nanosec == 123
    with pytest.raises(Exception):
        decode(b'\x00\x01\x00\x00\x01')        # truncated: neither decoder takes it


@pytest.mark.parametrize('parent', ['', 'odom', 'abc', 'ünï'])
@pytest.mark.parametrize('child', ['', 'a', 'abcd', 'base_link'])
def test_transform_cdr_is_rclpys_tf_message(parent, child):
    from sensing_nodes.core.geometry.transform import Transform
    from sensing_nodes.ros.cdr import transform_cdr
    from sensing_nodes.ros.tf import transform_message

    pose = np.random.default_rng(len(parent) + 10 * len(child)).normal(size=3).tolist()
    stamp = 1_700_000_000_123_456_789
    transform = Transform.from_planar(*pose)
    expected = transform_message(stamp, parent, child, transform)
    assert transform_cdr(stamp, parent, child, transform) == canonical_cdr(
        serialize_message(expected), 'tf2_msgs/msg/TFMessage')


def _rosbags_round_trip(raw: bytes, msgtype: str) -> bytes:
    """The definition canonical_cdr keeps: rosbags decodes the message and encodes it again."""
    from sensing_nodes.bags.storage import TYPESTORE

    if len(raw) < 4 or raw[:2] not in (b'\x00\x00', b'\x00\x01'):
        raise ValueError('not a CDR message')
    msgdef = TYPESTORE.get_msgdef(msgtype)
    decode = msgdef.deserialize_cdr_le if raw[1] else msgdef.deserialize_cdr_be
    message, _ = decode(memoryview(raw)[4:], 0, msgdef.cls, TYPESTORE)
    return bytes(TYPESTORE.serialize_cdr(message, msgtype, little_endian=bool(raw[1])))


def _outcome(function, raw: bytes, msgtype: str):
    try:
        return function(raw, msgtype)
    except Exception as exc:  # noqa: BLE001 - the same failure is part of the contract
        return type(exc)


def _varied_messages(rng):
    """rclpy messages of the shapes the bags hold: strings of every length modulo 4 before
    doubles, empty and non-empty sequences of strings, doubles and messages, bools, NaN."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from geometry_msgs.msg import Point, TransformStamped
    from sensor_msgs.msg import LaserScan, PointCloud2, PointField
    from tf2_msgs.msg import TFMessage
    from visualization_msgs.msg import Marker, MarkerArray

    def text():
        return ''.join(rng.choice(list('abü_/x')) for _ in range(rng.integers(0, 9)))

    def values(n):
        return [float(rng.choice([0.0, -2.25, np.nan, np.inf, rng.normal()])) for _ in range(n)]

    for _ in range(60):
        n = int(rng.integers(0, 4))
        yield JointState(name=[text() for _ in range(n)], position=values(int(rng.choice([0, n]))),
                         velocity=values(int(rng.choice([0, n]))), effort=values(0))
        scan = LaserScan(ranges=values(int(rng.integers(0, 5))), intensities=values(1))
        scan.header.frame_id, scan.angle_min = text(), float('nan')
        yield scan
        yield MarkerArray(markers=[Marker(ns=text(), text=text(), frame_locked=bool(i % 2),
                                          points=[Point(x=v) for v in values(i)])
                                   for i in range(n)])
        yield PointCloud2(fields=[PointField(name=text(), offset=4 * i, datatype=7, count=1)
                                  for i in range(n)], data=bytes(rng.integers(0, 256, n * 3)),
                          is_bigendian=bool(n % 2), is_dense=True)
        yield TFMessage(transforms=[TransformStamped(child_frame_id=text()) for _ in range(n)])
        yield DiagnosticArray(status=[DiagnosticStatus(name=text(), values=[
            KeyValue(key=text(), value=text())]) for _ in range(n)])
        yield make_odometry(int(rng.integers(0, 2**62)), text(), text(),
                            rng.normal(size=3).tolist(), np.diag(values(3)))


def test_canonical_cdr_is_rosbags_round_trip():
    """canonical_cdr decodes through rosbags' public decoder (which refuses bytes after the last
    field: it cuts them) and encodes again; the result (or the failure) must be the round
    trip's, also on bytes it should not take: padding left as rclpy left it, trailing bytes,
    truncations, and single bytes changed (a bool of 2, a string without its terminator, a
    signalling NaN float32, an impossible sequence length)."""
    from sensing_nodes.bags.storage import TYPESTORE, type_name

    rng = np.random.default_rng(15)
    checked = 0
    for msg in _varied_messages(rng):
        msgtype = type_name(msg)
        raw = serialize_message(msg)
        big = b'\x00\x00\x00\x00' + bytes(TYPESTORE.serialize_cdr(
            TYPESTORE.deserialize_cdr(_rosbags_round_trip(raw, msgtype), msgtype), msgtype,
            little_endian=False))[4:]
        variants = [raw, big, raw + bytes(5), raw[:int(rng.integers(0, len(raw)))]]
        for _ in range(8):
            changed = bytearray(raw)
            changed[int(rng.integers(4, len(raw)))] = int(rng.choice([1, 2, 0x7f, 0xa0, 0xff]))
            variants.append(bytes(changed))
        for variant in variants:
            assert _outcome(canonical_cdr, variant, msgtype) == \
                _outcome(_rosbags_round_trip, variant, msgtype), (msgtype, variant.hex())
            checked += 1
    assert checked == 60 * 7 * 12


def test_message_cdr_is_the_canonical_form_of_rclpys_bytes():
    """An rclpy message encoded by rosbags' typestore (message_cdr, what BagWriter.write
    stores) gives the bytes canonical_cdr makes of what rclpy serialises: the same message,
    padding zero, for every shape the bags hold."""
    from sensing_nodes.bags.storage import message_cdr

    rng = np.random.default_rng(16)
    checked = 0
    for msg in _varied_messages(rng):
        raw = serialize_message(msg)
        assert message_cdr(msg) == canonical_cdr(raw, type_name(msg)), type_name(msg)
        checked += 1
    assert checked == 60 * 7


def _same_message(got, expected, msgtype: str, path: str = '') -> None:
    """got (the generated decoder's) has expected's (rosbags') fields: equal values of the same
    Python types, numpy arrays of the same dtype and bytes, field by field."""
    from sensing_nodes.bags.storage import TYPESTORE

    assert type(got).__msgtype__ == msgtype, path
    for name, desc in TYPESTORE.get_msgdef(msgtype).fields:
        a, b, where = getattr(got, name), getattr(expected, name), f'{path}.{name}'
        if isinstance(b, np.ndarray):
            assert isinstance(a, np.ndarray) and a.dtype == b.dtype, where
            assert a.tobytes() == b.tobytes() and not a.flags.writeable, where
        elif hasattr(b, '__msgtype__'):
            _same_message(a, b, b.__msgtype__, where)
        elif isinstance(b, list):
            assert isinstance(a, list) and len(a) == len(b), where
            for k, (x, y) in enumerate(zip(a, b)):
                if hasattr(y, '__msgtype__'):
                    _same_message(x, y, y.__msgtype__, f'{where}[{k}]')
                else:
                    assert type(x) is type(y) and x == y, f'{where}[{k}]'
        else:
            assert type(a) is type(b), (where, type(a), type(b))
            assert a == b or (a != a and b != b), (where, a, b)


def test_generated_decoder_reads_what_rosbags_reads():
    """cdr_decoder's generated decoders give rosbags' messages (every field, type and array
    dtype), or refuse bytes (rosbags, then rclpy, decide) that rosbags refuses too: the
    varied messages and Imu, with trailing bytes, truncated and with single bytes changed
    (a string without its terminator, an impossible sequence length, ...)."""
    from sensing_nodes.bags.storage import TYPESTORE, type_name
    from sensing_nodes.ros.cdr import _fast_decoder

    def rosbags(raw, msgtype):
        msgdef = TYPESTORE.get_msgdef(msgtype)
        return msgdef.deserialize_cdr_le(memoryview(raw)[4:], 0, msgdef.cls, TYPESTORE)[0]

    rng = np.random.default_rng(24)
    imus = []
    for k in range(20):
        imu = Imu()
        imu.header.frame_id = 'imu_link'[:k % 9]
        imu.header.stamp.sec, imu.header.stamp.nanosec = k, 1000 * k
        imu.orientation.z, imu.angular_velocity.x = rng.normal(size=2).tolist()
        imu.linear_acceleration_covariance = rng.normal(size=9).tolist()
        imus.append(imu)
    decoded = refused = 0
    for msg in [*_varied_messages(rng), *imus]:
        msgtype = type_name(msg)
        decode = _fast_decoder(msgtype)
        raw = serialize_message(msg)
        variants = [raw, raw + bytes(5), raw[:int(rng.integers(0, len(raw)))]]
        for _ in range(6):
            changed = bytearray(raw)
            changed[int(rng.integers(4, len(raw)))] = int(rng.choice([1, 2, 0x7f, 0xff]))
            variants.append(bytes(changed))
        for variant in variants:
            got, expected = _outcome(lambda r, _: decode(r), variant, msgtype), \
                _outcome(rosbags, variant, msgtype)
            if isinstance(got, type):
                refused += 1
                continue
            assert not isinstance(expected, type), (msgtype, variant.hex())
            _same_message(got, expected, msgtype)
            decoded += 1
    assert decoded > 2000 and refused > 100
    # cdr_decoder takes the generated decoder's message, and rosbags' for big-endian bytes.
    odometry = make_odometry(5, 'odom', 'base_link', (1.0, 2.0, 0.5), np.eye(3))
    assert type(cdr_decoder(Odometry)(serialize_message(odometry))).__msgtype__ == \
        'nav_msgs/msg/Odometry'


def _marker_array(lines, stamp_ns: int, frame_id: str, width: float):
    """What line_extractor published as rclpy messages before it packed its own bytes."""
    from geometry_msgs.msg import Point
    from std_msgs.msg import ColorRGBA, Header
    from visualization_msgs.msg import Marker, MarkerArray

    from sensing_nodes.ros.conversions import ns_to_stamp

    header = Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame_id)
    clear = Marker(header=header, ns='lines', id=0, action=Marker.DELETEALL)
    if not lines:
        return MarkerArray(markers=[clear])
    marker = Marker(header=header, ns='lines', id=0, type=Marker.LINE_LIST, action=Marker.ADD)
    marker.pose.orientation.w = 1.0
    marker.scale.x = width
    marker.color = ColorRGBA(r=1.0, g=0.45, b=0.0, a=1.0)
    marker.points = [Point(x=x, y=y, z=0.0) for x0, y0, x1, y1 in lines
                     for x, y in ((x0, y0), (x1, y1))]
    return MarkerArray(markers=[clear, marker])


@pytest.mark.parametrize('frame_id', FRAME_IDS)
def test_markers_and_point_cloud_cdr_are_rclpys(frame_id):
    from sensor_msgs.msg import PointCloud2, PointField
    from std_msgs.msg import Header

    from sensing_nodes.ros.cdr import line_list_markers_cdr, point_cloud2_cdr
    from sensing_nodes.ros.conversions import ns_to_stamp

    rng = np.random.default_rng(len(frame_id))
    stamp = 1_700_000_000_123_456_789
    fields = [('r', 0, PointField.FLOAT64), ('first', 8, PointField.UINT32),
              ('ünï', 12, PointField.UINT32)]
    for count in (0, 1, 7):
        lines = [tuple(v) for v in rng.normal(size=(count, 4)).tolist()]
        assert line_list_markers_cdr(stamp, frame_id, 'lines', 0.03, (1.0, 0.45, 0.0, 1.0),
                                     lines) == canonical_cdr(serialize_message(_marker_array(
                                         lines, stamp, frame_id, 0.03)),
                                         'visualization_msgs/msg/MarkerArray')
        data = rng.integers(0, 256, 16 * count, dtype=np.uint8).tobytes()
        cloud = PointCloud2(header=Header(stamp=ns_to_stamp(stamp), frame_id=frame_id),
                            height=1, width=count, is_bigendian=False, point_step=16,
                            row_step=16 * count, is_dense=True, data=data,
                            fields=[PointField(name=n, offset=o, datatype=d, count=1)
                                    for n, o, d in fields])
        assert point_cloud2_cdr(stamp, frame_id, fields, 16, count, data) == canonical_cdr(
            serialize_message(cloud), 'sensor_msgs/msg/PointCloud2')
