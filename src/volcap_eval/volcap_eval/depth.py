"""`volcap eval depth`: depth cleaning scored against a synthetic bag's ground truth.

Methods: ``raw`` (nothing removed), ``paper_horizontal`` and ``paper_all`` (paper 000: the
colour mask and range gate, then Eq. 5 with horizontal or all neighbours) and ``volcap`` (our
flying-pixel filter, the same mask with its depth-aware boundary band). Scored on the raw depth
grid, where the ground truth lives, over capture frames; the clean plate is learnt from the
bag's clean-plate frames:

- ``flying_recall``: GT flying pixels near the subject (within 3 px) that do not reach the output;
- ``flying_precision``: of the pixels the flying-pixel filter removes near the subject, the share
  that are GT flying pixels (null when it removes none);
- ``valid_kept``: valid subject surface pixels (no flying, no speckle) that reach the output;
- ``mask_iou``: foreground mask against the GT subject at colour resolution (raw: every pixel
  with registered depth);
- ``depth_mae_mm``: mean |depth - GT surface| of output pixels near the subject;
- ``filled_per_frame``, ``filled_mae_mm``: raw holes amid sparse returns (dark material) given
  depth by the cleaner, per camera frame, and that depth's mean error where it reaches the
  output near the subject.

``filter_only`` scores the flying-pixel filter alone over the whole image (no mask, no gate).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from volcap_core.errors import BadInput
from volcap_core.figures import write_png
from volcap_core.files import write_json
from volcap_filter.figures import depth_panels, mask_panels
from volcap_filter.pipeline import DepthCleaner, DepthFilterConfig
from volcap_pipeline.replay import cleaned_frame_sets
from volcap_studio.session import GroundTruth

METHODS = ('raw', 'paper_horizontal', 'paper_all', 'volcap')
NEAR_SUBJECT_PX = 3


def method_config(method: str) -> DepthFilterConfig:
    if method == 'raw':
        return DepthFilterConfig(flying_method='none', mask_mode='none', range_gate=False, boundary_px=0)
    if method in ('paper_horizontal', 'paper_all'):
        return DepthFilterConfig(flying_method=method, boundary_px=0)
    if method == 'volcap':
        return DepthFilterConfig()
    raise BadInput(f'unknown method {method!r}; choose from {METHODS}')


@dataclass
class _Tally:
    counts: dict = field(default_factory=lambda: dict.fromkeys(
        ('fly', 'fly_removed', 'flagged', 'flagged_fly', 'good', 'good_kept', 'inter', 'union', 'err_sum', 'err_n',
         'f_fly', 'f_flagged', 'f_hit', 'f_good', 'f_good_kept', 'filled', 'filled_err_sum', 'filled_n'), 0.0))
    ms: list = field(default_factory=list)

    def add(self, **values):
        for k, v in values.items():
            self.counts[k] += float(v)

    def result(self) -> dict:
        c = self.counts

        def ratio(a, b):
            return round(c[a] / c[b], 4) if c[b] else None
        return {'flying_recall': ratio('fly_removed', 'fly'), 'flying_precision': ratio('flagged_fly', 'flagged'),
                'valid_kept': ratio('good_kept', 'good'), 'mask_iou': ratio('inter', 'union'),
                'depth_mae_mm': round(1000 * c['err_sum'] / c['err_n'], 2) if c['err_n'] else None,
                'filled_per_frame': round(c['filled'] / max(len(self.ms), 1)),
                'filled_mae_mm': round(1000 * c['filled_err_sum'] / c['filled_n'], 2) if c['filled_n'] else None,
                'filter_only': {'flying_recall': ratio('f_hit', 'f_fly'), 'flying_precision': ratio('f_hit', 'f_flagged'),
                                'valid_kept': ratio('f_good_kept', 'f_good')},
                'ms_per_frame': round(float(np.median(self.ms)), 2) if self.ms else None,
                'flying_pixels': int(c['fly']), 'subject_pixels': int(c['good'])}


def evaluate_depth(bag: str | Path, methods: tuple[str, ...] = METHODS, max_frames: int | None = None,
                   figures: Path | None = None, progress: bool = True,
                   configs: dict[str, DepthFilterConfig] | None = None) -> dict:
    """Score each method on the bag's capture frames; with ``figures``, write PNGs of the first
    capture frame of the first camera there. ``configs`` replaces a method's default settings
    (a bench comparing one setting's values)."""
    gt = GroundTruth(bag)
    figure_camera = gt.rig.names[0]
    tallies = {m: _Tally() for m in methods}
    figure_frames = {}
    configs = {m: (configs or {}).get(m) or method_config(m) for m in methods}
    captures = 0
    bar = tqdm(desc='evaluating depth cleaning', unit='frame set', disable=not progress)
    for fs, cleaned in cleaned_frame_sets(bag, configs, output_size='half', limit=max_frames):
        captures += 1
        arrays = gt.arrays(fs.index)
        for name, frame in fs.cameras.items():
            truth = _truth(arrays, name, frame.depth)
            for m in methods:
                c = cleaned[m][name]
                tallies[m].ms.append(sum(c.result.timings_ms.values()))
                _score(tallies[m], c.result, truth, frame, c.cleaner)
                if figures is not None and name == figure_camera and name not in figure_frames.get(m, {}):
                    figure_frames.setdefault(m, {})[name] = (frame, c.result)
        bar.update()
    bar.close()
    if captures == 0:
        raise BadInput(f'{bag} has no capture frames with ground truth')
    report = {'bag': str(bag), 'frames': captures, 'cameras': len(gt.rig.cameras),
              'methods': {m: tallies[m].result() for m in methods}}
    r = report['methods']
    if 'paper_all' in r and 'paper_horizontal' in r:
        a, h = r['paper_all'], r['paper_horizontal']
        report['paper_claim_all_beats_horizontal'] = {
            'recall': (a['flying_recall'] or 0) > (h['flying_recall'] or 0),
            'valid_kept': (a['valid_kept'] or 0) > (h['valid_kept'] or 0)}
    if figures is not None:
        report['figures'] = [str(p) for p in write_depth_figures(Path(figures), figure_frames)]
    return report


def _truth(arrays: dict, name: str, raw: np.ndarray) -> dict:
    valid = raw > 0
    subject = arrays[f'{name}/depth_subject']
    flying = arrays[f'{name}/flying'] & valid
    speckle = arrays[f'{name}/speckle']
    size = 2 * NEAR_SUBJECT_PX + 1
    near = cv2.dilate(subject.astype(np.uint8), np.ones((size, size), np.uint8)).astype(bool)
    return {'near': near, 'flying': flying, 'good': subject & valid & ~flying & ~speckle,
            'clean': arrays[f'{name}/depth_clean'], 'color_subject': arrays[f'{name}/color_subject'],
            'good_all': valid & ~flying & ~speckle}


def _score(tally: _Tally, res, truth: dict, frame, cleaner: DepthCleaner) -> None:
    near, fly, good = truth['near'], truth['flying'], truth['good']
    kept = res.reached_output()
    flagged = res.flying & near
    clean = truth['clean']
    err_px = kept & near & (clean > 0)
    if res.mask is not None:
        pred = res.mask
    else:   # no mask: whatever has depth is foreground
        c = cleaner.registration.color_model
        pred = cv2.resize((res.depth > 0).view(np.uint8), (c.width, c.height), interpolation=cv2.INTER_NEAREST) > 0
    gt_mask = truth['color_subject']
    filled = res.filled if res.filled is not None else np.zeros(frame.depth.shape, np.float32)
    has_fill = filled > 0
    tally.add(fly=(fly & near).sum(), fly_removed=(fly & near & ~kept).sum(), flagged=flagged.sum(),
              flagged_fly=(flagged & fly).sum(), good=good.sum(), good_kept=(good & kept).sum(),
              inter=(pred & gt_mask).sum(), union=(pred | gt_mask).sum(),
              # the depth each pixel carries into the output: its return, or the fill of a hole
              err_sum=np.abs(np.where(has_fill, filled, frame.depth)[err_px] - clean[err_px]).sum(),
              err_n=err_px.sum(), filled=has_fill.sum(),
              filled_err_sum=np.abs(filled[err_px & has_fill] - clean[err_px & has_fill]).sum(),
              filled_n=(err_px & has_fill).sum(),
              f_fly=fly.sum(), f_flagged=res.flying.sum(), f_hit=(res.flying & fly).sum(),
              f_good=truth['good_all'].sum(), f_good_kept=(truth['good_all'] & ~res.flying).sum())


def format_report(report: dict) -> str:
    keys = ('flying_recall', 'flying_precision', 'valid_kept', 'mask_iou', 'depth_mae_mm', 'ms_per_frame')
    lines = [f"depth cleaning on {report['frames']} frame sets x {report['cameras']} cameras",
             '| method | ' + ' | '.join(keys) + ' | filter-only recall / precision / kept |',
             '|---' * (len(keys) + 2) + '|']
    for m, r in report['methods'].items():
        f = r['filter_only']
        lines.append(f'| {m} | ' + ' | '.join('-' if r[k] is None else f'{r[k]:g}' for k in keys)
                     + f" | {f['flying_recall']} / {f['flying_precision']} / {f['valid_kept']} |")
    if 'paper_claim_all_beats_horizontal' in report:
        c = report['paper_claim_all_beats_horizontal']
        lines.append(f"paper claim 'all directions beats horizontal': recall {'yes' if c['recall'] else 'no'}, "
                     f"valid kept {'yes' if c['valid_kept'] else 'no'}")
    return '\n'.join(lines)


def write_report(report: dict, path: Path) -> None:
    write_json(path, report)


def write_depth_figures(out_dir: Path, frames: dict) -> list[Path]:
    """``frames[method][camera] = (BagFrame, CleanResult)``: one mask and one depth figure per
    method and camera."""
    written = []
    for method, cams in frames.items():
        for name, (frame, result) in cams.items():
            if result.mask is not None:
                p = out_dir / f'{method}_{name}_mask.png'
                write_png(p, mask_panels(frame.color, result.mask))
                written.append(p)
            p = out_dir / f'{method}_{name}_depth.png'
            write_png(p, depth_panels(frame.depth, result))
            written.append(p)
    return written
