"""The networks of the neural harmonisation in torch: paper 001's colour field E (``ColorField``)
and per-camera mapping D (``CaptureMapper``) with their positional encoding, and our default E,
``HashGridField``: a multi-resolution hash-grid encoding of the surface (Instant-NGP, Müller et
al. 2022) with a small camera-conditioned response head. The layouts are described in
``neural`` and docs/color.md."""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from .config import MAPPER_FORMS

# a view correction's units (rad, m) per unit of its parameter, and its learning rate against
# the field's: steps of 1e-5 rad and 1e-5 m, so over a short run a correction can reach a few
# tenths of a degree and a few millimetres, what calibration and tracking errors are
REGISTRATION_SCALE = 0.01
REGISTRATION_LR_SCALE = 0.1

# Instant-NGP's spatial hash: the coordinates times these primes, xor-ed (the first is 1 so a
# coarse level whose grid fits the table is indexed without collisions along x)
HASH_PRIMES = (1, 2654435761, 805459861)

# a recorded value that rounds to 255: the camera saturated
SATURATED = 1.0 - 0.5 / 255.0


def positional_encoding(v: torch.Tensor, frequencies: int) -> torch.Tensor:
    """gamma(v) = (v, sin(2^0 pi v), cos(2^0 pi v), ..., sin(2^(L-1) pi v), cos(2^(L-1) pi v))."""
    scales = (2.0 ** torch.arange(frequencies, device=v.device, dtype=v.dtype)) * math.pi
    x = (v[..., None] * scales).flatten(-2)
    return torch.cat([v, torch.sin(x), torch.cos(x)], dim=-1)


class _Normalised(nn.Module):
    """The z-score statistics of the training points and camera centres, kept with the weights."""

    def __init__(self, point_mean, point_std, camera_mean, camera_std):
        super().__init__()
        for name, v in (('point_mean', point_mean), ('point_std', point_std), ('camera_mean', camera_mean),
                        ('camera_std', camera_std)):
            self.register_buffer(name, torch.as_tensor(np.asarray(v, np.float32)))

    def camera_code(self, cameras: torch.Tensor, frequencies: int) -> torch.Tensor:
        return positional_encoding((cameras - self.camera_mean) / self.camera_std, frequencies)


class ColorField(_Normalised):
    """Paper 001's E: (world point, world camera centre) -> sRGB in [0, 1]. The pixel position
    ``xy`` is accepted for a common signature and not used."""

    def __init__(self, point_mean, point_std, camera_mean, camera_std, width: int = 256,
                 point_frequencies: int = 10, camera_frequencies: int = 4):
        super().__init__(point_mean, point_std, camera_mean, camera_std)
        self.point_frequencies, self.camera_frequencies = point_frequencies, camera_frequencies
        p_dim, c_dim = 3 + 6 * point_frequencies, 3 + 6 * camera_frequencies
        self.trunk = nn.ModuleList([nn.Linear(p_dim, width)] + [nn.Linear(width, width) for _ in range(3)])
        self.skip = nn.ModuleList([nn.Linear(width + p_dim, width)] + [nn.Linear(width, width) for _ in range(3)])
        self.feature = nn.Linear(width, width)
        self.view = nn.Linear(width + c_dim, width // 2)
        self.rgb = nn.Linear(width // 2, 3)

    def forward(self, points: torch.Tensor, cameras: torch.Tensor, xy: torch.Tensor | None = None) -> torch.Tensor:
        p = positional_encoding((points - self.point_mean) / self.point_std, self.point_frequencies)
        c = self.camera_code(cameras, self.camera_frequencies)
        h = p
        for layer in self.trunk:
            h = torch.relu(layer(h))
        h = torch.cat([h, p], dim=-1)
        for layer in self.skip:
            h = torch.relu(layer(h))
        h = torch.cat([self.feature(h), c], dim=-1)
        return torch.sigmoid(self.rgb(torch.relu(self.view(h))))

    def optimiser_groups(self) -> list[dict]:
        return [{'params': list(self.parameters())}]


class _Gather(torch.autograd.Function):
    """``table[index]`` whose backward scatters with ``index_add_``: on the CPU 5x faster than
    the embedding's own backward (measured: 11 vs 57 ms for 786 432 lookups into 786 432 rows),
    which sorts the indices first."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(index)
        ctx.rows = table.shape[0]
        return table.index_select(0, index.reshape(-1)).reshape(*index.shape, table.shape[1])

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        (index,) = ctx.saved_tensors
        grad = grad.reshape(-1, grad.shape[-1])
        table_grad = torch.zeros((ctx.rows, grad.shape[1]), dtype=grad.dtype, device=grad.device)
        return table_grad.index_add_(0, index.reshape(-1), grad), None


class HashGrid(nn.Module):
    """Multi-resolution hash encoding of points in the unit cube: ``levels`` grids from
    ``coarsest`` to ``finest`` cells per side in a geometric progression, each a table of
    ``2**log2_table`` x ``features`` trainable entries indexed by the spatial hash of a cell
    corner (directly where the level's grid fits the table), trilinearly interpolated; the
    levels' features concatenated. Plain torch: the same code on the CPU and CUDA."""

    def __init__(self, levels: int, log2_table: int, coarsest: int, finest: int, features: int = 2):
        super().__init__()
        growth = math.exp((math.log(finest) - math.log(coarsest)) / max(levels - 1, 1))
        resolution = [int(math.floor(coarsest * growth ** lv)) for lv in range(levels)]
        size = 2 ** log2_table
        self.levels, self.size, self.features = levels, size, features
        self.register_buffer('resolution', torch.tensor(resolution, dtype=torch.float32))
        # a level whose (res + 1)^3 corners fit the table is indexed densely, without collisions
        self.register_buffer('dense', torch.tensor([(r + 1) ** 3 <= size for r in resolution]))
        self.register_buffer('stride', torch.tensor([[1, r + 1, (r + 1) ** 2] if (r + 1) ** 3 <= size
                                                     else list(HASH_PRIMES) for r in resolution], dtype=torch.int64))
        self.register_buffer('offset', torch.arange(levels, dtype=torch.int64)[:, None] * size)
        # Instant-NGP initialises the entries uniformly in +-1e-4
        self.table = nn.Parameter(torch.empty(levels * size, features).uniform_(-1e-4, 1e-4))

    @property
    def out_features(self) -> int:
        return self.levels * self.features

    def forward(self, unit: torch.Tensor) -> torch.Tensor:
        """(N, 3) points in [0, 1] -> (N, levels * features)."""
        pos = unit.clamp(0.0, 1.0)[:, None, :] * self.resolution[None, :, None]          # N, L, 3
        cell = pos.floor()
        frac = pos - cell
        # per axis the two corner coordinates' keys and weights, combined into the 8 corners by
        # broadcasting (a third of the work of expanding the corners first)
        cell = cell.long()
        key = torch.stack([cell, cell + 1], -1) * self.stride[None, :, :, None]           # N, L, 3, 2
        kx, ky, kz = (k for k in key.unbind(2))
        kx, ky, kz = kx[:, :, :, None, None], ky[:, :, None, :, None], kz[:, :, None, None, :]
        dense = self.dense[None, :, None, None, None]
        index = (torch.where(dense, kx + ky + kz, kx ^ ky ^ kz) % self.size
                 + self.offset[None, :, :, None, None]).flatten(2)                         # N, L, 8
        wx, wy, wz = torch.stack([1.0 - frac, frac], -1).unbind(2)                          # N, L, 2 each
        weight = (wx[:, :, :, None, None] * wy[:, :, None, :, None] * wz[:, :, None, None, :]).flatten(2)
        values = _Gather.apply(self.table, index)                               # N, L, 8, F
        return (values * weight[..., None].to(values.dtype)).sum(2).flatten(1)


def srgb_to_linear(rgb: torch.Tensor) -> torch.Tensor:
    """The sRGB transfer function inverted (IEC 61966-2-1), in torch (``volcap_core.color.srgb_to_linear``,
    colour-science's, is numpy; the test checks the two agree)."""
    rgb = rgb.clamp(0.0, 1.0)
    return torch.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(linear: torch.Tensor) -> torch.Tensor:
    """The sRGB transfer function, in torch; values above 1 follow the curve on (clip later)."""
    linear = linear.clamp_min(0.0)
    return torch.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear.clamp_min(1e-8) ** (1 / 2.4) - 0.055)


class CameraResponse(nn.Module):
    """How each camera records linear surface colour, as a camera pipeline does: a fall-off over
    the image symmetric about its centre (vignetting: quadratic in x and y, quartic in the
    radius), a gain per channel (exposure, white balance) and a monotone tone curve per channel
    (piecewise linear, ``knots`` segments over [0, 1], starting as the sRGB curve). Few
    parameters per camera, fitted on all its pixels, so a camera's response is defined over the
    whole gamut, also for colours it did not see. Deliberately no more: a tilt of the fall-off
    or a full 3x3 matrix would also take up the scene's own lighting, which differs from view
    to view (on rgbd_box: 3.54 -> 2.85 CIEDE2000 to the truth without the tilt, 2.56 -> 2.34
    with gains instead of the matrix). Where a chart measured each camera's channel crosstalk,
    it is applied after the gains, fixed (``set_crosstalk``)."""

    def __init__(self, cameras: int, knots: int = 24):
        super().__init__()
        self.knots = knots
        self.gains = nn.Parameter(torch.ones(cameras, 3))
        # each camera's channel crosstalk, applied after the gains; fixed, not learnt (see
        # ``set_crosstalk``): the identity unless a chart measured it
        self.register_buffer('crosstalk', torch.eye(3).repeat(cameras, 1, 1))
        self.falloff = nn.Parameter(torch.zeros(cameras, 3))        # x^2, y^2, r^4
        edges = torch.linspace(0.0, 1.0, max(knots, 1) + 1)
        srgb = linear_to_srgb(edges)
        steps = (srgb[1:] - srgb[:-1]).clamp_min(1e-4) * max(knots, 1)       # slope of each segment
        self.tone = nn.Parameter(torch.log(torch.expm1(steps)).repeat(cameras, 3, 1))   # softplus^-1
        if knots == 0:      # a power law per channel instead, starting at 1 / 2.2
            self.tone = nn.Parameter(torch.full((cameras, 3), math.log(1 / 2.2)))

    def forward(self, linear: torch.Tensor, camera: torch.Tensor, xy: torch.Tensor, mixed: bool = True
                ) -> torch.Tensor:
        """The camera's recording of ``linear``; ``mixed=False`` leaves its crosstalk out (the
        camera as it would record without the mixing a chart measured: a reference's view)."""
        u = (xy - 0.5) * 2.0                                              # -1 .. 1 edge to edge
        u2 = u * u
        r2 = u2.sum(-1, keepdim=True) / 2.0                               # 1 at the corners
        f = self.falloff[camera]
        fall = 1.0 + (f[:, :2] * u2).sum(-1, keepdim=True) + f[:, 2:3] * r2 * r2
        x = self.gains[camera] * linear * fall
        # products and a sum, not a matrix product: autocast would run that in bf16 and round
        # every colour to 8 bits of mantissa (rgbd_box, seed 0: E's held-out RMS 17.8 -> 20.0)
        if mixed:
            x = (self.crosstalk[camera] * x[:, None, :]).sum(-1)
        if self.knots == 0:
            return x.clamp(1e-6, 1.0) ** torch.exp(self.tone[camera])
        # the tone curve: sum of the segments' slopes times how much of each segment x covers
        slope = nn.functional.softplus(self.tone[camera])                 # N, 3, K
        pos = x.clamp(0.0, 1.0)[..., None] * self.knots - torch.arange(self.knots, device=x.device)
        return ((pos.clamp(0.0, 1.0) * slope).sum(-1) / self.knots).clamp(0.0, 1.0)

    def set_crosstalk(self, matrices) -> None:
        """Fix each camera's channel crosstalk, (cameras, 3, 3) with rows summing to 1 (grey stays
        grey; the gains keep exposure and white balance). A matrix learnt with the field would also
        take up the scene's lighting as it differs from view to view (the docstring above); one
        measured on a chart under the studio's light cannot (``crosstalk_from_chart``)."""
        m = torch.as_tensor(np.asarray(matrices, np.float32), device=self.crosstalk.device)
        if m.shape != self.crosstalk.shape or not torch.isfinite(m).all():
            raise ValueError(f'crosstalk must be finite {tuple(self.crosstalk.shape)}, got {tuple(m.shape)}')
        self.crosstalk.copy_(m)

    def unclipped(self, linear: torch.Tensor, camera: torch.Tensor, xy: torch.Tensor, iterations: int = 16
                  ) -> torch.Tensor:
        """``linear`` with each channel scaled down to the brightest colour this camera records
        below saturation (``SATURATED``) where it records it saturated, else unchanged. A
        clipped pixel says only that the colour is at least that bright: mapping it as the
        brightest unclipped one keeps D continuous and monotone at the clip, as inverting the
        response does, instead of the mean of every brighter colour the field holds (rgbd_box,
        seed 0: a clipped pixel 4.6 CIEDE2000 from the truth against 1.5 for the gain model).
        Bisection per channel (the response is per channel), ``iterations`` halvings."""
        with torch.no_grad():
            low = torch.zeros_like(linear)
            high = torch.ones_like(linear)
            clipped = self(linear, camera, xy) >= SATURATED
            for _ in range(iterations):
                mid = (low + high) / 2
                below = self(linear * mid, camera, xy) < SATURATED
                low = torch.where(below, mid, low)
                high = torch.where(below, high, mid)
            return torch.where(clipped, linear * low, linear)


class HashGridField(_Normalised):
    """Our E: (world point, world camera centre, pixel x y in [0, 1]) -> sRGB in [0, 1].

    The point's hash-grid features go through a small MLP to the linear colour of the surface
    (3 channels, non-negative); the camera's ``CameraResponse`` records it, given where in its
    image the point lies. The factorisation is the point: the texture lives in the one field
    every camera shares and a camera can only change how a colour is recorded, so E's colour of
    a point as another camera would record it is well defined, and so is the reference (the
    colour at the image centre, where there is no fall-off). The camera is the training camera
    nearest to the centre given."""

    def __init__(self, point_min, point_extent, centres, levels: int = 12, log2_table: int = 16,
                 coarsest: int = 16, finest: int = 512, width: int = 64):
        centres = np.asarray(centres, np.float32).reshape(-1, 3)
        super().__init__(np.zeros(3), np.ones(3), centres.mean(0), np.ones(3))
        self.register_buffer('point_min', torch.as_tensor(np.asarray(point_min, np.float32)))
        self.register_buffer('point_extent', torch.as_tensor(np.float32(point_extent)))
        self.register_buffer('centres', torch.as_tensor(centres))
        self.grid = HashGrid(levels, log2_table, coarsest, finest)
        self.latent = nn.Sequential(nn.Linear(self.grid.out_features, width), nn.ReLU(), nn.Linear(width, 3))
        self.response = CameraResponse(len(centres))
        # per camera a small rigid correction of its view (rotation vector about its centre,
        # translation), in units of REGISTRATION_SCALE (rad, m) so Adam's steps suit both; see
        # ``register``
        self.registration = nn.Parameter(torch.zeros(len(centres), 6))

    def surface_color(self, points: torch.Tensor) -> torch.Tensor:
        """Linear colour of the surface at ``points`` (the shared latent field)."""
        return nn.functional.softplus(self.latent(self.grid((points - self.point_min) / self.point_extent)))

    def camera_index(self, cameras: torch.Tensor) -> torch.Tensor:
        return torch.cdist(cameras.float(), self.centres).argmin(1)

    def register(self, points: torch.Tensor, cameras: torch.Tensor) -> torch.Tensor:
        """``points`` seen by the cameras at ``cameras`` moved by their view's correction: a
        small rotation about the camera centre (first order: calibration or tracking error and a
        colour-to-depth shift both move a view's points about its centre) and a translation. The
        corrections are taken relative to their mean over the cameras, so the rig as a whole does
        not drift. Identity until trained (``RegisteredField``)."""
        idx = self.camera_index(cameras)
        corr = self.corrections()
        rot, shift = corr[idx, :3], corr[idx, 3:]
        return points + torch.cross(rot, points - self.centres[idx], dim=-1) + shift

    def corrections(self) -> torch.Tensor:
        """(cameras, 6) each view's correction: rotation vector (rad) and translation (m),
        relative to their mean over the cameras."""
        return (self.registration - self.registration.mean(0)) * REGISTRATION_SCALE

    def forward(self, points: torch.Tensor, cameras: torch.Tensor, xy: torch.Tensor | None = None) -> torch.Tensor:
        if xy is None:
            xy = torch.full((len(points), 2), 0.5, device=points.device)
        return self.response(self.surface_color(points), self.camera_index(cameras), xy)

    def optimiser_groups(self) -> list[dict]:
        # Instant-NGP: a tiny epsilon for the sparse table entries, weight decay on the MLP only
        return [{'params': list(self.grid.parameters()), 'eps': 1e-15},
                {'params': list(self.latent.parameters()), 'weight_decay': 1e-6},
                {'params': list(self.response.parameters())},
                {'params': [self.registration], 'lr_scale': REGISTRATION_LR_SCALE}]


class RegisteredField(nn.Module):
    """A ``HashGridField`` trained together with the registration of its views: each training
    pixel's point is moved by its camera's correction (``HashGridField.register``) before the
    field is looked up, so a view misregistered by a millimetre does not smear the texture
    every view shares (rgbd_box, seeds 0-2, 1 mm cells: E's held-out RMS 18.6 -> 16.7 levels on
    seed 0, corrections of 0.02-0.07 deg and 0.6-1.3 mm; docs/benchmarks.md). After training the corrections are applied to the samples
    once (``neural.harmonise``) and the field is used unwrapped."""

    def __init__(self, field: HashGridField):
        super().__init__()
        self.field = field

    def forward(self, points: torch.Tensor, cameras: torch.Tensor, xy: torch.Tensor | None = None) -> torch.Tensor:
        return self.field(self.field.register(points, cameras), cameras, xy)

    def optimiser_groups(self) -> list[dict]:
        return self.field.optimiser_groups()


class CaptureMapper(nn.Module):
    """D: (sRGB in [0, 1], pixel x y in [0, 1]) -> harmonised sRGB in [0, 1]; the paper's 5 -> width
    x layers -> 3 ReLU network. How its output changes the colour (``form``):

    - ``gain`` (ours, the default): per-channel gains in linear light, exp of the output, which
      starts at zero, so D starts as the identity. A camera's exposure and white balance are
      gains in linear light, so the correction D learns is smooth over the whole range, up to
      a saturated pixel (rgbd_box: pixels the camera clipped were mapped to 4.6 CIEDE2000 from
      the truth by the logit form, whose correction must change steeply near white).
    - ``logit``: the output added to the input colour's logit, a sigmoid after it (the form
      before 2026-12-06): starts as the identity too; a deep ReLU stack learning the whole
      mapping stalled at 15 levels RMS with greyed-out colours (rgbd_box, docs/color.md).
    - ``none``: the paper's, the whole mapping with a sigmoid output (folders written before
      the skip).

    ``unmix`` (gain form): a fixed 3x3 applied to the linear colour before the gains, the inverse
    of the camera's channel crosstalk where a chart measured it (``CameraResponse.set_crosstalk``):
    colour-dependent gains from a small MLP cannot represent a matrix's inverse (a three-camera
    sphere with 10 % crosstalk: 3-4 a*b* units off the truth with it learnt, ``test_neural``),
    and once it is undone what is left of the camera is per channel again. The identity
    otherwise."""

    def __init__(self, width: int = 128, layers: int = 8, form: str = 'gain'):
        super().__init__()
        if form not in MAPPER_FORMS:
            raise ValueError(f'mapper form must be one of {MAPPER_FORMS}, not {form!r}')
        sizes = [5] + [width] * layers
        self.hidden = nn.ModuleList([nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:])])
        self.rgb = nn.Linear(width, 3)
        self.form = form
        if form != 'none':
            nn.init.zeros_(self.rgb.weight)
            nn.init.zeros_(self.rgb.bias)
        self.register_buffer('unmix', torch.eye(3))

    def forward(self, rgb: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
        h = torch.cat([rgb, xy], dim=-1)
        for layer in self.hidden:
            h = torch.relu(layer(h))
        out = self.rgb(h)
        if self.form == 'gain':
            linear = (self.unmix * srgb_to_linear(rgb)[:, None, :]).sum(-1)     # fp32 under autocast
            mapped = linear_to_srgb(linear * torch.exp(out))
            # trained on the colour as mapped (a loss on a clipped output has no gradient past
            # white); applied, clipped to the image's range
            return mapped if self.training else mapped.clamp(0.0, 1.0)
        if self.form == 'logit':
            out = out + torch.logit(rgb.clamp(0.0, 1.0), eps=1e-3)
        return torch.sigmoid(out)
