"""Colour seams on a fused model: where the model passes from one camera's view to another's,
how different the colours are that the two cameras give the same place.

A renderer that textures the model from the cameras (or a fusion that favours the best view)
switches cameras across the model; where two cameras disagree on a colour, the switch shows as
a seam. Each vertex is given to the camera that sees it best: visible (in the image, not behind
the model's own surface along the ray, facing it by at least ``MIN_FACING``), and the most
frontal once each camera's facing is averaged over the surrounding surface (``OWNER_SMOOTHING``
rounds of neighbour averaging, about 2 cm at 4 mm voxels). Without the averaging the
marching-cubes normals, 14 degrees apart between neighbouring vertices at the median, break
ownership into salt and pepper: a quarter of all edges crossed cameras on the demo's model,
against 3 % with it. A mesh edge whose two vertices belong to different cameras crosses a seam;
at each end of it the two cameras' colours at that vertex (bilinear in their images) are compared:

- ``seam_de``: mean CIEDE2000 between the two cameras' colours at the seam vertices (the seam a
  camera switch would show);
- ``seam_de_reference``: the same with each view's ``reference`` image where the caller gives
  one (``volcap eval fusion`` gives a synthetic camera's true colours: what remains there is the
  shading that changes with the view and the colour-to-depth registration, which no colour
  correction removes);
- ``model_step_seam_de`` / ``model_step_other_de``: the model's own vertex-colour step across
  seam edges and across every other edge: what the fused colours show there (TSDF averaging
  blends the cameras, so a seam in the cameras need not be one in the model).

No ground truth is needed: the caller gives the colour images the fusion integrated (corrected)
and their poses in the model's frame. ``volcap eval fusion`` reports it per frame.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
import scipy.sparse as sp

from volcap_core.camera import CameraModel
from volcap_core.color import delta_e2000
from volcap_core.poses import invert
from volcap_core.sampling import sample_bilinear

from .tsdf import FusedModel

MIN_FACING = 0.2          # cos of the angle between the surface normal and the view ray
OWNER_SMOOTHING = 30      # rounds of averaging each camera's facing with the neighbouring vertices'
VISIBLE_MM = 3.0          # farther than the first surface along the ray by more than this: occluded


@dataclass
class SeamView:
    """One camera's colour image as the fusion integrated it, posed in the model's frame."""
    name: str
    color: np.ndarray           # (H, W, 3) uint8 RGB
    camera: CameraModel         # the colour image's intrinsics
    T_frame_camera: np.ndarray  # (4, 4) camera -> the model's frame
    reference: np.ndarray | None = None     # (H, W, 3) uint8: other colours on the same grid (e.g. the truth)


def vertex_normals(model: FusedModel) -> np.ndarray:
    mesh = model.legacy_mesh()
    mesh.compute_vertex_normals()
    return np.asarray(mesh.vertex_normals)


def camera_colors(model: FusedModel, views: list[SeamView], normals: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(facing, colours, reference colours): per view and vertex, the view's facing (|cos|
    between the normal and the ray; 0 where the view does not see the vertex) and its colour
    there (sRGB in [0, 1]); the reference colours likewise where every view has a reference."""
    v = model.vertices.astype(np.float64)
    normals = vertex_normals(model) if normals is None else normals
    scene = model.raycasting_scene()
    with_reference = all(view.reference is not None for view in views)
    facing = np.zeros((len(views), len(v)), np.float32)
    colors = np.zeros((len(views), len(v), 3), np.float32)
    reference = np.zeros_like(colors) if with_reference else None
    for k, view in enumerate(views):
        eye = view.T_frame_camera[:3, 3]
        ray = v - eye
        dist = np.linalg.norm(ray, axis=1)
        ray /= np.maximum(dist, 1e-9)[:, None]
        cos = np.abs(np.sum(normals * ray, axis=1))     # marching cubes' normals may face either way
        T = invert(view.T_frame_camera)
        local = v @ T[:3, :3].T + T[:3, 3]
        ok = (local[:, 2] > 0.05) & (cos >= MIN_FACING)
        px = np.full((len(v), 2), -1.0)
        px[ok] = view.camera.project(local[ok])
        ok &= (px[:, 0] >= 0) & (px[:, 0] <= view.camera.width - 1) & (px[:, 1] >= 0) \
            & (px[:, 1] <= view.camera.height - 1)
        idx = np.flatnonzero(ok)
        rays = np.concatenate([np.broadcast_to(eye, (len(idx), 3)), ray[idx]], axis=1).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays))['t_hit'].numpy()
        idx = idx[hit >= dist[idx] - VISIBLE_MM / 1000]
        if not len(idx):
            continue
        colors[k, idx] = sample_bilinear(view.color, px[idx]).astype(np.float32) / 255.0
        if reference is not None:
            reference[k, idx] = sample_bilinear(view.reference, px[idx]).astype(np.float32) / 255.0
        facing[k, idx] = cos[idx]
    return facing, colors, reference


def mesh_edges(triangles: np.ndarray) -> np.ndarray:
    """(E, 2) the mesh's unique edges, lower vertex first."""
    t = triangles.astype(np.int64)
    return np.unique(np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1), axis=0)


def owners(facing: np.ndarray, edges: np.ndarray, rounds: int = OWNER_SMOOTHING) -> np.ndarray:
    """Per vertex the view that sees it best (-1: none): the largest facing after ``rounds`` of
    averaging each view's facing with the neighbouring vertices', among the views that see it."""
    n = facing.shape[1]
    a, b = edges[:, 0], edges[:, 1]
    adjacency = sp.coo_matrix((np.ones(2 * len(edges)), (np.r_[a, b], np.r_[b, a])), shape=(n, n)).tocsr() \
        + sp.identity(n, format='csr')
    step = sp.diags(1.0 / np.asarray(adjacency.sum(axis=1)).ravel()) @ adjacency
    smooth = facing.T.astype(np.float64)
    for _ in range(rounds):
        smooth = step @ smooth
    smooth = np.where(facing.T > 0, smooth, 0.0)
    return np.where(smooth.max(axis=1) > 0, smooth.argmax(axis=1), -1)


def seam_score(model: FusedModel, views: list[SeamView]) -> dict:
    """The model's colour seams (module docstring); figures are None where no seam was found
    (one camera sees everything, or the model is empty)."""
    empty = {'seam_de': None, 'seam_de_median': None, 'seam_de_reference': None, 'seam_vertices': 0,
             'seam_share': 0.0, 'model_step_seam_de': None, 'model_step_other_de': None, 'pairs': {}}
    if len(model.triangles) == 0 or len(views) < 2:
        return empty
    facing, colors, reference = camera_colors(model, views)
    edges = mesh_edges(model.triangles)
    best = owners(facing, edges)
    a, b = edges[:, 0], edges[:, 1]
    owned = (best[a] >= 0) & (best[b] >= 0)
    crossing = owned & (best[a] != best[b])
    if not crossing.any():
        return empty
    # each end of a crossing edge, scored between its own camera and the other end's camera
    ends = np.concatenate([np.stack([a, best[a], best[b]], 1), np.stack([b, best[b], best[a]], 1)])[np.tile(crossing, 2)]
    ends = np.unique(ends, axis=0)
    vertex, mine, theirs = ends.T
    both = facing[theirs, vertex] > 0           # the other camera sees this end too
    vertex, mine, theirs = vertex[both], mine[both], theirs[both]
    if not len(vertex):
        return empty
    de = delta_e2000(colors[mine, vertex].astype(np.float64), colors[theirs, vertex].astype(np.float64))
    de_reference = None if reference is None else float(delta_e2000(
        reference[mine, vertex].astype(np.float64), reference[theirs, vertex].astype(np.float64)).mean())
    pairs: dict[str, list[float]] = {}
    for i, j, d in zip(np.minimum(mine, theirs), np.maximum(mine, theirs), de):
        pairs.setdefault(f'{views[i].name}-{views[j].name}', []).append(float(d))
    model_rgb = model.colors.astype(np.float64) / 255.0
    step = delta_e2000(model_rgb[a[owned]], model_rgb[b[owned]])
    on_seam = crossing[owned]
    seam_vertices = len(np.unique(vertex))
    return {'seam_de': float(de.mean()), 'seam_de_median': float(np.median(de)), 'seam_de_reference': de_reference,
            'seam_vertices': seam_vertices, 'seam_share': float(seam_vertices / max(1, int((best >= 0).sum()))),
            'model_step_seam_de': float(step[on_seam].mean()),
            'model_step_other_de': float(step[~on_seam].mean()) if (~on_seam).any() else None,
            'pairs': {k: {'de': float(np.mean(d)), 'vertices': len(d)} for k, d in sorted(pairs.items())}}
