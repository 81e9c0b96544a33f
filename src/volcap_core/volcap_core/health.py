"""Rig health from the frames' stamps alone: what a multi-camera operator checks first.

Per camera, over a sliding window: delivered rate, dropped frames (gaps in the stamps of more
than 1.5 frame periods), the colour-depth stamp offset, the camera's offset from the rest of
the rig (its depth stamp minus the median of every camera's nearest depth stamp, modulo the
frame period so that a frame the monitor lost is no offset) and how fast that offset changes
(drift, ms per second of capture: a camera whose sync cable or clock slips shows here long
before its frames stop pairing). Per rig: each frame set's stamp spread.
No ROS: ``volcap monitor`` feeds it from subscriptions, tests from plain numbers.
"""
from __future__ import annotations

from collections import deque
from dataclasses import asdict, dataclass, field

import numpy as np

from .errors import BadInput
from .sync import DEFAULT_PERIOD_NS, PeriodEstimate, tolerance_for_period

STREAMS = ('color', 'depth')


@dataclass
class CameraHealth:
    camera: str
    frames: int = 0                        # depth frames in the window
    rate_hz: float = 0.0
    dropped: int = 0                       # frames missing from the stamps since the start
    color_depth_offset_ms: float | None = None   # median colour stamp minus nearest depth stamp
    rig_offset_ms: float | None = None     # latest offset from the other cameras
    drift_ms_per_s: float | None = None    # slope of that offset over the window
    silent_s: float | None = None          # seconds since its last frame, once past the silence limit
    warnings: list[str] = field(default_factory=list)

    @property
    def level(self) -> str:
        return 'error' if self.silent_s is not None else 'warn' if self.warnings else 'ok'

    def to_dict(self) -> dict:
        return {**asdict(self), 'level': self.level}


@dataclass
class RigHealthReport:
    cameras: dict[str, CameraHealth]
    period_ms: float
    tolerance_ms: float
    spread_ms_median: float | None         # per frame set: latest minus earliest camera's depth stamp
    spread_ms_max: float | None

    @property
    def warnings(self) -> list[str]:
        return [f'{c}: {w}' for c, h in self.cameras.items() for w in h.warnings]

    def to_dict(self) -> dict:
        return {'period_ms': self.period_ms, 'tolerance_ms': self.tolerance_ms,
                'spread_ms_median': self.spread_ms_median, 'spread_ms_max': self.spread_ms_max,
                'cameras': {c: h.to_dict() for c, h in self.cameras.items()}}


class RigHealth:
    def __init__(self, cameras: list[str], window_s: float = 10.0, drift_warn_ms_per_s: float = 0.2,
                 min_rate_share: float = 0.9, silent_periods: float = 10.0):
        if not cameras:
            raise BadInput('the rig health monitor needs at least one camera')
        self.cameras = list(cameras)
        self.window_ns = int(window_s * 1e9)
        self.drift_warn = drift_warn_ms_per_s
        self.min_rate_share = min_rate_share
        self.silent_periods = silent_periods
        self.period = PeriodEstimate()
        self._stamps = {(c, s): deque() for c in self.cameras for s in STREAMS}   # (receive_ns, stamp_ns)
        self._last = {}
        self.dropped = dict.fromkeys(self.cameras, 0)

    def add(self, camera: str, stream: str, stamp_ns: int, receive_ns: int) -> None:
        key = (camera, stream)
        if key not in self._stamps:
            return
        self.period.add(key, stamp_ns)
        if stream == 'depth':
            last = self._last.get(camera)
            period = self.period.period_ns
            if last is not None and period and stamp_ns - last > 1.5 * period:
                self.dropped[camera] += int(round((stamp_ns - last) / period)) - 1
            self._last[camera] = stamp_ns
        q = self._stamps[key]
        q.append((receive_ns, stamp_ns))
        while q and q[-1][1] - q[0][1] > self.window_ns:
            q.popleft()

    def silent(self, now_ns: int) -> dict[str, float]:
        """Cameras with no frame (either stream) for ``silent_periods`` frame periods, and for how
        many seconds; ``now_ns`` on the clock ``add`` was given receive times on. A camera never
        heard from counts from the first frame of any camera."""
        last = {cam: max(self._stamps[(cam, s)][-1][0] for s in STREAMS if self._stamps[(cam, s)])
                for cam in self.cameras if any(self._stamps[(cam, s)] for s in STREAMS)}
        return silent_cameras(self.cameras, last, now_ns, self.period.period_ns, self.silent_periods)

    def report(self, now_ns: int | None = None) -> RigHealthReport:
        """``now_ns`` (receive clock): also name the cameras that have gone silent."""
        period = self.period.period_ns or DEFAULT_PERIOD_NS
        silent = self.silent(now_ns) if now_ns is not None else {}
        tolerance = tolerance_for_period(period)
        depth = {c: np.array([s for _, s in self._stamps[(c, 'depth')]], dtype=np.int64) for c in self.cameras}
        out = {}
        for cam in self.cameras:
            h = CameraHealth(cam, frames=len(depth[cam]), dropped=self.dropped[cam])
            received = np.array([r for r, _ in self._stamps[(cam, 'depth')]], dtype=np.int64)
            if len(received) > 1 and received[-1] > received[0]:
                h.rate_hz = (len(received) - 1) / ((received[-1] - received[0]) / 1e9)
            colors = np.array([s for _, s in self._stamps[(cam, 'color')]], dtype=np.int64)
            if len(colors) and len(depth[cam]):
                h.color_depth_offset_ms = float(np.median(colors - _nearest(depth[cam], colors))) / 1e6
            self._rig_offset(cam, depth, h, period)
            if cam in silent:
                h.silent_s = round(silent[cam], 2)
                h.warnings.append(f'silent for {silent[cam]:.1f} s: no frames (camera, driver or filter down?)')
            self._warn(h, period, tolerance)
            out[cam] = h
        spread = _spreads(depth, period)
        return RigHealthReport(out, period / 1e6, tolerance / 1e6,
                               float(np.median(spread)) / 1e6 if spread.size else None,
                               float(spread.max()) / 1e6 if spread.size else None)

    def _rig_offset(self, cam: str, depth: dict, h: CameraHealth, period: int) -> None:
        own = depth[cam]
        rig = [depth[c] for c in self.cameras if len(depth[c])]
        if len(rig) < 2 or len(own) < 2:
            return
        # A frame the monitor lost (or one from before it joined) makes the nearest stamp a whole
        # period off: each difference is taken modulo the period, so only the sub-period offset
        # counts, then the median over every camera (itself included), which one drifting camera
        # moves not at all. Unwrapped over time, a camera drifting past half a period stays a line.
        differences = np.stack([_nearest(d, own) for d in rig]) - own
        wrapped = (differences + period // 2) % period - period // 2
        offsets = np.unwrap(-np.median(wrapped, axis=0), period=period)
        h.rig_offset_ms = float(offsets[-1]) / 1e6
        t = (own - own[0]) / 1e9
        if t[-1] >= 2.0:   # a slope needs a few seconds of capture
            h.drift_ms_per_s = float(np.polyfit(t, offsets / 1e6, 1)[0])

    def _warn(self, h: CameraHealth, period: int, tolerance: int) -> None:
        if h.frames == 0:
            h.warnings.append('no depth frames')
            return
        expected = 1e9 / period
        if h.frames > 2 and h.rate_hz < self.min_rate_share * expected:
            h.warnings.append(f'{h.rate_hz:.1f} Hz delivered, the stamps say {expected:.1f} Hz')
        if h.dropped:
            h.warnings.append(f'{h.dropped} frames dropped')
        if h.color_depth_offset_ms is not None and abs(h.color_depth_offset_ms) * 1e6 > tolerance:
            h.warnings.append(f'colour {h.color_depth_offset_ms:+.1f} ms from depth: beyond the '
                              f'{tolerance / 1e6:.1f} ms pairing tolerance')
        if h.drift_ms_per_s is not None and abs(h.drift_ms_per_s) > self.drift_warn:
            h.warnings.append(f'drifting {h.drift_ms_per_s:+.2f} ms/s from the rig (check sync cable and '
                              'clock)')
        elif h.rig_offset_ms is not None and abs(h.rig_offset_ms) * 1e6 > tolerance:
            h.warnings.append(f'{h.rig_offset_ms:+.1f} ms from the rig: its frames no longer join the frame sets')


def silent_cameras(cameras: list[str], last_ns: dict[str, int], now_ns: int, period_ns: int | None,
                   periods: float = 10.0, min_s: float = 0.5) -> dict[str, float]:
    """{camera: seconds silent} for the cameras whose last frame (``last_ns``, receive clock) is
    more than ``periods`` frame periods (and ``min_s``) before ``now_ns``. A camera never heard
    from counts from the first frame of any camera; before any frame, none is silent."""
    if not last_ns:
        return {}
    limit = max(periods * (period_ns or DEFAULT_PERIOD_NS), min_s * 1e9)
    first = min(last_ns.values())
    out = {}
    for cam in cameras:
        quiet = now_ns - last_ns.get(cam, first)
        if quiet > limit:
            out[cam] = quiet / 1e9
    return out


class SilenceWatch:
    """Cameras that went silent while frames were expected, counted in frames, not seconds: a
    camera is silent once the busiest camera has delivered ``frames`` frames since its last one
    (and ``min_s`` has passed). So the rule holds at any rate, a bag replayed at a twentieth of
    real time as much as a live rig; when every camera is quiet together (a phase without output,
    the end of a take) nobody is silent: the stage is idle (``idle_s``)."""

    def __init__(self, frames: float = 10.0, min_s: float = 0.5):
        self.frames = frames
        self.min_s = min_s
        self.count = 0                       # frames of the busiest camera
        self._counts: dict[str, int] = {}
        self._mark: dict[str, int] = {}      # camera -> the busiest camera's count at its last frame
        self._last_ns: dict[str, int] = {}

    def arrived(self, camera: str, now_ns: int) -> None:
        """One frame of ``camera`` (count one stream per frame set)."""
        n = self._counts[camera] = self._counts.get(camera, 0) + 1
        self.count = max(self.count, n)
        self._mark[camera] = self.count
        self._last_ns[camera] = now_ns

    def silent(self, cameras: list[str], now_ns: int) -> dict[str, float]:
        """{camera: seconds since its last frame} for the silent ones (never heard from: since the
        first frame of any camera)."""
        if not self._last_ns:
            return {}
        first = min(self._last_ns.values())
        out = {}
        for cam in cameras:
            quiet_ns = now_ns - self._last_ns.get(cam, first)
            if self.count - self._mark.get(cam, 0) >= self.frames and quiet_ns > self.min_s * 1e9:
                out[cam] = quiet_ns / 1e9
        return out

    def idle_s(self, now_ns: int) -> float:
        """Seconds since any camera delivered (0 before the first frame)."""
        return (now_ns - max(self._last_ns.values())) / 1e9 if self._last_ns else 0.0


def _nearest(sorted_stamps: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """For each query, the nearest of ``sorted_stamps`` (non-empty, ascending)."""
    if len(sorted_stamps) == 1:
        return np.full(len(queries), sorted_stamps[0])
    i = np.clip(np.searchsorted(sorted_stamps, queries), 1, len(sorted_stamps) - 1)
    before, after = sorted_stamps[i - 1], sorted_stamps[i]
    return np.where(np.abs(queries - before) <= np.abs(after - queries), before, after)


def _spreads(depth: dict[str, np.ndarray], period: int) -> np.ndarray:
    """Per depth frame of the first camera with frames: the spread of every camera's nearest stamp
    (each taken modulo the period, as in ``_rig_offset``: a lost frame is no spread)."""
    present = [d for d in depth.values() if len(d)]
    if len(present) < 2:
        return np.zeros(0, np.int64)
    reference = present[0]
    differences = np.stack([_nearest(d, reference) for d in present]) - reference
    wrapped = (differences + period // 2) % period - period // 2
    return wrapped.max(axis=0) - wrapped.min(axis=0)
