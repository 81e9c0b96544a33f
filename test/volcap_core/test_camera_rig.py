import numpy as np
import pytest

from volcap_core.camera import CameraModel
from volcap_core.poses import from_xyz_quat, invert, look_at, rotation_angle_deg, to_xyz_quat, transform_points
from volcap_core.rig import Rig, rig_camera_from_k4a


def test_k4a_factory_calibration_modes(shared_data):
    cam = rig_camera_from_k4a(shared_data / 'azure_kinect' / 'calibration.json', 'cam0')
    assert (cam.color.width, cam.color.height) == (1280, 720)
    assert (cam.depth.width, cam.depth.height) == (640, 576)
    # Square pixels once the 4:3 calibration image is cropped to 720p and the depth crop applied.
    assert cam.color.fx == pytest.approx(cam.color.fy, rel=1e-3)
    assert cam.depth.fx == pytest.approx(cam.depth.fy, rel=1e-3)
    assert 600 < cam.color.fx < 625 and 495 < cam.depth.fx < 515
    assert 300 < cam.depth.cx < 340 and 320 < cam.depth.cy < 360
    assert cam.color.distortion_model == 'rational_polynomial'
    # Colour camera about 32 mm from the depth camera, tilted by ~6 degrees.
    assert np.linalg.norm(cam.T_color_depth[:3, 3]) == pytest.approx(0.032, abs=0.002)
    assert rotation_angle_deg(cam.T_color_depth[:3, :3], np.eye(3)) == pytest.approx(4.95, abs=0.5)


def test_project_undistort_round_trip(shared_data):
    cam = rig_camera_from_k4a(shared_data / 'azure_kinect' / 'calibration.json', 'cam0').color
    rays = cam.pixel_rays()
    px = cam.project(rays.reshape(-1, 3) * 2.0)
    grid = np.stack(np.meshgrid(np.arange(cam.width), np.arange(cam.height)), axis=-1).reshape(-1, 2)
    assert np.abs(px - grid).max() < 1e-6
    # computed once per lens and shared, so nobody may change it; an equal lens is the same lens
    assert cam.pixel_rays() is rays and not rays.flags.writeable
    with pytest.raises(ValueError):
        rays[0, 0, 0] = 1.0
    same = CameraModel.from_dict(cam.to_dict())
    assert same.pixel_rays() is rays and cam.scaled(640, 360).pixel_rays().shape == (360, 640, 3)


def test_scaled_keeps_rays():
    cam = CameraModel(640, 480, 500.0, 500.0, 319.5, 239.5)
    half = cam.scaled(320, 240)
    assert half.cx == pytest.approx(159.5) and half.fx == pytest.approx(250.0)
    p = np.array([[0.1, -0.2, 1.5]])
    assert half.project(p)[0] == pytest.approx((cam.project(p)[0] + 0.5) / 2 - 0.5)


def test_camera_model_validation():
    with pytest.raises(ValueError, match='distortion'):
        CameraModel(10, 10, 5, 5, 5, 5, (0.1, 0.2))
    with pytest.raises(ValueError, match='focal'):
        CameraModel(10, 10, 0, 5, 5, 5)


def test_rig_yaml_round_trip(shared_data):
    cams = [rig_camera_from_k4a(shared_data / 'azure_kinect' / 'calibration.json', f'cam{i}') for i in range(3)]
    rig = Rig(cams, 'test')
    again = Rig.from_yaml(rig.to_yaml())
    assert again.names == ['cam0', 'cam1', 'cam2']
    assert again.camera('cam1').color == cams[1].color
    assert np.allclose(again.camera('cam2').T_color_depth, cams[2].T_color_depth)
    with pytest.raises(ValueError, match='unique'):
        Rig([cams[0], cams[0]])
    with pytest.raises(KeyError, match='cam9'):
        rig.camera('cam9')
    with pytest.raises(ValueError, match='newer'):
        Rig.from_yaml(rig.to_yaml().replace('version: 1', 'version: 99'))


def test_not_a_k4a_calibration():
    with pytest.raises(ValueError, match='Azure Kinect'):
        rig_camera_from_k4a({'foo': 1}, 'cam0')


def test_pose_conventions():
    T = look_at((1.0, -2.0, 1.5), (0.0, 0.0, 1.0))
    # Optical frame: z towards the target, y pointing down in the world.
    z_world = T[:3, 2]
    assert z_world @ (np.array([0, 0, 1.0]) - T[:3, 3]) > 0
    assert T[:3, 1] @ np.array([0, 0, 1.0]) < 0
    target_cam = transform_points(invert(T), np.array([0.0, 0.0, 1.0]))
    assert target_cam[:2] == pytest.approx([0, 0], abs=1e-12) and target_cam[2] > 0
    xyz, q = to_xyz_quat(T)
    assert np.allclose(from_xyz_quat(xyz, q), T)


def test_depth_to_millimetres_marks_invalid_depth_as_none():
    from volcap_core.camera import depth_to_millimetres
    metres = np.array([[1.2344, 1.2346, np.nan, np.inf], [-0.5, 0.0, 70.0, 0.0004]], np.float32)
    mm = depth_to_millimetres(metres)
    assert mm.dtype == np.uint16
    assert mm.tolist() == [[1234, 1235, 0, 0], [0, 0, 65535, 0]]
