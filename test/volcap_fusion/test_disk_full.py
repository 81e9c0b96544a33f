"""A full disk mid-take: every file on it is whole or absent, the index lists only whole frames,
and the error names the file and the free space."""
import json
import os

import numpy as np
import pytest

from volcap_core.bag_reader import BagReader
from volcap_core.bag_writer import BagWriter
from volcap_core.files import WriteError, atomic_write
from volcap_fusion.glb import EncodeConfig
from volcap_fusion.sequence import SUMMARY, SequenceWriter, binary_ply_size, read_ply, read_sequence
from volcap_fusion.tsdf import FusedModel


def sheet(n: int = 90) -> FusedModel:
    """About 16 000 triangles: a frame of ~300 KB (PLY) + ~200 KB (raw GLB)."""
    y, z = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    vertices = np.stack([np.zeros_like(y), y, z], -1).reshape(-1, 3).astype(np.float32)
    i = np.arange(n - 1)
    a = (i[:, None] * n + i[None, :]).reshape(-1)
    triangles = np.concatenate([np.stack([a, a + 1, a + n], 1), np.stack([a + 1, a + n + 1, a + n], 1)])
    colors = np.random.default_rng(0).integers(0, 256, (len(vertices), 3)).astype(np.uint8)
    return FusedModel(vertices, colors, triangles.astype(np.int32), ['cam0'])


def test_sequence_on_a_full_disk_keeps_every_whole_frame(small_disk):
    folder = small_disk(2_500_000)
    writer = SequenceWriter(folder, encoding=EncodeConfig(encoding='raw', max_triangles=0))
    model = sheet()
    with pytest.raises(WriteError) as failure:
        for k in range(100):
            writer.write(model, 1_000_000_000 + k * 33_333_333)
    message = str(failure.value)
    assert 'disk full' in message and 'MB free' in message and str(folder) in message
    whole = writer.written
    assert whole >= 2
    _, frames = read_sequence(folder)
    assert [f['index'] for f in frames] == list(range(whole))
    for f in frames:                    # every listed frame is whole
        assert os.path.getsize(folder / f['ply']) == binary_ply_size(folder / f['ply'])
        assert len(read_ply(folder / f['ply']).triangles) == len(model.triangles)
        assert os.path.getsize(folder / f['glb']) == f['glb_bytes']
    names = {p.name for p in folder.iterdir()}
    assert not [n for n in names if n.startswith('.')]          # no partial temporary file
    assert f'{whole:06d}.ply' not in names and f'{whole:06d}.glb' not in names
    writer.close()                      # the partial frame was removed: the summary fits
    assert json.loads((folder / SUMMARY).read_text())['frames'] == whole
    assert oct(os.stat(folder / frames[0]['glb']).st_mode & 0o777) == '0o644'


def test_atomic_write_on_a_full_disk_keeps_the_old_file(small_disk):
    folder = small_disk(1_000_000)
    atomic_write(folder / 'calibration.yaml', lambda f: f.write(b'old'))
    with pytest.raises(WriteError, match='calibration.yaml: disk full'):
        atomic_write(folder / 'calibration.yaml', lambda f: f.write(b'x' * 2_000_000))
    assert (folder / 'calibration.yaml').read_bytes() == b'old'
    assert [p.name for p in folder.iterdir()] == ['calibration.yaml']


def test_bag_on_a_full_disk_is_readable_up_to_the_failure(small_disk):
    from sensor_msgs.msg import Image
    folder = small_disk(3_000_000)
    frame = Image(height=100, width=100, encoding='rgb8', step=300, data=bytes(30_000))
    writer = BagWriter(folder / 'bag', chunk_bytes=100_000)
    writer.open()
    with pytest.raises(WriteError, match='disk full'):
        for k in range(1000):
            writer.write('cam0/color/image_raw', frame, k)
    written = writer.count
    try:
        writer.close()        # the failed chunk was cut off, so the summary may fit; if not, the file
    except WriteError:        # stays readable without it
        pass
    with BagReader(folder / 'bag') as bag:
        read = [m.stamp_ns for m in bag.messages()]
    # Every chunk written before the failure (about 3 messages each) is read back.
    assert read == list(range(len(read))) and written - 8 <= len(read) < written
