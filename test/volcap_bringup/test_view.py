"""The browser player (`volcap view`) in headless Chromium, against the synthetic studio's own
renders: a person fused from eight ideal RGB-D views (true depth, the colours the cameras see),
written as a compressed sequence, played by three.js. The screenshot must show the person upright
and centred where the studio's renderer draws it from the same viewpoint, in the same colours,
and the frames must advance. Every GLB passes the Khronos glTF validator."""
import json
import subprocess
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from volcap_core.camera import CameraModel
from volcap_core.color import delta_e2000
from volcap_core.poses import look_at
from volcap_fusion.glb import EncodeConfig
from volcap_fusion.sequence import SequenceWriter, read_manifest
from volcap_fusion.tsdf import CameraView, FusionConfig, TsdfFusion
from volcap_studio.ideal import HAT, JEANS, SHIRT, SKIN, IdealView, ring_views

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope='module')
def person_sequence(tmp_path_factory):
    """Three frames of the person fused at 6 mm from the studio's eight stand cameras."""
    views = [CameraView(name, v.depth_mm, camera, v.rgb, camera, T) for name, camera, T, v in ring_views()]
    model = TsdfFusion(FusionConfig(voxel_size=0.006)).fuse(views, on_floor=True)
    folder = tmp_path_factory.mktemp('view') / 'frames'
    writer = SequenceWriter(folder, ('glb',), EncodeConfig(encoding='meshopt'))
    for k in range(3):
        writer.write(model, 1_000_000_000 + k * 100_000_000)     # 10 fps: frames change while we watch
    writer.close()
    return folder


def serve(folder: Path, port: int, live: bool = False) -> str:
    from volcap_bringup.view import ViewConfig, run_view
    url, ready = [], threading.Event()
    threading.Thread(target=run_view, args=(ViewConfig(folder, live, '127.0.0.1', port),
                                            lambda u: (url.append(u), ready.set())), daemon=True).start()
    assert ready.wait(30), 'volcap view did not start'
    return url[0]


def test_every_glb_passes_the_khronos_validator(person_sequence, tmp_path):
    from volcap_fusion.tsdf import FusedModel
    paths = [person_sequence / f['glb'] for f in read_manifest(person_sequence)]
    small = FusedModel(np.eye(3, dtype=np.float32), np.full((3, 3), 90, np.uint8), np.array([[0, 1, 2]], np.int32))
    for encoding in ('raw', 'draco'):     # the other encodings, on a tiny mesh
        writer = SequenceWriter(tmp_path / encoding, ('glb',), EncodeConfig(encoding=encoding))
        writer.write(small, 5)
        paths.append(tmp_path / encoding / '000000.glb')
    out = subprocess.run(['node', str(REPO / 'web' / 'validate.mjs'), *map(str, paths)], capture_output=True,
                         text=True, timeout=120)
    reports = [json.loads(line) for line in out.stdout.splitlines()]
    assert len(reports) == len(paths), out.stderr
    for r in reports:
        assert r['numErrors'] == 0 and r['numWarnings'] == 0, r
    assert out.returncode == 0


def test_the_player_shows_the_person_upright_centred_in_true_colour(person_sequence, browser, free_port, tmp_path):
    url = serve(person_sequence, free_port)
    page = browser.new_page(viewport={'width': 480, 'height': 640})
    errors = []
    page.on('pageerror', lambda e: errors.append(str(e)))
    page.goto(url)
    page.wait_for_function('window.volcap && window.volcap.shown >= 1', timeout=60_000)
    seen = set()
    deadline = time.monotonic() + 20
    while len(seen) < 3 and time.monotonic() < deadline:      # 10 fps: every frame within a second
        seen.add(page.evaluate('window.volcap.index'))
        time.sleep(0.03)
    assert seen == {0, 1, 2}, f'frames shown: {seen}'
    page.evaluate('window.volcap.hud(false)')
    view = page.evaluate('window.volcap.camera()')
    shot = tmp_path / 'player.png'
    page.screenshot(path=str(shot))
    page.close()
    assert not errors, errors
    image = cv2.cvtColor(cv2.imread(str(shot)), cv2.COLOR_BGR2RGB)
    h, w = image.shape[:2]

    # the studio's render from the player's viewpoint (glTF (x, y, z) is studio (y, z, x))
    g2s = lambda p: np.array([p[2], p[0], p[1]], float)
    f = (h / 2) / np.tan(np.radians(view['fov']) / 2)
    truth = IdealView(CameraModel(w, h, f, f, (w - 1) / 2, (h - 1) / 2),
                       look_at(g2s(view['position']), g2s(view['target'])))
    background = np.array([0x30, 0x34, 0x3a])
    drawn = np.abs(image.astype(int) - background).sum(axis=2) > 12
    drawn = cv2.morphologyEx(drawn.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)).astype(bool)
    person = truth.material >= 0
    iou = (drawn & person).sum() / (drawn | person).sum()
    assert iou > 0.85, f'the drawn person overlaps the studio render by {iou:.2f}'
    rows = np.nonzero(drawn.any(axis=1))[0]
    assert truth.material[rows[0]:rows[0] + 25][person[rows[0]:rows[0] + 25]].tolist().count(HAT) > 0  # head up
    cols = np.nonzero(drawn.any(axis=0))[0]
    assert abs((cols[0] + cols[-1]) / 2 - w / 2) < 0.1 * w, 'not centred'
    inner = lambda m: cv2.erode(m.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool) & drawn
    for part, name in ((SHIRT, 'shirt'), (JEANS, 'trousers'), (SKIN, 'skin')):
        region = inner(truth.material == part)
        assert region.sum() > 200, name
        de = delta_e2000(image[region].mean(axis=0) / 255.0, truth.rgb[region].mean(axis=0) / 255.0)
        assert de <= 5.0, f'{name}: mean colour {de:.1f} CIEDE2000 from the studio render'
