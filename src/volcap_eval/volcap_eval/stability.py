"""`volcap eval stability RUN [BAG]`: how much the fused model changes from one frame to the next
beyond what the subject does (``volcap_fusion.stability`` measures; this module adds the truth).

With a synthetic bag the ground truth knows the subject's motion: it is posed rigidly per frame,
so between frames k and k + 1 it moves by ``T_world_subject[k+1] T_world_subject[k]^-1``, which
is taken out before the two fused models are compared; what is left is shimmer. A ``volcap
synth --motion none`` studio holds still, so nothing is taken out. Without a bag every change is
scored: pick the frames of a real take where the subject holds still (``first``, ``frames``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from volcap_core.errors import BadInput
from volcap_core.poses import invert, matrix_from_list, transform_points
from volcap_fusion.sequence import T_world_frame, read_ply, read_sequence
from volcap_fusion.stability import SAMPLES, WITHIN_MM, sequence_stability


def subject_poses(bag: str | Path, entries: list[dict]) -> list[np.ndarray]:
    """T_world_subject at each fused frame, from the synthetic bag's ground truth."""
    from volcap_studio.session import GroundTruth
    gt = GroundTruth(bag)
    truth = {f['stamp_ns']: f for f in gt.frames if 'T_world_subject' in f}
    stamps = np.array(sorted(truth), dtype=np.int64)
    if not len(stamps):
        raise BadInput(f'{bag}: the ground truth has no subject frames')
    poses = []
    for e in entries:
        nearest = int(stamps[np.argmin(np.abs(stamps - e['stamp_ns']))])
        if abs(nearest - e['stamp_ns']) > 20_000_000:
            raise BadInput(f'fused frame {e["index"]} (stamp {e["stamp_ns"]}) has no ground-truth frame')
        poses.append(matrix_from_list(truth[nearest]['T_world_subject']))
    return poses


def evaluate_stability(run_dir: str | Path, bag: str | Path | None = None, first: int = 0, frames: int | None = None,
                       samples: int = SAMPLES, progress: bool = True) -> dict:
    frames_dir = Path(run_dir) / 'frames'
    headers, entries = read_sequence(frames_dir)
    entries = entries[first:None if frames is None else first + frames]
    if len(entries) < 2:
        raise BadInput(f'{frames_dir}: {len(entries)} fused frame(s) from frame {first}; stability needs two or more')
    poses = subject_poses(bag, entries) if bag is not None else None

    def models():
        for e in tqdm(entries, desc='fused frames', unit='frame', disable=not progress):
            model = read_ply(frames_dir / e['ply'])
            model.vertices = transform_points(T_world_frame(headers, e['index']), model.vertices).astype(np.float32)
            yield model

    motion = (lambda k: poses[k + 1] @ invert(poses[k])) if poses is not None else None
    report = sequence_stability(models(), WITHIN_MM, samples, motion)
    for pair, a, b in zip(report['pairs'], entries, entries[1:]):
        pair.update(index=a['index'], next_index=b['index'])
    report.update(first=first, scored='after the subject\'s true motion (ground truth)' if bag is not None
                  else 'every change (no ground truth: the subject should hold still)')
    return report
