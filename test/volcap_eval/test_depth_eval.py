"""`volcap eval depth` on a rendered studio and `volcap eval registration` on the real Azure Kinect recording."""
import json

from volcap_core.poses import invert
from volcap_eval.depth import evaluate_depth
from volcap_filter.registration import DepthRegistration


def test_depth_evaluation_on_the_studio(studio_bag, tmp_path):
    report = evaluate_depth(studio_bag, max_frames=1, figures=tmp_path / 'fig', progress=False)
    m = report['methods']
    assert set(m) == {'raw', 'paper_horizontal', 'paper_all', 'volcap'}
    ours, paper = m['volcap'], m['paper_all']
    # Measured on this bag (seed 7, one capture set): recall 0.980, kept 0.986, IoU 0.987 (before
    # dark material's sparse returns were kept and closed: 0.977, 0.980, 0.987).
    assert ours['flying_recall'] >= 0.96 and ours['valid_kept'] >= 0.975 and ours['mask_iou'] >= 0.98
    assert ours['flying_precision'] > paper['flying_precision']
    # the holes between dark material's sparse returns get depth on its surface (880 a camera
    # frame, 2.48 mm off on this bag; the returns themselves 3.1); the paper's filter fills nothing
    assert ours['filled_per_frame'] > 100 and ours['filled_mae_mm'] < 6
    assert paper['filled_per_frame'] == 0 and paper['filled_mae_mm'] is None
    assert ours['valid_kept'] > paper['valid_kept']
    assert m['raw']['flying_precision'] is None and m['raw']['mask_iou'] < 0.5
    assert (tmp_path / 'fig' / 'volcap_cam0_mask.png').exists()
    assert (tmp_path / 'fig' / 'paper_all_cam0_depth.png').exists()
    json.dumps(report)


def test_real_kinect_registration_lines_up(k4a_bag, tmp_path):
    from volcap_eval.registration import check_registration
    report = check_registration(k4a_bag, tmp_path / 'overlay.png')
    assert report['median_offset_px'] <= 1.5 and report['edge_pixels'] > 500
    assert (tmp_path / 'overlay.png').stat().st_size > 10_000


def test_wrong_extrinsic_direction_is_visible_on_the_real_recording(k4a_bag):
    """The check can fail: the inverted depth-to-colour transform puts edges far off."""
    from volcap_core.bag_reader import BagReader
    from volcap_core.frames import frame_sets, read_rig
    from volcap_eval.registration import edge_offsets
    with BagReader(k4a_bag) as reader:
        cam = read_rig(reader).cameras[0]
    f = next(frame_sets(k4a_bag)).cameras['cam0']
    wrong = DepthRegistration(f.depth_model, f.color_model, invert(cam.T_color_depth), (1280, 720))
    report, _ = edge_offsets(f.color, wrong.register(f.depth).depth)
    assert report['median_offset_px'] > 5.0
