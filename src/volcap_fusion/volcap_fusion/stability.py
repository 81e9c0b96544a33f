"""How much a fused sequence changes from one time step to the next: what a viewer sees as
shimmer on a subject that holds still.

Each fused frame is made from scratch, so the sensor's noise, the marching-cubes edge of the
weight threshold and the cameras' colour noise all show as motion. Between two consecutive
models A and B, points are spread uniformly by area over each surface (with their vertex colours
interpolated at the point) and matched to the closest point of the other surface:

- surface jitter: RMS distance (mm) of the matched points, both directions;
- colour flicker: mean CIEDE2000 between a point's colour and the other model's colour at the
  closest point (interpolated the same way);
- appeared / vanished: the share of B's surface farther than ``within_mm`` from A, and of A's
  from B (holes that open and close, fragments that come and go).

Where the subject's true motion between the two frames is known (`volcap eval stability` with a
synthetic bag: the subject is posed rigidly per frame), it is taken out before matching, so a
turning subject is scored for its shimmer alone. Without it every change counts: a subject that
holds still (``volcap synth --motion none``, the still frames of a real take) scores its shimmer,
a moving one its motion too. No ground truth is needed: `volcap run` reports the figures for
every sequence it writes.
"""
from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass

import numpy as np
import open3d as o3d

from volcap_core.color import delta_e2000

from .tsdf import FusedModel

WITHIN_MM = 5.0           # farther than this from the other frame's surface: appeared or vanished
SAMPLES = 50_000          # points per model and pair; 0.1 s a pair on one core


@dataclass
class FrameChange:
    jitter_rms_mm: float | None      # None where the two models share no surface
    flicker_de: float | None
    appeared: float                  # of B's (scored) surface
    vanished: float                  # of A's (scored) surface
    matched: int                     # scored points within ``within_mm``, both directions


def surface_points(model: FusedModel, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points spread uniformly by area over the model and their colours (sRGB in
    [0, 1], the vertex colours interpolated at the point)."""
    v = model.vertices.astype(np.float64)
    t = model.triangles
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    area = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    rng = np.random.default_rng(seed)
    faces = rng.choice(len(t), count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    points = np.einsum('nk,nkd->nd', w, v[t[faces]])
    colors = np.einsum('nk,nkd->nd', w, model.colors[t[faces]].astype(np.float64) / 255.0)
    return points, colors


class SurfaceLookup:
    """Closest points of a model's surface, with its interpolated colour there."""

    def __init__(self, model: FusedModel):
        self.model = model
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(model.vertices, np.float32)),
                                 o3d.core.Tensor(np.ascontiguousarray(model.triangles, np.uint32)))

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(distance in metres, colour in [0, 1]) at the closest surface point of each point."""
        r = self.scene.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))
        closest = r['points'].numpy().astype(np.float64)
        prim = r['primitive_ids'].numpy().astype(np.int64)
        uv = r['primitive_uvs'].numpy().astype(np.float64)
        # Open3D's barycentrics: point = (1 - u - v) p0 + u p1 + v p2
        w = np.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        colors = np.einsum('nk,nkd->nd', w, self.model.colors[self.model.triangles[prim]].astype(np.float64) / 255.0)
        return np.linalg.norm(closest - points, axis=1), colors


@dataclass
class Matches:
    """The points of two consecutive models matched to the other's surface, both directions
    (B's points, then A's): where each lies on its own model, how far it is from the other
    surface (m) and the two colours there; ``shares``: B's and A's surface farther than
    ``within_mm`` (appeared, vanished)."""
    points: np.ndarray
    distances: np.ndarray
    own: np.ndarray
    other: np.ndarray
    shares: tuple[float, float]


def matched_points(a: FusedModel, b: FusedModel, within_mm: float = WITHIN_MM, samples: int = SAMPLES,
                   motion: np.ndarray | None = None, seed: int = 0,
                   lookups: tuple[SurfaceLookup, SurfaceLookup] | None = None) -> Matches:
    """Points spread over B and over A, each matched to the other surface after the subject's
    true ``motion`` (4x4, A to B; distances are kept by rigid motions); the matches within
    ``within_mm``. Both models must have triangles."""
    look_a, look_b = lookups or (SurfaceLookup(a), SurfaceLookup(b))
    forward = np.eye(4) if motion is None else np.asarray(motion, np.float64)
    backward = np.linalg.inv(forward)
    points, distances, own, other, shares = [], [], [], [], []
    for model, lookup, T, s in ((b, look_a, backward, seed), (a, look_b, forward, seed + 1)):
        p, colors = surface_points(model, samples, s)
        d, c = lookup.closest(p @ T[:3, :3].T + T[:3, 3])
        near = d <= within_mm / 1000
        shares.append(float(1.0 - near.mean()))
        points.append(p[near])
        distances.append(d[near])
        own.append(colors[near])
        other.append(c[near])
    return Matches(*(np.concatenate(x) for x in (points, distances, own, other)), (shares[0], shares[1]))


def frame_change(a: FusedModel, b: FusedModel, within_mm: float = WITHIN_MM, samples: int = SAMPLES,
                 motion: np.ndarray | None = None, seed: int = 0,
                 lookups: tuple[SurfaceLookup, SurfaceLookup] | None = None) -> FrameChange:
    """The change from model ``a`` to the next one ``b`` (both in one frame). ``motion`` (4x4)
    is how the subject truly moved from ``a`` to ``b`` (a rigid synthetic subject's pose change):
    the change is scored after it, so only shimmer is left."""
    if len(a.triangles) == 0 or len(b.triangles) == 0:
        empty_a, empty_b = len(a.triangles) == 0, len(b.triangles) == 0
        return FrameChange(None, None, 0.0 if empty_b else 1.0, 0.0 if empty_a else 1.0, 0)
    m = matched_points(a, b, within_mm, samples, motion, seed, lookups)
    if not len(m.distances):
        return FrameChange(None, None, *m.shares, 0)
    flicker = delta_e2000(m.own, m.other)
    return FrameChange(float(np.sqrt(np.mean(m.distances ** 2)) * 1000), float(np.mean(flicker)), *m.shares,
                       len(m.distances))


def sequence_stability(models: Iterable[FusedModel], within_mm: float = WITHIN_MM, samples: int = SAMPLES,
                       motion: Callable[[int], np.ndarray] | None = None) -> dict:
    """Frame-to-frame change over a sequence of models: per pair (``motion(k)``: the subject's true
    motion from model k to k + 1, if known) and the means over the pairs."""
    pairs, previous, look_prev = [], None, None
    for k, model in enumerate(models):
        look = SurfaceLookup(model) if len(model.triangles) else None
        if previous is not None:
            change = frame_change(previous, model, within_mm, samples, None if motion is None else motion(k - 1),
                                  seed=k, lookups=(look_prev, look) if look_prev and look else None)
            pairs.append(asdict(change))
        previous, look_prev = model, look
    return {**summarise(pairs), 'within_mm': within_mm, 'pairs': pairs}


def summarise(pairs: list[dict]) -> dict:
    """Means over frame pairs: surface jitter (RMS over the pairs' RMS), colour flicker, and the
    surface appearing or vanishing per frame (the mean of the two shares)."""
    jitter = [p['jitter_rms_mm'] for p in pairs if p['jitter_rms_mm'] is not None]
    flicker = [p['flicker_de'] for p in pairs if p['flicker_de'] is not None]
    return {'frame_pairs': len(pairs),
            'jitter_rms_mm': float(np.sqrt(np.mean(np.square(jitter)))) if jitter else None,
            'flicker_de': float(np.mean(flicker)) if flicker else None,
            'appear_vanish': float(np.mean([0.5 * (p['appeared'] + p['vanished']) for p in pairs])) if pairs else None}


def format_stability(report: dict) -> str:
    """One line for a report."""
    if not report.get('frame_pairs'):
        return 'stability: fewer than two fused frames'
    jitter, flicker = report['jitter_rms_mm'], report['flicker_de']
    return (f'stability over {report["frame_pairs"]} frame pairs: surface jitter '
            f'{"-" if jitter is None else f"{jitter:.2f}"} mm RMS, colour flicker '
            f'{"-" if flicker is None else f"{flicker:.2f}"} CIEDE2000, '
            f'{100 * report["appear_vanish"]:.2f} % of the surface appearing or vanishing per frame')
