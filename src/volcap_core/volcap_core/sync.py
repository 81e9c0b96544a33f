"""Multi-camera frame-set synchroniser.

Gathers one item per (camera, stream) whose capture stamps agree within a tolerance. A set is
emitted as soon as it is complete; a set still incomplete ``timeout_ns`` after its first item
arrived, or pushed out by ``max_pending`` newer sets, is emitted incomplete with the missing
(camera, stream) pairs named, so a slow or dead camera never stalls the rest. Memory is bounded:
at most ``max_pending`` open sets and a short history of emitted stamps (to recognise late
items, which are counted and dropped rather than opening a new set).

The stamp tolerance is either fixed or, by default, derived from the frame period the stamps
show: just under half a period, so that the vendor drivers' separately stamped colour and depth
(8-15 ms apart at 30 fps) still pair while consecutive frames never do.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any, Hashable, Sequence

import numpy as np

from .errors import BadInput

# Until the stamps show the frame period, assume the rig's 30 fps.
DEFAULT_PERIOD_NS = 33_333_333
# An automatic tolerance stays this far below half the period (stamp jitter of the next frame).
PERIOD_MARGIN_NS = 1_000_000


def tolerance_for_period(period_ns: int) -> int:
    """The automatic stamp tolerance for a frame period: just under half of it."""
    return max(PERIOD_MARGIN_NS, int(period_ns) // 2 - PERIOD_MARGIN_NS)


def tolerance_ns_from_ms(ms: float) -> int | None:
    """A ``sync_tolerance_ms`` setting as the synchroniser takes it (0: automatic)."""
    return int(ms * 1e6) if ms > 0 else None


class PeriodEstimate:
    """The frame period as the median stamp interval of each (camera, stream) over the last frames;
    intervals of a second or more (pauses, restarts) are ignored, dropped frames barely move it."""

    def __init__(self, window: int = 64):
        self._last: dict[Hashable, int] = {}
        self._intervals: deque[int] = deque(maxlen=window)
        self._median: int | None = None     # recomputed only after a new interval

    def add(self, key: Hashable, stamp_ns: int) -> None:
        last = self._last.get(key)
        self._last[key] = stamp_ns
        if last is not None and 0 < stamp_ns - last < 1_000_000_000:
            self._intervals.append(stamp_ns - last)
            self._median = None

    @property
    def period_ns(self) -> int | None:
        if self._median is None and self._intervals:
            self._median = int(np.median(self._intervals))
        return self._median


@dataclass
class FrameSet:
    stamp_ns: int
    items: dict[tuple[str, Hashable], Any]
    missing: list[tuple[str, Hashable]] = field(default_factory=list)

    @property
    def complete(self) -> bool:
        return not self.missing

    def get(self, camera: str, stream: Hashable = None):
        return self.items.get((camera, stream))


@dataclass
class SyncStats:
    complete: int = 0
    incomplete: int = 0
    late: int = 0
    duplicate: int = 0
    unknown: int = 0


@dataclass
class _Pending:
    stamp_ns: int
    first_arrival_ns: int
    items: dict = field(default_factory=dict)


class FrameSetSynchronizer:
    def __init__(self, cameras: Sequence[str], streams: Sequence[Hashable] = (None,),
                 tolerance_ns: int | None = None, timeout_ns: int = 200_000_000, max_pending: int = 4):
        """``tolerance_ns`` None: derived from the frame period the stamps show."""
        if not cameras:
            raise BadInput('synchroniser needs at least one camera')
        if (tolerance_ns is not None and tolerance_ns < 0) or timeout_ns <= 0 or max_pending < 1:
            raise BadInput('tolerance must be >= 0, timeout > 0 and max_pending >= 1')
        self.keys = [(c, s) for c in cameras for s in streams]
        self._known = set(self.keys)
        self.fixed_tolerance_ns = None if tolerance_ns is None else int(tolerance_ns)
        self.period = PeriodEstimate()
        self.timeout_ns = int(timeout_ns)
        self.max_pending = int(max_pending)
        self._pending: list[_Pending] = []
        self._emitted = deque(maxlen=4 * max_pending)
        self.stats = SyncStats()

    @property
    def tolerance_ns(self) -> int:
        if self.fixed_tolerance_ns is not None:
            return self.fixed_tolerance_ns
        return tolerance_for_period(self.period.period_ns or DEFAULT_PERIOD_NS)

    @property
    def pending(self) -> int:
        return len(self._pending)

    def add(self, camera: str, stamp_ns: int, item: Any, stream: Hashable = None,
            now_ns: int | None = None) -> list[FrameSet]:
        """Offer one item; returns the frame sets this completes or forces out (oldest first)."""
        key = (camera, stream)
        now_ns = stamp_ns if now_ns is None else now_ns
        if key not in self._known:
            self.stats.unknown += 1
            return []
        self.period.add(key, stamp_ns)
        tolerance = self.tolerance_ns
        if any(abs(stamp_ns - s) <= tolerance for s in self._emitted):
            self.stats.late += 1
            return []
        target = min((p for p in self._pending if abs(p.stamp_ns - stamp_ns) <= tolerance),
                     key=lambda p: abs(p.stamp_ns - stamp_ns), default=None)
        out: list[FrameSet] = []
        if target is None:
            target = _Pending(stamp_ns, now_ns)
            self._pending.append(target)
            self._pending.sort(key=lambda p: p.stamp_ns)
            while len(self._pending) > self.max_pending:
                out.append(self._emit(self._pending[0]))
        if key in target.items:
            self.stats.duplicate += 1
            return out
        target.items[key] = item
        if len(target.items) == len(self.keys):
            out.append(self._emit(target))
        return out + self.poll(now_ns)

    def poll(self, now_ns: int) -> list[FrameSet]:
        """Emit the sets whose first item arrived more than ``timeout_ns`` before ``now_ns``."""
        expired = [p for p in self._pending if now_ns - p.first_arrival_ns > self.timeout_ns]
        return [self._emit(p) for p in expired]

    def flush(self) -> list[FrameSet]:
        """Emit every open set now (end of stream)."""
        return [self._emit(p) for p in list(self._pending)]

    def _emit(self, pending: _Pending) -> FrameSet:
        self._pending.remove(pending)
        self._emitted.append(pending.stamp_ns)
        missing = [k for k in self.keys if k not in pending.items]
        if missing:
            self.stats.incomplete += 1
        else:
            self.stats.complete += 1
        return FrameSet(pending.stamp_ns, dict(pending.items), missing)
