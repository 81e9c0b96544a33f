"""`volcap eval stability` on a still studio fused with the pipeline's own cleaning, and on the
same sequence with jitter and colour flicker injected: it must see them."""
import json

import numpy as np

from volcap_core.camera import depth_to_millimetres
from volcap_core.poses import invert
from volcap_eval.stability import evaluate_stability
from volcap_filter.pipeline import DepthFilterConfig
from volcap_fusion.sequence import SequenceWriter
from volcap_fusion.tsdf import CameraView, FusedModel, FusionConfig, TsdfFusion
from volcap_pipeline.replay import cleaned_frame_sets
from volcap_studio.session import GroundTruth


def fused_sequence(bag) -> tuple[list[FusedModel], list[int], np.ndarray]:
    gt = GroundTruth(bag)
    T_sw = np.asarray(gt.doc['T_studio_world'], float)
    fusion = TsdfFusion(FusionConfig())
    models, stamps = [], []
    for fs, cleaned in cleaned_frame_sets(bag, {'volcap': DepthFilterConfig()}):
        views = [CameraView(cam, depth_to_millimetres(c.result.depth), c.model, c.color, c.frame.color_model,
                            T_sw @ gt.T_world_color(cam)) for cam, c in cleaned['volcap'].items()]
        models.append(fusion.fuse(views, on_floor=True))
        stamps.append(fs.stamp_ns)
    return models, stamps, T_sw


def write_run(folder, models, stamps, T_sw):
    writer = SequenceWriter(folder / 'frames', formats=('ply',))
    for model, stamp in zip(models, stamps):
        writer.write(model, stamp, T_world_frame=invert(T_sw))
    return folder


def test_a_still_subject_scores_low_and_injected_jitter_and_flicker_are_seen(still_bag, tmp_path):
    from volcap_bringup import cli
    models, stamps, T_sw = fused_sequence(still_bag)
    assert len(models) == 4
    still = evaluate_stability(write_run(tmp_path / 'still', models, stamps, T_sw), still_bag, progress=False)
    assert still['frame_pairs'] == 3
    # measured: 0.71 mm, 0.57 CIEDE2000, 0.13 % (four cameras, from the first frame); shaken: 1.61 mm, 2.40
    assert still['jitter_rms_mm'] < 1.0 and still['flicker_de'] < 1.0 and still['appear_vanish'] < 0.01, still

    rng = np.random.default_rng(0)
    shaken = []
    for k, m in enumerate(models):       # 1.5 mm of rigid shake and 6 levels of red, frame by frame
        direction = rng.normal(size=3)
        offset = 0.0015 * direction / np.linalg.norm(direction)
        colors = m.colors.astype(int)
        colors[:, 0] += 6 if k % 2 else 0
        shaken.append(FusedModel((m.vertices + offset).astype(np.float32), np.clip(colors, 0, 255).astype(np.uint8),
                                 m.triangles))
    shook = evaluate_stability(write_run(tmp_path / 'shaken', shaken, stamps, T_sw), still_bag, progress=False)
    assert shook['jitter_rms_mm'] > 2 * still['jitter_rms_mm'] and shook['jitter_rms_mm'] > 1.0, shook
    assert shook['flicker_de'] > still['flicker_de'] + 1.0, shook

    report = tmp_path / 'stability.json'
    assert cli.main(['eval', 'stability', str(tmp_path / 'still'), str(still_bag), '--json', str(report),
                     '--quiet']) == 0
    assert json.loads(report.read_text())['jitter_rms_mm'] == still['jitter_rms_mm']
    assert cli.main(['eval', 'stability', str(tmp_path / 'still'), '--frames', '1']) == 2     # a user's mistake
    assert cli.main(['eval', 'stability', str(tmp_path / 'still'), '--first', '3']) == 2      # one frame left
