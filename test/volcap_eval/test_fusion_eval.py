"""Real posed RGB-D frames fused (`volcap fuse-frames`) against a bare Open3D integration."""

from volcap_fusion.tsdf import FusionConfig


def test_real_rgbd_frames_match_a_bare_open3d_integration(shared_data, tmp_path):
    from volcap_eval.fusion import fuse_frames, surface_distance
    folder = shared_data / 'rgbd_box'
    ours, bare, poses = fuse_frames(folder, folder / 'intrinsics.K.txt', FusionConfig(voxel_size=0.01), stride=5)
    assert len(poses) == 10 and len(ours.triangles) > 2000
    d = surface_distance(ours, bare)
    assert d['mean_mm'] < 0.5, d     # pinhole frames: the same integration (measured 0.00 mm)


