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

from volcap_core.errors import BadInput
from volcap_core.files import atomic_write

from .neural_nets import ColorField


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
