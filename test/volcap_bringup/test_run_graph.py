"""`volcap run`: a synthetic bag through bag_player, a camera_pipeline per camera and
tsdf_fusion (here composed in one process; in processes: test_demo); the fused output reaches the
runner's renderer probe, one mesh per capture frame set, and `volcap eval fusion` scores it."""
import json

import pytest

from volcap_bringup.cli import main
from volcap_studio.session import GroundTruth

pytestmark = pytest.mark.ros


@pytest.fixture(scope='module')
def capture_bag(tmp_path_factory, shared_data):
    """8 cameras: a 3-frame clean plate (the filters learn the mask from it), 2 capture frames."""
    from volcap_studio.session import synthesize
    from volcap_studio.studio import SynthConfig
    out = tmp_path_factory.mktemp('capture') / 'bag'
    synthesize(out, SynthConfig(cameras=8, frames=2, board_poses=0, background_frames=3, seed=3), progress=False)
    return out


def corrupt_a_clean_plate_chunk(bag, out):
    """A copy of ``bag`` with random bytes in the middle of a chunk holding clean-plate frames
    (its CRC no longer matches), as a bad disk sector leaves a recording."""
    import shutil

    import numpy as np
    from mcap.reader import make_reader
    shutil.copytree(bag, out, ignore=shutil.ignore_patterns('ground_truth'))
    shutil.copytree(bag / 'ground_truth', out / 'ground_truth')
    (mcap,) = out.glob('*.mcap')
    plate = [f['stamps']['cam0']['color'] for f in GroundTruth(bag).frames_in('clean_plate')]
    with open(mcap, 'rb') as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    margin = (plate[1] - plate[0]) // 2          # the cameras' stamps jitter around cam0's
    chunk = next(c for c in chunks if c.message_start_time > plate[0] + margin and
                 c.message_end_time < plate[-1] - margin)
    data = bytearray(mcap.read_bytes())
    middle = chunk.chunk_start_offset + chunk.chunk_length // 2
    data[middle:middle + 4096] = np.random.default_rng(0).integers(0, 256, 4096, np.uint8).tobytes()
    mcap.write_bytes(bytes(data))
    return out


@pytest.mark.timeout(400)
@pytest.mark.parametrize('mode', ['composed'])     # each node its own process: test_demo
def test_volcap_run_fuses_every_capture_frame_set(capture_bag, tmp_path, mode, gt_calibration):
    """Composed, from a copy of the bag with a corrupt chunk in its clean plate, which is skipped
    and reported, not a reason to fuse nothing."""
    gt = GroundTruth(capture_bag)
    gt_calibration(gt).save(tmp_path / 'calibration.yaml')
    out = tmp_path / 'run'
    bag = capture_bag if mode == 'processes' else corrupt_a_clean_plate_chunk(capture_bag, tmp_path / 'damaged')
    assert main(['run', str(bag), '--calibration', str(tmp_path / 'calibration.yaml'), '--out', str(out),
                 '--voxel', '0.01', '--rate', '0.1', '--quiet'] + (['--composed'] if mode == 'composed' else [])) == 0
    metrics = json.loads((out / 'metrics.json').read_text())
    if mode == 'processes':
        assert metrics['bag_damage'] == ''
    else:
        assert 'skipped a damaged chunk' in metrics['bag_damage'] and 'messages lost' in metrics['bag_damage']
    captures = len(gt.frames_in('capture'))
    assert metrics['capture_frame_sets_in_bag'] == captures == 2
    assert metrics['frames_written'] == captures
    assert metrics['probe']['meshes_received'] == captures and metrics['probe']['clouds_received'] == captures
    assert all(c == 0 for c in metrics['node_exit_codes'].values()), metrics['node_exit_codes']
    assert metrics['probe']['latency_ms_median'] > 0
    for frame in metrics['frames']:
        assert (out / 'frames' / frame['ply']).exists() and (out / 'frames' / frame['glb']).exists()
        assert frame['missing'] == [] and frame['triangles'] > 5000
        assert frame['glb_triangles'] <= 30_000 and frame['glb_bytes'] < 200_000     # the default budget
    assert metrics['mode'] == mode
    assert len(metrics['renders']) == 2 and (out / 'renders' / 'raw_vs_clean.png').exists()
    assert len(list((out / 'renders').glob('*.png'))) == 3
    report = tmp_path / 'fusion.json'
    assert main(['eval', 'fusion', str(out), str(capture_bag), '--json', str(report), '--quiet']) == 0
    scores = json.loads(report.read_text())
    assert scores['frames'] == captures
    # 10 mm voxels, ground-truth poses, full-size clean depth: measured 1.56 mm and 83.0 % of the
    # observable surface (60.0 % of the whole mesh), the same in both modes
    assert scores['accuracy_mm'] < 2.0 and scores['completeness'] > 0.78


def test_the_player_is_asked_only_for_session_topics_the_bag_has(studio_bag):
    """A volcap bag carries /volcap/rig and /volcap/phase, not /tf_static: asking for it made the
    player warn on every healthy run (`make demo`)."""
    from volcap_bringup.run_graph import expected_subscribers, played_topics
    from volcap_core import topics
    from volcap_core.bag_reader import BagReader
    from volcap_core.frames import camera_topics, read_rig
    with BagReader(studio_bag) as reader:
        cameras = read_rig(reader).names
        layout = camera_topics(reader, cameras)
        played = played_topics(reader, cameras, layout)
        assert set(played) <= set(reader.topics)
    assert topics.RIG in played and topics.PHASE in played and topics.TF_STATIC not in played
    assert all(layout[c]['color'] in played and layout[c]['depth'] in played for c in cameras)
    assert set(expected_subscribers(cameras, layout, played)) == set(played)
