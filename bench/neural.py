"""Neural colour harmonisation timings (paper 001) at rig sizes, each against the bare torch call
measured in the same run:

- training: ``volcap harmonise`` with its defaults on 8 cameras (or a models folder it wrote,
  with ``--models``): time per step of E and of D against one bare torch step of the same
  network on the same batch, and the time to convergence (the first epoch whose loss is within
  5 % of the final loss above the floor the last epochs reach);
- live form per 1280x720 frame: ``ImageCorrector`` on a camera's region LUT, against running
  its network D on every pixel with torch (the paper's way of regenerating an image) and
  against the plain 33^3 3D LUT of the colour stage.

    python bench/neural.py BAG CALIBRATION [--frames 6] [--out bench_out/neural] [--models DIR]
"""
import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from color_stage import median_ms  # bench/ is on the path when run as a script

from volcap_color.apply import ImageCorrector, RegionLut
from volcap_color.neural_models import load_harmonisation
from volcap_color.neural_nets import CaptureMapper, ColorField
from volcap_color.neural_train import use_bf16
from volcap_core import transport
from volcap_core.color import ColorModel


def bare_step_ms(model, inputs, target, bf16: bool) -> float:
    """One plain Adam step of ``model`` on the whole batch: the raw library cost."""
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)

    def step():
        with torch.autocast('cpu', dtype=torch.bfloat16, enabled=bf16):
            out = model(*inputs)
        loss = torch.mean((out.float() - target) ** 2)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return median_ms(step, repeat=10)


def converged_epoch(losses: list[float], tolerance: float = 0.05) -> int:
    floor = min(losses[-max(3, len(losses) // 10):])
    start = losses[0] - floor
    for i, v in enumerate(losses):
        if v - floor <= tolerance * start:
            return i + 1
    return len(losses)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('bag')
    p.add_argument('calibration')
    p.add_argument('--frames', type=int, default=6)
    p.add_argument('--out', default='bench_out/neural')
    p.add_argument('--models', help='a volcap harmonise output to time instead of training one')
    args = p.parse_args()
    transport.configure()
    models = Path(args.models or args.out)
    if not args.models:
        from volcap_bringup.cli import main as volcap
        t0 = time.perf_counter()
        volcap(['harmonise', args.bag, '--calibration', args.calibration, '--out', str(models),
                '--frames', str(args.frames)])
        print(f'volcap harmonise (defaults) wall time: {time.perf_counter() - t0:.0f} s')
    harm = load_harmonisation(models)
    manifest = harm.report
    cfg = harm.config
    bf16 = use_bf16(cfg.precision, torch.device('cpu'))
    result = {'models': str(models), 'threads': torch.get_num_threads(), 'bf16': bf16}

    field = manifest['field']
    e_step = field['seconds'] / field['steps'] * 1e3
    n = cfg.field_batch
    bare_e = ColorField(np.zeros(3), np.ones(3), np.zeros(3), np.ones(3), cfg.field_width, cfg.point_frequencies,
                        cfg.camera_frequencies)
    e_bare = bare_step_ms(bare_e, (torch.rand(n, 3), torch.rand(n, 3)), torch.rand(n, 3), bf16)
    conv = converged_epoch(field['losses'])
    result['field'] = {'samples': manifest['field_samples'], 'epochs': len(field['losses']), 'steps': field['steps'],
                       'seconds': field['seconds'], 'step_ms': e_step, 'bare_step_ms': e_bare,
                       'converged_epoch': conv, 'seconds_to_converge': field['seconds'] * conv / len(field['losses']),
                       'final_rms_levels': 255 * field['losses'][-1] ** 0.5}
    d_seconds = sum(r['seconds'] for r in manifest['mappers'].values())
    d_steps = sum(r['steps'] for r in manifest['mappers'].values())
    m = cfg.mapper_batch
    d_bare = bare_step_ms(CaptureMapper(cfg.mapper_width, cfg.mapper_layers), (torch.rand(m, 3), torch.rand(m, 2)),
                          torch.rand(m, 3), bf16)
    result['mappers'] = {'cameras': len(manifest['mappers']), 'seconds': d_seconds,
                         'step_ms': d_seconds / d_steps * 1e3, 'bare_step_ms': d_bare}
    result['harmonise_seconds'] = manifest.get('seconds')
    print(f"E: {result['field']['samples']} samples x {result['field']['epochs']} epochs, {field['seconds']:.0f} s; "
          f"{e_step:.1f} ms per step vs bare torch step {e_bare:.1f} ms ({e_step / e_bare:.2f}x); "
          f"converged (within 5 %) at epoch {conv}, {result['field']['seconds_to_converge']:.0f} s; "
          f"final RMS {result['field']['final_rms_levels']:.2f} levels")
    print(f"D: {len(manifest['mappers'])} cameras, {d_seconds:.0f} s; {result['mappers']['step_ms']:.2f} ms per step "
          f"vs bare {d_bare:.2f} ms ({result['mappers']['step_ms'] / d_bare:.2f}x)")
    if manifest.get('seconds'):
        s = manifest['seconds']
        print(f"harmonise total {s['total']:.0f} s: views {s['views']:.0f}, training {s['training']:.0f}, "
              f"export {s['export']:.0f}")

    image = np.random.default_rng(0).integers(0, 256, (720, 1280, 3), dtype=np.uint8)
    cam = harm.cameras[0]
    lut = RegionLut.load(models / f'{cam}.lut.npz')
    live = ImageCorrector(lut)
    out = live(image)
    live_ms = median_ms(lambda: live(image, out), repeat=30)
    plain = ImageCorrector(ColorModel('root_polynomial_2', np.hstack([np.eye(3) * 1.05, np.full((3, 3), 0.02)])))
    plain_ms = median_ms(lambda: plain(image, out), repeat=30)
    ys, xs = np.mgrid[0:720, 0:1280]
    xy = np.stack([(xs.reshape(-1) + 0.5) / 1280, (ys.reshape(-1) + 0.5) / 720], axis=1)
    net_ms = median_ms(lambda: harm.map_colors(cam, image.reshape(-1, 3) / 255.0, xy), repeat=3)
    n_nodes, (nx, ny) = lut.table.shape[0], lut.grid
    result['live'] = {'region_lut_ms': live_ms, 'plain_3d_lut_ms': plain_ms, 'torch_network_ms': net_ms,
                      'lut': f'{n_nodes}^3 x {nx}x{ny}', 'export_error': manifest.get('export_error', {}).get(cam)}
    print(f'live form {n_nodes}^3 x {nx}x{ny} region LUT on 1280x720: {live_ms:.1f} ms; torch D on every pixel '
          f'{net_ms:.0f} ms ({net_ms / live_ms:.0f}x slower); plain 33^3 3D LUT {plain_ms:.1f} ms '
          f'({live_ms / plain_ms:.2f}x)')
    out_json = Path(args.out) / 'bench_neural.json'
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(result, indent=2))
    print(f'wrote {out_json}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
