"""Bags a recording never closed (power loss, kill -9): every reader of the package reads them up
to their last complete record, says what it read and what was lost, and works on it; a bag with
nothing readable is refused with exit 2. The writer closes a chunk per second of bag time, so
an unclosed bag loses at most that."""

from __future__ import annotations

import shutil
from io import BytesIO
from pathlib import Path

import pytest
from harness import REPO, run_to_exit

from sensing_nodes.bags.storage import BagError, BagReader, BagWriter, topic_counts

BAGS = REPO / 'bags'
NOMINAL = BAGS / 'nominal'


# -- the intact file, read by the mcap package (independent of bags/recovery.py) ---------------
def _file_order(mcap: Path) -> list[tuple[str, int, bytes]]:
    """(topic, log time, data) of every message, in file order."""
    from mcap.reader import make_reader

    with mcap.open('rb') as handle:
        return [(channel.topic, message.log_time, message.data) for _, channel, message in
                make_reader(handle).iter_messages(log_time_order=False)]


def _chunks(mcap: Path) -> list:
    """The chunk indexes of the file's summary, in file order."""
    from mcap.reader import make_reader

    with mcap.open('rb') as handle:
        chunks = make_reader(handle).get_summary().chunk_indexes
    return sorted(chunks, key=lambda c: c.chunk_start_offset)


def _message_offsets(mcap: Path, chunk) -> list[int]:
    """Offsets of a chunk's messages in its (uncompressed) records, from its message indexes."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import MessageIndex

    data = mcap.read_bytes()
    offsets = []
    for at in chunk.message_index_offsets.values():
        length = int.from_bytes(data[at + 1:at + 9], 'little')
        index = MessageIndex.read(ReadDataStream(BytesIO(data[at + 9:at + 9 + length])))
        offsets += [offset for _, offset in index.records]
    return sorted(offsets)


def _cut_copy(source: Path, target: Path, at: int, keep_metadata: bool = True) -> Path:
    """A copy of a bag folder with its MCAP file cut after `at` bytes (and no metadata.yaml, as a
    crash leaves it, unless keep_metadata)."""
    shutil.copytree(source, target)
    if not keep_metadata:
        (target / 'metadata.yaml').unlink()
    mcap = next(target.glob('*.mcap'))
    with mcap.open('r+b') as handle:
        handle.truncate(at)
    return target


def _read(bag: Path) -> list[tuple[str, int, bytes]]:
    return [(topic, stamp, raw) for topic, stamp, raw in BagReader(bag).raw()]


@pytest.fixture(scope='module')
def plain_nominal(tmp_path_factory) -> Path:
    """bags/nominal rewritten with plain 1 MiB chunks (written at close)."""
    source = BagReader(NOMINAL)
    path = tmp_path_factory.mktemp('plain') / 'plain'
    with BagWriter(path, chunk_s=None) as bag:
        for topic, info in source.topics.items():
            bag.add_topic(topic, info.msgtype, list(info.qos) or None)
        bag.write_raw_many((t, raw, s) for t, s, raw in source.raw())
    return path


@pytest.mark.parametrize('keep_metadata', [True, False])
def test_a_message_cut_in_half_is_dropped_and_every_message_before_it_read(
        tmp_path, plain_nominal, keep_metadata):
    """Cut inside a message record in the second chunk: the bag reads as exactly the first
    chunk's messages and the second chunk's before the cut one, and says so."""
    mcap = plain_nominal / 'plain.mcap'
    first, second = _chunks(mcap)[:2]
    offsets = _message_offsets(mcap, second)
    k = len(offsets) // 2
    records_start = second.chunk_start_offset + 9 + 40     # plain: no compression name
    bag = _cut_copy(plain_nominal, tmp_path / 'cut', records_start + offsets[k] + 30,
                    keep_metadata)
    read_before = len(_message_offsets(mcap, first)) + k
    assert sorted(_read(bag)) == sorted(_file_order(mcap)[:read_before])
    damage = BagReader(bag).damage
    assert 'was not closed: it ends inside a chunk record' in damage, damage
    assert f'{k} complete messages read from the part of it that is there' in damage
    assert f'read {read_before} messages' in damage
    if keep_metadata:   # metadata.yaml counts what was recorded: the loss per topic is named
        lost = len(_file_order(mcap)) - read_before
        assert f'lost {lost} of the {len(_file_order(mcap))} messages' in damage
        assert '/scan ' in damage.split('lost')[1]
    else:
        assert 'no metadata.yaml' in damage and 'unknown' in damage


@pytest.fixture(scope='module')
def cuts(tmp_path_factory) -> dict[str, tuple[Path, int]]:
    """Copies of bags/nominal (zstd chunks) cut inside its third chunk, inside the first message
    index after its second chunk, and after its header only: name -> (bag, messages before
    the cut that no chunk of it holds in part: a lower bound of what must be read)."""
    mcap = NOMINAL / 'nominal.mcap'
    chunks = _chunks(mcap)
    folder = tmp_path_factory.mktemp('cuts')
    whole_two = len(_message_offsets(mcap, chunks[0])) + len(_message_offsets(mcap, chunks[1]))
    third = chunks[2]
    index_after_second = min(chunks[1].message_index_offsets.values())
    return {
        'mid_chunk': (_cut_copy(NOMINAL, folder / 'mid_chunk',
                                third.chunk_start_offset + third.chunk_length // 2), whole_two),
        'mid_record': (_cut_copy(NOMINAL, folder / 'mid_record', index_after_second + 20,
                                 keep_metadata=False), whole_two),
        'header_only': (_cut_copy(NOMINAL, folder / 'header_only', chunks[0].chunk_start_offset),
                        0),
    }


@pytest.mark.parametrize('name', ['mid_chunk', 'mid_record'])
def test_a_cut_shipped_bag_reads_its_whole_chunks_and_the_part_of_a_cut_one(cuts, name):
    """zstd chunks: the complete chunks' messages, and from a chunk cut in the middle the
    messages of its whole zstd blocks: a prefix, in file order, of the intact file's."""
    bag, whole = cuts[name]
    everything = _file_order(NOMINAL / 'nominal.mcap')
    read = _read(bag)
    assert len(read) >= whole
    assert sorted(read) == sorted(everything[:len(read)])
    if name == 'mid_chunk':
        assert len(read) > whole      # some of the cut chunk's messages were recovered
    stamps = [s for _, s, _ in read]
    assert stamps == sorted(stamps)


def test_sensing_eval_scores_a_cut_bag_up_to_the_cut_and_says_what_was_lost(cuts, tmp_path):
    bag, _ = cuts['mid_chunk']
    out = tmp_path / 'eval.json'
    result = run_to_exit('sensing_eval', [str(bag), '--json', str(out)])
    assert result.returncode == 0, result.stderr
    assert 'warning' in result.stderr and 'was not closed' in result.stderr
    assert 'lost' in result.stderr and '/ground_truth/odom' in result.stderr.split('lost')[1]
    truth = BagReader(bag).topics['/ground_truth/odom'].count
    import json

    report = json.loads(out.read_text())
    # Relations between the reference's consecutive messages that were read, and no more.
    assert report['estimates']['/wheel/odom']['relations_asked'] == truth - 1
    assert 0.9 * (truth - 1) <= report['estimates']['/wheel/odom']['relations'] <= truth - 1


def test_sensing_pipeline_processes_a_cut_bag_up_to_the_cut(cuts, tmp_path):
    bag, _ = cuts['mid_record']
    out = tmp_path / 'out'
    result = run_to_exit('sensing_pipeline', [str(bag), str(out), '--no-progress'], timeout=120)
    assert result.returncode == 0, result.stderr
    assert 'was not closed' in result.stderr and 'no metadata.yaml' in result.stderr
    scans = BagReader(bag).topics['/scan'].count
    counts = topic_counts(out)
    assert counts['/scan'][1] == scans > 0
    assert counts['/scan_match/odom'][1] == counts['/scan/lines'][1] == scans


def test_sensing_replay_plays_a_cut_bag_up_to_the_cut(cuts, tmp_path):
    bag, _ = cuts['mid_chunk']
    out = tmp_path / 'out'
    result = run_to_exit('sensing_replay', [
        str(bag), str(out), '--launch', '--nodes', 'line_extractor',
        '--expect', '/scan=/scan/lines,/scan/lines/table', '--no-progress'], timeout=150)
    assert result.returncode == 0, result.stdout + result.stderr
    assert 'was not closed' in result.stderr and 'lost' in result.stderr
    scans = BagReader(bag).topics['/scan'].count
    assert topic_counts(out)['/scan/lines'][1] == scans > 0


@pytest.mark.parametrize('tool, extra', [
    ('sensing_eval', []), ('sensing_pipeline', ['{out}', '--no-progress']),
    ('sensing_replay', ['{out}', '--launch', '--no-progress'])])
def test_a_bag_with_nothing_readable_exits_2_saying_why(cuts, tmp_path, tool, extra):
    bag, _ = cuts['header_only']
    out = tmp_path / 'out'
    result = run_to_exit(tool, [str(bag), *[a.format(out=out) for a in extra]])
    assert result.returncode == 2, result.stdout + result.stderr
    assert f'{bag}: nothing readable: nominal.mcap was not closed' in result.stderr
    assert 'before its first chunk or message' in result.stderr
    assert 'Traceback' not in result.stderr and not out.exists()


def test_an_unclosed_writer_loses_at_most_the_last_second(tmp_path):
    """BagWriter's file while it is still open (what kill -9 leaves): every message more than
    chunk_s (1 s) of bag time before the last one written is in it; after flush() all are.
    With 1 MiB chunks only (chunk_s=None) the first MiB is still in memory: nothing."""
    from std_msgs.msg import String

    stamps = [1_000_000_000 + k * 10_000_000 for k in range(500)]    # 5 s at 100 Hz
    with BagWriter(tmp_path / 'open') as bag:
        for k, stamp in enumerate(stamps):
            msg = String()
            msg.data = f'message {k}'
            bag.write('/chatter', msg, stamp)
        on_disk = [s for _, s, _ in BagReader(tmp_path / 'open').raw()]
        assert on_disk == stamps[:len(on_disk)]
        assert on_disk[-1] >= stamps[-1] - 1_000_000_000
        bag.flush()
        assert [s for _, s, _ in BagReader(tmp_path / 'open').raw()] == stamps
    assert 'metadata.yaml' in {p.name for p in (tmp_path / 'open').iterdir()}
    with BagWriter(tmp_path / 'whole', chunk_s=None) as bag:
        for stamp in stamps:
            bag.write('/chatter', String(), stamp)
        with pytest.raises(BagError, match='nothing readable'):
            BagReader(tmp_path / 'whole')


def test_sqlite3_bags_without_metadata_or_cut_short_read_what_sqlite_can(tmp_path):
    """A rosbag2 sqlite3 bag (written by rosbags): without metadata.yaml it reads whole; cut
    short, SQLite calls it malformed, and its rows read in id order up to the first missing
    page, a prefix of the bag; cut inside its first pages, nothing is readable."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from sensing_nodes.bags.storage import TYPESTORE

    string = TYPESTORE.types['std_msgs/msg/String']
    written = []
    with Writer(tmp_path / 'bag', version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        connection = writer.add_connection('/chatter', 'std_msgs/msg/String', typestore=TYPESTORE)
        for k in range(5000):
            raw = bytes(TYPESTORE.serialize_cdr(string(data=f'{k:060d}'), 'std_msgs/msg/String'))
            writer.write(connection, 1_000_000_000 + k * 10_000_000, raw)
            written.append(raw)
    db3 = tmp_path / 'bag' / 'bag.db3'
    no_metadata = tmp_path / 'no_metadata'
    shutil.copytree(tmp_path / 'bag', no_metadata)
    (no_metadata / 'metadata.yaml').unlink()
    assert [raw for _, _, raw in BagReader(no_metadata).raw()] == written
    assert 'no metadata.yaml' in BagReader(no_metadata).damage

    cut = tmp_path / 'cut'
    shutil.copytree(tmp_path / 'bag', cut)
    with (cut / 'bag.db3').open('r+b') as handle:
        handle.truncate(int(db3.stat().st_size * 0.6))
    read = [raw for _, _, raw in BagReader(cut).raw()]
    assert 0.4 * len(written) < len(read) < len(written) and read == written[:len(read)]
    damage = BagReader(cut).damage
    assert 'bag.db3 is cut short' in damage and f'lost {len(written) - len(read)} of' in damage

    with (cut / 'bag.db3').open('r+b') as handle:
        handle.truncate(3000)
    with pytest.raises(BagError, match='nothing readable'):
        BagReader(cut)
