"""The compact wire's formats, checked against their published definitions, not against volcap's
own decoder: compressed_depth_image_transport's ConfigHeader + PNG (read here with struct and
Pillow), image_proc crop_decimate's camera_info roi / binning (image_geometry's arithmetic), and
image_transport's format strings."""
import io
import struct

import numpy as np
import pytest
from PIL import Image as PilImage

from volcap_core import wire
from volcap_core.camera import CameraModel
from volcap_core.conversions import MessageConversionError, compressed_to_rgb

MODEL = CameraModel(640, 360, 305.0, 306.0, 319.3, 181.7, (0.1, -0.05, 0.001, 0.002, 0.01))


def _masked_depth(seed=0):
    rng = np.random.default_rng(seed)
    depth = np.zeros((360, 640), np.uint16)
    yy, xx = np.mgrid[:360, :640]
    blob = ((xx - 300) / 80.0) ** 2 + ((yy - 170) / 150.0) ** 2 < 1
    depth[blob] = rng.integers(1500, 3500, blob.sum())
    return depth


def spec_decode_compressed_depth(data: bytes, fmt: str) -> np.ndarray:
    """compressed_depth_image_transport's decoder, from its source: the format names the
    encoding before ';' and 'compressedDepth png' after it; a 12-byte ConfigHeader (enum
    compressionFormat, float depthParam[2]) precedes the PNG."""
    encoding, rest = fmt.split(';')
    assert encoding == '16UC1' and rest.strip() == 'compressedDepth png'
    compression_format, a, b = struct.unpack('<iff', data[:12])
    assert compression_format == 0            # INV_DEPTH, what every encoder writes
    image = PilImage.open(io.BytesIO(data[12:]))
    assert image.mode in ('I;16', 'I;16B', 'I')
    return np.asarray(image, dtype=np.uint16)


@pytest.mark.parametrize('binning', [1, 2, 3])
def test_depth_region_is_lossless_and_placed_as_image_geometry_does(binning):
    depth = _masked_depth()
    region = wire.foreground_region(depth > 0, binning, margin=4)
    assert region.x % binning == region.y % binning == region.width % binning == region.height % binning == 0
    crop = np.ascontiguousarray(region.take(depth))
    msg = wire.encode_depth(crop, 123, 'cam0_color')
    assert msg.format == '16UC1; compressedDepth png'
    decoded = spec_decode_compressed_depth(bytes(msg.data), msg.format)
    np.testing.assert_array_equal(decoded, crop)                      # lossless inside the region
    np.testing.assert_array_equal(wire.decode_depth(msg), crop)
    # nothing valid is outside the region
    outside = depth.copy()
    outside[region.y:region.y + region.height, region.x:region.x + region.width] = 0
    assert not outside.any()
    # camera_info as crop_decimate writes it; image_geometry's effective intrinsics
    info = wire.region_info(MODEL, region, 123, 'cam0_color')
    assert (info.width, info.height) == (640, 360) and info.binning_x == info.binning_y == binning
    assert (info.roi.x_offset, info.roi.y_offset, info.roi.width, info.roi.height) == \
        (region.x, region.y, region.width, region.height)
    assert decoded.shape == (info.roi.height // binning, info.roi.width // binning)
    fx, cx = info.k[0] / binning, (info.k[2] - info.roi.x_offset) / binning
    fy, cy = info.k[4] / binning, (info.k[5] - info.roi.y_offset) / binning
    # a pixel of the decimated crop is the full image's pixel b * j + offset, at the same ray
    j, i = decoded.shape[1] // 2, decoded.shape[0] // 3
    assert decoded[i, j] == depth[region.y + binning * i, region.x + binning * j]
    full_u, full_v = region.x + binning * j, region.y + binning * i
    assert np.isclose((j - cx) / fx, (full_u - MODEL.cx) / MODEL.fx)
    assert np.isclose((i - cy) / fy, (full_v - MODEL.cy) / MODEL.fy)
    # the fusion host puts it back on the binned grid
    model, back = wire.info_region(info)
    canvas, placed = wire.place_region(decoded, back, model)
    np.testing.assert_array_equal(canvas, depth[::binning, ::binning][:canvas.shape[0], :canvas.shape[1]])
    assert placed.fx == pytest.approx(MODEL.fx / binning) and placed.dist == MODEL.dist


def test_colour_region_jpeg_and_mask():
    yy, xx = np.mgrid[:720, :1280]           # texture at a cloth's scale, not sensor noise
    color = np.stack([120 + 50 * np.sin(xx / 9.0), 110 + 40 * np.cos(yy / 7.0), 100 + 30 * np.sin((xx + yy) / 13.0)],
                     axis=-1).astype(np.uint8)
    depth = _masked_depth()
    region = wire.foreground_region(depth > 0, 1, 4)
    color_region = region.scaled_to((640, 360), (1280, 720), 1, margin=1)
    rows, cols = wire.pixels_under(color_region, (1280, 720), (640, 360))
    crop = wire.mask_outside(np.ascontiguousarray(color_region.take(color)), depth[np.ix_(rows, cols)] > 0, 8)
    msg = wire.encode_color(crop, 5, 'f', quality=95)
    assert msg.format == 'rgb8; jpeg compressed bgr8'
    back = np.asarray(PilImage.open(io.BytesIO(bytes(msg.data))).convert('RGB'))
    np.testing.assert_array_equal(back, compressed_to_rgb(msg))
    inside = depth[np.ix_(rows, cols)] > 0
    assert np.abs(back[inside].astype(int) - color_region.take(color)[inside]).mean() < 2
    far = ~np.asarray(__import__('cv2').dilate(inside.astype(np.uint8), np.ones((41, 41), np.uint8)), bool)
    assert far.any() and back[far].max() <= 8            # nothing outside the mask is sent


def test_bad_wire_messages_are_clear_errors():
    msg = wire.encode_depth(np.ones((4, 4), np.uint16))
    msg.format = '32FC1; compressedDepth png'
    with pytest.raises(MessageConversionError, match='16UC1'):
        wire.decode_depth(msg)
    msg = wire.encode_depth(np.ones((4, 4), np.uint16))
    msg.data = bytes(msg.data)[:12]
    with pytest.raises(MessageConversionError, match='no image'):
        wire.decode_depth(msg)
    msg.data = bytes(12) + b'not a png'
    with pytest.raises(MessageConversionError, match='not a 16-bit'):
        wire.decode_depth(msg)
    with pytest.raises(MessageConversionError, match='uint16'):
        wire.encode_depth(np.ones((4, 4), np.float32))
    info = wire.region_info(MODEL, wire.Region(600, 0, 80, 8))
    with pytest.raises(MessageConversionError, match='outside'):
        wire.info_region(info)
    with pytest.raises(MessageConversionError, match='is 4x4 pixels'):
        wire.place_region(np.zeros((3, 3), np.uint16), wire.Region(0, 0, 4, 4), MODEL)
    assert wire.foreground_region(np.zeros((5, 5), bool)) is None

