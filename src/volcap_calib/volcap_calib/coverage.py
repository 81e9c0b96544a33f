"""How well the board views gathered so far tie the rig together, and what to show next.

The joint solve places every camera through the board views it shares with others. A camera
linked to the reference by one chain of shared views (a bridge in the camera graph) inherits
every link's error along the chain; one that closes a loop (two independent paths, as the ring's
far stands do when the board is shown between every pair of neighbouring stands) is held from
both sides. ``rig_coverage`` reads that from the observations alone (no solve), cheaply enough
for the calibration service to report it every second while the board moves.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from itertools import combinations

import numpy as np

from .extrinsics import Observation, chain_poses


@dataclass
class CameraCoverage:
    views: int                     # board views of this camera
    hops: int | None               # shortest chain of shared views to the reference (None: unlinked)
    paths: int                     # edge-independent chains to the reference (1: no loop closes on it)
    partners: dict[str, int]       # camera -> board views shared with it

    def to_dict(self) -> dict:
        return {'views': self.views, 'hops': self.hops, 'paths': self.paths, 'partners': dict(self.partners)}


@dataclass
class Coverage:
    reference: str
    cameras: dict[str, CameraCoverage]
    weak: dict[str, str] = field(default_factory=dict)       # camera -> why
    advice: list[str] = field(default_factory=list)

    @property
    def linked(self) -> list[str]:
        return [c for c, v in self.cameras.items() if v.hops is not None]

    @property
    def unlinked(self) -> list[str]:
        return [c for c, v in self.cameras.items() if v.hops is None]

    def summary(self) -> str:
        text = f'{len(self.linked)}/{len(self.cameras)} cameras linked to {self.reference}'
        if self.weak:
            text += '; weak: ' + ', '.join(f'{c} ({why})' for c, why in self.weak.items())
        return text + ('; ' + ' '.join(self.advice) if self.advice else '; coverage complete')

    def to_dict(self) -> dict:
        return {'reference': self.reference, 'linked': self.linked, 'unlinked': self.unlinked,
                'weak': dict(self.weak), 'advice': list(self.advice),
                'cameras': {c: v.to_dict() for c, v in self.cameras.items()}}


def rig_coverage(observations: list[Observation], cameras: list[str], reference: str,
                 min_shared_views: int = 2) -> Coverage:
    """Links (shared board views) between cameras, each camera's chain to the reference, the
    cameras whose placement rests on too little, and where to hold the board next.

    A camera is weak when it is unlinked, when fewer than ``min_shared_views`` of its views are
    shared with linked cameras, or when a single chain of two or more links carries it (no loop
    closes on it). ``advice_for`` says what to show next."""
    views_of: dict[str, set[int]] = {c: set() for c in cameras}
    for o in observations:
        if o.camera in views_of:
            views_of[o.camera].add(o.view)
    shared = {(a, b): len(views_of[a] & views_of[b]) for a, b in combinations(cameras, 2)}
    partners = {c: {} for c in cameras}
    for (a, b), n in shared.items():
        if n:
            partners[a][b] = n
            partners[b][a] = n
    hops = _hops(partners, reference)
    report = {c: CameraCoverage(len(views_of[c]), hops.get(c),
                                _edge_disjoint_paths(partners, c, reference) if c in hops and c != reference else 0,
                                dict(sorted(partners[c].items(), key=lambda kv: -kv[1])))
              for c in cameras}
    weak: dict[str, str] = {}
    for c, cov in report.items():
        if c == reference:
            continue
        if cov.hops is None:
            weak[c] = ('never saw the board' if not cov.views else
                       f'{cov.views} views, none shared with a camera linked to {reference}')
            continue
        support = sum(n for p, n in cov.partners.items() if p in hops)
        if support < min_shared_views:
            weak[c] = f'{support} view{"s" * (support != 1)} shared with the linked cameras'
        elif cov.paths < 2 and cov.hops >= 2:
            weak[c] = f'hangs on a single chain of {cov.hops} links (no loop closes on it)'
    coverage = Coverage(reference, report, weak)
    coverage.advice = advice_for(observations, coverage)
    return coverage


def _hops(partners: dict[str, dict[str, int]], reference: str) -> dict[str, int]:
    hops, queue = {reference: 0}, deque([reference])
    while queue:
        c = queue.popleft()
        for p in partners[c]:
            if p not in hops:
                hops[p] = hops[c] + 1
                queue.append(p)
    return hops


def _edge_disjoint_paths(partners: dict[str, dict[str, int]], source: str, sink: str, cap: int = 2) -> int:
    """Edge-independent paths between two cameras (up to ``cap``), by augmenting paths on the
    unit-capacity camera graph."""
    flow: dict[tuple[str, str], int] = {}
    paths = 0
    while paths < cap:
        parent, queue = {source: None}, deque([source])
        while queue and sink not in parent:
            c = queue.popleft()
            for p in partners[c]:
                if p not in parent and flow.get((c, p), 0) < 1:
                    parent[p] = c
                    queue.append(p)
        if sink not in parent:
            break
        node = sink
        while parent[node] is not None:
            prev = parent[node]
            flow[(prev, node)] = flow.get((prev, node), 0) + 1
            flow[(node, prev)] = flow.get((node, prev), 0) - 1
            node = prev
        paths += 1
    return paths


MAX_PAIR_ANGLE_DEG = 130.0   # the board at most 65 deg from each camera's axis (charts are sampled to 70)


def advice_for(observations: list[Observation], coverage: Coverage) -> list[str]:
    """Where to hold the board next, one sentence per weak camera: a linked one is paired with
    the nearest well-placed camera it shares no views with yet (closing a loop), by the chained
    first guess of the poses, among the cameras that can see one board with it (axes within
    ``MAX_PAIR_ANGLE_DEG``); an unlinked one, having no pose yet, with any linked camera."""
    report, weak, reference = coverage.cameras, coverage.weak, coverage.reference
    if not weak:
        return []
    positions = {}
    cameras = list(report)
    linked = [c for c in cameras if report[c].hops is not None]
    if len(linked) > 1:
        T_cam, _, _ = chain_poses([o for o in observations if o.camera in linked], linked, reference)
        positions = {c: T[:3, 3] for c, T in T_cam.items()}
    axes = {c: T[:3, 2] for c, T in T_cam.items()} if positions else {}
    strong = [c for c in linked if c not in weak]

    def can_share(a: str, b: str) -> bool:
        # one board seen by both: their optical axes within MAX_PAIR_ANGLE_DEG (facing cameras
        # across a ring cannot both see the board's face)
        return a in axes and b in axes and float(axes[a] @ axes[b]) >= np.cos(np.radians(MAX_PAIR_ANGLE_DEG))

    out = []
    for c in weak:
        if c not in positions:
            # No pose relative to the linked cameras yet: any linked neighbour will do.
            out.append(f'show the board to {c} together with a linked camera ({", ".join(linked)}).'
                       if report[c].views else f'show the board to {c} together with any linked camera.')
            continue
        # Pair it with a camera that can see the board with it: a well-placed one it does not
        # share views with yet (that closes a loop), else its nearest well-placed one; when none
        # of those can (every other camera weak, the reference across the ring), a linked one it
        # shares no views with, so the views added tie the ring together.
        near = [p for p in linked if p != c and can_share(c, p)]
        others = ([p for p in near if p in strong and p not in report[c].partners] or
                  [p for p in near if p in strong] or [p for p in near if p not in report[c].partners] or near)
        # Among them the fewest links from the reference first (a shared view shortens c's
        # chain), then the nearest.
        partner = (min(others, key=lambda p: (report[p].hops, np.linalg.norm(positions[p] - positions[c])))
                   if others else reference)
        out.append(f'hold the board between {c} and {partner} (both must see it).')
    return out

