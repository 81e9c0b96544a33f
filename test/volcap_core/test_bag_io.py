import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import Image
from std_msgs.msg import String

from volcap_core.bag_io import BagError, message_class
from volcap_core.bag_reader import BagReader
from volcap_core.bag_writer import BagWriter
from volcap_core.conversions import image_to_numpy, numpy_to_image, stamp_to_ns
from volcap_driver.playback import Schedule, output_topic, parse_counts, parse_remaps, restamp_cdr


def write_sample(path, n=6, compression='none', shape=(48, 64)):
    frames = [np.full((*shape, 3), (k * 20) % 256, np.uint8) for k in range(n)]
    with BagWriter(path, compression) as bag:
        bag.add_topic('volcap/rig', 'std_msgs/msg/String', latched=True)
        bag.write('volcap/rig', String(data='cameras: []'), 1_000)
        for k, img in enumerate(frames):
            stamp = 2_000_000_000 + k * 33_000_000
            bag.write('cam0/color/image_raw', numpy_to_image(img, 'rgb8', stamp, 'cam0_color_optical_frame'), stamp)
    return frames


@pytest.mark.parametrize('compression', ['none', 'zstd'])
def test_write_read_round_trip(tmp_path, compression):
    frames = write_sample(tmp_path / 'bag', compression=compression)
    with BagReader(tmp_path / 'bag') as bag:
        assert bag.topics == {'volcap/rig': 'std_msgs/msg/String', 'cam0/color/image_raw': 'sensor_msgs/msg/Image'}
        assert bag.latched_topics == {'volcap/rig'}
        assert bag.message_count == 7
        msgs = list(bag.messages(['cam0/color/image_raw']))
    assert [m.stamp_ns for m in msgs] == [2_000_000_000 + k * 33_000_000 for k in range(6)]
    for m, img in zip(msgs, frames):
        decoded = m.decode()
        assert stamp_to_ns(decoded.header.stamp) == m.stamp_ns
        assert np.array_equal(image_to_numpy(decoded), img)


def test_zstd_is_smaller_and_mcap_tools_decode_it(tmp_path):
    write_sample(tmp_path / 'plain', shape=(240, 320))
    write_sample(tmp_path / 'packed', compression='zstd', shape=(240, 320))
    plain = (tmp_path / 'plain' / 'plain_0.mcap').stat().st_size
    packed = (tmp_path / 'packed' / 'packed_0.mcap').stat().st_size
    assert packed < plain / 5
    with open(tmp_path / 'packed' / 'packed_0.mcap', 'rb') as f:
        decoded = [(c.topic, m) for _, c, _, m in make_reader(f, decoder_factories=[DecoderFactory()],
                                                               validate_crcs=True).iter_decoded_messages()]
    # Stored fully qualified, as `ros2 bag record` writes; the reader hands out relative names.
    images = [m for topic, m in decoded if topic == '/cam0/color/image_raw']
    assert len(images) == 6 and images[3].encoding == 'rgb8' and images[3].width == 320
    assert bytes(images[3].data)[:3] == bytes([60, 60, 60])


def write_chunked(path, n, chunk_bytes):
    frames = [np.full((60, 80, 3), k, np.uint8) for k in range(n)]
    with BagWriter(path, chunk_bytes=chunk_bytes) as bag:
        bag.add_topic('volcap/rig', 'std_msgs/msg/String', latched=True)
        bag.write('volcap/rig', String(data='cameras: []'), 999)
        for k, img in enumerate(frames):
            bag.write('cam0/color/image_raw', numpy_to_image(img, 'rgb8', 1000 + k, 'f'), 1000 + k)
    return frames


@pytest.mark.parametrize('kept', [0.3, 0.6, 0.9])
def test_every_whole_chunk_of_a_cut_bag_is_read(tmp_path, kept):
    write_chunked(tmp_path / 'bag', 40, chunk_bytes=1)        # one message per chunk
    mcap = tmp_path / 'bag' / 'bag_0.mcap'
    data = mcap.read_bytes()
    mcap.write_bytes(data[:int(len(data) * kept)])
    for recorder_killed in (False, True):
        if recorder_killed:
            (tmp_path / 'bag' / 'metadata.yaml').unlink()
        with BagReader(tmp_path / 'bag') as bag:
            read = [image_to_numpy(m.decode())[0, 0, 0] for m in bag.messages(['cam0/color/image_raw'])]
            assert 'cut off' in bag.damage and ('no metadata.yaml' in bag.damage) == recorder_killed
            assert bag.topics['cam0/color/image_raw'] == 'sensor_msgs/msg/Image'
            assert bag.latched_topics == {'volcap/rig'}
    whole = int(40 * kept)           # messages are the same size: the cut falls in message `whole`
    assert whole - 1 <= len(read) <= whole and read == list(range(len(read)))


def test_a_corrupt_chunk_is_skipped_and_counted(tmp_path):
    write_chunked(tmp_path / 'bag', 10, chunk_bytes=1)
    mcap = tmp_path / 'bag' / 'bag_0.mcap'
    data = bytearray(mcap.read_bytes())
    at = data.index(bytes([4]) * 1000)              # the pixels of frame 4
    data[at:at + 500] = np.random.default_rng(1).integers(0, 256, 500, np.uint8).tobytes()
    mcap.write_bytes(bytes(data))
    with BagReader(tmp_path / 'bag') as bag:
        read = [image_to_numpy(m.decode())[0, 0, 0] for m in bag.messages(['cam0/color/image_raw'])]
        assert read == [0, 1, 2, 3, 5, 6, 7, 8, 9]
        assert len(bag.losses) == 1 and '1 messages lost' in bag.damage and 'crc' in bag.damage.lower()
        assert bag.verify() == 10


def test_split_bag_and_an_unlisted_last_file(tmp_path):
    with BagWriter(tmp_path / 'bag', split_bytes=30_000, chunk_bytes=1) as bag:
        for k in range(20):
            bag.write('cam0/color/image_raw', numpy_to_image(np.full((60, 80, 3), k, np.uint8), 'rgb8', k, 'f'), k)
    files = sorted(p.name for p in (tmp_path / 'bag').glob('*.mcap'))
    assert len(files) >= 3 and files[0] == 'bag_0.mcap'
    with BagReader(tmp_path / 'bag') as bag:
        assert not bag.damage and bag.message_count == 20
        assert [image_to_numpy(m.decode())[0, 0, 0] for m in bag.messages()] == list(range(20))
    # A recorder killed while writing the last file: metadata.yaml lists only the closed ones.
    w = BagWriter(tmp_path / 'killed', split_bytes=30_000, chunk_bytes=1)
    w.open()
    for k in range(20):
        w.write('cam0/color/image_raw', numpy_to_image(np.full((60, 80, 3), k, np.uint8), 'rgb8', k, 'f'), k)
    w.abandon()
    with BagReader(tmp_path / 'killed') as bag:
        assert 'not in metadata.yaml' in bag.damage
        assert [image_to_numpy(m.decode())[0, 0, 0] for m in bag.messages()] == list(range(20))


def test_garbage_and_missing_bags(tmp_path):
    with pytest.raises(BagError, match='does not exist'):
        BagReader(tmp_path / 'nope')
    (tmp_path / 'empty').mkdir()
    with pytest.raises(BagError, match='no metadata.yaml'):
        BagReader(tmp_path / 'empty')
    write_sample(tmp_path / 'bag')
    (tmp_path / 'bag' / 'bag_0.mcap').write_bytes(b'not an mcap file at all' * 10)
    with pytest.raises(BagError, match='no message could be read.*invalid magic'):
        BagReader(tmp_path / 'bag')
    with pytest.raises(BagError, match='exists'):
        BagWriter(tmp_path / 'bag').open()


def test_sqlite3_bags_are_read(tmp_path):
    ts = get_typestore(Stores.ROS2_JAZZY)
    with Writer(tmp_path / 'sq', version=9, storage_plugin=StoragePlugin.SQLITE3) as w:
        conn = w.add_connection('cam0/color/image_raw', 'sensor_msgs/msg/Image', typestore=ts)
        for k in range(3):
            w.write(conn, 10 + k, serialize_message(numpy_to_image(np.full((4, 5, 3), k, np.uint8), 'rgb8', 10 + k)))
    with BagReader(tmp_path / 'sq') as bag:
        msgs = list(bag.messages())
    assert [image_to_numpy(m.decode())[0, 0, 0] for m in msgs] == [0, 1, 2]


@pytest.mark.parametrize('storage', [StoragePlugin.MCAP, StoragePlugin.SQLITE3])
@pytest.mark.parametrize('name', ['/cam0/color/image_raw', 'cam0/color/image_raw'])
def test_both_topic_name_forms_read_alike(tmp_path, storage, name):
    """A bag by `ros2 bag record` (fully qualified names) and one by older volcap (relative)."""
    ts = get_typestore(Stores.ROS2_JAZZY)
    with Writer(tmp_path / 'b', version=9, storage_plugin=storage) as w:
        conn = w.add_connection(name, 'sensor_msgs/msg/Image', typestore=ts)
        w.write(conn, 10, serialize_message(numpy_to_image(np.full((4, 5, 3), 7, np.uint8), 'rgb8', 10)))
    with BagReader(tmp_path / 'b') as bag:
        assert bag.topics == {'cam0/color/image_raw': 'sensor_msgs/msg/Image'}
        assert bag.topic_counts == {'cam0/color/image_raw': 1}
        for wanted in (['/cam0/color/image_raw'], ['cam0/color/image_raw'], None):
            assert [m.topic for m in bag.messages(wanted)] == ['cam0/color/image_raw']


def test_message_class_errors():
    assert message_class('sensor_msgs/msg/Image') is Image
    with pytest.raises(BagError, match='not available'):
        message_class('nonexistent_msgs/msg/Foo')


def test_restamp_patches_only_the_header_stamp():
    img = numpy_to_image(np.arange(60, dtype=np.uint8).reshape(4, 5, 3), 'rgb8', 123, 'frame')
    patched = deserialize_message(restamp_cdr(serialize_message(img), 9_876_543_210_012), Image)
    assert stamp_to_ns(patched.header.stamp) == 9_876_543_210_012
    assert patched.header.frame_id == 'frame' and bytes(patched.data) == bytes(img.data)
    with pytest.raises(ValueError):
        restamp_cdr(b'\x01\x02', 0)


def test_topic_mapping_and_schedule():
    remaps = parse_remaps(['cam0/color/image_raw:=/k4a/rgb/image_raw'])
    assert output_topic('cam0/color/image_raw', remaps, 'studio') == 'k4a/rgb/image_raw'
    assert output_topic('/cam1/depth/image_raw', remaps, '/studio/') == 'studio/cam1/depth/image_raw'
    assert output_topic('volcap/rig', {}, '') == 'volcap/rig'
    with pytest.raises(ValueError, match='FROM:=TO'):
        parse_remaps(['nonsense'])
    assert parse_counts(['/cam0/rgb/image_raw/compressed=3', 'volcap/phase=9']) == {
        'cam0/rgb/image_raw/compressed': 3, 'volcap/phase': 9}
    with pytest.raises(ValueError, match='TOPIC=N'):
        parse_counts(['cam0/color/image_raw=two'])
    s = Schedule(bag_start_ns=1000, wall_start_ns=50, rate=2.0)
    assert s.wall_time(3000) == 1050
    assert Schedule(1000, 50, 1.0, as_fast_as_possible=True).wall_time(10**12) == 50
    assert s.rebase(3000, 1050, 0.5).wall_time(4000) == 3050


def test_a_chunk_of_many_small_messages_is_written_whole(tmp_path):
    """Thousands of camera_info-sized messages in one chunk: more pieces than one writev takes."""
    from sensor_msgs.msg import CameraInfo
    with BagWriter(tmp_path / 'bag', chunk_bytes=16 << 20) as bag:
        for k in range(5000):
            bag.write('cam0/color/camera_info', CameraInfo(width=k + 1, height=1), k)
    with BagReader(tmp_path / 'bag') as bag:
        assert [m.decode().width for m in bag.messages()] == list(range(1, 5001))
        assert not bag.damage


def test_restamping_keeps_a_frame_sets_capture_offsets_at_any_rate():
    from volcap_driver.playback import SetRestamper
    restamper = SetRestamper()
    half_period = 16_000_000
    # two cameras 1 ms apart, played at a tenth of real time: the wall targets are 10 ms apart
    s = Schedule(bag_start_ns=0, wall_start_ns=5_000_000_000, rate=0.1)
    stamps = [restamper.stamp(t, s.wall_time(t), half_period) for t in (1_000_000_000, 1_001_000_000)]
    assert stamps[1] - stamps[0] == 1_000_000            # still 1 ms: the set stays a set
    nxt = restamper.stamp(1_033_000_000, s.wall_time(1_033_000_000), half_period)
    assert nxt == s.wall_time(1_033_000_000)              # the next set moves to its own play time


@pytest.mark.parametrize('kept', [0.35, 0.7])
def test_a_cut_bag_is_self_describing_for_the_mcap_readers(tmp_path, kept):
    """Every whole chunk declares its channels (and their schemas) before its messages, as the
    reference writer does for the chunk of a channel's first message: the ``mcap`` library's
    stream reader, which knows nothing but the records it has met, decodes every message of a
    cut file up to the cut; and a file whose first chunk is damaged still names the rest."""
    from mcap.records import Channel, Chunk, Message, Schema
    from mcap.stream_reader import StreamReader, breakup_chunk
    write_chunked(tmp_path / 'bag', 20, chunk_bytes=30_000)       # a few messages per chunk
    mcap = tmp_path / 'bag' / 'bag_0.mcap'
    data = bytearray(mcap.read_bytes())
    cut = bytes(data[:int(len(data) * kept)])
    known, decoded, chunks = {}, [], 0
    import io
    try:
        for record in StreamReader(io.BytesIO(cut), emit_chunks=True).records:
            if isinstance(record, Chunk):
                chunks += 1
                declared = {}
                for r in breakup_chunk(record, validate_crc=True):
                    if isinstance(r, Schema):
                        declared[('schema', r.id)] = r
                    elif isinstance(r, Channel):
                        assert ('schema', r.schema_id) in declared       # schema before channel, same chunk
                        declared[('channel', r.id)] = r
                        known[r.id] = r.topic
                    elif isinstance(r, Message):
                        assert ('channel', r.channel_id) in declared     # this chunk names it
                        decoded.append((known[r.channel_id], r.log_time))
            assert not isinstance(record, (Channel, Schema))             # only inside chunks
    except Exception as e:   # the cut: the stream reader stops at the partial record
        assert 'EndOfFile' in type(e).__name__ or 'Invalid' in type(e).__name__ or 'truncat' in str(e).lower(), e
    images = [t for topic, t in decoded if topic == '/cam0/color/image_raw']
    assert chunks >= 2 and images == list(range(1000, 1000 + len(images))) and len(images) >= 20 * kept - 4
    # a damaged first chunk: the later ones still decode with their names
    first = data.index(bytes([0]) * 1000)
    data[first:first + 200] = bytes(range(200))
    mcap.write_bytes(bytes(data))
    with BagReader(tmp_path / 'bag') as bag:
        read = [image_to_numpy(m.decode())[0, 0, 0] for m in bag.messages(['cam0/color/image_raw'])]
    assert read and read[0] > 0 and read == list(range(read[0], 20))
