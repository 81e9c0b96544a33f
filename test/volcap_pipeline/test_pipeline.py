"""The pipeline layer: one camera's frames through CameraPipeline (the depth filter's and the
colour corrector's own session classes), a bag replayed through it, and `volcap fuse-frames`."""
import json

import numpy as np

from volcap_color.corrector import CameraCorrection
from volcap_core.bag_reader import BagReader
from volcap_core.calibration import Calibration, CameraCalibration
from volcap_core.frames import frame_sets, read_rig
from volcap_core.topics import CAPTURE, CLEAN_PLATE
from volcap_filter.pipeline import DepthFilterConfig
from volcap_pipeline.camera import CameraPipeline
from volcap_pipeline.replay import cleaned_frame_sets


def _gain_calibration(camera: str, gain: float) -> str:
    color = {'method': 'matrix_3x3', 'matrix': (np.eye(3) * gain).tolist()}
    return Calibration(camera, f'{camera}_color_optical_frame',
                       {camera: CameraCalibration(np.eye(4), f'{camera}_color_optical_frame', color=color)}).to_yaml()


def test_one_camera_learns_its_plate_then_cleans_and_corrects(studio_bag):
    with BagReader(studio_bag) as reader:
        rig = read_rig(reader)
    cam = rig.names[0]
    correction = CameraCorrection(cam)
    assert correction.set_calibration(_gain_calibration(cam, 0.25))[0]
    pipeline = CameraPipeline(cam, rig=rig, correction=correction)
    kinds, cleaned = [], []
    for fs in frame_sets(studio_bag, phases=(CLEAN_PLATE, CAPTURE), cameras=[cam]):
        outcomes, out = pipeline.add(fs.cameras[cam], fs.stamp_ns, fs.phase)
        kinds += [o.kind for o in outcomes]
        if out is not None:
            cleaned.append((fs, out))
    assert 'learnt' in kinds and 'plate_done' in kinds and 'failed' not in kinds
    assert len(cleaned) == 2                          # the bag's two capture frames
    fs, out = cleaned[-1]
    depth = out.result.depth
    assert depth.shape == (out.model.height, out.model.width) == out.color.shape[:2]
    assert 0 < np.count_nonzero(depth) < 0.5 * depth.size      # the subject, not the room
    # a quarter of the light is about half the sRGB level; the raw frame is left as it was
    assert 0.4 < out.color.mean() / out.frame.color.mean() < 0.65
    view = out.fusion_view(np.eye(4))
    assert view.name == cam and view.depth_mm.dtype == np.uint16 and view.color is out.color


def test_replay_gives_every_camera_of_every_capture_set(studio_bag):
    sets = list(cleaned_frame_sets(studio_bag, {'volcap': DepthFilterConfig()}, output_size='half'))
    with BagReader(studio_bag) as reader:
        names = read_rig(reader).names
    assert len(sets) == 2
    for fs, cleaned in sets:
        assert fs.phase == CAPTURE and sorted(cleaned['volcap']) == sorted(names)
        for c in cleaned['volcap'].values():
            assert c.result.depth.shape == (c.frame.color_model.height // 2, c.frame.color_model.width // 2)


def test_fuse_frames_command_writes_mesh_report_and_render(shared_data, tmp_path):
    from volcap_bringup.cli import main
    out = tmp_path / 'box.ply'
    assert main(['fuse-frames', str(shared_data / 'rgbd_box'), '--out', str(out), '--stride', '5']) == 0
    report = json.loads(out.with_suffix('.json').read_text())
    # the command's own preset where nothing is given (volcap_pipeline.FOLDER_FUSION): 1 cm voxels
    assert report['frames'] == 10 and report['voxel_size'] == 0.01 and report['triangles'] > 2000
    assert report['depth_within_2cm'] > 0.8 and out.stat().st_size > 10_000     # 0.86 from 10 of the 50 frames
    assert out.with_suffix('.png').stat().st_size > 10_000
    assert main(['fuse-frames', str(shared_data / 'rgbd_box'), '--out', str(tmp_path / 'b.ply'), '--stride', '25',
                 '--depth-max', '9']) == 2          # beyond the setting's range: the user's mistake
