"""`volcap live`: the graph on a looped bag with fresh stamps, admission control on. Meshes keep
arriving from the whole rig; a fusion too slow for the input rate makes the stages drop frame
sets, and every drop is counted. No timing thresholds: only counts, and each run lasts until what
it checks has happened (a loaded machine takes longer, up to a cap). The bag plays at half speed
(15 fps): on a loaded 2-core CI machine 4 cameras at 30 fps take the cores before any work is done
(docs/live.md), which is what bench/live.py measures."""
import pytest

from volcap_bringup.live import LiveConfig, run_live
from volcap_core.calibration import Calibration, CameraCalibration
from volcap_studio.session import GroundTruth

pytestmark = pytest.mark.ros


@pytest.fixture(scope='module')
def live_bag(tmp_path_factory, shared_data):
    """4 cameras: a 2-frame clean plate, then 3 capture frames that the player loops."""
    from volcap_studio.session import synthesize
    from volcap_studio.studio import SynthConfig
    out = tmp_path_factory.mktemp('live') / 'bag'
    synthesize(out, SynthConfig(cameras=4, frames=3, board_poses=0, background_frames=2, seed=5), progress=False)
    return out


@pytest.fixture(scope='module')
def live_calibration(live_bag, tmp_path_factory):
    gt = GroundTruth(live_bag)
    calibration = Calibration(gt.rig.names[0], gt.doc['world_frame'],
                              {c: CameraCalibration(gt.T_world_color(c), f'{c}_color_optical_frame')
                               for c in gt.rig.names})
    return calibration.save(tmp_path_factory.mktemp('live_cal') / 'calibration.yaml')


def after_warmup(result, warmup):
    return [s for s in result['summaries'] if s['t_s'] >= warmup]


def meshes_after_warmup(meshes: int, warmup: float, summaries_with_share: int = 0, whole: bool = False):
    """A run's stop condition: ``meshes`` meshes arrived after the warm-up, and the controller
    reported ``summaries_with_share`` times after it with meshes to judge (complete_share), one of
    them (``whole``) a second in which every mesh was fused from every camera."""
    def done(progress: dict) -> bool:
        shares = [s['complete_share'] for s in progress['summaries']
                  if s['t_s'] >= warmup and s['complete_share'] is not None]
        return progress['meshes_after_warmup'] >= meshes and len(shares) >= summaries_with_share \
            and (not whole or 1.0 in shares)
    return done


@pytest.mark.timeout(420)
def test_live_graph_keeps_delivering_whole_meshes(live_bag, live_calibration):
    # the rate is bench/live.py's to measure (65-69 meshes in 30 s on an idle 2-core machine, 2 in
    # a loaded CI run); here meshes keep coming after the warm-up, where a stalled graph gives none
    result = run_live(LiveConfig(live_calibration, bag=live_bag, voxel_size=0.01, rate=0.5, seconds=240, warmup_s=8,
                                 probe=True), stop_when=meshes_after_warmup(4, 8, summaries_with_share=2, whole=True))
    assert all(c == 0 for c in result['node_exit_codes'].values()), result['node_exit_codes']
    meshes = result['meshes']
    assert result['meshes_in_window'] >= 4, (len(meshes), result['summaries'][-3:])
    stamps = [stamp for _, stamp, _ in meshes]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)     # newest first, none twice
    # whole sets are assembled: a second of meshes all fused from every camera (a camera that never
    # arrives gives none in 240 s). How many sets a loaded machine fuses short of a camera is
    # bench/live.py's to measure: CI under load saw one second of [0.0, 1.0].
    shares = [s['complete_share'] for s in after_warmup(result, 8) if s['complete_share'] is not None]
    assert 1.0 in shares, shares
    # one process per camera
    assert result['summaries'][-1]['stages_reporting'] == {'camera_pipeline': 4, 'depth_filter': 0,
                                                           'color_corrector': 0, 'tsdf_fusion': 1}


@pytest.mark.timeout(420)
def test_an_overloaded_fusion_stays_live_and_says_so(live_bag, live_calibration):
    """2 mm voxels with every frame set admitted (admission fixed at 1): on this machine more than
    the fusion can do, on a GPU machine perhaps not. Whatever the machine, the graph stays live
    (meshes keep arriving after the warm-up, where a stalled graph gives none), and whatever the
    fusion drops is reported as trouble. How much it drops is bench/live.py's to measure; the
    drop accounting itself is test_worker's."""
    result = run_live(LiveConfig(live_calibration, bag=live_bag, voxel_size=0.002, depth_scale=1.0, every=1,
                                 rate=0.5, seconds=240, warmup_s=8, probe=True),
                      stop_when=meshes_after_warmup(2, 8, summaries_with_share=2))
    assert all(c == 0 for c in result['node_exit_codes'].values()), result['node_exit_codes']
    summaries = after_warmup(result, 8)
    assert {s['admit_every'] for s in summaries} == {1}
    assert result['meshes_in_window'] >= 2, result['summaries'][-3:]
    for s in summaries:
        if s['drops_per_s']['tsdf_fusion']['dropped'] > 0:
            assert s['trouble'], s


@pytest.mark.timeout(420)
def test_a_recorded_wire_feeds_the_fusion_host_alone(live_bag, live_calibration, tmp_path):
    """`volcap wire` records what the camera hosts send; `volcap live --bag WIREBAG` starts only
    the fusion host on it (no camera pipeline), and meshes come out in stamp order from every
    camera."""
    from volcap_core import wire
    from volcap_core.bag_reader import BagReader
    from volcap_pipeline.wire_bag import WireBagConfig, record_wire
    report = record_wire(WireBagConfig(live_bag, live_calibration, tmp_path / 'wire', progress=False))
    assert report.frame_sets == 3 and report.cameras == ['cam0', 'cam1', 'cam2', 'cam3']
    assert report.bytes_per_camera_frame < report.raw_bytes_per_camera_frame / 10
    with BagReader(tmp_path / 'wire') as bag:
        counts = bag.topic_counts
        assert all(counts[f'{c}/{t}'] == 3 for c in report.cameras for t in
                   (wire.WIRE_DEPTH, wire.WIRE_COLOR, wire.WIRE_DEPTH_INFO, wire.WIRE_COLOR_INFO))
        first = next(bag.messages(['cam0/' + wire.WIRE_DEPTH])).decode()
        info = next(bag.messages(['cam0/' + wire.WIRE_DEPTH_INFO])).decode()
    assert first.format == '16UC1; compressedDepth png' and 0 < info.roi.width < info.width
    result = run_live(LiveConfig(live_calibration, bag=tmp_path / 'wire', voxel_size=0.01, rate=0.5, seconds=240,
                                 warmup_s=6, probe=True), stop_when=meshes_after_warmup(3, 6, summaries_with_share=2))
    assert all(c == 0 for c in result['node_exit_codes'].values()), result['node_exit_codes']
    assert set(result['node_exit_codes']) - {'volcap_renderer_probe'} == {'bag_player', 'tsdf_fusion'}
    stamps = [stamp for _, stamp, _ in result['meshes']]
    assert len(stamps) >= 3 and stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
    shares = [s['complete_share'] for s in after_warmup(result, 6) if s['complete_share'] is not None]
    assert shares and sum(shares) / len(shares) > 0.5, shares
    assert result['summaries'][-1]['stages_reporting']['camera_pipeline'] == 0
