import pytest

from volcap_core.sync import FrameSetSynchronizer, PeriodEstimate, tolerance_for_period

MS = 1_000_000
CAMS = ['cam0', 'cam1', 'cam2']


def feed(sync, items):
    out = []
    for cam, stream, stamp, now in items:
        out += sync.add(cam, stamp, (cam, stream, stamp), stream=stream, now_ns=now)
    return out


def test_complete_sets_with_jitter():
    sync = FrameSetSynchronizer(CAMS, ('color', 'depth'), tolerance_ns=2 * MS)
    items = []
    for k in range(3):
        t = 1000 * MS + k * 33 * MS
        for i, cam in enumerate(CAMS):
            items += [(cam, 'color', t + i * 300_000, t), (cam, 'depth', t - i * 200_000, t)]
    sets = feed(sync, items)
    assert [s.complete for s in sets] == [True] * 3
    assert [s.stamp_ns for s in sets] == [1000 * MS, 1033 * MS, 1066 * MS]
    assert sets[1].get('cam2', 'depth')[2] == 1033 * MS - 400_000
    assert sync.pending == 0 and sync.stats.complete == 3


def test_missing_camera_times_out_and_is_named():
    sync = FrameSetSynchronizer(CAMS, tolerance_ns=2 * MS, timeout_ns=100 * MS)
    sets = feed(sync, [('cam0', None, 0, 0), ('cam1', None, 0, 0)])
    assert sets == []
    sets = sync.poll(50 * MS)
    assert sets == []
    sets = sync.poll(150 * MS)
    assert len(sets) == 1 and not sets[0].complete and sets[0].missing == [('cam2', None)]
    assert sync.stats.incomplete == 1


def test_late_camera_is_dropped_not_reopened():
    sync = FrameSetSynchronizer(CAMS, tolerance_ns=2 * MS, timeout_ns=100 * MS)
    feed(sync, [('cam0', None, 0, 0), ('cam1', None, 0, 0)])
    assert len(sync.poll(200 * MS)) == 1
    assert feed(sync, [('cam2', None, MS, 210 * MS)]) == []
    assert sync.stats.late == 1 and sync.pending == 0


def test_memory_is_bounded_when_a_camera_is_dead():
    sync = FrameSetSynchronizer(CAMS, tolerance_ns=2 * MS, timeout_ns=10**12, max_pending=3)
    out = []
    for k in range(50):
        out += feed(sync, [('cam0', None, k * 33 * MS, k), ('cam1', None, k * 33 * MS, k)])
        assert sync.pending <= 3
    assert len(out) == 47 and all(s.missing == [('cam2', None)] for s in out)
    assert [s.stamp_ns for s in sync.flush()] == [47 * 33 * MS, 48 * 33 * MS, 49 * 33 * MS]


def test_duplicates_and_unknown_cameras_are_counted():
    sync = FrameSetSynchronizer(CAMS, tolerance_ns=2 * MS)
    feed(sync, [('cam0', None, 0, 0), ('cam0', None, MS, 0), ('camX', None, 0, 0)])
    assert sync.stats.duplicate == 1 and sync.stats.unknown == 1


def test_sets_do_not_merge_frames_further_apart_than_tolerance():
    sync = FrameSetSynchronizer(['a', 'b'], tolerance_ns=2 * MS, timeout_ns=100 * MS)
    assert feed(sync, [('a', None, 0, 0), ('b', None, 5 * MS, 0)]) == []
    assert sync.pending == 2


def test_invalid_arguments():
    with pytest.raises(ValueError):
        FrameSetSynchronizer([])
    with pytest.raises(ValueError):
        FrameSetSynchronizer(['a'], max_pending=0)


@pytest.mark.parametrize('fps', [30, 15, 5])
@pytest.mark.parametrize('offset_ms', [0, 8, 15])
def test_automatic_tolerance_pairs_separately_stamped_colour_and_depth(fps, offset_ms):
    """Real drivers stamp colour and depth apart: 8 or 15 ms at 30 fps must still pair, and
    consecutive frames never do."""
    period = 1_000_000_000 // fps
    sync = FrameSetSynchronizer(CAMS, ('color', 'depth'), timeout_ns=10**12)
    sets = []
    for k in range(60):
        depth_stamp = 5 * 10**9 + k * period
        for cam in CAMS:
            sets += sync.add(cam, depth_stamp, ('d', k), stream='depth')
            sets += sync.add(cam, depth_stamp + offset_ms * MS, ('c', k), stream='color')
    sets += sync.flush()
    assert len(sets) == 60 and all(fs.complete for fs in sets)
    assert all(fs.get(cam, 'color')[1] == fs.get(cam, 'depth')[1] for fs in sets for cam in CAMS)
    assert sync.stats.late == 0
    assert sync.tolerance_ns == tolerance_for_period(period) and offset_ms * MS < sync.tolerance_ns < period / 2


def test_period_estimate_ignores_pauses_and_dropped_frames():
    est = PeriodEstimate()
    stamps = [k * 33_333_333 for k in range(40) if k % 7]            # every seventh frame dropped
    stamps += [stamps[-1] + 5 * 10**9 + k * 33_333_333 for k in range(5)]   # a 5 s pause
    for s in stamps:
        est.add('cam0', s)
    assert abs(est.period_ns - 33_333_333) <= 1
