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

Surface points come from the cleaned depth registered to colour (``evaluate.capture_views``).
Each D also sees some pixels the cleaning removed (the room), aimed at the camera's affine map
onto the reference (``background``, ours), so its output there is not arbitrary. Defaults are
the authors' published settings (DESIGN.md) except the sample counts, which bound training time
on a CPU, and our ``mean`` reference and background samples. Training is deterministic for a seed on one device and
precision; after every epoch a checkpoint is written atomically and ``resume`` carries on from
it.
"""
from __future__ import annotations

import io
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from volcap_core.errors import BadInput
from volcap_core.files import atomic_write, write_json

from .apply import ImageCorrector, RegionLut, pixel_centres
from .config import HarmoniseConfig
from .correspondence import View, split_frame_sets
from .figures import training_figure

CHECKPOINT = 'checkpoint.pt'
FIELD_FILE = 'field.pt'
MANIFEST = 'manifest.json'
HELD_OUT = 20_000        # at most this many pixels per camera are kept from D's training to check it


def positional_encoding(v: torch.Tensor, frequencies: int) -> torch.Tensor:
    """gamma(v) = (v, sin(2^0 pi v), cos(2^0 pi v), ..., sin(2^(L-1) pi v), cos(2^(L-1) pi v))."""
    scales = (2.0 ** torch.arange(frequencies, device=v.device, dtype=v.dtype)) * math.pi
    x = (v[..., None] * scales).flatten(-2)
    return torch.cat([v, torch.sin(x), torch.cos(x)], dim=-1)


class ColorField(nn.Module):
    """E: (world point, world camera centre) -> sRGB in [0, 1]."""

    def __init__(self, point_mean, point_std, camera_mean, camera_std, width: int = 256,
                 point_frequencies: int = 10, camera_frequencies: int = 4):
        super().__init__()
        for name, v in (('point_mean', point_mean), ('point_std', point_std), ('camera_mean', camera_mean),
                        ('camera_std', camera_std)):
            self.register_buffer(name, torch.as_tensor(np.asarray(v, np.float32)))
        self.point_frequencies, self.camera_frequencies = point_frequencies, camera_frequencies
        p_dim, c_dim = 3 + 6 * point_frequencies, 3 + 6 * camera_frequencies
        self.trunk = nn.ModuleList([nn.Linear(p_dim, width)] + [nn.Linear(width, width) for _ in range(3)])
        self.skip = nn.ModuleList([nn.Linear(width + p_dim, width)] + [nn.Linear(width, width) for _ in range(3)])
        self.feature = nn.Linear(width, width)
        self.view = nn.Linear(width + c_dim, width // 2)
        self.rgb = nn.Linear(width // 2, 3)

    def forward(self, points: torch.Tensor, cameras: torch.Tensor) -> torch.Tensor:
        p = positional_encoding((points - self.point_mean) / self.point_std, self.point_frequencies)
        c = positional_encoding((cameras - self.camera_mean) / self.camera_std, self.camera_frequencies)
        h = p
        for layer in self.trunk:
            h = torch.relu(layer(h))
        h = torch.cat([h, p], dim=-1)
        for layer in self.skip:
            h = torch.relu(layer(h))
        h = torch.cat([self.feature(h), c], dim=-1)
        return torch.sigmoid(self.rgb(torch.relu(self.view(h))))


class CaptureMapper(nn.Module):
    """D: (sRGB in [0, 1], pixel x y in [0, 1]) -> harmonised sRGB in [0, 1]."""

    def __init__(self, width: int = 128, layers: int = 8):
        super().__init__()
        sizes = [5] + [width] * layers
        self.hidden = nn.ModuleList([nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:])])
        self.rgb = nn.Linear(width, 3)

    def forward(self, rgb: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
        h = torch.cat([rgb, xy], dim=-1)
        for layer in self.hidden:
            h = torch.relu(layer(h))
        return torch.sigmoid(self.rgb(h))


# --- training data ------------------------------------------------------------------------------
@dataclass
class SurfaceSamples:
    """Pixels with a surface point, from one or more views."""
    points: np.ndarray      # (N, 3) float32 world
    centres: np.ndarray     # (N, 3) float32 world position of the camera that saw it
    colors: np.ndarray     # (N, 3) float32 sRGB [0, 1]
    xy: np.ndarray          # (N, 2) float32 pixel centre / image size (``apply.pixel_centres``)

    def __len__(self) -> int:
        return len(self.points)

    def select(self, keep: np.ndarray) -> SurfaceSamples:
        return SurfaceSamples(*(getattr(self, k)[keep] for k in ('points', 'centres', 'colors', 'xy')))


def view_samples(view: View, count: int | None, rng: np.random.Generator) -> SurfaceSamples:
    """Up to ``count`` random pixels of ``view`` with depth (all of them for None)."""
    h, w = view.depth.shape
    valid = np.flatnonzero(view.depth.reshape(-1) > 0)
    if count is not None and len(valid) > count:
        valid = np.sort(rng.choice(valid, count, replace=False))
    y, x = np.divmod(valid, w)
    local = view.rays().reshape(-1, 3)[valid] * view.depth.reshape(-1)[valid, None]
    T = view.T_world_camera
    points = (local @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
    return SurfaceSamples(points, np.broadcast_to(T[:3, 3].astype(np.float32), points.shape).copy(),
                          view.color.reshape(-1, 3)[valid].astype(np.float32) / 255.0, pixel_centres(x, y, w, h))


def concat_samples(parts: list[SurfaceSamples]) -> SurfaceSamples:
    return SurfaceSamples(*(np.concatenate([getattr(p, k) for p in parts]) for k in
                            ('points', 'centres', 'colors', 'xy')))


def training_samples(sets: list[list[View]], cameras: list[str], total: int | None, seed: int) -> SurfaceSamples:
    """About ``total`` samples shared evenly by every view of every frame set (all for None)."""
    rng = np.random.default_rng(seed)
    views = [v for views in sets for v in views if v.name in cameras]
    if not views:
        raise BadInput('no view of the calibrated cameras to train on')
    share = None if total is None else max(1, total // len(views))
    samples = concat_samples([view_samples(v, share, rng) for v in views])
    if not len(samples):
        raise BadInput('the training views have no pixel with depth: is the subject in view and the clean plate '
                         'learnt?')
    return samples


# --- devices and the training loop --------------------------------------------------------------
def torch_device(name: str) -> torch.device:
    if name == 'auto':
        return torch.device('cuda' if torch.cuda.is_available() else 'cpu')
    if name == 'cuda' and not torch.cuda.is_available():
        raise BadInput('--device cuda: torch sees no CUDA device')
    return torch.device(name)


def cpu_has_bf16() -> bool:
    """Whether this CPU computes bf16 natively (AVX512-BF16 or AMX); elsewhere autocast emulates it slowly."""
    try:
        flags = Path('/proc/cpuinfo').read_text()
    except OSError:
        return False
    return 'avx512_bf16' in flags or 'amx_bf16' in flags


def use_bf16(precision: str, device: torch.device) -> bool:
    if precision not in ('auto', 'bf16', 'fp32'):
        raise BadInput(f'precision must be auto, bf16 or fp32, not {precision!r}')
    if precision != 'auto':
        return precision == 'bf16'
    return torch.cuda.is_bf16_supported() if device.type == 'cuda' else cpu_has_bf16()


@dataclass
class TrainResult:
    losses: list[float] = field(default_factory=list)      # mean MSE per epoch
    seconds: float = 0.0
    steps: int = 0


def _save_atomic(obj, path: Path) -> None:
    buf = io.BytesIO()
    torch.save(obj, buf)
    atomic_write(path, lambda f: f.write(buf.getvalue()))


def train(model: nn.Module, inputs: tuple[torch.Tensor, ...], target: torch.Tensor, *, epochs: int, batch: int,
          lr: float, seed: int, bf16: bool, label: str, lr_final: float | None = None,
          checkpoint: Path | None = None, settings: dict | None = None, progress: bool = True) -> TrainResult:
    """Adam on the MSE of ``model(*inputs)`` against ``target``, shuffled afresh each epoch from
    ``seed``; the learning rate decays exponentially from ``lr`` to ``lr_final`` over the epochs
    (constant for None). With ``checkpoint``, the state after each epoch is saved there under
    ``label`` with ``settings``, and a checkpoint of the same label is resumed from (a clear error
    if its settings differ)."""
    device = target.device
    optimiser = torch.optim.Adam(model.parameters(), lr=lr)
    gamma = (lr_final / lr) ** (1.0 / max(epochs, 1)) if lr_final else 1.0
    schedule = torch.optim.lr_scheduler.ExponentialLR(optimiser, gamma)
    result, start = TrainResult(), 0
    if checkpoint is not None and checkpoint.exists():
        state = torch.load(checkpoint, map_location=device, weights_only=False)
        if state['label'] == label:
            if state.get('settings') != settings:
                raise BadInput(f'--resume: {checkpoint} ({label}) was trained with other settings; use a new --out '
                                 'or leave out --resume')
            model.load_state_dict(state['model'])
            optimiser.load_state_dict(state['optimiser'])
            schedule.load_state_dict(state['schedule'])
            result = TrainResult(state['losses'], state['seconds'], state['steps'])
            start = len(result.losses)
    n = len(target)
    steps_per_epoch = max(1, math.ceil(n / batch))
    bar = tqdm(total=epochs * steps_per_epoch, initial=start * steps_per_epoch, desc=label, unit='step',
               disable=not progress, dynamic_ncols=True)
    model.train()
    for epoch in range(start, epochs):
        t0 = time.perf_counter()
        order = torch.randperm(n, generator=torch.Generator().manual_seed(seed * 100_003 + epoch)).to(device)
        total = torch.zeros((), device=device)    # summed on the device: no sync per step on CUDA
        for s in range(steps_per_epoch):
            idx = order[s * batch:(s + 1) * batch]
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
                out = model(*(x[idx] for x in inputs))
            loss = torch.mean((out.float() - target[idx]) ** 2)
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            total += loss.detach() * len(idx)
            bar.update()
            if s % 20 == 0:
                bar.set_postfix(epoch=epoch + 1, loss=f"{float(loss.detach()):.2e}")
        schedule.step()
        result.losses.append(float(total) / n)
        result.seconds += time.perf_counter() - t0
        result.steps += steps_per_epoch
        if checkpoint is not None:
            _save_atomic({'label': label, 'model': model.state_dict(), 'optimiser': optimiser.state_dict(),
                          'schedule': schedule.state_dict(), 'settings': settings, **asdict(result)}, checkpoint)
    bar.close()
    model.eval()
    return result


@torch.no_grad()
def predict(model: nn.Module, inputs: tuple[torch.Tensor, ...], bf16: bool, chunk: int = 65536) -> torch.Tensor:
    """``model(*inputs)`` in chunks, as float32."""
    device = inputs[0].device
    out = []
    for s in range(0, len(inputs[0]), chunk):
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
            out.append(model(*(x[s:s + chunk] for x in inputs)).float())
    return torch.cat(out) if out else torch.zeros((0, 3), device=device)


def reference_color(field_model: ColorField, points: torch.Tensor, centres: np.ndarray, bf16: bool
                     ) -> torch.Tensor:
    """E's colour of ``points`` as seen from each of ``centres`` (one row: that camera), averaged."""
    total = torch.zeros((len(points), 3), device=points.device)
    for c in centres:
        cam = torch.as_tensor(np.asarray(c, np.float32), device=points.device).expand(len(points), 3)
        total += predict(field_model, (points, cam), bf16)
    return total / len(centres)


# --- the whole job -------------------------------------------------------------------------------
@dataclass
class Harmonisation:
    """What ``harmonise`` trained: E, one D per camera and the reference they map to."""
    cameras: list[str]
    centres: dict[str, np.ndarray]
    field: ColorField
    mappers: dict[str, CaptureMapper]
    reference: str
    config: HarmoniseConfig
    device: torch.device
    bf16: bool
    report: dict

    def reference_centres(self) -> np.ndarray:
        names = self.cameras if self.reference == 'mean' else [self.reference]
        return np.stack([self.centres[c] for c in names])

    def map_colors(self, camera: str, rgb: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """D of ``camera`` on sRGB (N, 3) in [0, 1] at normalised pixel positions (N, 2)."""
        t = lambda a: torch.as_tensor(np.asarray(a, np.float32), device=self.device)
        return predict(self.mappers[camera], (t(rgb), t(xy)), self.bf16).cpu().numpy().astype(np.float64)


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


def load_harmonisation(models_dir: str | Path, device: str = 'cpu') -> Harmonisation:
    """The networks ``harmonise`` wrote into ``models_dir`` (with its manifest)."""
    models_dir = Path(models_dir)
    manifest_path = models_dir / MANIFEST
    if not manifest_path.exists():
        raise FileNotFoundError(f'{models_dir} has no {MANIFEST}: not a volcap harmonise output')
    manifest = json.loads(manifest_path.read_text())
    # folders written before identifiers were spelt "color" say lut_colours
    cfg_dict = {k.replace('colour', 'color'): v for k, v in manifest['config'].items()}
    cfg_dict['lut_grid'] = tuple(cfg_dict['lut_grid'])
    cfg = HarmoniseConfig(**cfg_dict)
    dev = torch_device(device)
    state = torch.load(models_dir / FIELD_FILE, map_location=dev, weights_only=False)['state']
    field_model = ColorField(state['point_mean'], state['point_std'], state['camera_mean'], state['camera_std'],
                             cfg.field_width, cfg.point_frequencies, cfg.camera_frequencies).to(dev)
    field_model.load_state_dict(state)
    field_model.eval()
    mappers = {}
    for cam in manifest['cameras']:
        m = CaptureMapper(cfg.mapper_width, cfg.mapper_layers).to(dev)
        m.load_state_dict(torch.load(models_dir / f'{cam}.mapper.pt', map_location=dev, weights_only=False)['state'])
        m.eval()
        mappers[cam] = m
    centres = {c: np.asarray(v, np.float32) for c, v in manifest['centres'].items()}
    return Harmonisation(manifest['cameras'], centres, field_model, mappers, manifest['reference'], cfg, dev,
                         use_bf16(cfg.precision, dev), manifest)


# --- the live form -------------------------------------------------------------------------------
def bake_region_lut(harm: Harmonisation, camera: str, colors: int | None = None,
                    grid: tuple[int, int] | None = None) -> RegionLut:
    """D of ``camera`` sampled on ``colours``^3 colour nodes at each of ``grid`` (nx, ny) image
    nodes: what ``color_corrector`` applies at frame rate."""
    n = colors or harm.config.lut_colors
    nx, ny = grid or harm.config.lut_grid
    axis = np.linspace(0.0, 1.0, n, dtype=np.float32)
    rgb = np.stack(np.meshgrid(axis, axis, axis, indexing='ij'), axis=-1).reshape(-1, 1, 3)
    yx = np.stack(np.meshgrid(np.linspace(0, 1, ny, dtype=np.float32), np.linspace(0, 1, nx, dtype=np.float32),
                              indexing='ij'), axis=-1).reshape(1, -1, 2)
    rgb_all = np.broadcast_to(rgb, (n ** 3, nx * ny, 3)).reshape(-1, 3)
    xy_all = np.broadcast_to(yx[..., ::-1], (n ** 3, nx * ny, 2)).reshape(-1, 2)
    mapped = harm.map_colors(camera, rgb_all, xy_all)
    return RegionLut((mapped * 255.0).astype(np.float32).reshape(n, n, n, ny, nx, 3))


def export_error(harm: Harmonisation, camera: str, lut: RegionLut, images: list[np.ndarray]) -> dict:
    """The live form against D itself on every pixel of ``images`` (uint8 RGB), both as 8-bit
    images: mean, 99th percentile and maximum absolute difference in levels."""
    diffs = []
    corrector = ImageCorrector(lut)
    for img in images:
        h, w = img.shape[:2]
        ys, xs = np.mgrid[0:h, 0:w]
        xy = pixel_centres(xs.reshape(-1), ys.reshape(-1), w, h)
        net = np.round(np.clip(harm.map_colors(camera, img.reshape(-1, 3) / 255.0, xy), 0, 1) * 255.0)
        diffs.append(np.abs(corrector(img).reshape(-1, 3).astype(np.float64) - net).reshape(-1))
    d = np.concatenate(diffs)
    return {'mean_levels': float(d.mean()), 'p99_levels': float(np.percentile(d, 99)), 'max_levels': float(d.max()),
            'pixels': int(d.size // 3)}


def _mapper_error(field_model: ColorField, mapper: CaptureMapper, samples: SurfaceSamples, ref_centres: np.ndarray,
                  bf16: bool) -> dict:
    """D against E's reference colour on ``samples`` (pixels D was not trained on): RMS and 99th
    percentile of the difference, in levels."""
    device = next(mapper.parameters()).device
    t = lambda a: torch.as_tensor(a, device=device)
    target = reference_color(field_model, t(samples.points), ref_centres, bf16)
    d = (predict(mapper, (t(samples.colors), t(samples.xy)), bf16) - target).cpu().numpy() * 255.0
    return {'rms_levels': float(np.sqrt(np.mean(d ** 2))), 'p99_levels': float(np.percentile(np.abs(d), 99)),
            'pixels': len(samples)}


def export_live(harm: Harmonisation, out_dir: str | Path, check_views: list[View], progress: bool = True) -> dict:
    """Bake every camera's D into ``<camera>.lut.npz`` and measure the LUT against D on every
    pixel of ``check_views`` (frame sets not trained on, where there are any)."""
    out_dir = Path(out_dir)
    errors = {}
    for cam in tqdm(harm.cameras, desc='live form (region LUTs)', unit='camera', disable=not progress):
        lut = bake_region_lut(harm, cam)
        lut.save(out_dir / f'{cam}.lut.npz', camera=cam, reference=harm.reference)
        mine = [v.color for v in check_views if v.name == cam]
        if mine:
            errors[cam] = export_error(harm, cam, lut, mine)
    return {'export_error': errors}


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
