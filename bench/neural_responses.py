"""E's camera responses against the hidden ones of ``volcap eval color-frames``' distorted views
(issue 29): where the neural method's distance to the truth comes from.

For a ``bench/neural.py`` output folder: every camera's response as E learnt it, over a grey
ramp of the latent colour at the image centre, inverted through the camera's hidden response
(``ColorResponse.true_colors``, the ideal camera's colour). Were E's responses exact, every
camera would give the same colour for the same latent colour; the difference of each camera
from the mean over the cameras is its response error (what D, inverting E's response, carries
into the harmonised colours), per channel in levels: RMS and mean over the ramp.

    python bench/neural_responses.py [--out bench_out/neural] [--seed 0]
"""
import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from volcap_color.neural_models import load_harmonisation
from volcap_studio.render import ColorResponse

RAMP = np.linspace(0.02, 0.8, 40)       # latent (linear) grey levels, within the scene's gamut


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--out', default='bench_out/neural')
    p.add_argument('--seed', type=int, default=0)
    args = p.parse_args()
    out = Path(args.out)
    harm = load_harmonisation(out / f'frames_seed{args.seed}')
    report = json.loads((out / f'frames_seed{args.seed}.json').read_text())
    hidden = {c: ColorResponse.from_dict(v) for c, v in report['responses'].items()}
    size = (640, 480)                    # rgbd_box's images
    centre = np.tile([[(size[0] - 1) / 2, (size[1] - 1) / 2]], (len(RAMP), 1))
    latent = torch.as_tensor(np.repeat(RAMP[:, None], 3, 1), dtype=torch.float32)
    field, true = harm.field, {}
    for c in harm.cameras:
        k = field.camera_index(torch.as_tensor(harm.centres[c][None])).expand(len(RAMP))
        with torch.no_grad():
            recorded = field.response(latent, k, torch.full((len(RAMP), 2), 0.5)).numpy()
        true[c] = hidden[c].true_colors(recorded, centre, size)
    mean = np.mean(list(true.values()), axis=0)
    spread = np.sqrt(np.mean([(t - mean) ** 2 for t in true.values()])) * 255
    print(f'seed {args.seed}: E\'s responses inverted through the hidden ones, RMS over every camera from their '
          f'mean {spread:.2f} levels (0 for exact responses)')
    for c, t in true.items():
        d = (t - mean) * 255
        print(f'{c} (hidden gamma {hidden[c].gamma:.2f}, gain {hidden[c].gain:.2f}): RMS '
              f'{np.round(np.sqrt((d ** 2).mean(0)), 1)}, mean {np.round(d.mean(0), 1)} levels (R, G, B)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
