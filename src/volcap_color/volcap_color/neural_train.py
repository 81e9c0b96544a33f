"""Training the networks: the device and precision (bf16 autocast where the device computes it
natively), the deterministic, checkpointed training loop, and chunked prediction."""
from __future__ import annotations

import io
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from volcap_core.color import LUMINANCE, linear_to_srgb, srgb_to_linear
from volcap_core.errors import BadInput
from volcap_core.files import atomic_write


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
          checkpoint: Path | None = None, settings: dict | None = None, progress: bool = True,
          weights: torch.Tensor | None = None, robust: float = 0.0) -> TrainResult:
    """Adam on the MSE of ``model(*inputs)`` against ``target`` (weighted per sample by
    ``weights``, mean 1, where given; with ``robust`` > 0 the Cauchy loss
    robust^2 log(1 + (r / robust)^2) of each residual r instead of r^2), shuffled afresh each epoch from
    ``seed``; the learning rate decays exponentially from ``lr`` to ``lr_final`` over the epochs
    (constant for None). With ``checkpoint``, the state after each epoch is saved there under
    ``label`` with ``settings``, and a checkpoint of the same label is resumed from (a clear error
    if its settings differ)."""
    device = target.device
    groups = model.optimiser_groups() if hasattr(model, 'optimiser_groups') else [{'params': list(model.parameters())}]
    for g in groups:        # a group may ask for a multiple of the learning rate
        if 'lr_scale' in g:
            g['lr'] = lr * g.pop('lr_scale')
    optimiser = torch.optim.Adam(groups, lr=lr)
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
            sq = (out.float() - target[idx]) ** 2
            if robust > 0:
                sq = robust ** 2 * torch.log1p(sq / robust ** 2)
            loss = torch.mean(sq if weights is None else sq * weights[idx, None])
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


# Where the reference is looked at in every camera's image: the centre, where lenses have no
# fall-off, so vignetting is not part of the reference
CENTRE_XY = (0.5, 0.5)


def field_color(field_model: nn.Module, points: torch.Tensor, centre, bf16: bool, xy: torch.Tensor | None = None
                ) -> torch.Tensor:
    """E's colour of ``points`` as the camera at ``centre`` records them at ``xy`` (default: the image centre)."""
    cam = torch.as_tensor(np.asarray(centre, np.float32), device=points.device).expand(len(points), 3)
    if xy is None:
        xy = torch.as_tensor(CENTRE_XY, dtype=torch.float32, device=points.device).expand(len(points), 2)
    return predict(field_model, (points, cam, xy), bf16)


class _Call(nn.Module):
    """A function as a module, for ``predict``'s chunking."""

    def __init__(self, fn):
        super().__init__()
        self.fn = fn

    def forward(self, *args):
        return self.fn(*args)


@dataclass
class Reference:
    """The colour every D maps its camera onto: E's colour of the point as each of ``centres``
    records it at its image centre, averaged; with ``chart_models`` (one per centre, sRGB ->
    chart-corrected sRGB) each camera's view is corrected by its chart model first (absolute
    colour); with ``gains`` a white balance in linear light is applied to the average.
    ``unmixed``: each camera's view without the channel crosstalk its chart measured (a
    ``HashGridField``'s responses hold it), so that the average has none of the cameras' mixing."""
    field_model: nn.Module
    centres: np.ndarray
    bf16: bool
    chart_models: list | None = None
    gains: np.ndarray | None = None
    matrix: np.ndarray | None = None       # (3, 3) applied to the average in linear light
    unmixed: bool = False

    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        return self._combine(self._views(points), points.device)

    def from_surface_color(self, latent: torch.Tensor) -> torch.Tensor:
        """The reference of linear surface colours ``latent`` (a ``HashGridField``'s shared field)."""
        return self._combine(self._recorded(latent), latent.device)

    def _combine(self, views: list[torch.Tensor], device: torch.device) -> torch.Tensor:
        total = torch.zeros((len(views[0]), 3), device=device)
        for i, rgb in enumerate(views):
            if self.chart_models is not None:
                rgb = torch.as_tensor(self.chart_models[i].apply(rgb.cpu().numpy()).astype(np.float32),
                                      device=device)
            total += rgb
        mean = total / len(self.centres)
        if self.gains is None and self.matrix is None:
            return mean
        balanced = srgb_to_linear(mean.cpu().numpy())
        if self.matrix is not None:
            balanced = balanced @ self.matrix.T
        if self.gains is not None:
            balanced = balanced * self.gains
        balanced = np.clip(balanced, 0.0, 1.0)
        return torch.as_tensor(linear_to_srgb(balanced).astype(np.float32), device=device)

    def _views(self, points: torch.Tensor):
        """E's colour of ``points`` as each reference camera records it at its image centre; a
        field with a shared surface colour (``HashGridField``) computes it once for all cameras."""
        surface = getattr(self.field_model, 'surface_color', None)
        if surface is None:
            return [field_color(self.field_model, points, c, self.bf16) for c in self.centres]
        return self._recorded(predict(_Call(surface), (points,), self.bf16))

    def _recorded(self, latent: torch.Tensor, unmixed: bool | None = None) -> list[torch.Tensor]:
        model = self.field_model
        mixed = not (self.unmixed if unmixed is None else unmixed)
        xy = torch.as_tensor(CENTRE_XY, dtype=torch.float32, device=latent.device).expand(len(latent), 2)
        out = []
        for c in self.centres:
            cam = torch.as_tensor(np.asarray(c, np.float32), device=latent.device).expand(len(latent), 3)
            out.append(predict(_Call(lambda a, k: model.response(a, model.camera_index(k), xy[:len(a)], mixed)),
                               (latent, cam), self.bf16))
        return out


def chart_anchor_matrix(reference: Reference, chart_models: list, points: torch.Tensor, form: str = 'gains'
                        ) -> np.ndarray:
    """The matrix in linear light that takes ``reference``'s average camera closest to the
    average of the same cameras each corrected by its chart model, over ``points`` (least
    squares; colours clipped in either left out): ``form`` ``matrix_3x3``, a full 3x3, or
    ``gains``, one gain per channel that takes grey where that 3x3 does (a diagonal matrix: the
    charts' white balance and exposure). The reference anchored this way is absolute colour,
    as the charts say, and the charts' own per-camera fitting error (each model a few patches
    under the studio's lights) stays out of it: averaging eight charts' corrections put that
    error into the reference's every colour differently (the synthetic studio, seed 7: the
    neural method 1.48 CIEDE2000 from the truth that way, docs/benchmarks.md).

    Gains by default: a chart's patches under the studio's mixed lights and the board's sheen
    read less saturated than their reference, and the chart models' matrices saturate every
    colour to make up for it. A full 3x3 carried that into the reference: on studio seeds 7 /
    0 / 3 / 11 the neural method's saturated chroma 5-11 % above the truth's (4-8 % with the
    gains), 0.94 CIEDE2000 from the truth on average under one shared 3x3 (0.92) and 1.41 at
    one shared exposure gain (1.25; docs/benchmarks.md). With gains the reference is
    ``unmixed`` where the charts measured crosstalk: the gains cannot take it out."""
    if form not in ('gains', 'matrix_3x3'):
        raise ValueError(f'unknown chart anchor form {form!r} (gains, matrix_3x3)')
    # the chart models take the cameras' recordings, mixing and all; the average they are fitted
    # from is the reference's own (without the mixing where it is ``unmixed``, which only a
    # ``HashGridField`` can be). E's surface colour is evaluated once for both.
    if reference.unmixed:
        latent = predict(_Call(reference.field_model.surface_color), (points,), reference.bf16)
        recorded, own = reference._recorded(latent, unmixed=False), reference._recorded(latent, unmixed=True)
    else:
        recorded = own = reference._views(points)
    plain, charted = (srgb_to_linear(Reference(reference.field_model, reference.centres, reference.bf16, models)
                                     ._combine(views, points.device).cpu().numpy().astype(np.float64))
                      for views, models in ((own, None), (recorded, chart_models)))
    ok = np.all((plain > 0.002) & (plain < 0.98) & (charted > 0.002) & (charted < 0.98), axis=1)
    if ok.sum() < 100:
        raise BadInput(f'only {int(ok.sum())} surface colours are neither black nor clipped: too few to anchor '
                       'the reference to the charts (use --anchor none or grey_world)')
    matrix = np.linalg.lstsq(plain[ok], charted[ok], rcond=None)[0].T
    if form == 'gains':
        # the gains that take grey where the full fit takes it: least-squares gains per channel
        # would take up part of the saturation too, as the channels of coloured surfaces differ
        matrix = np.diag(matrix.sum(1))
    # the cameras' exposure stays: under the studio's lights a chart reads half as bright as its
    # reference, and a reference twice as bright as every camera clips what they recorded
    # below white (seed 7: 1.54 CIEDE2000 from the truth unscaled)
    luminance = LUMINANCE @ plain[ok].mean(0) / (LUMINANCE @ (plain[ok] @ matrix.T).mean(0))
    return (matrix * luminance).astype(np.float32)


def grey_world_gains(reference: Reference, points: torch.Tensor) -> np.ndarray:
    """Per-channel gains in linear light that make the reference's average over ``points``
    neutral at the same mean level: a cast every camera shares is removed (grey world)."""
    mean = srgb_to_linear(reference(points).cpu().numpy().astype(np.float64)).mean(0)
    return (mean.mean() / np.maximum(mean, 1e-6)).astype(np.float32)
