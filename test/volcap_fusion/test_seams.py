"""The seam score: two cameras on a textured wall, one with a known colour offset."""
import numpy as np
import pytest

from volcap_core.camera import CameraModel
from volcap_core.color import delta_e2000
from volcap_fusion.seams import SeamView, seam_score
from volcap_fusion.tsdf import FusedModel

WALL_Z = 2.0


def texture(xy: np.ndarray) -> np.ndarray:
    """The wall's true colour (sRGB in [0, 1]) at world (x, y): smooth, saturated variation."""
    x, y = xy[..., 0], xy[..., 1]
    return np.stack([0.55 + 0.25 * np.sin(6 * x), 0.45 + 0.2 * np.cos(5 * y), 0.35 + 0.15 * np.sin(4 * (x + y))], -1)


def wall(n: int = 120, half: float = 0.5) -> FusedModel:
    """A grid mesh of the plane z = WALL_Z, coloured with the texture."""
    g = np.linspace(-half, half, n)
    x, y = np.meshgrid(g, g)
    vertices = np.stack([x.ravel(), y.ravel(), np.full(x.size, WALL_Z)], 1).astype(np.float32)
    k = np.arange(n * n).reshape(n, n)
    a, b, c, d = k[:-1, :-1].ravel(), k[:-1, 1:].ravel(), k[1:, :-1].ravel(), k[1:, 1:].ravel()
    triangles = np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)]).astype(np.int32)
    colors = np.round(texture(vertices[:, :2].astype(np.float64)) * 255).astype(np.uint8)
    return FusedModel(vertices, colors, triangles)


def camera_at(x: float) -> tuple[CameraModel, np.ndarray]:
    """A camera at (x, 0, 0) looking down +z (the wall), turned towards the wall's centre."""
    model = CameraModel(640, 480, 500.0, 500.0, 319.5, 239.5)
    yaw = np.arctan2(-x, WALL_Z)
    R = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, [x, 0, 0]
    return model, T


def render(model: CameraModel, T: np.ndarray, gain=(1.0, 1.0, 1.0)) -> np.ndarray:
    """What the camera sees of the wall (uint8 RGB), its colours multiplied by ``gain``."""
    rays = model.pixel_rays() @ T[:3, :3].T
    t = (WALL_Z - T[2, 3]) / rays[..., 2]
    hit = T[:3, 3] + rays * t[..., None]
    rgb = np.clip(texture(hit[..., :2]) * np.asarray(gain), 0, 1)
    return np.round(rgb * 255).astype(np.uint8)


def views(gain_b=(1.0, 1.0, 1.0)) -> list[SeamView]:
    """Two cameras on the wall; cam1's colours through ``gain_b``, each with its true colours as
    the reference."""
    (ma, Ta), (mb, Tb) = camera_at(-0.6), camera_at(0.6)
    return [SeamView('cam0', render(ma, Ta), ma, Ta, reference=render(ma, Ta)),
            SeamView('cam1', render(mb, Tb, gain_b), mb, Tb, reference=render(mb, Tb))]


def test_two_cameras_that_agree_leave_no_seam():
    score = seam_score(wall(200), views())          # 40 000 vertices: more than one OpenCV map holds
    assert score['seam_vertices'] > 50            # the best view changes down the middle of the wall
    assert score['seam_de'] < 0.3, score           # only the images' 8-bit rounding and interpolation
    assert list(score['pairs']) == ['cam0-cam1']


@pytest.mark.parametrize('gain', [(1.08, 1.0, 1.0), (1.0, 0.92, 1.1)])
def test_a_known_colour_offset_is_the_seam(gain):
    model = wall()
    score = seam_score(model, views(gain))
    # the seam runs where the two cameras face the wall equally: x = 0
    xy = model.vertices[:, :2].astype(np.float64)
    middle = np.abs(xy[:, 0]) < 0.02
    truth = texture(xy[middle])
    expected = delta_e2000(truth, np.clip(truth * np.asarray(gain), 0, 1)).mean()
    assert score['seam_de'] == pytest.approx(expected, abs=0.25), (score['seam_de'], expected)
    assert score['seam_de'] > 1.0
    assert score['seam_de_reference'] < 0.3         # the true colours agree: the offset is all the camera's


def test_a_rough_surface_keeps_one_seam_line():
    """Depth noise tilts a fused surface's normals from vertex to vertex; the seam stays one line
    down the middle of the wall instead of breaking into salt and pepper."""
    model = wall(160)
    rng = np.random.default_rng(0)
    model.vertices[:, 2] += rng.normal(0, 0.0015, len(model.vertices)).astype(np.float32)   # 1.5 mm on 6 mm spacing
    score = seam_score(model, views())
    x = model.vertices[:, 0]
    assert score['seam_share'] < 0.05, score['seam_share']
    # the owner is the nearer-facing camera away from the middle
    from volcap_fusion.seams import camera_colors, mesh_edges, owners
    facing, _, _ = camera_colors(model, views())
    best = owners(facing, mesh_edges(model.triangles))
    assert (best[x < -0.1] == 0).mean() > 0.99 and (best[x > 0.1] == 1).mean() > 0.99


def test_a_camera_that_does_not_see_the_wall_makes_no_seam():
    model = wall()
    ma, Ta = camera_at(-0.6)
    away = Ta.copy()
    away[:3, :3] = Ta[:3, :3] @ np.diag([-1.0, 1.0, -1.0])     # turned round: the wall is behind it
    score = seam_score(model, [SeamView('cam0', render(ma, Ta), ma, Ta),
                               SeamView('cam1', np.zeros((480, 640, 3), np.uint8), ma, away)])
    assert score['seam_de'] is None and score['seam_vertices'] == 0


def test_a_vertex_hidden_from_a_camera_takes_no_colour_from_it():
    """A second wall in front of cam1 hides the left half of the first from it: no seam is
    scored with cam1's colours of the wall it cannot see (its image there shows the blocker)."""
    back = wall()
    ma, Ta = camera_at(-0.6)
    mb, Tb = camera_at(0.6)
    blocker = wall(20, 0.15)
    blocker.vertices[:, 2] = 1.0
    blocker.vertices[:, 0] += 0.35           # between cam1 and the wall's left half
    merged = FusedModel(np.concatenate([back.vertices, blocker.vertices]),
                        np.concatenate([back.colors, blocker.colors]),
                        np.concatenate([back.triangles, blocker.triangles + len(back.vertices)]))
    from volcap_fusion.seams import camera_colors
    facing, _, _ = camera_colors(merged, [SeamView('cam0', render(ma, Ta), ma, Ta),
                                       SeamView('cam1', render(mb, Tb), mb, Tb)])
    # the wall's points on the line from cam1 through the blocker's centre
    centre = blocker.vertices.mean(axis=0).astype(np.float64)
    direction = (centre - Tb[:3, 3]) / np.linalg.norm(centre - Tb[:3, 3])
    shadow = Tb[:3, 3] + direction * (WALL_Z - Tb[2, 3]) / direction[2]
    near = np.linalg.norm(back.vertices[:, :2] - shadow[:2], axis=1) < 0.03
    assert near.any() and (facing[1, :len(back.vertices)][near] == 0).all()
    assert (facing[0, :len(back.vertices)][near] > 0).all()
