"""Every message of every kind of bag the project writes or ships decodes with rosbags (strict),
mcap-ros2-support and rclpy and is stored in canonical CDR; the project's bag reader opens bags
written by rosbag2 itself (MCAP and sqlite3); and metadata.yaml has the fields, types and values
rosbag2 (Jazzy, metadata version 9) reads.

rosbag2's reader (rosbag2_storage/yaml.hpp, version 9) decodes: version, storage_identifier,
duration.nanoseconds, starting_time.nanoseconds_since_epoch, message_count,
topics_with_message_count[{topic_metadata{name, type, serialization_format,
offered_qos_profiles (a YAML sequence from version 9 on), type_description_hash}, message_count}],
relative_file_paths, compression_format, compression_mode, files[{path, starting_time, duration,
message_count}], custom_data (a map), ros_distro.
"""

from __future__ import annotations

import re
import time
from collections import Counter
from pathlib import Path

import pytest
import yaml
from harness import REPO, run_to_exit
from rclpy.serialization import deserialize_message

from sensing_nodes.bags.storage import BagReader, BagWriter, canonical_cdr, message_class

CARMEN = Path(__file__).resolve().parents[2] / 'shared' / 'datasets' / 'carmen'
ROSBAG2 = Path(__file__).resolve().parents[2] / 'shared' / 'datasets' / 'ros' / 'rosbag2-resources'
TOP_KEYS = {'version', 'storage_identifier', 'duration', 'starting_time', 'message_count',
            'topics_with_message_count', 'compression_format', 'compression_mode',
            'relative_file_paths', 'files', 'custom_data', 'ros_distro'}
TOPIC_KEYS = {'name', 'type', 'serialization_format', 'offered_qos_profiles',
              'type_description_hash'}
FILE_KEYS = {'path', 'starting_time', 'duration', 'message_count'}
QOS_KEYS = {'history', 'depth', 'reliability', 'durability', 'deadline', 'lifespan', 'liveliness',
            'liveliness_lease_duration', 'avoid_ros_namespace_conventions'}


def expected_name(info: dict, topic: str) -> str:
    return next(t['topic_metadata']['type'] for t in info['topics_with_message_count']
                if t['topic_metadata']['name'] == topic).split('/')[-1]


@pytest.fixture(scope='module')
def written_bags(tmp_path_factory):
    """One bag of each writer: the shipped bags (replay output), sensor_sim --record, a plain
    BagWriter, carmen_to_bag (when the shared logs are there)."""
    from nav_msgs.msg import Odometry

    tmp = tmp_path_factory.mktemp('bags')
    bags = {'nominal': REPO / 'bags' / 'nominal', 'strong_errors': REPO / 'bags' / 'strong_errors'}
    record = run_to_exit('sensor_sim', ['--record', str(tmp / 'sim'), '--duration', '1.0',
                                        '--quiet'])
    assert record.returncode == 0, record.stderr
    bags['sensor_sim'] = tmp / 'sim'
    with BagWriter(tmp / 'writer') as writer:
        msg = Odometry()
        for k in range(3):
            msg.header.stamp.sec = 10 + k
            writer.write('/odom', msg, (10 + k) * 1_000_000_000)
    bags['bag_writer'] = tmp / 'writer'
    log = CARMEN / 'freiburg-101-corrected.log.gz'
    if log.is_file():
        from sensing_nodes.tools.carmen_to_bag import convert

        convert(log, tmp / 'carmen')
        bags['carmen_to_bag'] = tmp / 'carmen'
    return bags


def _metadata(bag: Path) -> dict:
    return yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']


@pytest.mark.parametrize('name', ['nominal', 'strong_errors', 'sensor_sim', 'bag_writer',
                                  'carmen_to_bag'])
def test_every_message_decodes_with_rosbags_mcap_ros2_and_rclpy(written_bags, name):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.highlevel import AnyReader

    from sensing_nodes.bags.storage import TYPESTORE

    if name not in written_bags:
        pytest.skip(f'CARMEN logs not found in {CARMEN}')
    bag = written_bags[name]
    info = _metadata(bag)
    expected = {t['topic_metadata']['name']: t['message_count']
                for t in info['topics_with_message_count']}
    # rosbags' AnyReader (strict: a size mismatch raises) and rclpy decode every message, and
    # every message is canonical CDR (zero padding, nothing after the last field).
    with AnyReader([bag], default_typestore=TYPESTORE) as reader:
        counted = Counter()
        for connection, _, raw in reader.messages():
            counted[connection.topic] += 1
            reader.deserialize(raw, connection.msgtype)
            deserialize_message(raw, message_class(connection.msgtype))
            assert canonical_cdr(raw, connection.msgtype) == bytes(raw), connection.topic
    assert dict(counted) == {t: n for t, n in expected.items() if n}
    for path in info['relative_file_paths']:
        with open(bag / path, 'rb') as handle:
            reader = make_reader(handle, decoder_factories=[DecoderFactory()])
            assert reader.get_header().profile == 'ros2'
            summary = reader.get_summary()
            assert {s.encoding for s in summary.schemas.values()} == {'ros2msg'}
            assert {c.message_encoding for c in summary.channels.values()} == {'cdr'}
            assert {c.topic: summary.statistics.channel_message_counts[i]
                    for i, c in summary.channels.items()} == {t: n for t, n in expected.items()}
        decoded = Counter()
        with open(bag / path, 'rb') as handle:
            reader = make_reader(handle, decoder_factories=[DecoderFactory()])
            for _, channel, _, msg in reader.iter_decoded_messages():
                assert type(msg).__name__ == expected_name(info, channel.topic)
                decoded[channel.topic] += 1
        assert decoded == counted


# rosbag2's own test bags: (folder, {topic: (type, messages)}).
ROSBAG2_BAGS = {
    'mcap_talker': (
        'rosbag2_py/test/resources/mcap/talker',
        {
            '/topic': ('std_msgs/msg/String', 10),
            '/rosout': ('rcl_interfaces/msg/Log', 10),
            '/parameter_events': ('rcl_interfaces/msg/ParameterEvent', 0),
        },
    ),
    'sqlite3_talker': (
        'rosbag2_py/test/resources/sqlite3/talker',
        {
            '/topic': ('std_msgs/msg/String', 10),
            '/rosout': ('rcl_interfaces/msg/Log', 10),
            '/parameter_events': ('rcl_interfaces/msg/ParameterEvent', 0),
        },
    ),
    'cdr_test': (
        'rosbag2_tests/resources/mcap/cdr_test',
        {
            '/test_topic': ('test_msgs/msg/BasicTypes', 3),
            '/array_topic': ('test_msgs/msg/Arrays', 4),
        },
    ),
}


@pytest.mark.parametrize('name', sorted(ROSBAG2_BAGS))
def test_reader_opens_bags_written_by_rosbag2(name):
    """Metadata versions 4 and 7, MCAP and sqlite3: every message comes out, in stamp order.
    (rosbags' own folder reader yields none of the talker bags' messages: it matches the files'
    topics against metadata.yaml's QoS, which rosbag2 wrote differently.)"""
    folder, topics = ROSBAG2_BAGS[name]
    bag = ROSBAG2 / folder
    if not (bag / 'metadata.yaml').is_file():
        pytest.skip(f'rosbag2 test bags not found in {ROSBAG2}')
    reader = BagReader(bag)
    assert {t: (i.msgtype, i.count) for t, i in reader.topics.items()} == topics
    rows = list(reader.raw())
    assert Counter(t for t, _, _ in rows) == Counter({t: n for t, (_, n) in topics.items() if n})
    stamps = [s for _, s, _ in rows]
    assert stamps == sorted(stamps)
    if '/topic' in topics:   # the talker: rclpy messages, in order
        said = [m.data for _, _, m in reader.messages(['/topic'])]
        assert said == [f'Hello, world! {k}' for k in range(10)]


def test_replayed_bags_record_the_offered_qos():
    """`ros2 bag play` publishes each topic with the QoS recorded for it: the raw sensor streams
    best effort, as the simulator (a driver) offers them, the nodes' estimates reliable."""
    info = _metadata(REPO / 'bags' / 'nominal')
    reliability = {t['topic_metadata']['name']: {q['reliability'] for q in
                                                 t['topic_metadata']['offered_qos_profiles']}
                   for t in info['topics_with_message_count']}
    for topic in ('/scan', '/imu/data_raw', '/joint_states'):
        assert reliability[topic] == {'best_effort'}
    for topic in ('/wheel/odom', '/imu/data', '/scan_match/odom', '/odometry/filtered',
                  '/scan/lines', '/scan/lines/table'):
        assert reliability[topic] == {'reliable'}


@pytest.mark.parametrize('name', ['nominal', 'strong_errors', 'sensor_sim', 'bag_writer',
                                  'carmen_to_bag'])
def test_metadata_follows_rosbag2_version_9(written_bags, name, probe):
    from rosbags.rosbag2 import Reader

    if name not in written_bags:
        pytest.skip(f'CARMEN logs not found in {CARMEN}')
    bag = written_bags[name]
    info = _metadata(bag)
    assert set(info) == TOP_KEYS
    assert info['version'] == 9
    assert info['storage_identifier'] == 'mcap'
    # MCAP chunk compression is inside the file (storage level): rosbag2's own fields stay empty.
    assert info['compression_format'] == '' and info['compression_mode'] == ''
    assert info['custom_data'] is None or isinstance(info['custom_data'], dict)
    assert isinstance(info['ros_distro'], str)
    with Reader(bag) as reader:
        stamps = [t for _, t, _ in reader.messages()]
    assert info['message_count'] == len(stamps)
    assert info['starting_time'] == {'nanoseconds_since_epoch': min(stamps)}
    assert info['duration'] == {'nanoseconds': max(stamps) - min(stamps)}
    assert [f['path'] for f in info['files']] == info['relative_file_paths']
    for entry in info['files']:
        assert set(entry) == FILE_KEYS and (bag / entry['path']).is_file()
        assert entry['message_count'] == info['message_count']
        assert entry['starting_time'] == info['starting_time']
    assert (
        sum(t['message_count'] for t in info['topics_with_message_count']) == info['message_count']
    )
    for topic in info['topics_with_message_count']:
        assert set(topic) == {'topic_metadata', 'message_count'}
        meta = topic['topic_metadata']
        assert set(meta) == TOPIC_KEYS
        assert meta['serialization_format'] == 'cdr'
        assert isinstance(meta['offered_qos_profiles'], list)  # a sequence from version 9 on
        for qos in meta['offered_qos_profiles']:
            assert set(qos) == QOS_KEYS
            assert qos['reliability'] in {'reliable', 'best_effort', 'system_default'}
            assert qos['durability'] in {'volatile', 'transient_local', 'system_default'}
            for key in ('deadline', 'lifespan', 'liveliness_lease_duration'):
                assert set(qos[key]) == {'sec', 'nsec'}
        assert re.fullmatch(r'[a-z][a-z0-9_]*/msg/[A-Za-z0-9]+', meta['type'])  # REP 144
        # The hash ROS 2 computes for the type (what `ros2 bag play` compares).
        assert meta['type_description_hash'] == _live_type_hash(probe, meta['type'])


_HASHES: dict[str, str] = {}


def _live_type_hash(probe, type_name: str) -> str:
    if type_name not in _HASHES:
        topic = '/interop_hash_' + type_name.replace('/', '_')
        publisher = probe.create_publisher(message_class(type_name), topic, 1)
        deadline = time.monotonic() + 10.0
        infos = []
        while not infos and time.monotonic() < deadline:
            infos = probe.get_publishers_info_by_topic(topic)
            time.sleep(0.05)
        _HASHES[type_name] = str(infos[0].topic_type_hash)
        probe.destroy_publisher(publisher)
    return _HASHES[type_name]


@pytest.mark.parametrize('compress', [False, True])
@pytest.mark.parametrize('chunk_s', [None, 0.2])
def test_bag_writer_writes_what_rosbags_writer_writes(written_bags, tmp_path, compress, chunk_s):
    """BagWriter writes its MCAP through the mcap package's writer: rosbags reads from it what
    rosbags' own Writer stores for the same rows (topics, types, definitions, type hashes,
    offered QoS, every message's bag time and canonical bytes, metadata.yaml's counts and
    times); with chunk_s no chunk spans more bag time; and rows of canonical_topics are stored
    as given."""
    from mcap.reader import make_reader
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer

    from sensing_nodes.bags.storage import CANONICAL_KEY, TYPESTORE, bag_qos

    source = BagReader(written_bags['sensor_sim'])
    rows = [(t, raw, s) for t, s, raw in source.raw()]
    assert len(rows) > 400
    with BagWriter(tmp_path / 'ours', compress=compress, chunk_s=chunk_s) as bag:
        for topic, info in source.topics.items():
            bag.add_topic(topic, info.msgtype, list(info.qos) or None)
        bag.write_raw_many(rows[:200])
        bag.write_raw_many(rows[200:])
    with Writer(tmp_path / 'rosbags', version=9, storage_plugin=StoragePlugin.MCAP) as bag:
        connections = {topic: bag.add_connection(
            topic, info.msgtype, typestore=TYPESTORE,
            offered_qos_profiles=[bag_qos(q) for q in info.qos])
            for topic, info in source.topics.items()}
        for topic, raw, stamp in rows:
            bag.write(connections[topic], stamp,
                      canonical_cdr(raw, connections[topic].msgtype))

    def content(path):
        with Reader(path) as reader:
            kinds = [(c.topic, c.msgtype, c.msgdef, c.digest, c.msgcount,
                      c.ext.offered_qos_profiles) for c in reader.connections]
            return kinds, [(c.topic, stamp, bytes(raw)) for c, stamp, raw in reader.messages()]

    assert content(tmp_path / 'ours') == content(tmp_path / 'rosbags')
    ours, theirs = (_metadata(tmp_path / name) for name in ('ours', 'rosbags'))
    assert ours.pop('custom_data') == {CANONICAL_KEY: 'canonical'}   # BagWriter says so
    assert theirs.pop('custom_data') is None
    for info in (ours, theirs):
        info.pop('ros_distro')
        info['relative_file_paths'] = [p.rsplit('.', 1)[1] for p in info['relative_file_paths']]
        for entry in info['files']:
            entry['path'] = entry['path'].rsplit('.', 1)[1]
    assert ours == theirs
    with (tmp_path / 'ours' / 'ours.mcap').open('rb') as handle:
        chunks = make_reader(handle).get_summary().chunk_indexes
    assert len(chunks) >= (1 if chunk_s is None else 4)     # 1 s of bag time
    assert {c.compression for c in chunks} == {'zstd' if compress else ''}
    if chunk_s is not None:    # closed by the first message chunk_s after the chunk's first
        stamps = sorted(s for _, _, s in rows)
        step = max(b - a for a, b in zip(stamps, stamps[1:]))
        assert all(c.message_end_time - c.message_start_time <= chunk_s * 1e9 + step
                   for c in chunks)
    # Rows of canonical_topics are not made canonical (here: bytes after the last field kept).
    with BagWriter(tmp_path / 'as_given') as bag:
        bag.add_topic('/imu/data_raw', 'sensor_msgs/msg/Imu')
        raw = next(raw for t, raw, _ in rows if t == '/imu/data_raw') + bytes(4)
        bag.write_raw_many([('/imu/data_raw', raw, 5)], canonical_topics={'/imu/data_raw'})
    assert [bytes(m) for _, _, m in BagReader(tmp_path / 'as_given').raw()] == [raw]
