"""The studio's own render of a subject through an ideal camera: no sensor noise, no colour
response, no lens. What the player tests and ``bench/stream.py`` compare a fused, encoded and
drawn model against: the colour (sRGB of the shaded surface), true depth and the material under
every pixel."""
from __future__ import annotations

import numpy as np

from volcap_core.camera import CameraModel
from volcap_core.color import linear_to_srgb
from volcap_core.poses import make_transform

from .render import SceneRaycaster, shade
from .scene import SceneObject, person, studio_lights

JEANS, SHOES, SHIRT, SKIN, HAT = range(5)          # person()'s materials
# person() faces -y; turned to face +x, the studio frame's front (towards the reference camera)
FACING_FRONT = make_transform(np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]), (0, 0, 0))


def person_facing_front() -> SceneObject:
    subject = person()
    subject.pose = FACING_FRONT
    return subject


class IdealView:
    """One pinhole camera's view of ``subject`` in the studio frame, lit by the studio lights."""

    def __init__(self, camera: CameraModel, T_studio_camera: np.ndarray, subject: SceneObject | None = None):
        subject = subject or person_facing_front()
        caster = SceneRaycaster([subject])
        rays = camera.pixel_rays().reshape(-1, 3) @ np.asarray(T_studio_camera)[:3, :3].T
        eye = np.asarray(T_studio_camera, float)[:3, 3]
        hits = caster.cast(eye, rays)
        lights, ambient = studio_lights()
        radiance = np.zeros((len(rays), 3), np.float32)
        radiance[hits.idx] = shade(hits, eye.astype(np.float32), lights, ambient)
        h, w = camera.height, camera.width
        self.rgb = np.round(linear_to_srgb(np.clip(radiance, 0, 1)) * 255).astype(np.uint8).reshape(h, w, 3)
        z = np.where(np.isfinite(hits.t), hits.t, 0.0)        # z = 1 rays: the ray parameter is depth
        self.depth_mm = np.round(z * 1000).astype(np.uint16).reshape(h, w)
        material = np.full(len(rays), -1, np.int64)
        material[hits.idx] = hits.material
        self.material = material.reshape(h, w)


def ring_views(camera: CameraModel | None = None) -> list[tuple[str, CameraModel, np.ndarray, IdealView]]:
    """(name, camera, T_studio_camera, view) of the studio's eight stand cameras seeing the person."""
    from .studio import SynthConfig, stand_layout
    camera = camera or CameraModel(640, 360, 305.0, 305.0, 319.5, 179.5)
    subject = person_facing_front()
    return [(name, camera, T, IdealView(camera, T, subject)) for name, T in stand_layout(SynthConfig())]
