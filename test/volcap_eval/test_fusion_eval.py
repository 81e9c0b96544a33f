"""Real posed RGB-D frames fused (`volcap fuse-frames`) against a bare Open3D integration, and a
room scanned from inside (cameras that do not converge) kept whole."""

from volcap_fusion.tsdf import FusionConfig


def test_real_rgbd_frames_match_a_bare_open3d_integration(shared_data, tmp_path):
    from volcap_pipeline.rig import depth_kept, fuse_frames, surface_distance
    folder = shared_data / 'rgbd_box'
    ours, bare, views = fuse_frames(folder, folder / 'intrinsics.K.txt', FusionConfig(voxel_size=0.01, depth_max=6.5),
                                    stride=5)
    assert len(views) == 10 and len(ours.triangles) > 2000
    d = surface_distance(ours, bare)     # the bare mesh is not cropped: a box that cuts shows here
    assert d['mean_mm'] < 0.5, d     # pinhole frames: the same integration (measured 0.00 mm)
    assert depth_kept(ours, views) >= 0.95 and ours.depth_left_out < 0.05


def test_a_room_scanned_from_inside_is_kept_whole(tmp_path):
    from volcap_pipeline.rig import depth_kept, fuse_frames
    from volcap_studio.room import RoomConfig, write_room_frames
    folder = write_room_frames(tmp_path / 'room', RoomConfig(frames=12))
    ours, _, views = fuse_frames(folder, folder / 'intrinsics.K.txt', FusionConfig(voxel_size=0.02, depth_max=6.5))
    assert ours.capture_volume == 'depth bounds'
    assert depth_kept(ours, views) >= 0.95
