"""Neural colour harmonisation (paper 001, Section 3): an implicit colour field E and one
mapping network D per camera, in torch.

- E(x_p, y_p, z_p, x_c, y_c, z_c) -> rgb: the colour of surface point p as camera c sees it.
  Inputs are z-score normalised, then positionally encoded (L = 10 for the point, 4 for the
  camera); eight 256-wide ReLU layers with the point encoding concatenated again before the
  fifth, a linear feature layer, the camera encoding concatenated to it, one 128-wide ReLU layer
  and a sigmoid output (the NeRF / DeepSDF layout of the paper's Fig. 2). MSE against the
  cameras' pixels, Adam.
- D(r, g, b, x, y) -> rgb per camera: 5 -> 128 x 8 -> 3 with a sigmoid (Fig. 4), trained on the
  camera's own pixels to reproduce E's colour of the pixel's surface point for the reference:
  one camera (the paper), or ``mean``, the average of E over every camera position (ours: no
  camera's view-dependent highlights are favoured). x and y are the pixel centre over the
  image size, in [0, 1], so D does not depend on the image resolution.

Surface points come from the cleaned depth registered to colour (``volcap_pipeline.replay.capture_views``).
Each D also sees some pixels the cleaning removed (the room), aimed at the camera's affine map
onto the reference (``background``, ours), so its output there is not arbitrary. Defaults are
the authors' published settings (DESIGN.md) except the sample counts, which bound training time
on a CPU, and our ``mean`` reference and background samples. Training is deterministic for a seed on one device and
precision; after every epoch a checkpoint is written atomically and ``resume`` carries on from
it.

This module is the job (``harmonise``, ``run`` and its report); the networks are
``neural_nets``, the training data ``neural_samples``, device, precision and the training loop
``neural_train``, the saved networks ``neural_models``, the live form ``neural_live``.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from volcap_core.errors import BadInput
from volcap_core.files import write_json

from .apply import pixel_centres
from .config import HarmoniseConfig
from .correspondence import View, split_frame_sets
from .figures import training_figure
from .neural_live import _mapper_error, export_live
from .neural_models import CHECKPOINT, FIELD_FILE, MANIFEST, Harmonisation
from .neural_nets import CaptureMapper, ColorField
from .neural_samples import SurfaceSamples, training_samples
from .neural_train import TrainResult, _save_atomic, reference_color, torch_device, train, use_bf16

HELD_OUT = 20_000        # at most this many pixels per camera are kept from D's training to check it


def _field_for(samples: SurfaceSamples, cfg: HarmoniseConfig) -> ColorField:
    centres = np.unique(samples.centres, axis=0)
    camera_std = np.maximum(centres.std(0), 1e-3) if len(centres) > 1 else np.ones(3, np.float32)
    return ColorField(samples.points.mean(0), np.maximum(samples.points.std(0), 1e-3), centres.mean(0), camera_std,
                      cfg.field_width, cfg.point_frequencies, cfg.camera_frequencies)


def _with_background(views: list[View], mine: SurfaceSamples, target: torch.Tensor, count: int,
                     rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, torch.Tensor]:
    """D's training inputs and targets with ``count`` pixels that have no surface point (the
    background the cleaning removed) added, each aimed at the camera's affine colour map onto
    E's reference fitted on ``mine``: E knows nothing there, and without them D's output on
    colours and image regions it never saw (the room round the subject) is arbitrary."""
    empty = [(v, np.flatnonzero(v.depth.reshape(-1) <= 0)) for v in views]
    total = sum(len(idx) for _, idx in empty)
    if count <= 0 or total == 0:
        return mine.colors, mine.xy, target
    colors, xy = [], []
    for v, idx in empty:
        pick = rng.choice(idx, min(len(idx), max(1, count * len(idx) // total)), replace=False)
        h, w = v.depth.shape
        y, x = np.divmod(pick, w)
        colors.append(v.color.reshape(-1, 3)[pick].astype(np.float32) / 255.0)
        xy.append(pixel_centres(x, y, w, h))
    colors, xy = np.concatenate(colors), np.concatenate(xy)
    design = np.hstack([mine.colors, np.ones((len(mine), 1), np.float32)])
    affine = np.linalg.lstsq(design, target.cpu().numpy(), rcond=None)[0]
    aimed = np.clip(np.hstack([colors, np.ones((len(colors), 1), np.float32)]) @ affine, 0.0, 1.0)
    return (np.concatenate([mine.colors, colors]), np.concatenate([mine.xy, xy]),
            torch.cat([target, torch.as_tensor(aimed.astype(np.float32), device=target.device)]))


def _finished(path: Path, cfg: HarmoniseConfig, resume: bool, device: torch.device) -> dict | None:
    """With ``resume``, a network an interrupted run already finished (same settings), else None."""
    if not resume or not path.exists():
        return None
    saved = torch.load(path, map_location=device, weights_only=False)
    if saved.get('config') != asdict(cfg) or 'result' not in saved:
        raise BadInput(f'--resume: {path} was trained with other settings; use a new --out or leave out --resume')
    return saved


def harmonise(train_sets: list[list[View]], cameras: list[str], cfg: HarmoniseConfig, out_dir: str | Path,
              resume: bool = False, progress: bool = True) -> Harmonisation:
    """Train E on every training view, then each camera's D against E's reference colour; the
    networks, ``manifest.json`` and ``checkpoint.pt`` (during training) go to ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if cfg.reference != 'mean' and cfg.reference not in cameras:
        raise BadInput(f'reference {cfg.reference!r} is not one of the cameras ({", ".join(cameras)}) or mean')
    checkpoint = out_dir / CHECKPOINT
    if not resume:
        checkpoint.unlink(missing_ok=True)
    device = torch_device(cfg.device)
    bf16 = use_bf16(cfg.precision, device)
    torch.manual_seed(cfg.seed)
    torch.use_deterministic_algorithms(True, warn_only=device.type == 'cuda')
    centres = {v.name: v.T_world_camera[:3, 3].astype(np.float32) for views in train_sets for v in views}
    missing = [c for c in cameras if c not in centres]
    if missing:
        raise BadInput(f'{", ".join(missing)} are in no training frame set')

    samples = training_samples(train_sets, cameras, cfg.points, cfg.seed)
    t = lambda a: torch.as_tensor(a, device=device)
    field_model = _field_for(samples, cfg).to(device)
    done = _finished(out_dir / FIELD_FILE, cfg, resume, device)
    if done:
        field_model.load_state_dict(done['state'])
        field_result = TrainResult(**done['result'])
    else:
        field_result = train(field_model, (t(samples.points), t(samples.centres)), t(samples.colors),
                             epochs=cfg.field_epochs, batch=cfg.field_batch, lr=cfg.field_lr,
                             lr_final=cfg.field_lr_final, seed=cfg.seed, bf16=bf16, label='E (colour field)',
                             checkpoint=checkpoint, settings=asdict(cfg), progress=progress)
        _save_atomic({'state': field_model.state_dict(), 'config': asdict(cfg), 'result': asdict(field_result)},
                     out_dir / FIELD_FILE)
    field_model.eval()

    names = cameras if cfg.reference == 'mean' else [cfg.reference]
    ref_centres = np.stack([centres[c] for c in names])
    mappers, mapper_results, fits, held_out = {}, {}, {}, {}
    for i, cam in enumerate(cameras):
        # every pixel with depth, shuffled: a tenth (at most HELD_OUT) is kept back to check D
        # against E, D trains on up to mapper_points of the rest
        own = [v for views in train_sets for v in views if v.name == cam]
        pixels = training_samples([own], cameras, None, 0)
        rng = np.random.default_rng(cfg.seed + 1 + i)
        order = rng.permutation(len(pixels))
        n_held = min(HELD_OUT, len(pixels) // 10)
        mine = pixels.select(order[n_held:n_held + cfg.mapper_points])
        torch.manual_seed(cfg.seed + 1 + i)
        mapper = CaptureMapper(cfg.mapper_width, cfg.mapper_layers).to(device)
        done = _finished(out_dir / f'{cam}.mapper.pt', cfg, resume, device)
        if done:
            mapper.load_state_dict(done['state'])
            mapper_results[cam] = TrainResult(**done['result'])
        else:
            target = reference_color(field_model, t(mine.points), ref_centres, bf16)
            rgb, xy, target = _with_background(own, mine, target, int(cfg.background * len(mine)), rng)
            mapper_results[cam] = train(mapper, (t(rgb), t(xy)), target, epochs=cfg.mapper_epochs,
                                        batch=cfg.mapper_batch, lr=cfg.mapper_lr, lr_final=cfg.mapper_lr_final,
                                        seed=cfg.seed + 1 + i, bf16=bf16, label=f'D {cam}', checkpoint=checkpoint,
                                        settings=asdict(cfg), progress=progress)
            _save_atomic({'state': mapper.state_dict(), 'config': asdict(cfg), 'result': asdict(mapper_results[cam])},
                         out_dir / f'{cam}.mapper.pt')
        mapper.eval()
        mappers[cam] = mapper
        fits[cam] = len(mine)
        if n_held:
            held_out[cam] = _mapper_error(field_model, mapper, pixels.select(order[:n_held]), ref_centres, bf16)
    checkpoint.unlink(missing_ok=True)
    report = {
        'cameras': cameras, 'reference': cfg.reference, 'device': str(device), 'bf16': bf16,
        'threads': torch.get_num_threads(), 'field_samples': len(samples), 'mapper_samples': fits,
        'field': asdict(field_result), 'mappers': {c: asdict(r) for c, r in mapper_results.items()},
        'mapper_error': held_out,
        'centres': {c: v.tolist() for c, v in centres.items()}, 'config': asdict(cfg)}
    return Harmonisation(cameras, centres, field_model, mappers, cfg.reference, cfg, device, bf16, report)


@dataclass
class HarmoniseReport:
    manifest: dict          # also written to ``out_dir/manifest.json``
    cameras: list[str]
    out_dir: Path

    def lines(self) -> list[str]:
        m = self.manifest
        out = [f"E: {m['field_samples']} samples, {len(m['field']['losses'])} epochs, final RMS "
               f"{255 * m['field']['losses'][-1] ** 0.5:.2f} levels, {m['field']['seconds']:.0f} s "
               f"({m['device']}{', bf16' if m['bf16'] else ''})"]
        for c in self.cameras:
            d, e = m['mapper_error'].get(c), m['export_error'].get(c)
            if d and e:
                out.append(f'{c}: D vs E\'s reference on held-out pixels RMS {d["rms_levels"]:.2f} levels; live LUT '
                           f'vs D mean {e["mean_levels"]:.2f}, p99 {e["p99_levels"]:.0f}, max {e["max_levels"]:.0f} '
                           'levels')
        out.append(f'wrote {self.out_dir}/ (manifest.json, field.pt, <camera>.mapper.pt, <camera>.lut.npz, '
                   f'training.png) in {m["seconds"]["total"]:.0f} s')
        return out


def run(sets: list[list[View]], cameras: list[str], cfg: HarmoniseConfig, out_dir: str | Path,
        train_sets: str = 'even', resume: bool = False, progress: bool = True, sources: dict | None = None,
        views_seconds: float = 0.0) -> HarmoniseReport:
    """`volcap harmonise` on views of capture frame sets: train (on the 1st, 3rd, ... set with
    ``train_sets='even'``, the sets the colour evaluation fits on, so it scores D on sets it never
    saw; or on all), export the live form checked on the other sets, write the manifest (with
    ``sources``, e.g. the bag and calibration) and the training figure."""
    if train_sets not in ('even', 'all'):
        raise BadInput(f"train_sets must be 'even' or 'all', got {train_sets!r}")
    cfg.validate()
    trained, checked = split_frame_sets(len(sets)) if train_sets == 'even' else (list(range(len(sets))),) * 2
    t1 = time.perf_counter()
    harm = harmonise([sets[i] for i in trained], cameras, cfg, out_dir, resume=resume, progress=progress)
    t2 = time.perf_counter()
    live = export_live(harm, out_dir, [v for i in checked for v in sets[i]], progress=progress)
    t3 = time.perf_counter()
    manifest = {**harm.report, **live, **(sources or {}),
                'frame_sets': {'read': len(sets), 'trained': trained, 'checked': checked,
                               'checked_held_out': checked != trained},
                'seconds': {'views': views_seconds, 'training': t2 - t1, 'export': t3 - t2,
                            'total': views_seconds + t3 - t1}}
    out = Path(out_dir)
    write_json(out / MANIFEST, manifest)
    training_figure(out / 'training.png', manifest)
    return HarmoniseReport(manifest, cameras, out)
