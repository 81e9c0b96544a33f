"""E's camera responses against the hidden ones of ``volcap eval color-frames``' distorted views
(issue 29): where the neural method's distance to the truth comes from.

For a ``bench/neural.py`` output folder, E's response of every camera at its image centre over
a grey ramp of the latent colour, against the camera's hidden response (``ColorResponse``:
gain, white balance, crosstalk, gamma) after the best transform shared by every camera (a
scale per channel and one power, Nelder-Mead): RMS and mean difference per camera and channel,
in levels.

    python bench/neural_responses.py [--out bench_out/neural] [--seed 0]
"""
import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.optimize import minimize

from volcap_color.neural_models import load_harmonisation
from volcap_studio.render import ColorResponse


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--out', default='bench_out/neural')
    p.add_argument('--seed', type=int, default=0)
    args = p.parse_args()
    out = Path(args.out)
    harm = load_harmonisation(out / f'frames_seed{args.seed}')
    report = json.loads((out / f'frames_seed{args.seed}.json').read_text())
    hidden = {c: ColorResponse.from_dict(v) for c, v in report['responses'].items()}
    field = harm.field
    ramp = torch.linspace(0.02, 0.8, 40)[:, None].repeat(1, 3)
    centre = torch.full((40, 2), 0.5)
    rows = []
    for c in harm.cameras:
        k = int(field.camera_index(torch.as_tensor(harm.centres[c][None]))[0])
        with torch.no_grad():
            recorded = field.response(ramp, torch.full((40,), k), centre).numpy()
        rows.append((c, recorded, hidden[c]))

    def true(r: ColorResponse, radiance: np.ndarray) -> np.ndarray:
        x = (radiance * r.gain * np.asarray(r.white_balance)) @ np.asarray(r.crosstalk).T
        return np.clip(x, 0.0, 1.0) ** (1.0 / r.gamma)

    def shared(v, r):        # the hidden response of the latent ramp under the shared transform
        lat = ramp.numpy() ** v[3]
        return np.stack([true(r, np.outer(v[ch] * lat[:, ch], np.ones(3)))[:, ch] for ch in range(3)], 1)
    fit = minimize(lambda v: np.mean([np.mean((e - shared(v, r)) ** 2) for _, e, r in rows]), [1, 1, 1, 1],
                   method='Nelder-Mead', options={'maxiter': 4000})
    print(f'shared transform: scale per channel {np.round(fit.x[:3], 3)}, power {fit.x[3]:.3f}; '
          f'RMS over every camera {np.sqrt(fit.fun) * 255:.2f} levels')
    for c, e, r in rows:
        d = (e - shared(fit.x, r)) * 255
        print(f'{c} (hidden gamma {r.gamma:.2f}, gain {r.gain:.2f}): RMS {np.round(np.sqrt((d ** 2).mean(0)), 1)}, '
              f'mean {np.round(d.mean(0), 1)} levels (R, G, B)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
