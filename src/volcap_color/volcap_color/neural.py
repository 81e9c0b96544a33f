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
  image size, in [0, 1], so D does not depend on the image resolution. Ours corrects in gains
  per channel in linear light (``CaptureMapper``, ``mapper_form``) and aims a pixel the camera
  recorded saturated at the reference of its clip level (``mapper_targets``).

Surface points come from the cleaned depth registered to colour (``volcap_pipeline.replay.capture_views``),
by default (``volcap_pipeline.harmonise``, ours) as the training views' fused surface ray-cast
back into each view: the views' own depths disagree by 2.6-3.0 mm at the median on real
texture, so without it one point of the subject is a different place in E for every camera.
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

import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Protocol

import numpy as np
import torch
from torch import nn

from volcap_core.color import srgb_to_lab
from volcap_core.errors import BadInput
from volcap_core.files import write_json

from .apply import pixel_centres
from .config import HarmoniseConfig
from .correspondence import View, split_frame_sets
from .figures import training_figure
from .neural_live import _mapper_error, export_live
from .neural_models import CHECKPOINT, FIELD_FILE, MANIFEST, Harmonisation
from .neural_nets import CaptureMapper, ColorField, HashGridField, RegisteredField
from .neural_samples import SurfaceSamples, training_samples
from .neural_train import (
    Reference,
    TrainResult,
    _Call,
    _save_atomic,
    chart_anchor_matrix,
    field_color,
    grey_world_gains,
    predict,
    torch_device,
    train,
    use_bf16,
)

SURFACE_KEPT = 0.5       # a camera with fewer of its pixels on the fused surface than this is reported
TEXTURE_KEPT = 0.9       # a D keeping less of its pixels' L* spread or saturated chroma is reported
HELD_OUT = 20_000        # at most this many pixels per camera are kept from training to check E and D


MIN_CELL_MM = 1.0        # finer cells than this cost table size and time for texture no camera here resolves

class Surface(Protocol):
    """Where a frame set's training pixels lie: the views -> the same views with each pixel's
    depth replaced by the surface E and D are to sample it on (0: leave the pixel out), and what
    to report of it. The pipeline composes one from the fusion
    (``volcap_pipeline.harmonise.FusedSurface``): this stage may not import the fusion itself."""
    settings: dict          # what decides the surface: a run resumes only with the same

    def __call__(self, views: list[View]) -> tuple[list[View], dict]: ...


def pixel_footprint_mm(views: list[View]) -> float:
    """The views' median pixel footprint on the surface they see (median depth over the focal
    length), in mm, at least ``MIN_CELL_MM``: the finest detail the images hold, so the size of the
    hash grid's finest cells (rgbd_box: 0.67 mm; a studio camera at 2-3 m about 3 mm)."""
    sizes = [float(np.median(v.depth[v.depth > 0])) / v.camera.fx * 1000.0 for v in views if np.any(v.depth > 0)]
    if not sizes:
        raise BadInput('the training views have no pixel with depth')
    return max(MIN_CELL_MM, float(np.median(sizes)))


def _set_crosstalk(field_model: nn.Module, cfg: HarmoniseConfig, cameras: list[str], centres: dict,
                   chart_models: dict | None) -> dict | None:
    """Give a hash-grid E's camera responses the crosstalk each camera's chart model measured
    (``crosstalk_from_chart``, where every camera has one); returns it per camera (None without)."""
    if not (cfg.crosstalk_from_chart and isinstance(field_model, HashGridField) and chart_models
            and all(c in chart_models for c in cameras)):
        return None
    matrices = {c: chart_crosstalk(chart_models[c]) for c in cameras}
    index = field_model.camera_index(torch.as_tensor(np.stack([centres[c] for c in cameras]),
                                                     device=field_model.centres.device)).tolist()
    fixed = np.tile(np.eye(3), (len(field_model.centres), 1, 1))
    for c, i in zip(cameras, index):
        fixed[i] = matrices[c]
    field_model.response.set_crosstalk(fixed)
    return matrices


def _field_for(samples: SurfaceSamples, cfg: HarmoniseConfig, cell_mm: float = 4.0) -> nn.Module:
    centres = np.unique(samples.centres, axis=0)
    camera_std = np.maximum(centres.std(0), 1e-3) if len(centres) > 1 else np.ones(3, np.float32)
    if cfg.field == 'paper':
        return ColorField(samples.points.mean(0), np.maximum(samples.points.std(0), 1e-3), centres.mean(0),
                          camera_std, cfg.field_width, cfg.point_frequencies, cfg.camera_frequencies)
    low, high = samples.points.min(0), samples.points.max(0)
    extent = float(max((high - low).max(), 1e-3)) * 1.02          # a margin so no point sits on the edge
    start = (low + high) / 2 - extent / 2
    finest = max(2, math.ceil(extent / (cell_mm / 1000.0)))
    return HashGridField(start, extent, centres, cfg.grid_levels, cfg.grid_log2_table, min(16, finest), finest,
                         cfg.head_width)


def _with_background(views: list[View], inputs: np.ndarray, xy: np.ndarray, target: torch.Tensor, count: int,
                     rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, torch.Tensor]:
    """D's training inputs and targets with ``count`` pixels that have no surface point (the
    background the cleaning removed) added, each aimed at the camera's affine colour map onto
    E's reference fitted on ``inputs``: E knows nothing there, and without them D's output on
    colours and image regions it never saw (the room round the subject) is arbitrary."""
    empty = [(v, np.flatnonzero(v.depth.reshape(-1) <= 0)) for v in views]
    total = sum(len(idx) for _, idx in empty)
    if count <= 0 or total == 0:
        return inputs, xy, target
    colors, bg_xy = [], []
    for v, idx in empty:
        pick = rng.choice(idx, min(len(idx), max(1, count * len(idx) // total)), replace=False)
        h, w = v.depth.shape
        y, x = np.divmod(pick, w)
        colors.append(v.color.reshape(-1, 3)[pick].astype(np.float32) / 255.0)
        bg_xy.append(pixel_centres(x, y, w, h))
    colors, bg_xy = np.concatenate(colors), np.concatenate(bg_xy)
    design = np.hstack([inputs, np.ones((len(inputs), 1), np.float32)])
    affine = np.linalg.lstsq(design, target.cpu().numpy(), rcond=None)[0]
    aimed = np.clip(np.hstack([colors, np.ones((len(colors), 1), np.float32)]) @ affine, 0.0, 1.0)
    return (np.concatenate([inputs, colors]), np.concatenate([xy, bg_xy]),
            torch.cat([target, torch.as_tensor(aimed.astype(np.float32), device=target.device)]))


def _with_gamut(field_model: HashGridField, reference: Reference, mine: SurfaceSamples, centre: np.ndarray,
                rgb: np.ndarray, xy: np.ndarray, target: torch.Tensor, count: int, rng: np.random.Generator,
                bf16: bool) -> tuple[np.ndarray, np.ndarray, torch.Tensor]:
    """D's training pairs with ``count`` more: random linear surface colours spanning those the
    field holds on this camera's pixels (each channel up to its 99.5th percentile), as E's
    response records them for this camera at random image positions, aimed at their reference.
    The field is smoother than the images, so without these D would be trained on a narrower
    gamut than the pixels it corrects, and greys out the most saturated ones."""
    device = target.device
    latent = predict(_Call(field_model.surface_color), (torch.as_tensor(mine.points, device=device),), bf16)
    top = torch.quantile(latent[:200_000], 0.995, dim=0).clamp_min(1e-3).cpu().numpy()
    colors = torch.as_tensor((rng.random((count, 3)) * top).astype(np.float32), device=device)
    where = torch.as_tensor(rng.random((count, 2)).astype(np.float32), device=device)
    cam = torch.as_tensor(np.asarray(centre, np.float32), device=device).expand(count, 3)
    index = field_model.camera_index(cam)
    with torch.no_grad():
        recorded = field_model.response(colors, index, where)
    return (np.concatenate([rgb, recorded.cpu().numpy()]), np.concatenate([xy, where.cpu().numpy()]),
            torch.cat([target, reference.from_surface_color(field_model.response.unclipped(colors, index, where))]))


def _finished(path: Path, cfg: HarmoniseConfig, resume: bool, device: torch.device, surface: dict | None
              ) -> dict | None:
    """With ``resume``, a network an interrupted run already finished (same settings and
    surface), else None."""
    if not resume or not path.exists():
        return None
    saved = torch.load(path, map_location=device, weights_only=False)
    if saved.get('config') != asdict(cfg) or saved.get('surface') != surface or 'result' not in saved:
        raise BadInput(f'--resume: {path} was trained with other settings; use a new --out or leave out --resume')
    return saved


def _held_out_split(samples: SurfaceSamples, cameras: list[str], seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(held out, training) sample indices: per camera a tenth of its pixels, at most HELD_OUT,
    kept from E and from its D; both in a random order."""
    rng = np.random.default_rng(seed)
    held, rest = [], []
    for i in range(len(cameras)):
        mine = rng.permutation(np.flatnonzero(samples.camera == i))
        n = min(HELD_OUT, len(mine) // 10)
        held.append(mine[:n])
        rest.append(mine[n:])
    return np.concatenate(held), rng.permutation(np.concatenate(rest))


def edge_weights(samples: SurfaceSamples, edge_levels: float, device: torch.device) -> torch.Tensor | None:
    """E's per-sample weights 1 / (1 + (g / edge_levels)^2) for luminance gradient g, scaled to
    mean 1 (None for edge_levels 0): at a texture edge a few millimetres of registration or depth
    error change a pixel's colour completely, and those pixels would otherwise dominate the fit
    of every camera's response."""
    if edge_levels <= 0:
        return None
    w = 1.0 / (1.0 + (samples.gradient / edge_levels) ** 2)
    return torch.as_tensor((w / max(w.mean(), 1e-12)).astype(np.float32), device=device)


def _resolve_anchor(cfg: HarmoniseConfig, names: list[str], chart_models: dict | None) -> str:
    have_charts = bool(chart_models) and all(c in chart_models for c in names)
    if cfg.anchor == 'chart' and not have_charts:
        missing = [c for c in names if c not in (chart_models or {})]
        raise BadInput(f'--anchor chart: the calibration has no chart colour model for {", ".join(missing)}')
    if cfg.anchor == 'auto':
        return 'chart' if have_charts else 'none'
    return cfg.anchor


def _registered(field_model: nn.Module, samples: SurfaceSamples) -> SurfaceSamples:
    """``samples`` with each point moved by its camera's view correction (``HashGridField.register``)."""
    if not isinstance(field_model, HashGridField):
        return samples
    device = next(field_model.parameters()).device
    points = predict(_Call(field_model.register), (torch.as_tensor(samples.points, device=device),
                                                   torch.as_tensor(samples.centres, device=device)), False)
    return replace(samples, points=points.cpu().numpy())


def registration_report(field_model: nn.Module, cameras: list[str], centres: dict) -> dict | None:
    """Each camera's view correction learnt with E: rotation in degrees, translation in mm."""
    if not isinstance(field_model, HashGridField):
        return None
    corr = field_model.corrections().detach().cpu().numpy()
    idx = field_model.camera_index(torch.as_tensor(np.stack([centres[c] for c in cameras]),
                                                   device=field_model.centres.device)).cpu().numpy()
    return {c: {'rotation_deg': float(np.degrees(np.linalg.norm(corr[k, :3]))),
                'translation_mm': float(np.linalg.norm(corr[k, 3:]) * 1000.0)} for c, k in zip(cameras, idx)}


def field_error(field_model: nn.Module, samples: SurfaceSamples, cameras: list[str], bf16: bool) -> dict:
    """E against the cameras' own pixels ``samples`` (pixels it was not trained on): RMS in
    levels, over all and per camera."""
    device = next(field_model.parameters()).device
    t = lambda a: torch.as_tensor(a, device=device)
    pred = predict(field_model, (t(samples.points), t(samples.centres), t(samples.xy)), bf16).cpu().numpy()
    sq = ((pred - samples.colors) * 255.0) ** 2
    per = {c: float(np.sqrt(sq[samples.camera == i].mean())) for i, c in enumerate(cameras)
           if np.any(samples.camera == i)}
    if not len(sq):
        return {'rms_levels': None, 'per_camera': per, 'pixels': 0}
    return {**error_spread(sq), 'per_camera': per}


def error_spread(sq: np.ndarray) -> dict:
    """RMS, median, 90th percentile and the best 95 %'s RMS (levels) of per-pixel squared
    colour errors ``sq`` (N, 3): on real texture a few per cent of the pixels (object edges
    where colour and depth disagree, highlights) hold most of the squared error."""
    pixel = np.sqrt(sq.mean(1))
    best = np.sort(pixel)[:max(1, int(0.95 * len(pixel)))]
    return {'rms_levels': float(np.sqrt(sq.mean())), 'pixels': len(pixel),
            'median_levels': float(np.median(pixel)), 'p90_levels': float(np.percentile(pixel, 90)),
            'rms_best_95_levels': float(np.sqrt((best ** 2).mean()))}


def harmonise(train_sets: list[list[View]], cameras: list[str], cfg: HarmoniseConfig, out_dir: str | Path,
              resume: bool = False, progress: bool = True, chart_models: dict | None = None,
              surface: Surface | None = None) -> Harmonisation:
    """Train E on every training view, then each camera's D onto the reference; the networks,
    ``manifest.json`` and ``checkpoint.pt`` (during training) go to ``out_dir``. ``chart_models``
    (camera -> ``ColorModel`` from the calibration's chart) anchor the reference in absolute
    colour (``cfg.anchor``). ``surface``: where each training pixel's surface point is (see
    ``Surface``; None: each view's own depth, as the paper)."""
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
    names = cameras if cfg.reference == 'mean' else [cfg.reference]
    anchor = _resolve_anchor(cfg, names, chart_models)

    surface_sets, surface_report = _on_surface(train_sets, surface)
    pixels = training_samples(surface_sets, cameras, None, cfg.seed)    # every pixel with depth
    held, rest = _held_out_split(pixels, cameras, cfg.seed)
    samples = pixels.select(rest[:cfg.field_setting('points')])
    t = lambda a: torch.as_tensor(a, device=device)
    cell_mm = cfg.grid_cell_mm or pixel_footprint_mm([v for views in train_sets for v in views if v.name in cameras])
    field_model = _field_for(samples, cfg, cell_mm).to(device)
    crosstalk = _set_crosstalk(field_model, cfg, cameras, centres, chart_models)
    on = None if surface is None else dict(surface.settings)        # what the networks are trained on
    done = _finished(out_dir / FIELD_FILE, cfg, resume, device, on)
    if done:
        field_model.load_state_dict(done['state'])
        field_result = TrainResult(**done['result'])
    else:
        trained = RegisteredField(field_model) if isinstance(field_model, HashGridField) and cfg.register_views \
            else field_model
        field_result = train(trained, (t(samples.points), t(samples.centres), t(samples.xy)), t(samples.colors),
                             epochs=cfg.field_setting('field_epochs'), batch=cfg.field_setting('field_batch'),
                             lr=cfg.field_setting('field_lr'), lr_final=cfg.field_setting('field_lr_final'),
                             seed=cfg.seed, bf16=bf16, label='E (colour field)', checkpoint=checkpoint,
                             settings={**asdict(cfg), 'surface': on}, progress=progress,
                             weights=edge_weights(samples, cfg.edge_levels, device), robust=cfg.robust_levels / 255.0)
        _save_atomic({'state': field_model.state_dict(), 'config': asdict(cfg), 'surface': on,
                      'result': asdict(field_result)},
                     out_dir / FIELD_FILE)
    field_model.eval()
    # the views' corrections learnt with E, applied once: from here on every surface point of
    # a camera's pixel is where E's field has it
    pixels = _registered(field_model, pixels)
    samples = pixels.select(rest[:cfg.field_setting('points')])
    held_samples = pixels.select(held)
    e_error = field_error(field_model, held_samples, cameras, bf16)

    reference = Reference(field_model, np.stack([centres[c] for c in names]), bf16)
    if anchor == 'chart':
        # with gains the reference keeps no camera's mixing: the gains cannot take it out as the
        # 3x3 did (and as the charts do), and the truth a chart stands for has none
        reference.unmixed = cfg.anchor_fit == 'gains' and crosstalk is not None
        reference.matrix = chart_anchor_matrix(reference, [chart_models[c] for c in names],
                                               t(samples.points[:200_000]), cfg.anchor_fit)
    if anchor == 'grey_world':
        reference.gains = grey_world_gains(reference, t(samples.points[:200_000]))
    mappers, mapper_results, fits, d_error, texture = {}, {}, {}, {}, {}
    for i, cam in enumerate(cameras):
        own = [v for views in train_sets for v in views if v.name == cam]
        mine = pixels.select(rest[pixels.camera[rest] == i][:cfg.mapper_points])
        torch.manual_seed(cfg.seed + 1 + i)
        mapper = CaptureMapper(cfg.mapper_width, cfg.mapper_layers, cfg.mapper_form).to(device)
        if crosstalk is not None and cfg.mapper_form == 'gain':
            mapper.unmix.copy_(torch.as_tensor(np.linalg.inv(crosstalk[cam]), dtype=torch.float32))
        done = _finished(out_dir / f'{cam}.mapper.pt', cfg, resume, device, on)
        if done:
            mapper.load_state_dict(done['state'])
            mapper_results[cam] = TrainResult(**done['result'])
        else:
            rng = np.random.default_rng(cfg.seed + 1 + i)
            target = mapper_targets(field_model, reference, mine, centres[cam], bf16)
            inputs = mapper_inputs(field_model, mine, centres[cam], cfg.mapper_input, bf16)
            rgb, xy, target = _with_background(own, inputs, mine.xy, target, int(cfg.background * len(mine)), rng)
            if cfg.mapper_input == 'field' and isinstance(field_model, HashGridField) and cfg.gamut > 0:
                rgb, xy, target = _with_gamut(field_model, reference, mine, centres[cam], rgb, xy, target,
                                              int(cfg.gamut * len(mine)), rng, bf16)
            mapper_results[cam] = train(mapper, (t(rgb), t(xy)), target, epochs=cfg.mapper_epochs,
                                        batch=cfg.mapper_batch, lr=cfg.mapper_lr, lr_final=cfg.mapper_lr_final,
                                        seed=cfg.seed + 1 + i, bf16=bf16, label=f'D {cam}', checkpoint=checkpoint,
                                        settings={**asdict(cfg), 'surface': on}, progress=progress)
            _save_atomic({'state': mapper.state_dict(), 'config': asdict(cfg), 'surface': on,
                          'result': asdict(mapper_results[cam])},
                         out_dir / f'{cam}.mapper.pt')
        mapper.eval()
        mappers[cam] = mapper
        fits[cam] = len(mine)
        check = held_samples.select(held_samples.camera == i)
        if len(check):
            wanted = mapper_targets(field_model, reference, check, centres[cam], bf16)
            d_error[cam] = _mapper_error(field_model, mapper, check, wanted, cfg.mapper_input, bf16)
            # what D makes of the camera's own pixels against what the reference says they are
            texture[cam] = texture_kept(wanted.cpu().numpy(),
                                        predict(mapper, (t(check.colors), t(check.xy)), bf16).cpu().numpy())
    checkpoint.unlink(missing_ok=True)
    report = {
        'cameras': cameras, 'reference': cfg.reference, 'anchor': anchor, 'device': str(device), 'bf16': bf16,
        'anchor_gains': None if reference.gains is None else reference.gains.tolist(),
        'anchor_matrix': None if reference.matrix is None else reference.matrix.round(5).tolist(),
        'reference_unmixed': reference.unmixed,
        'threads': torch.get_num_threads(), 'field_samples': len(samples), 'mapper_samples': fits,
        'crosstalk': None if crosstalk is None else {c: m.round(4).tolist() for c, m in crosstalk.items()},
        'field': asdict(field_result), 'field_error': e_error, 'grid_cell_mm': cell_mm, 'surface': surface_report,
        'registration': registration_report(field_model, cameras, centres), 'mappers': {c: asdict(r) for c, r in
                                                                           mapper_results.items()},
        'mapper_error': d_error, 'texture': texture,
        'centres': {c: v.tolist() for c, v in centres.items()}, 'config': asdict(cfg)}
    return Harmonisation(cameras, centres, field_model, mappers, cfg.reference, cfg, device, bf16, report)


def _on_surface(train_sets: list[list[View]], surface: Surface | None) -> tuple[list[list[View]], dict]:
    """The training sets as ``surface`` places their pixels, and its report per frame set."""
    if surface is None:
        return train_sets, {'source': 'views', 'frame_sets': []}
    placed, reports = [], []
    for views in train_sets:
        moved, report = surface(views)
        if [(v.name, v.depth.shape) for v in moved] != [(v.name, v.depth.shape) for v in views]:
            raise ValueError('the surface must return the same views on the same pixel grids')
        placed.append(moved)
        reports.append(report)
    return placed, {'source': reports[0].get('source', 'given') if reports else 'given', 'frame_sets': reports}


def mapper_targets(field_model: nn.Module, reference: Reference, samples: SurfaceSamples, centre: np.ndarray,
                   bf16: bool) -> torch.Tensor:
    """What D is to give the pixels ``samples`` of the camera at ``centre``: the reference
    colour of each pixel's surface point; with a ``HashGridField``, where the camera records
    the point saturated, the reference of the brightest colour it records below saturation
    (``CameraResponse.unclipped``), as inverting its response would."""
    device = next(field_model.parameters()).device
    points = torch.as_tensor(samples.points, device=device)
    if not isinstance(field_model, HashGridField):
        return reference(points)
    index = field_model.camera_index(torch.as_tensor(np.asarray(centre, np.float32), device=device)[None])
    latent = predict(_Call(field_model.surface_color), (points,), bf16)
    latent = predict(_Call(lambda a, xy: field_model.response.unclipped(a, index.expand(len(a)), xy)),
                     (latent, torch.as_tensor(samples.xy, device=device)), False)
    return reference.from_surface_color(latent)


def mapper_inputs(field_model: nn.Module, samples: SurfaceSamples, centre: np.ndarray, kind: str, bf16: bool
                  ) -> np.ndarray:
    """What D is trained to map: E's colour of each point as this camera records it at its pixel
    (``field``), or the pixel's own colour (``pixels``, the paper)."""
    if kind == 'pixels':
        return samples.colors
    device = next(field_model.parameters()).device
    return field_color(field_model, torch.as_tensor(samples.points, device=device), centre, bf16,
                       torch.as_tensor(samples.xy, device=device)).cpu().numpy()


def texture_kept(before: np.ndarray, after: np.ndarray, saturated: float = 25.0) -> dict:
    """How much texture ``after`` keeps of ``before`` (sRGB in [0, 1], the same pixels; in
    ``harmonise``: E's reference colours of a camera's held-out pixels, and D's output on them):
    the mean CIELAB chroma of the pixels saturated in ``before`` (C* >= ``saturated``) and the
    spread (standard deviation) of L*, in both, and their ratios. The reference is smoother
    than the images, so a D that keeps the texture scores at or above 1."""
    lab_b, lab_a = srgb_to_lab(np.asarray(before, np.float64)), srgb_to_lab(np.asarray(after, np.float64))
    chroma_b, chroma_a = np.hypot(lab_b[:, 1], lab_b[:, 2]), np.hypot(lab_a[:, 1], lab_a[:, 2])
    sat = chroma_b >= saturated
    out = {'lightness_spread_before': float(lab_b[:, 0].std()), 'lightness_spread_after': float(lab_a[:, 0].std()),
           'saturated_pixels': int(sat.sum())}
    out['lightness_kept'] = out['lightness_spread_after'] / max(out['lightness_spread_before'], 1e-9)
    if sat.any():
        out.update(chroma_before=float(chroma_b[sat].mean()), chroma_after=float(chroma_a[sat].mean()))
        out['chroma_kept'] = out['chroma_after'] / out['chroma_before']
    return out


def chart_models(calibration) -> dict:
    """The calibration's chart colour models by camera (cameras without one are left out)."""
    from volcap_core.color import ColorModel
    return {c: ColorModel.from_dict(cam.color) for c, cam in calibration.cameras.items() if cam.color}


def chart_crosstalk(model) -> np.ndarray:
    """The channel crosstalk a chart colour model says its camera has: (3, 3), rows summing to 1.

    The chart model maps the camera's linear colour to the true one, locally ``A``; the camera is
    then ``A^-1 = M diag(d)``, crosstalk ``M`` after per-channel gains ``d`` (exposure, white
    balance, the light's colour). Rows of ``M`` summing to 1 fix the split: ``d^-1 = A 1``. ``A`` is
    the model's Jacobian at mid grey, so any linear-light model form serves. The identity for the
    paper's diagonal (no crosstalk) or a model that is not invertible there."""
    if model.method == 'paper_diagonal':
        return np.eye(3)
    grey, step = np.full((1, 3), 0.18), 1e-3
    base = model.apply_linear(grey)[0]
    jac = np.stack([(model.apply_linear(grey + step * np.eye(3)[j])[0] - base) / step for j in range(3)], axis=1)
    if not np.all(np.isfinite(jac)) or np.linalg.cond(jac) > 1e3:
        return np.eye(3)
    return np.linalg.inv(jac) @ np.diag(jac @ np.ones(3))


@dataclass
class HarmoniseReport:
    manifest: dict          # also written to ``out_dir/manifest.json``
    cameras: list[str]
    out_dir: Path

    def lines(self) -> list[str]:
        m = self.manifest
        fe = m['field_error']
        held = fe['rms_levels']
        spread = (f" (median {fe['median_levels']:.1f}, 95 % best {fe['rms_best_95_levels']:.1f})"
                  if 'median_levels' in fe else '')
        cell = f", {m['grid_cell_mm']:.1f} mm cells" if m.get('grid_cell_mm') else ''
        out = [f"E ({m['config']['field']}{cell}): {m['field_samples']} samples, {len(m['field']['losses'])} epochs, "
               f"final loss {m['field']['losses'][-1]:.2e}, held-out pixels RMS "
               + ('-' if held is None else f'{held:.2f}') + f" levels{spread}, {m['field']['seconds']:.0f} s "
               f"({m['device']}{', bf16' if m['bf16'] else ''}); reference: {m['reference']}, anchor {m['anchor']}"
               + (f" ({m['config'].get('anchor_fit', 'matrix_3x3')}"
                  f"{', the cameras without their crosstalk' if m.get('reference_unmixed') else ''})"
                  if m['anchor'] == 'chart' else '')]
        reg = m.get('registration')
        if reg:
            worst = max(reg, key=lambda c: reg[c]['translation_mm'])
            out.append(f"views registered with E: corrections up to {max(r['rotation_deg'] for r in reg.values()):.2f} "
                       f"deg and {reg[worst]['translation_mm']:.1f} mm ({worst})")
        out += self._surface_lines()
        for c in self.cameras:
            d, e, k = m['mapper_error'].get(c), m['export_error'].get(c), m['texture'].get(c, {})
            if d and e:
                out.append(f'{c}: D vs E\'s reference on held-out pixels RMS {d["rms_levels"]:.2f} levels; live LUT '
                           f'vs D mean {e["mean_levels"]:.2f}, p99 {e["p99_levels"]:.0f}, max {e["max_levels"]:.0f} '
                           f'levels; texture kept: L* spread {k.get("lightness_kept", 0):.0%}, chroma '
                           + (f'{k["chroma_kept"]:.0%}' if 'chroma_kept' in k else '-'))
        for c in self.cameras:
            k = m['texture'].get(c, {})
            if min(k.get('lightness_kept', 1.0), k.get('chroma_kept', 1.0)) < TEXTURE_KEPT:
                out.append(f'WARNING: {c}: D keeps {k["lightness_kept"]:.0%} of the lightness spread and '
                           f'{k.get("chroma_kept", 1.0):.0%} of the saturated chroma the reference gives its pixels: '
                           'it is flattening texture (is E converged? see field_error in the manifest)')
        out.append(f'wrote {self.out_dir}/ (manifest.json, field.pt, <camera>.mapper.pt, <camera>.lut.npz, '
                   f'training.png) in {m["seconds"]["total"]:.0f} s')
        return out

    def _surface_lines(self) -> list[str]:
        s = surface_summary(self.manifest)
        if s['kept'] is None:
            return []
        kept = s['kept_per_camera']
        out = [f"training pixels on the {s['source']} surface: {s['kept']:.0%} of them kept (fewest: "
               f"{min(kept, key=kept.get)} {min(kept.values()):.0%}), the views' own depth "
               + ('-' if s['median_difference_mm'] is None else f"{s['median_difference_mm']:.1f} mm")
               + f" from it at the median, {s['seconds']:.0f} s"]
        out += [f'WARNING: {c}: only {k:.0%} of its pixels with depth lie on the surface the views fuse to: is its '
                'pose (the calibration) right?' for c, k in kept.items() if k < SURFACE_KEPT]
        return out


def surface_summary(manifest: dict) -> dict:
    """Where a harmonisation's training pixels lay (its manifest's ``surface``): the source; the
    share of the views' pixels with depth kept, per camera and on average, and the median
    distance of the views' own depth from the surface (None with each view's own depth); the
    seconds it took."""
    surface = manifest.get('surface') or {}
    views = [v for s in surface.get('frame_sets', []) for v in s.get('views', [])]
    kept = {c: float(np.mean([v['kept'] for v in views if v['view'] == c])) for c in dict.fromkeys(
        v['view'] for v in views)}
    apart = [v['median_difference_mm'] for v in views if v.get('median_difference_mm') is not None]
    return {'source': surface.get('source'), 'kept_per_camera': kept,
            'kept': float(np.mean(list(kept.values()))) if kept else None,
            'median_difference_mm': float(np.median(apart)) if apart else None,
            'seconds': float(sum(s.get('seconds', 0.0) for s in surface.get('frame_sets', [])))}


def run(sets: list[list[View]], cameras: list[str], cfg: HarmoniseConfig, out_dir: str | Path,
        train_sets: str = 'even', resume: bool = False, progress: bool = True, sources: dict | None = None,
        views_seconds: float = 0.0, chart_models: dict | None = None, surface: Surface | None = None
        ) -> HarmoniseReport:
    """`volcap harmonise` on views of capture frame sets: train (on the 1st, 3rd, ... set with
    ``train_sets='even'``, the sets the colour evaluation fits on, so it scores D on sets it never
    saw; or on all), export the live form checked on the other sets, write the manifest (with
    ``sources``, e.g. the bag and calibration) and the training figure. ``chart_models``:
    ``chart_models(calibration)``; ``surface``: see ``harmonise`` (the pipeline's
    ``volcap_pipeline.harmonise.run`` gives the fused surface)."""
    if train_sets not in ('even', 'all'):
        raise BadInput(f"train_sets must be 'even' or 'all', got {train_sets!r}")
    cfg.validate()
    trained, checked = split_frame_sets(len(sets)) if train_sets == 'even' else (list(range(len(sets))),) * 2
    t1 = time.perf_counter()
    harm = harmonise([sets[i] for i in trained], cameras, cfg, out_dir, resume=resume, progress=progress,
                     chart_models=chart_models, surface=surface)
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
