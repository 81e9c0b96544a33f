"""color_corrector in its own process: every camera of a replayed bag corrected with the
published calibration, a newly published calibration used without a restart, bad images
reported while the node keeps going."""
import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import Image
from std_msgs.msg import String

from volcap_bringup.processes import start_node, stop
from volcap_core import qos, topics
from volcap_core.calibration import Calibration, CameraCalibration
from volcap_core.conversions import image_to_numpy, numpy_to_image, stamp_to_ns
from volcap_studio.session import GroundTruth

pytestmark = pytest.mark.ros


def _calibration(cameras, gain):
    """Every camera with a 3x3 model that scales linear RGB by ``gain``."""
    color = {'method': 'matrix_3x3', 'matrix': (np.eye(3) * gain).tolist()}
    return Calibration(cameras[0], f'{cameras[0]}_color_optical_frame',     # the reference is a calibrated camera
                       {c: CameraCalibration(np.eye(4), f'{c}_color_optical_frame', color=color) for c in cameras})


def test_every_camera_of_a_replayed_bag_is_corrected(studio_bag, ros_context, procs, play, probe_factory):
    cams = GroundTruth(studio_bag).rig.names
    # Reliable probes: every raw frame the player sends and every corrected one are seen.
    outputs = [(f'/{c}/{topics.COLOR_CORRECTED}', Image, qos.EVERY_FRAME) for c in cams]
    probe = probe_factory(outputs + [(f'/{c}/{topics.COLOR_IMAGE}', Image, qos.EVERY_FRAME) for c in cams]
                          + [('/' + topics.DIAGNOSTICS, DiagnosticArray, qos.EVENTS)])
    calib_pub = probe.node.create_publisher(String, '/' + topics.CALIBRATION, qos.LATCHED)
    calib_pub.publish(String(data=_calibration(cams, 0.25).to_yaml()))

    def every_model_loaded():
        # a corrector reports its camera's model (OK) once the latched calibration is in: on a
        # loaded machine that took 4-8 s, longer than the bag plays
        loaded = {s.name.rsplit(' ', 1)[-1] for _, m in probe.got['/' + topics.DIAGNOSTICS] for s in m.status
                  if 'colour corrector' in s.name and 'corrected with' in s.message}
        return loaded >= set(cams)
    try:
        for c in cams:
            procs.append(start_node('volcap_color', 'color_corrector', {}, namespace=c))
        assert probe.spin_until(every_model_loaded, timeout=120), 'a corrector never reported its colour model'
        # only what the correctors take (the player would wait for subscribers to anything else);
        # each colour topic has two subscribers, its corrector and the probe
        played = [f'{c}/{topics.COLOR_IMAGE}' for c in cams]
        play(studio_bag, wait_for_subscribers=60.0, topics=played, rate=0.5, subscribers=[f'{t}=2' for t in played])
        probe.assert_all_arrive([t for t, _, _ in outputs], timeout=150)
    finally:
        probe.close()
    compared = 0
    for c in cams:
        _, out = probe.got[f'/{c}/{topics.COLOR_CORRECTED}'][-1]
        raw = {m.header.stamp.sec * 10**9 + m.header.stamp.nanosec: m
               for _, m in probe.got[f'/{c}/{topics.COLOR_IMAGE}']}
        stamp = out.header.stamp.sec * 10**9 + out.header.stamp.nanosec
        assert out.encoding == 'rgb8' and out.header.frame_id == f'{c}_color_optical_frame'
        assert stamp in raw, f'{c}: corrected frame {stamp} has no raw frame of that stamp'
        before, after = image_to_numpy(raw[stamp]), image_to_numpy(out)
        assert after.shape == before.shape
        # a quarter of the light is about half the sRGB level
        assert 0.4 < after.mean() / before.mean() < 0.65
        compared += 1
    assert compared == len(cams)


def test_new_calibration_is_used_without_restart_and_bad_images_are_reported(ros_context, procs, probe_factory):
    cam = 'cam3'
    probe = probe_factory([(f'/{cam}/{topics.COLOR_CORRECTED}', Image, qos.SENSOR),
                           ('/' + topics.DIAGNOSTICS, DiagnosticArray, qos.EVENTS)])
    image_pub = probe.node.create_publisher(Image, f'/{cam}/{topics.COLOR_IMAGE}', qos.DRIVER)
    calib_pub = probe.node.create_publisher(String, '/' + topics.CALIBRATION, qos.LATCHED)
    grey = np.full((48, 64, 3), 128, np.uint8)
    stamp = [0]

    def level_after(calibration=None, unlike=None, timeout=60):
        """The output level once it is steady (and differs from ``unlike``), from images sent
        after this call (not one still in flight from before)."""
        if calibration is not None:
            calib_pub.publish(String(data=calibration.to_yaml()))
        seen, since = [], stamp[0]

        def changed():
            stamp[0] += 10_000_000
            image_pub.publish(numpy_to_image(grey, 'rgb8', stamp[0], 'f'))
            got = [m for _, m in probe.got[f'/{cam}/{topics.COLOR_CORRECTED}'] if stamp_to_ns(m.header.stamp) > since]
            seen.append(int(image_to_numpy(got[-1])[0, 0, 0]) if got else None)
            return (len(seen) > 5 and seen[-1] is not None and seen[-1] == seen[-3] == seen[-5]
                    and seen[-1] != unlike)
        assert probe.spin_until(changed, timeout)
        return seen[-1]

    def diagnostic(text):
        return any(text in s.message for _, m in probe.got['/' + topics.DIAGNOSTICS] for s in m.status)
    try:
        procs.append(start_node('volcap_color', 'color_corrector', {}, namespace=cam))
        assert probe.spin_until(lambda: image_pub.get_subscription_count() > 0, timeout=60)
        assert level_after() == 128                              # no model yet: passed through
        assert probe.spin_until(lambda: diagnostic('no colour model yet'), timeout=10)
        darker = level_after(_calibration([cam], 0.5), unlike=128)
        brighter = level_after(_calibration([cam], 1.5), unlike=darker)
        assert darker < 110 and brighter > 145
        calib_pub.publish(String(data=_calibration(['cam0'], 2.0).to_yaml()))   # not for this camera: kept
        assert probe.spin_until(lambda: diagnostic('no camera'), timeout=10)
        assert level_after() == brighter
        image_pub.publish(numpy_to_image(grey[:, :, 0], 'mono8', 1, 'f'))
        assert probe.spin_until(lambda: diagnostic('image skipped'), timeout=10)
        assert level_after() == brighter                         # still running
        # Malformed calibrations on the latched topic: refused, the last good model kept ...
        good = yaml.safe_load(_calibration([cam], 1.5).to_yaml())
        for bad in ({**good, 'cameras': [cam]}, {**good, 'cameras': {cam: {**good['cameras'][cam], 'colour': 'x'}}},
                    {**good, 'cameras': {cam: {**good['cameras'][cam],
                                               'colour': {'method': 'matrix_3x3', 'matrix': [[1, 2]]}}}}):
            calib_pub.publish(String(data=yaml.safe_dump(bad)))
            assert probe.spin_until(lambda: diagnostic('calibration not used'), timeout=10)
            assert level_after() == brighter
        # ... and a corrector started while the bad one is latched comes up and passes images through.
        assert stop(procs.pop()) == 0
        procs.append(start_node('volcap_color', 'color_corrector', {}, namespace=cam))
        assert level_after() == 128
        assert procs[-1].poll() is None
    finally:
        probe.close()


def test_neural_models_are_applied_live(ros_context, procs, tmp_path, probe_factory):
    """With ``neural_models`` the node applies the camera's exported region LUT (here one that
    maps every colour to a level set by the image column: left half 40, right half 200),
    whatever the calibration says; a folder without the camera's LUT falls back and says so."""
    from volcap_color.apply import RegionLut
    table = np.zeros((2, 2, 2, 2, 2, 3), np.float32)
    table[..., 0, :], table[..., 1, :] = 40.0, 200.0
    RegionLut(table).save(tmp_path / 'cam2.lut.npz')
    probe = probe_factory([(f'/{c}/{topics.COLOR_CORRECTED}', Image, qos.SENSOR) for c in ('cam2', 'cam5')]
                          + [('/' + topics.DIAGNOSTICS, DiagnosticArray, qos.EVENTS)])
    pubs = {c: probe.node.create_publisher(Image, f'/{c}/{topics.COLOR_IMAGE}', qos.DRIVER) for c in ('cam2', 'cam5')}
    calib_pub = probe.node.create_publisher(String, '/' + topics.CALIBRATION, qos.LATCHED)
    calib_pub.publish(String(data=_calibration(['cam2', 'cam5'], 0.25).to_yaml()))
    grey = np.full((48, 64, 3), 128, np.uint8)
    try:
        for c in ('cam2', 'cam5'):
            procs.append(start_node('volcap_color', 'color_corrector', {'neural_models': str(tmp_path)}, namespace=c))
        assert probe.spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), timeout=60)

        def latest(c):
            got = probe.got[f'/{c}/{topics.COLOR_CORRECTED}']
            return image_to_numpy(got[-1][1]) if got else None

        def corrected():
            for p in pubs.values():
                p.publish(numpy_to_image(grey, 'rgb8', 1, 'f'))
            # cam5 passes images through until the latched calibration reaches it
            return latest('cam2') is not None and latest('cam5') is not None and latest('cam5').mean() < 100
        assert probe.spin_until(corrected, timeout=60)
        out = latest('cam2')
        # the outermost pixel centres are half a pixel inside the two image nodes
        assert abs(int(out[20, 0, 0]) - 41) <= 1 and abs(int(out[20, 63, 0]) - 199) <= 1
        assert np.all(np.diff(out[20, :, 0].astype(int)) >= 0)
        assert probe.spin_until(lambda: any('cam5' in s.message and 'not a region LUT' in s.message
                                            for _, m in probe.got['/' + topics.DIAGNOSTICS] for s in m.status),
                                timeout=10)
    finally:
        probe.close()
