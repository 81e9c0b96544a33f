"""The ChArUco + colour-chart calibration board: geometry, reference colours and artwork.

Patches are numbered 0-23 in the chart's reading order (row-major from the top left), the
order of colour-science's ColorChecker data (dark skin ... black).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
import yaml

from volcap_core.errors import BadInput

DEFAULT_BOARD = Path(__file__).with_name('config') / 'board.yaml'


@dataclass(frozen=True)
class ChartLayout:
    reference: str = 'ColorChecker24 - After November 2014'
    columns: int = 6
    rows: int = 4
    patch_size: float = 0.06
    gap: float = 0.012
    origin: tuple[float, float] = (0.09, 0.405)


@dataclass(frozen=True)
class BoardConfig:
    squares_x: int = 8
    squares_y: int = 5
    square_size: float = 0.075
    marker_size: float = 0.055
    dictionary: str = 'DICT_5X5_100'
    margin: float = 0.02
    chart: ChartLayout = field(default_factory=ChartLayout)

    def __post_init__(self):
        if self.marker_size >= self.square_size:
            raise BadInput('marker_size must be smaller than square_size')
        if not hasattr(cv2.aruco, self.dictionary):
            raise BadInput(f'unknown ArUco dictionary {self.dictionary!r}')

    @classmethod
    def from_yaml(cls, path: str | Path = DEFAULT_BOARD) -> 'BoardConfig':
        d = yaml.safe_load(Path(path).read_text())
        chart = ChartLayout(**{**d.get('chart', {}), 'origin': tuple(d.get('chart', {}).get('origin', (0.09, 0.405)))})
        return cls(**{k: v for k, v in d.items() if k != 'chart'}, chart=chart)

    def to_dict(self) -> dict:
        d = asdict(self)
        d['chart']['origin'] = list(self.chart.origin)
        return d

    @property
    def grid_size(self) -> tuple[float, float]:
        return self.squares_x * self.square_size, self.squares_y * self.square_size

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of the printed board in board coordinates."""
        gw, gh = self.grid_size
        c = self.chart
        cw = c.columns * c.patch_size + (c.columns - 1) * c.gap
        ch = c.rows * c.patch_size + (c.rows - 1) * c.gap
        m = self.margin
        return (min(0.0, c.origin[0]) - m, min(0.0, c.origin[1]) - m,
                max(gw, c.origin[0] + cw) + m, max(gh, c.origin[1] + ch) + m)

    def charuco_board(self) -> 'cv2.aruco.CharucoBoard':
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_size, self.marker_size,
                                      dictionary)

    def charuco_corners(self) -> np.ndarray:
        """(M, 3) board coordinates of the inner chessboard corners, in ChArUco id order."""
        return np.asarray(self.charuco_board().getChessboardCorners(), dtype=np.float64).reshape(-1, 3)

    def patch_corners(self) -> np.ndarray:
        """(24, 4, 3) board coordinates of each patch's corners (TL, TR, BR, BL)."""
        c = self.chart
        out = []
        for r in range(c.rows):
            for k in range(c.columns):
                x0 = c.origin[0] + k * (c.patch_size + c.gap)
                y0 = c.origin[1] + r * (c.patch_size + c.gap)
                s = c.patch_size
                out.append([[x0, y0, 0], [x0 + s, y0, 0], [x0 + s, y0 + s, 0], [x0, y0 + s, 0]])
        return np.asarray(out, dtype=np.float64)

    def render(self, px_per_m: float = 2000.0) -> np.ndarray:
        """sRGB uint8 artwork of the whole board; pixel (0, 0) is the corner at extent[:2]."""
        x0, y0, x1, y1 = self.extent
        img = np.full((round((y1 - y0) * px_per_m), round((x1 - x0) * px_per_m), 3), 255, np.uint8)
        gw, gh = (round(v * px_per_m) for v in self.grid_size)
        grid = self.charuco_board().generateImage((gw, gh), marginSize=0, borderBits=1)
        ox, oy = round(-x0 * px_per_m), round(-y0 * px_per_m)
        img[oy:oy + gh, ox:ox + gw] = grid[:, :, None]
        for corners, rgb in zip(self.patch_corners(), reference_srgb8(self.chart.reference)):
            (a, b), (c, d) = ((corners[0, :2] - (x0, y0)) * px_per_m).round().astype(int), \
                ((corners[2, :2] - (x0, y0)) * px_per_m).round().astype(int)
            img[b:d, a:c] = rgb
        return img


def reference_linear_rgb(name: str = ChartLayout.reference) -> np.ndarray:
    """(24, 3) linear sRGB (D65) of the chart's reference patches, adapted from the data's illuminant."""
    import colour as color_science
    chart = color_science.CCS_COLOURCHECKERS[name]
    xyY = np.array(list(chart.data.values()))
    XYZ = color_science.xyY_to_XYZ(xyY)
    rgb = color_science.XYZ_to_sRGB(XYZ, illuminant=chart.illuminant, chromatic_adaptation_transform='Bradford',
                                    apply_cctf_encoding=False)
    return np.clip(rgb, 0.0, 1.0)


def reference_srgb8(name: str = ChartLayout.reference) -> np.ndarray:
    """(24, 3) uint8 sRGB of the reference patches (what the board prints)."""
    import colour as color_science
    return np.round(color_science.cctf_encoding(reference_linear_rgb(name)) * 255).astype(np.uint8)


def write_board(path: str | Path, board: BoardConfig, dpi: int = 300) -> Path:
    """The board artwork at true scale: a PNG carrying its dpi, or a one-page PDF whose page is
    exactly the board's extent (print at 100 %, no scaling)."""
    import io

    from volcap_core.files import atomic_write
    path = Path(path)
    px_per_m = dpi / 0.0254
    art = board.render(px_per_m)
    suffix = path.suffix.lower()
    if suffix == '.png':
        import matplotlib.image
        buf = io.BytesIO()
        matplotlib.image.imsave(buf, art, format='png', dpi=dpi)
    elif suffix == '.pdf':
        import matplotlib
        matplotlib.use('Agg')
        import matplotlib.pyplot as plt
        x0, y0, x1, y1 = board.extent
        fig = plt.figure(figsize=((x1 - x0) / 0.0254, (y1 - y0) / 0.0254))
        fig.add_axes((0, 0, 1, 1)).imshow(art, interpolation='nearest')
        fig.axes[0].set_axis_off()
        buf = io.BytesIO()
        fig.savefig(buf, format='pdf', dpi=dpi)
        plt.close(fig)
    else:
        raise BadInput(f'board output must be .png or .pdf, got {path.name}')
    return atomic_write(path, lambda f: f.write(buf.getvalue()))
