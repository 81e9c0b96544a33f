import array

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField

from volcap_core.camera import CameraModel
from volcap_core.conversions import (
    IMAGE_ENCODINGS,
    MessageConversionError,
    camera_info_to_model,
    camera_model_to_info,
    color_to_rgb,
    depth_to_metres,
    image_to_numpy,
    matrix_to_pose,
    numpy_to_image,
    pointcloud2_to_points,
    points_to_pointcloud2,
    pose_to_matrix,
    stamp_to_ns,
)
from volcap_core.poses import look_at

RNG = np.random.default_rng(3)


def sample(encoding, h=5, w=7):
    scalar, channels = IMAGE_ENCODINGS[encoding]
    shape = (h, w, channels) if channels > 1 else (h, w)
    if np.dtype(scalar).kind == 'f':
        return RNG.uniform(0.3, 4.0, shape).astype(scalar)
    return RNG.integers(0, np.iinfo(scalar).max, shape, dtype=scalar)


def through_cdr(msg):
    """What a subscriber receives: data comes back as array.array."""
    return deserialize_message(serialize_message(msg), type(msg))


@pytest.mark.parametrize('encoding', list(IMAGE_ENCODINGS))
def test_image_round_trip(encoding):
    arr = sample(encoding)
    msg = numpy_to_image(arr, encoding, 1_234_567_890_123, 'cam0_color_optical_frame')
    got = through_cdr(msg)
    assert isinstance(got.data, array.array)
    assert stamp_to_ns(got.header.stamp) == 1_234_567_890_123
    out = image_to_numpy(got)
    assert out.dtype == arr.dtype and np.array_equal(out, arr)


@pytest.mark.parametrize('encoding', list(IMAGE_ENCODINGS))
def test_row_padding_and_big_endian(encoding):
    arr = sample(encoding)
    scalar, channels = IMAGE_ENCODINGS[encoding]
    dt = np.dtype(scalar).newbyteorder('>')
    row = arr.astype(dt).reshape(arr.shape[0], -1).view(np.uint8)
    pad = 5 * dt.itemsize
    padded = np.concatenate([row, np.full((arr.shape[0], pad), 0xAB, np.uint8)], axis=1)
    msg = Image(height=arr.shape[0], width=arr.shape[1], encoding=encoding, is_bigendian=1,
                step=padded.shape[1])
    msg.data = padded.tobytes()
    out = image_to_numpy(through_cdr(msg))
    assert out.dtype.isnative and np.array_equal(out, arr)


def test_image_errors_are_clear():
    msg = numpy_to_image(sample('rgb8'), 'rgb8')
    msg.encoding = 'yuv422'
    with pytest.raises(MessageConversionError, match='unsupported image encoding .yuv422.'):
        image_to_numpy(msg)
    msg = numpy_to_image(sample('16UC1'), '16UC1')
    msg.data = msg.data[:-3]
    with pytest.raises(MessageConversionError, match='needs .* bytes'):
        image_to_numpy(msg)
    msg = numpy_to_image(sample('mono8'), 'mono8')
    msg.step = 3
    with pytest.raises(MessageConversionError, match='step'):
        image_to_numpy(msg)
    with pytest.raises(MessageConversionError, match='dtype'):
        numpy_to_image(sample('16UC1'), '32FC1')
    with pytest.raises(MessageConversionError, match='shape'):
        numpy_to_image(sample('rgb8'), 'rgba8')


def test_color_and_depth_helpers():
    rgb = sample('rgb8')
    for enc, arr in [('rgb8', rgb), ('bgr8', rgb[:, :, ::-1]),
                     ('rgba8', np.dstack([rgb, np.full(rgb.shape[:2], 9, np.uint8)])),
                     ('bgra8', np.dstack([rgb[:, :, ::-1], np.full(rgb.shape[:2], 9, np.uint8)]))]:
        assert np.array_equal(color_to_rgb(numpy_to_image(np.ascontiguousarray(arr), enc)), rgb)
    mm = np.array([[0, 1000, 2500]], np.uint16)
    assert depth_to_metres(numpy_to_image(mm, '16UC1'))[0].tolist() == pytest.approx([0, 1.0, 2.5])
    m = np.array([[np.nan, 1.5, -1.0, np.inf]], np.float32)
    assert depth_to_metres(numpy_to_image(m, '32FC1')).tolist() == [[0, 1.5, 0, 0]]
    with pytest.raises(MessageConversionError, match='depth image expected'):
        depth_to_metres(numpy_to_image(rgb, 'rgb8'))


def test_camera_info_round_trip():
    cam = CameraModel(1280, 720, 611.8, 611.9, 639.3, 365.9, (0.3, -2.4, 1e-4, -1e-4, 1.4, 0.2, -2.3, 1.3))
    info = through_cdr(camera_model_to_info(cam, 5, 'f'))
    assert info.distortion_model == 'rational_polynomial' and info.header.frame_id == 'f'
    assert camera_info_to_model(info) == cam
    info.width = 0
    with pytest.raises(MessageConversionError, match='size'):
        camera_info_to_model(info)
    bad = CameraInfo(width=10, height=10, distortion_model='equidistant', k=[1.0] * 9)
    with pytest.raises(MessageConversionError, match='equidistant'):
        camera_info_to_model(bad)


def test_pointcloud_round_trip_with_color():
    xyz = RNG.normal(size=(100, 3)).astype(np.float32)
    rgb = RNG.integers(0, 256, (100, 3), dtype=np.uint8)
    msg = through_cdr(points_to_pointcloud2(xyz, rgb, 7, 'world'))
    assert [f.name for f in msg.fields] == ['x', 'y', 'z', 'rgb']
    assert msg.fields[3].datatype == PointField.FLOAT32
    got_xyz, got_rgb = pointcloud2_to_points(msg)
    assert np.array_equal(got_xyz, xyz) and np.array_equal(got_rgb, rgb)
    no_color, none = pointcloud2_to_points(points_to_pointcloud2(xyz))
    assert none is None and np.array_equal(no_color, xyz)


def test_pointcloud_padded_fields_and_nans():
    # x y z at 0/4/8, 4 bytes padding, rgb at 16, point_step 32 (as some drivers publish).
    n = 4
    buf = np.zeros(n, dtype=np.dtype({'names': ['x', 'y', 'z', 'rgb'], 'formats': ['<f4', '<f4', '<f4', '<u4'],
                                      'offsets': [0, 4, 8, 16], 'itemsize': 32}))
    buf['x'] = [1, 2, np.nan, 4]
    buf['rgb'] = [0xFF0000, 0x00FF00, 0, 0x0000FF]
    fields = [PointField(name=c, offset=o, datatype=PointField.FLOAT32, count=1)
              for c, o in (('x', 0), ('y', 4), ('z', 8), ('rgb', 16))]
    msg = PointCloud2(height=1, width=n, fields=fields, point_step=32, row_step=32 * n, is_dense=False)
    msg.data = buf.tobytes()
    xyz, rgb = pointcloud2_to_points(msg)
    assert xyz[:, 0].tolist() == [1, 2, 4]
    assert rgb.tolist() == [[255, 0, 0], [0, 255, 0], [0, 0, 255]]
    msg.data = msg.data[:40]
    with pytest.raises(MessageConversionError, match='too short'):
        pointcloud2_to_points(msg)


def test_pose_round_trip():
    T = look_at((1, 2, 3), (0, 0, 1))
    assert np.allclose(pose_to_matrix(matrix_to_pose(T)), T)


def test_jpeg_compressed_colour_decodes_as_the_drivers_send_it():
    from sensor_msgs.msg import CompressedImage

    from volcap_core.conversions import color_message_to_rgb, compressed_to_rgb, rgb_to_compressed
    rgb = np.zeros((72, 128, 3), np.uint8)
    rgb[:, :64] = (200, 30, 40)     # red left, blue right: a swapped channel order would show
    rgb[:, 64:] = (20, 40, 210)
    for fmt in ('bgra8; jpeg compressed bgr8', 'rgb8; jpeg compressed bgr8', 'jpeg'):   # Azure Kinect, image_transport
        msg = rgb_to_compressed(rgb, 5, 'cam0_rgb_camera_link')
        msg.format = fmt
        msg = deserialize_message(serialize_message(msg), CompressedImage)
        out = color_message_to_rgb(msg)
        assert out.shape == rgb.shape and np.abs(out[10:60, 10:50].astype(int) - (200, 30, 40)).max() < 12
        assert np.abs(out[10:60, 80:120].astype(int) - (20, 40, 210)).max() < 12
    with pytest.raises(MessageConversionError, match='cannot decode'):
        compressed_to_rgb(CompressedImage(format='jpeg', data=b'\xff\xd8 not a jpeg'))
    with pytest.raises(MessageConversionError, match='empty'):
        compressed_to_rgb(CompressedImage(format='jpeg'))
    with pytest.raises(MessageConversionError, match='JPEG or PNG'):
        compressed_to_rgb(CompressedImage(format='theora', data=b'x'))


def test_camera_info_distortion_as_each_driver_sends_it():
    """plumb_bob with 5 or 8 coefficients (Orbbec pads to 8), rational_polynomial with 8."""
    d8 = [0.3, -2.4, 0.0001, -0.0001, 1.4, 0.2, -2.3, 1.3]
    for model, d in (('plumb_bob', d8[:5]), ('plumb_bob', d8), ('rational_polynomial', d8)):
        info = CameraInfo(width=1280, height=720, distortion_model=model, d=d,
                          k=[600.0, 0, 640, 0, 600.0, 360, 0, 0, 1])
        assert camera_info_to_model(info).dist == tuple(d)
    with pytest.raises(MessageConversionError, match='distortion model'):
        camera_info_to_model(CameraInfo(width=4, height=3, distortion_model='equidistant', d=[0.0] * 4,
                                        k=[1.0, 0, 2, 0, 1, 1, 0, 0, 1]))


def test_tf_static_round_trip_and_lookup_through_a_driver_tree():
    from scipy.spatial.transform import Rotation
    from tf2_msgs.msg import TFMessage

    from volcap_core.conversions import tf_message_to_transforms, transforms_to_tf_message
    from volcap_core.poses import invert, make_transform
    from volcap_core.tf import StaticTransforms, TransformError
    T_dc = make_transform(Rotation.from_euler('xyz', [0.01, -0.02, 0.03]).as_matrix(), [-0.032, -0.002, 0.004])
    optical = make_transform(Rotation.from_euler('xyz', [-np.pi / 2, 0, -np.pi / 2]).as_matrix(), [0, 0, 0])
    # Orbbec's tree: link -> depth_frame -> color_frame, each frame -> its optical frame
    tree = [('cam0_link', 'cam0_depth_frame', np.eye(4)),
            ('cam0_depth_frame', 'cam0_color_frame', optical @ T_dc @ invert(optical)),
            ('cam0_depth_frame', 'cam0_depth_optical_frame', optical),
            ('cam0_color_frame', 'cam0_color_optical_frame', optical)]
    msg = deserialize_message(serialize_message(transforms_to_tf_message(tree, 7)), TFMessage)
    tf = StaticTransforms()
    for parent, child, T in tf_message_to_transforms(msg):
        tf.add(parent, child, T)
    assert len(tf) == 4
    # T_color_depth between the optical frames is the inverse of the depth-to-colour pose
    np.testing.assert_allclose(tf.lookup('cam0_color_optical_frame', 'cam0_depth_optical_frame'), invert(T_dc),
                               atol=1e-9)
    np.testing.assert_allclose(tf.lookup('/cam0_depth_optical_frame', 'cam0_color_optical_frame'), T_dc, atol=1e-9)
    with pytest.raises(TransformError, match='cam1_rgb_camera_link'):
        tf.lookup('cam1_rgb_camera_link', 'cam0_link')
    with pytest.raises(ValueError, match='finite'):
        tf.add('a', 'b', np.full((4, 4), np.nan))
