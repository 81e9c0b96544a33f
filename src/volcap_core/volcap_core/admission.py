"""Admission: which capture frame sets a live graph processes, decided once for the whole rig.

When the graph cannot process every frame set, each stage (every camera's depth filter and
colour corrector, the fusion) must drop the *same* sets, so that what survives is complete and a
camera's colour and depth are never split. Every stage applies one ``AdmissionRule`` to the
capture stamp of each frame: the stamps are put on a grid of frame periods (``origin_ns``, a
frame set's centre, and ``period_ns``) and one slot in ``every`` is admitted. Colour and depth of
a frame set sit within half a period of their slot (vendor drivers stamp them 8-15 ms apart at
30 fps), so every stage puts them in the same slot.

The rule is published latched on ``/volcap/admission`` by the live controller. A new rule
applies from ``since_ns``, a capture stamp a little ahead of the newest one the controller has
seen and half-way between two slots, so that stages which receive it a moment apart still switch
at the same frame set. ``AdmissionController`` chooses ``every`` from the graph's measured load
(additive decrease, multiplicative increase on drops, incomplete sets or latency over budget) and keeps
the grid on the stamps (re-anchored when the cameras' clock drifts from it).
"""
from __future__ import annotations

import json
import math
from collections import deque
from dataclasses import asdict, dataclass
from typing import Hashable

import numpy as np

from .errors import BadInput
from .sync import DEFAULT_PERIOD_NS, PeriodEstimate

# Stamp gaps longer than this are a pause (a restarted driver, a looped bag), not missed frames.
PAUSE_NS = 1_000_000_000


@dataclass(frozen=True)
class AdmissionRule:
    """Admit the capture stamps whose slot on the grid is a multiple of ``every``."""
    every: int = 1
    origin_ns: int = 0
    period_ns: int = DEFAULT_PERIOD_NS
    since_ns: int = 0

    def __post_init__(self):
        if self.every < 1 or self.period_ns <= 0:
            raise BadInput(f'admission needs every >= 1 and a positive period, got every={self.every} '
                             f'period_ns={self.period_ns}')

    def slot(self, stamp_ns: int) -> int:
        """The frame set's index on the grid (nearest slot)."""
        return (int(stamp_ns) - self.origin_ns + self.period_ns // 2) // self.period_ns

    def admits(self, stamp_ns: int) -> bool:
        return self.every == 1 or self.slot(stamp_ns) % self.every == 0

    def to_text(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)

    @classmethod
    def from_text(cls, text: str) -> 'AdmissionRule':
        """The rule a ``/volcap/admission`` message carries (ValueError when it is not one)."""
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as e:
            raise BadInput(f'admission rule is not JSON: {e}') from None
        if not isinstance(doc, dict) or set(doc) != {'every', 'origin_ns', 'period_ns', 'since_ns'}:
            raise BadInput(f'admission rule needs exactly every, origin_ns, period_ns, since_ns; got {text[:200]!r}')
        if not all(isinstance(v, int) and not isinstance(v, bool) for v in doc.values()):
            raise BadInput(f'admission rule fields must be integers; got {text[:200]!r}')
        return cls(**doc)


class Admission:
    """One stage's view of the admission rules: which frames it processes, and what it counts.

    ``admit(stream, stamp)`` applies the rule in force at that capture stamp and counts frames
    not admitted and admitted frames that never arrived (``missed``: a gap of admitted slots in
    one stream, e.g. frames a full keep-last queue overwrote or a camera dropped)."""

    def __init__(self, keep: int = 8):
        self.rules: list[AdmissionRule] = [AdmissionRule()]   # sorted by since_ns
        self.keep = keep
        self.admitted = self.not_admitted = self.missed = 0
        self._last: dict[Hashable, tuple[AdmissionRule, int, int]] = {}   # stream -> (rule, slot, stamp)

    def update(self, rule: AdmissionRule) -> None:
        """Add a rule (from ``rule.since_ns`` on); a rule for the same start replaces the old one."""
        rules = [r for r in self.rules if r.since_ns != rule.since_ns] + [rule]
        self.rules = sorted(rules, key=lambda r: r.since_ns)[-self.keep:]

    @property
    def current(self) -> AdmissionRule:
        return self.rules[-1]

    def rule_at(self, stamp_ns: int) -> AdmissionRule:
        for rule in reversed(self.rules):
            if rule.since_ns <= stamp_ns:
                return rule
        return self.rules[0]

    def admit(self, stream: Hashable, stamp_ns: int) -> bool:
        rule = self.rule_at(stamp_ns)
        if not rule.admits(stamp_ns):
            self.not_admitted += 1
            return False
        self.admitted += 1
        slot = rule.slot(stamp_ns)
        last = self._last.get(stream)
        # Up to a second of frames, or two admitted sets, apart: a longer gap is a pause.
        horizon = max(PAUSE_NS, 2 * rule.every * rule.period_ns)
        if last is not None and last[0] == rule and slot > last[1] and stamp_ns - last[2] < horizon:
            self.missed += (slot - last[1]) // rule.every - 1
        if last is None or slot > last[1] or last[0] != rule:
            self._last[stream] = (rule, slot, stamp_ns)
        return True

    def counts(self) -> dict[str, int]:
        return {'admitted': self.admitted, 'not_admitted': self.not_admitted, 'missed': self.missed,
                'admit_every': self.current.every}


class RigClock:
    """The rig's frame period and frame-set phase from the cameras' capture stamps.

    The period is measured over the longest unbroken run of one stream (its stamps counted in
    whole periods, so jitter averages out over the run); the phase is the circular mean of the
    recent stamps of every stream modulo the period: the centre of the frame sets, wherever the
    drivers put colour and depth."""

    def __init__(self, window: int = 256):
        self.rough = PeriodEstimate()
        self._runs: dict[Hashable, list[int]] = {}      # stream -> [first stamp, last stamp, periods]
        self._recent: deque[int] = deque(maxlen=window)

    def add(self, stream: Hashable, stamp_ns: int) -> None:
        stamp_ns = int(stamp_ns)
        self.rough.add(stream, stamp_ns)
        self._recent.append(stamp_ns)
        rough, run = self.rough.period_ns, self._runs.get(stream)
        if run is None or rough is None:
            self._runs[stream] = [stamp_ns, stamp_ns, 0]
            return
        gap = stamp_ns - run[1]
        if gap <= 0:
            return
        periods = round(gap / rough)
        if periods < 1 or gap > PAUSE_NS or abs(gap - periods * rough) > rough // 4:
            self._runs[stream] = [stamp_ns, stamp_ns, 0]     # a pause or a restart: a new run
        else:
            run[1], run[2] = stamp_ns, run[2] + periods

    @property
    def period_ns(self) -> int | None:
        longest = max(self._runs.values(), key=lambda r: r[2], default=None)
        if longest is None or longest[2] < 8:
            return self.rough.period_ns
        return round((longest[1] - longest[0]) / longest[2])

    @property
    def newest_ns(self) -> int | None:
        return max(self._recent) if self._recent else None

    def centre_ns(self, period_ns: int) -> int:
        """A stamp at the centre of a frame set (the one nearest the newest stamp)."""
        stamps = np.array(self._recent, dtype=np.int64)
        angles = 2 * np.pi * (stamps % period_ns) / period_ns
        phase = int(round(np.arctan2(np.sin(angles).mean(), np.cos(angles).mean()) / (2 * np.pi) * period_ns))
        newest = int(stamps.max())
        return newest - (newest - phase) % period_ns


class AdmissionController:
    """Chooses the rig's admission rule from the stamps the cameras send and the graph's load.

    ``observe(stream, stamp)`` with every camera stream's capture stamps (camera_info is enough)
    keeps the grid on the frame sets (``RigClock``); ``step(now_s, trouble, cpu_busy)`` once per
    control period returns a new rule when the decimation or the grid should change: ``trouble``
    (a stage dropped admitted frames, a frame set was fused incomplete, latency over budget)
    multiplies ``every`` by 1.5 (at most once per ``hold_s``); after ``calm_s`` without trouble,
    ``every`` falls by a third, or else by one, as far as the measured CPU use, scaled to the
    higher rate, stays under ``headroom``."""

    def __init__(self, min_every: int = 1, max_every: int = 60, hold_s: float = 2.0, calm_s: float = 4.0,
                 headroom: float = 0.85, lead_ns: int = 300_000_000):
        if not 1 <= min_every <= max_every:
            raise BadInput(f'need 1 <= min_every <= max_every, got {min_every}, {max_every}')
        self.min_every, self.max_every = min_every, max_every
        self.hold_s, self.calm_s, self.headroom, self.lead_ns = hold_s, calm_s, headroom, lead_ns
        self.clock = RigClock()
        self.rule = AdmissionRule(every=min_every)
        self._anchored = False
        self._changed_s = -math.inf
        self._calm_since_s: float | None = None

    def observe(self, stream: Hashable, stamp_ns: int) -> None:
        self.clock.add(stream, stamp_ns)

    def _next_every(self, now_s: float, trouble: bool, cpu_busy: float | None) -> int:
        every = self.rule.every
        if trouble:
            self._calm_since_s = None
            if now_s - self._changed_s >= self.hold_s:
                return min(self.max_every, max(every + 1, math.ceil(every * 1.5)))
            return every
        if self._calm_since_s is None:
            self._calm_since_s = now_s
        calm = now_s - max(self._calm_since_s, self._changed_s) >= self.calm_s
        if calm and every > self.min_every:
            # a third fewer while the CPU would have room even so (a start-up's trouble can leave
            # 1/11 on a host that does 1/2: one step per calm period took half a minute back)
            for lower in (max(self.min_every, every * 2 // 3), every - 1):
                if lower < every and (cpu_busy is None or cpu_busy * every / lower < self.headroom):
                    return lower
        return every

    def step(self, now_s: float, trouble: bool, cpu_busy: float | None = None) -> AdmissionRule | None:
        """The new rule when ``every`` or the grid should change, else None."""
        every = self._next_every(now_s, trouble, cpu_busy)
        period = self.clock.period_ns
        if period is None:
            return None
        centre = self.clock.centre_ns(period)
        old = self.rule
        offset = (centre - old.origin_ns + period // 2) % period - period // 2
        drifted = abs(offset) > period // 8 or abs(period - old.period_ns) * 30 > period // 8
        if every == old.every and self._anchored and not drifted:
            return None
        if every != old.every:
            self._changed_s = now_s
        # The switch is half-way between two frame sets, a little ahead of the newest stamp, so
        # no set straddles it; the new slot numbering starts with the set after it.
        target = self.clock.newest_ns + self.lead_ns
        since = centre + ((target - centre) // period) * period + period // 2
        origin = since + period - period // 2       # a new decimation starts with the set after the switch
        if every == old.every and self._anchored:
            # Re-anchored only: the next set the old rule admits keeps its turn, so no set is
            # admitted sooner than ``every`` periods after the last.
            turn = -(-old.slot(since) // every) * every
            nearest = old.origin_ns + turn * old.period_ns
            origin = centre + round((nearest - centre) / period) * period
            if origin <= since:
                origin += every * period
        self.rule = AdmissionRule(every=every, origin_ns=origin, period_ns=period, since_ns=since)
        self._anchored = True
        return self.rule
