"""Nodes in their own processes, talking to real rclpy subscribers in the test process."""
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String

from volcap_bringup.processes import start_node, stop
from volcap_core import qos
from volcap_core.bag_reader import BagReader
from volcap_core.conversions import image_to_numpy, stamp_to_ns
from volcap_studio.session import GroundTruth

pytestmark = pytest.mark.ros

def test_player_replays_with_original_stamps_and_latched_rig(studio_bag, probe_factory, procs, play):
    gt = GroundTruth(studio_bag)
    probe = probe_factory([('cam0/color/image_raw', Image, qos.EVERY_FRAME),
                           ('cam7/depth/camera_info', CameraInfo, qos.EVERY_FRAME),
                           ('volcap/rig', String, qos.LATCHED)])
    player = play(studio_bag, topics=['cam0/color/image_raw', 'cam7/depth/camera_info', 'volcap/rig'])
    assert probe.spin_until(lambda: player.poll() is not None, 60)
    assert player.returncode == 0
    probe.spin_until(lambda: len(probe.got['cam0/color/image_raw']) >= 5, 2)
    stamps = [stamp_to_ns(m.header.stamp) for _, m in probe.got['cam0/color/image_raw']]
    assert stamps == [f['stamps']['cam0']['color'] for f in gt.frames]
    with BagReader(studio_bag) as r:
        first = next(r.messages(['cam0/color/image_raw'])).decode()
    assert np.array_equal(image_to_numpy(probe.got['cam0/color/image_raw'][0][1]), image_to_numpy(first))
    assert len(probe.got['cam7/depth/camera_info']) == 5
    assert yaml.safe_load(probe.got['volcap/rig'][0][1].data)['cameras'][7]['name'] == 'cam7'


def test_late_subscriber_still_gets_the_rig(studio_bag, probe_factory, procs, play):
    early = probe_factory([('cam0/depth/image_raw', Image, qos.EVERY_FRAME)])
    # nobody subscribes to the rig yet: the player need not wait for anyone there
    play(studio_bag, exit_when_done=False, topics=['cam0/depth/image_raw', 'volcap/rig'], subscribers=['volcap/rig=0'])
    assert early.spin_until(lambda: len(early.got['cam0/depth/image_raw']) == 5, 60)
    late = probe_factory([('volcap/rig', String, qos.LATCHED)])
    assert late.spin_until(lambda: late.got['volcap/rig'], 20)
    assert stop(procs.pop()) == 0


def test_remap_and_namespace(studio_bag, probe_factory, procs, play):
    probe = probe_factory([('/k4a/rgb/image_raw', Image, qos.EVERY_FRAME),
                           ('/studio/cam1/depth/camera_info', CameraInfo, qos.EVERY_FRAME)])
    player = play(studio_bag, topics=['cam0/color/image_raw', 'cam1/depth/camera_info'],
                  remap=['cam0/color/image_raw:=/k4a/rgb/image_raw'], namespace='studio')
    assert probe.spin_until(lambda: player.poll() is not None, 60)
    probe.spin_until(lambda: len(probe.got['/k4a/rgb/image_raw']) == 5, 2)
    assert len(probe.got['/k4a/rgb/image_raw']) == 5
    assert len(probe.got['/studio/cam1/depth/camera_info']) == 5


def test_recorder_writes_what_the_player_publishes(studio_bag, tmp_path, probe_factory, procs, play):
    out = tmp_path / 'recorded'
    recorder = start_node('volcap_driver', 'recorder', {'out': str(out), 'compression': 'zstd',
                                                        'topics': ['/cam0/color/image_raw', '/volcap/rig']})
    procs.append(recorder)
    # The player starts once the recorder has discovered and subscribed to both its topics.
    player = play(studio_bag, topics=['cam0/color/image_raw', 'volcap/rig'])
    probe = probe_factory([('volcap/diagnostics', DiagnosticArray, qos.EVENTS)])
    assert probe.spin_until(lambda: player.poll() is not None, 60)
    assert player.returncode == 0

    def recorded() -> int:      # the recorder's own count of messages written, from its diagnostics
        counts = [int(v.value) for _, m in probe.got['volcap/diagnostics'] for s in m.status
                  if 'recorder' in s.name for v in s.values if v.key == 'messages']
        return counts[-1] if counts else 0
    assert probe.spin_until(lambda: recorded() >= 6, 30), recorded()     # 5 images and the rig
    assert stop(recorder) == 0
    with BagReader(out) as r:
        assert r.topics == {'cam0/color/image_raw': 'sensor_msgs/msg/Image', 'volcap/rig': 'std_msgs/msg/String'}
        assert 'volcap/rig' in r.latched_topics
        recorded = [m.decode() for m in r.messages(['cam0/color/image_raw'])]
    with BagReader(studio_bag) as r:
        original = {stamp_to_ns(m.header.stamp): m for m in (x.decode() for x in r.messages(['cam0/color/image_raw']))}
    assert len(recorded) == 5
    for m in recorded:
        assert bytes(m.data) == bytes(original[stamp_to_ns(m.header.stamp)].data)


def test_a_node_process_ends_with_its_last_words_and_its_exit_code(tmp_path, graph, procs):
    """A node's ``main`` (``volcap_core.ros.node_main``) skips the interpreter's teardown with
    ``os._exit`` once the node is shut down: what the node logs while shutting down still comes
    out (the recorder's closing line, through C's stdout into a pipe, where it is fully buffered),
    the node leaves the graph, and the exit code is the node's own (1: a recorder with no output)."""
    recorder = start_node('volcap_driver', 'recorder', {'out': str(tmp_path / 'take'), 'topics': ['/volcap/rig']},
                          env={'RCUTILS_LOGGING_USE_STDOUT': '1'}, stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True)
    procs.append(recorder)

    def recorders() -> int:
        return sum(1 for name in graph.node.get_node_names() if name == 'recorder')
    assert graph.spin_until(lambda: recorders() == 1, 60)
    assert stop(recorder) == 0
    printed = recorder.stdout.read()
    assert 'recorder started' in printed and 'closed bag: 0 messages on 0 topics' in printed, printed
    assert graph.spin_until(lambda: recorders() == 0, 60)
    unusable = start_node('volcap_driver', 'recorder', {'topics': ['/volcap/rig']}, stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True)
    procs.append(unusable)
    assert unusable.wait(120) == 1
    assert 'no output given' in unusable.stdout.read()


def test_recorder_killed_mid_take_loses_nothing_written(studio_bag, tmp_path, procs, play):
    """kill -9 while recording a split bag: the closed files are listed and whole, and
    `volcap bag recover` restores every message the recorder wrote, the open file's included."""
    import signal
    out = tmp_path / 'recorded'
    recorder = start_node('volcap_driver', 'recorder', {'out': str(out), 'topics': ['/cam0/color/image_raw'],
                                                        'max_bagfile_size': 1, 'chunk_size': 1})
    procs.append(recorder)
    play(studio_bag, exit_when_done=False, topics=['cam0/color/image_raw'], loop=True)
    deadline = time.monotonic() + 60
    while len(list(out.glob('*.mcap'))) < 4 and time.monotonic() < deadline:
        time.sleep(0.1)
    recorder.send_signal(signal.SIGKILL)
    recorder.wait(10)
    files = sorted(out.glob('*.mcap'))
    assert len(files) >= 4                      # one message per file (split at 1 byte)
    listed = yaml.safe_load((out / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert len(listed['relative_file_paths']) >= len(files) - 2
    with BagReader(out) as damaged:
        assert 'not in metadata.yaml' in damaged.damage
    run = subprocess.run([sys.executable, '-m', 'volcap_bringup.cli', 'bag', 'recover', str(out),
                          str(tmp_path / 'recovered')], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    with BagReader(studio_bag) as r:
        original = {stamp_to_ns(d.header.stamp): bytes(d.data)
                    for d in (m.decode() for m in r.messages(['cam0/color/image_raw']))}
    with BagReader(tmp_path / 'recovered') as r:
        assert not r.damage
        recovered = [m.decode() for m in r.messages()]
    # Every file holds the message it was opened for, except perhaps one killed before its write.
    assert len(files) - 1 <= len(recovered) <= len(files)
    assert all(bytes(m.data) == original[stamp_to_ns(m.header.stamp)] for m in recovered)


def test_recorder_on_a_full_disk_stops_loudly_and_keeps_what_it_wrote(studio_bag, tmp_path, procs, play,
                                                                      probe_factory, small_disk):
    out = small_disk(4_000_000) / 'take'
    probe = probe_factory([('volcap/diagnostics', DiagnosticArray, qos.EVENTS)])
    procs.append(start_node('volcap_driver', 'recorder', {'out': str(out), 'topics': ['/cam0/color/image_raw'],
                                                        'chunk_size': 100_000}))
    play(studio_bag, exit_when_done=False, topics=['cam0/color/image_raw'], loop=True)
    errors = lambda: [s.message for _, m in probe.got['volcap/diagnostics'] for s in m.status  # noqa: E731
                      if s.level == DiagnosticStatus.ERROR and 'recording' in s.name]
    assert probe.spin_until(errors, 60)
    assert 'disk full' in errors()[0] and 'MB free' in errors()[0] and str(out) in errors()[0]
    recorder = procs[0]
    assert recorder.poll() is None                  # still up, still saying so
    assert stop(recorder) == 1
    with BagReader(out) as bag:                     # whole up to the failure
        frames = [m.decode() for m in bag.messages()]
    assert len(frames) >= 1 and all(len(f.data) == f.step * f.height for f in frames)


def test_bad_bag_is_reported_and_the_node_keeps_running(tmp_path, probe_factory, procs, play):
    bad = tmp_path / 'bad'
    bad.mkdir()
    (bad / 'metadata.yaml').write_text('rosbag2_bagfile_information: {version: 9, storage_identifier: mcap}\n')
    probe = probe_factory([('volcap/diagnostics', DiagnosticArray, qos.EVENTS)])
    player = play(bad, exit_when_done=False)
    errors = lambda: [s for _, m in probe.got['volcap/diagnostics'] for s in m.status  # noqa: E731
                      if s.level == DiagnosticStatus.ERROR]
    assert probe.spin_until(lambda: errors(), 30)
    assert 'bad' in errors()[0].message
    # still running and reporting: the error is published again (every second)
    assert probe.spin_until(lambda: len(errors()) >= 2, 10)
    assert player.poll() is None
    assert stop(procs.pop()) == 1        # and says it failed when stopped


def test_truncated_bag_plays_what_it_can_and_says_what_was_lost(studio_bag, tmp_path, probe_factory, procs, play):
    import shutil
    bag = tmp_path / 'bag'
    shutil.copytree(studio_bag, bag, ignore=shutil.ignore_patterns('ground_truth'))
    (mcap,) = bag.glob('*.mcap')
    mcap.write_bytes(mcap.read_bytes()[:mcap.stat().st_size * 2 // 3])   # recorder killed mid-write
    probe = probe_factory([('volcap/diagnostics', DiagnosticArray, qos.EVENTS),
                           ('cam0/depth/camera_info', CameraInfo, qos.EVERY_FRAME)])
    play(bag, exit_when_done=False, topics=['cam0/depth/camera_info'])
    warned = lambda: [s for _, m in probe.got['volcap/diagnostics'] for s in m.status  # noqa: E731
                      if s.level == DiagnosticStatus.WARN and 'finished' in s.message]
    assert probe.spin_until(warned, 60)
    assert 'cut off' in warned()[0].message and mcap.name in warned()[0].message
    # The readable part was played.
    with BagReader(studio_bag) as whole:
        total = whole.topic_counts['cam0/depth/camera_info']
    assert 1 <= len(probe.got['cam0/depth/camera_info']) < total
    assert stop(procs.pop()) == 0


def test_import_k4a_and_replay(tmp_path, shared_data, probe_factory, procs, play):
    out = tmp_path / 'k4a'
    run = subprocess.run([sys.executable, '-m', 'volcap_bringup.cli', 'import-k4a',
                          str(shared_data / 'azure_kinect' / 'recording.mkv'), '--out', str(out), '--quiet'],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert 'device 001514394512' in run.stdout
    probe = probe_factory([('cam0/depth/image_raw', Image, qos.EVERY_FRAME),
                           ('cam0/color/image_raw', Image, qos.EVERY_FRAME),
                           ('volcap/rig', String, qos.LATCHED)])
    player = play(out, topics=['cam0/depth/image_raw', 'cam0/color/image_raw', 'volcap/rig'])
    assert probe.spin_until(lambda: player.poll() is not None, 60)
    assert probe.spin_until(lambda: probe.got['cam0/depth/image_raw'] and probe.got['cam0/color/image_raw'], 5)
    depth = image_to_numpy(probe.got['cam0/depth/image_raw'][0][1])
    color = image_to_numpy(probe.got['cam0/color/image_raw'][0][1])
    assert depth.shape == (576, 640) and color.shape == (720, 1280, 3)
    valid = depth[depth > 0] / 1000.0
    assert valid.size > 0.5 * depth.size and 0.3 < np.median(valid) < 3.0   # a desk scene within NFOV range
    rig = yaml.safe_load(probe.got['volcap/rig'][0][1].data)
    assert rig['cameras'][0]['serial'] == '001514394512'
    assert rig['cameras'][0]['depth']['width'] == 640


def test_synthetic_rig_publishes_live(probe_factory, procs, shared_data):
    probe = probe_factory([('cam1/depth/image_raw', Image, qos.EVERY_FRAME),
                           ('cam0/color/image_raw', Image, qos.EVERY_FRAME),
                           ('volcap/rig', String, qos.LATCHED)])
    procs.append(start_node('volcap_studio', 'synthetic_rig', {'cameras': 2, 'frames': 1, 'fps': 10.0}))
    assert probe.spin_until(lambda: len(probe.got['cam1/depth/image_raw']) >= 3 and probe.got['volcap/rig'], 120)
    stamps = [stamp_to_ns(m.header.stamp) for _, m in probe.got['cam1/depth/image_raw']]
    assert abs(stamps[-1] / 1e9 - time.time()) < 5          # live stamps, not bag stamps
    assert np.diff(stamps).min() > 0.05e9                       # ~10 fps
    assert image_to_numpy(probe.got['cam0/color/image_raw'][0][1]).shape == (720, 1280, 3)
    assert stop(procs.pop()) == 0


def test_start_offset_and_loop(studio_bag, probe_factory, procs, play):
    gt = GroundTruth(studio_bag)
    capture = {f['stamps']['cam4']['color'] for f in gt.frames_in('capture')}
    offset = (min(capture) - gt.frames[0]['stamps']['cam4']['color']) / 1e9 - 0.01
    probe = probe_factory([('cam4/color/camera_info', CameraInfo, qos.EVERY_FRAME)])
    play(studio_bag, topics=['cam4/color/camera_info'], start_offset=offset, loop=True,
         as_fast_as_possible=True, exit_when_done=False)
    assert probe.spin_until(lambda: len(probe.got['cam4/color/camera_info']) >= 6, 60)
    stamps = [stamp_to_ns(m.header.stamp) for _, m in probe.got['cam4/color/camera_info']]
    assert set(stamps) == capture            # only the capture part, again and again
    assert stop(procs.pop()) == 0


def test_a_player_that_cannot_keep_up_sends_an_even_subset():
    """A player that falls behind degrades as a camera does: whole frame sets (colour and depth
    stamped 12 ms apart stay together), one in N evenly spaced, N rising while it is late and
    falling again once it keeps up; a set far too late is sent and the schedule moves on."""
    from volcap_driver.playback import SetPacer
    period, half = 33_333_333, 16_666_666
    pacer = SetPacer(max_lag_ns=100_000_000)
    now, kept = 0, []
    for k in range(300):                 # sending a set costs 50 ms, a frame period is 33 ms
        target = k * period
        send, late = pacer.start_set(target, now)
        assert not late
        if send:
            assert all(pacer.send(target + 12_000_000, now, half) for _ in range(2))    # the set stays whole
            now = max(now, target) + 50_000_000
            kept.append(k)
        else:
            assert not pacer.send(target + 12_000_000, now, half)
    gaps = [b - a for a, b in zip(kept, kept[1:])]
    # what the player can send (33 / 50 ms: 2 sets in 3), in gaps of 1-4 sets, never a silence
    assert pacer.every in (2, 3) and max(gaps) <= 4
    assert 0.5 < len(kept) / 300 < 0.8
    # whatever grid the admission picks (one set in N from any origin), the subset meets it
    assert all(any(k % n == r for k in kept) for n in range(2, 6) for r in range(n))
    thinned = SetPacer(100_000_000)
    thinned.every, thinned.CALM_SETS = 4, 10**9          # held at 1 in 4
    sent = [k for k in range(400) if thinned.start_set(k * period, k * period)[0]]
    assert thinned.every == 4 and 0.2 < len(sent) / 400 < 0.26
    assert all(any(k % 4 == r for k in sent) for r in range(4))      # no fixed phase against 1 in 4
    assert 'one frame set in' in pacer.status() and pacer.left_out == 300 - len(kept)
    every = pacer.every
    for k in range(300, 300 + 3 * SetPacer.CALM_SETS * every):   # on time again: back to every set
        pacer.start_set(k * period, k * period)
    assert pacer.every < every
    assert SetPacer(100_000_000).start_set(0, 10**9) == (True, True)    # far too late: sent, schedule moves on
    assert all(SetPacer(0).start_set(0, 10**12) == (True, False) for _ in range(3))
