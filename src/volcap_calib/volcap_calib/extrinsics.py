"""Extrinsic calibration of the whole rig from views of a planar target.

Every camera's target detections become observations; each is posed by PnP (intrinsics and
distortion from camera_info) and, where the camera has depth, checked against the target plane
measured by depth. Cameras are chained through shared target views into one initial guess, then
one joint least-squares problem over all camera and target poses refines reprojection and
depth-to-plane residuals together with a robust loss. The paper's gradient-descent SED
minimisation (paper 000 Eqs. 1-3) is kept in ``sed_baseline`` for comparison.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np
from numba import njit
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from volcap_core.camera import CameraModel
from volcap_core.errors import BadInput, VolcapError
from volcap_core.poses import from_rotvec_t, invert, make_transform, rotation_angle_deg, to_rotvec_t, transform_points

from .config import SolverConfig  # noqa: F401 (re-exported: its home before config.py)
from .detect import Detection


class CalibrationError(VolcapError, RuntimeError):
    """Calibration cannot be trusted; ``cameras`` names each camera at fault and why."""

    def __init__(self, message: str, cameras: dict[str, str] | None = None):
        self.cameras = dict(cameras or {})
        detail = '; '.join(f'{c}: {r}' for c, r in sorted(self.cameras.items()))
        super().__init__(f'{message}: {detail}' if detail else message)


@dataclass
class Observation:
    """One camera's detection of the target in one view (board pose)."""
    camera: str
    view: int
    detection: Detection
    T_cam_target: np.ndarray                 # PnP pose
    pnp_rms_px: float
    plane_points: np.ndarray | None = None   # (M, 3) depth points on the target, colour frame

    @property
    def corners(self) -> int:
        return len(self.detection)


@dataclass
class CameraReport:
    views: int
    corners: int
    reproj_rms_px: float
    depth_rms_mm: float | None
    rejected: dict[int, str] = field(default_factory=dict)   # view -> reason
    # predicted RMS pose error relative to the reference (None: not predicted, e.g. the baseline)
    rot_sigma_deg: float | None = None
    trans_sigma_mm: float | None = None

    def to_dict(self) -> dict:
        return {'views': self.views, 'corners': self.corners, 'reproj_rms_px': self.reproj_rms_px,
                'depth_rms_mm': self.depth_rms_mm, 'rejected_views': {int(k): v for k, v in self.rejected.items()},
                'predicted_rot_err_deg': self.rot_sigma_deg, 'predicted_trans_err_mm': self.trans_sigma_mm}


@dataclass
class ExtrinsicResult:
    reference: str
    T_world_color: dict[str, np.ndarray]
    T_world_target: dict[int, np.ndarray]
    cameras: dict[str, CameraReport]
    method: str


# --- single observations -------------------------------------------------------------------

def target_pose(detection: Detection, camera: CameraModel) -> tuple[np.ndarray, float]:
    """T_cam_target by PnP (IPPE, then Levenberg-Marquardt) and its reprojection RMS in px.

    Raises ValueError for a degenerate view: too few corners or corners on one line."""
    obj, px = detection.object_points, detection.pixels
    if len(obj) < 4:
        raise BadInput(f'{len(obj)} corners, a pose needs 4')
    spread = np.linalg.svd(obj[:, :2] - obj[:, :2].mean(0), compute_uv=False)
    if spread[1] < 1e-3 * max(spread[0], 1e-9) or spread[1] < 1e-3:
        raise BadInput('corners are collinear (degenerate pose)')
    ok, rvec, tvec = cv2.solvePnP(obj, px, camera.K, camera.D, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise BadInput('PnP failed')
    rvec, tvec = cv2.solvePnPRefineLM(obj, px, camera.K, camera.D, rvec, tvec)
    T = make_transform(cv2.Rodrigues(rvec)[0], tvec)
    if T[2, 3] <= 0:
        raise BadInput('target behind the camera (degenerate pose)')
    return T, float(np.sqrt(np.mean(np.sum(corner_residuals(detection, T, camera) ** 2, axis=1))))


def corner_residuals(detection: Detection, T_cam_target: np.ndarray, camera: CameraModel) -> np.ndarray:
    """(N, 2) projected minus detected corner pixels for the target at ``T_cam_target``."""
    rvec = cv2.Rodrigues(T_cam_target[:3, :3])[0]
    proj, _ = cv2.projectPoints(detection.object_points, rvec, T_cam_target[:3, 3], camera.K, camera.D)
    return proj.reshape(-1, 2) - detection.pixels


@lru_cache(maxsize=32)
def _rays(camera: CameraModel) -> np.ndarray:
    rays = camera.pixel_rays().astype(np.float32)
    rays.flags.writeable = False
    return rays


def depth_points(depth_m: np.ndarray, depth_camera: CameraModel, T_color_depth: np.ndarray) -> np.ndarray:
    """(N, 3) points of every valid depth pixel, in the colour camera's frame."""
    if depth_m.shape != (depth_camera.height, depth_camera.width):
        raise BadInput(f'depth is {depth_m.shape[::-1]}, camera_info says '
                         f'{depth_camera.width}x{depth_camera.height}')
    valid = np.isfinite(depth_m) & (depth_m > 0)
    return transform_points(T_color_depth, _rays(depth_camera)[valid] * depth_m[valid, None])


def target_depth_points(depth_m: np.ndarray, depth_camera: CameraModel, T_color_depth: np.ndarray,
                        T_cam_target: np.ndarray, region: tuple[float, float, float, float],
                        inset: float = 0.02, max_offset: float = 0.05) -> np.ndarray:
    """Depth points (colour frame) that fall on the target plane inside ``region`` (target
    coordinates x0, y0, x1, y1) shrunk by ``inset``: mixed pixels at the target's border stay out."""
    local = transform_points(invert(T_cam_target), depth_points(depth_m, depth_camera, T_color_depth))
    x0, y0, x1, y1 = region
    keep = ((local[:, 0] > x0 + inset) & (local[:, 0] < x1 - inset) & (local[:, 1] > y0 + inset)
            & (local[:, 1] < y1 - inset) & (np.abs(local[:, 2]) < max_offset))
    return transform_points(T_cam_target, local[keep])


def fit_plane(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Unit normal n and offset d of the least-squares plane n.x = d."""
    c = points.mean(axis=0)
    n = np.linalg.svd(points - c, full_matrices=False)[2][2]
    return n, float(n @ c)


def depth_corners(obs: Observation, camera: CameraModel) -> np.ndarray:
    """The paper's 3D corners from depth: each corner's ray meets the plane reconstructed from
    the depth points on the board (paper 000 Fig. 8, "Board Plane Reconstruction")."""
    if obs.plane_points is None or len(obs.plane_points) < 10:
        raise BadInput('no depth on the target')
    n, d = fit_plane(obs.plane_points)
    rays = np.hstack([camera.undistort_pixels(obs.detection.pixels), np.ones((obs.corners, 1))])
    return rays * (d / (rays @ n))[:, None]


def kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Rigid T minimising sum |T src - dst|^2 (Umeyama without scale)."""
    cs, cd = src.mean(0), dst.mean(0)
    R = Rotation.align_vectors(dst - cd, src - cs)[0].as_matrix()
    return make_transform(R, cd - R @ cs)


def check_against_depth(obs: Observation, camera: CameraModel, cfg: SolverConfig) -> str | None:
    """Why the PnP pose disagrees with the depth-derived one (None when they agree)."""
    try:
        T_depth = kabsch(obs.detection.object_points, depth_corners(obs, camera))
    except ValueError:
        return None
    angle = rotation_angle_deg(T_depth[:3, :3], obs.T_cam_target[:3, :3])
    offset = float(np.linalg.norm(T_depth[:3, 3] - obs.T_cam_target[:3, 3]))
    if angle > cfg.max_pose_disagreement_deg or offset > cfg.max_pose_disagreement_m:
        return f'PnP and depth disagree by {angle:.1f} deg / {offset * 1000:.0f} mm'
    return None


# --- the rig -------------------------------------------------------------------------------

def chain_poses(observations: list[Observation], cameras: list[str], reference: str
                ) -> tuple[dict[str, np.ndarray], dict[int, np.ndarray], list[str]]:
    """Initial T_world_cam and T_world_target by walking the camera-view graph outward from the
    reference (world = reference colour frame); returns the cameras it could not reach."""
    by_camera: dict[str, list[Observation]] = {c: [] for c in cameras}
    by_view: dict[int, list[Observation]] = {}
    for o in sorted(observations, key=lambda o: -o.corners):
        by_camera[o.camera].append(o)
        by_view.setdefault(o.view, []).append(o)
    T_cam = {reference: np.eye(4)}
    T_view: dict[int, np.ndarray] = {}
    queue = deque([reference])
    while queue:
        cam = queue.popleft()
        for o in by_camera[cam]:
            if o.view in T_view:
                continue
            T_view[o.view] = T_cam[cam] @ o.T_cam_target
            for other in by_view[o.view]:
                if other.camera not in T_cam:
                    T_cam[other.camera] = T_view[o.view] @ invert(other.T_cam_target)
                    queue.append(other.camera)
    return T_cam, T_view, [c for c in cameras if c not in T_cam]


def solve_rig(observations: list[Observation], models: dict[str, CameraModel], reference: str,
              cfg: SolverConfig = SolverConfig(), rejected: dict[str, dict[int, str]] | None = None
              ) -> ExtrinsicResult:
    """Joint least squares over all camera and target poses (the reference camera fixed)."""
    cameras = list(models)
    rejected = {c: dict((rejected or {}).get(c, {})) for c in cameras}
    missing = {c: (f'never saw the target ({len(rejected[c])} views rejected: '
                   f'{"; ".join(sorted(set(rejected[c].values())))})' if rejected[c] else 'never saw the target')
               for c in cameras if not any(o.camera == c for o in observations)}
    if missing:
        raise CalibrationError('cameras without usable target views', missing)
    T_cam0, T_view0, unreached = chain_poses(observations, cameras, reference)
    if unreached:
        raise CalibrationError('cameras share no target view with the rest of the rig',
                               {c: 'not linked to the reference through shared views' for c in unreached})
    free = [c for c in cameras if c != reference]
    views = sorted(T_view0)
    cam_col = {c: 6 * i for i, c in enumerate(free)}
    view_col = {v: 6 * (len(free) + i) for i, v in enumerate(views)}
    x0 = np.concatenate([to_rotvec_t(T_cam0[c]) for c in free] + [to_rotvec_t(T_view0[v]) for v in views])
    rng = np.random.default_rng(0)
    depth_sets = {}
    if cfg.depth_weight > 0:
        for i, o in enumerate(observations):
            if o.plane_points is not None and len(o.plane_points) >= 10:
                pick = rng.choice(len(o.plane_points), min(cfg.depth_points, len(o.plane_points)), replace=False)
                depth_sets[i] = o.plane_points[pick]
    depth_scale = np.sqrt(cfg.depth_weight) / cfg.depth_sigma

    def unpack(x):
        T_cam = {reference: np.eye(4)} | {c: from_rotvec_t(x[cam_col[c]:cam_col[c] + 6]) for c in free}
        return T_cam, {v: from_rotvec_t(x[view_col[v]:view_col[v] + 6]) for v in views}

    def residual_parts(x):
        T_cam, T_view = unpack(x)
        reproj, depth = [], []
        for i, o in enumerate(observations):
            T_ct = invert(T_cam[o.camera]) @ T_view[o.view]
            reproj.append(corner_residuals(o.detection, T_ct, models[o.camera]))
            if i in depth_sets:
                depth.append(transform_points(invert(T_ct), depth_sets[i])[:, 2])
        return reproj, depth

    def residuals(x):
        reproj, depth = residual_parts(x)
        parts = [r.ravel() / cfg.pixel_sigma for r in reproj] + [d * depth_scale for d in depth]
        return np.concatenate(parts)

    sparsity = _sparsity(observations, depth_sets, cam_col, view_col, len(x0))
    sol = least_squares(residuals, x0, jac_sparsity=sparsity, loss='soft_l1', f_scale=cfg.robust_scale,
                        x_scale='jac', method='trf', xtol=1e-10, ftol=1e-10, max_nfev=200)
    T_cam, T_view = unpack(sol.x)
    sigmas = pose_sigmas(sol, {c: cam_col[c] for c in free})
    reproj, depth = residual_parts(sol.x)
    reports, bad = {}, {}
    depth_by_obs = dict(zip(depth_sets, depth))
    for c in cameras:
        idx = [i for i, o in enumerate(observations) if o.camera == c]
        r = np.vstack([reproj[i] for i in idx])
        d = [depth_by_obs[i] for i in idx if i in depth_by_obs]
        rms = float(np.sqrt(np.mean(np.sum(r ** 2, axis=1))))
        d_rms = float(np.sqrt(np.mean(np.concatenate(d) ** 2)) * 1000) if d else None
        reports[c] = CameraReport(len(idx), int(sum(observations[i].corners for i in idx)), rms, d_rms, rejected[c],
                                  *sigmas.get(c, (0.0, 0.0)))
        if rms > cfg.max_reproj_rms_px:
            bad[c] = f'reprojection RMS {rms:.2f} px after the joint solve (limit {cfg.max_reproj_rms_px})'
        elif d_rms is not None and d_rms > cfg.max_depth_rms_mm:
            bad[c] = f'depth residual {d_rms:.1f} mm after the joint solve (limit {cfg.max_depth_rms_mm})'
    if bad:
        raise CalibrationError('inconsistent cameras', bad)
    return ExtrinsicResult(reference, T_cam, T_view, reports, 'joint_least_squares')


def pose_sigmas(sol, columns: dict[str, int]) -> dict[str, tuple[float, float]]:
    """Predicted RMS rotation (deg) and position (mm) error of each free camera: the covariance
    sigma^2 (J^T J)^-1 of the solution (J the loss-weighted Jacobian at the optimum, sigma^2 the
    residual variance per degree of freedom), its camera block mapped from rotation-vector
    to rotation-angle space. Assumes independent corner and depth noise: correlated or
    systematic errors are not seen."""
    JtJ = sol.jac.T @ sol.jac      # sparse from the solver: the product is small, the Jacobian is not
    JtJ = JtJ.toarray() if hasattr(JtJ, 'toarray') else np.asarray(JtJ)
    dof = max(len(sol.fun) - len(sol.x), 1)
    variance = float(sol.fun @ sol.fun) / dof
    covariance = variance * np.linalg.pinv(JtJ, hermitian=True)
    out = {}
    for camera, col in columns.items():
        block = covariance[col:col + 6, col:col + 6]
        A = _rotvec_to_angle(sol.x[col:col + 3])
        rot = np.degrees(np.sqrt(max(np.trace(A @ block[:3, :3] @ A.T), 0.0)))
        out[camera] = (float(rot), float(np.sqrt(max(np.trace(block[3:, 3:]), 0.0)) * 1000))
    return out


def _rotvec_to_angle(rotvec: np.ndarray, step: float = 1e-6) -> np.ndarray:
    """(3, 3) d(rotation error vector)/d(rotation vector) at ``rotvec``: a rotation vector is
    not a rotation angle away from identity (near 180 deg it moves the rotation less)."""
    R = Rotation.from_rotvec(rotvec)
    return np.stack([(Rotation.from_rotvec(rotvec + step * e) * R.inv()).as_rotvec() / step
                     for e in np.eye(3)], axis=1)


def _sparsity(observations, depth_sets, cam_col, view_col, n_params):
    rows = sum(2 * o.corners + (len(depth_sets[i]) if i in depth_sets else 0) for i, o in enumerate(observations))
    S = lil_matrix((rows, n_params), dtype=np.int8)
    r = 0
    blocks = [(i, 2 * o.corners) for i, o in enumerate(observations)] + \
             [(i, len(depth_sets[i])) for i in depth_sets]
    for i, n in blocks:
        o = observations[i]
        if o.camera in cam_col:
            S[r:r + n, cam_col[o.camera]:cam_col[o.camera] + 6] = 1
        S[r:r + n, view_col[o.view]:view_col[o.view] + 6] = 1
        r += n
    return S


# --- paper baseline ------------------------------------------------------------------------

@njit(cache=True)
def _euler(a0, a1, a2):
    """R = Rz(a2) Ry(a1) Rx(a0) and its three partial derivatives."""
    ca, sa, cb, sb, cc, sc = np.cos(a0), np.sin(a0), np.cos(a1), np.sin(a1), np.cos(a2), np.sin(a2)
    Rx = np.array([[1.0, 0, 0], [0, ca, -sa], [0, sa, ca]])
    Ry = np.array([[cb, 0, sb], [0, 1.0, 0], [-sb, 0, cb]])
    Rz = np.array([[cc, -sc, 0], [sc, cc, 0], [0, 0, 1.0]])
    dRx = np.array([[0.0, 0, 0], [0, -sa, -ca], [0, ca, -sa]])
    dRy = np.array([[-sb, 0, cb], [0, 0.0, 0], [-cb, 0, -sb]])
    dRz = np.array([[-sc, -cc, 0], [cc, -sc, 0], [0, 0, 0.0]])
    return Rz @ Ry @ Rx, Rz @ Ry @ dRx, Rz @ dRy @ Rx, dRz @ Ry @ Rx


@njit(cache=True)
def _sed_descent(mX, mY, C, sXX, sYY, lr, max_iter, tol):
    """Gradient descent on f = mean |R X + t - Y|^2, written with the point sets' moments
    (means mX, mY, cross moment C = mean(Y X^T), mean squared norms) so each step is O(1)."""
    p = np.zeros(6)
    prev = np.inf
    it = 0
    for it in range(max_iter):
        R, d0, d1, d2 = _euler(p[0], p[1], p[2])
        t = p[3:]
        RmX = R @ mX
        loss = sXX + sYY + t @ t + 2 * t @ RmX - 2 * t @ mY - 2 * np.sum(R * C)
        if prev - loss <= tol * max(abs(loss), 1e-30):
            break
        prev = loss
        g = np.empty(6)
        for k, dR in enumerate((d0, d1, d2)):
            g[k] = 2 * (t @ (dR @ mX) - np.sum(dR * C))
        g[3:] = 2 * (RmX + t - mY)
        p -= lr * g
    return p, it + 1


def sed_gradient_descent(X_i: np.ndarray, X_ref: np.ndarray, lr: float = 0.01, max_iter: int = 1_000_000,
                         tol: float = 1e-15) -> tuple[np.ndarray, int]:
    """Paper 000 Eqs. 1-3: from R = I, t = 0 (Euler angles and translation), plain gradient
    descent with learning rate ``lr`` on the mean squared Euclidean distance between
    R X_i + t and X_ref, until the loss stops falling; returns T_ref_i and the iterations."""
    X_i, X_ref = np.asarray(X_i, np.float64), np.asarray(X_ref, np.float64)
    C = X_ref.T @ X_i / len(X_i)
    p, iterations = _sed_descent(X_i.mean(0), X_ref.mean(0), C, float(np.mean(np.sum(X_i ** 2, 1))),
                                 float(np.mean(np.sum(X_ref ** 2, 1))), lr, max_iter, tol)
    return make_transform(_euler(p[0], p[1], p[2])[0], p[3:]), iterations


def sed_baseline(observations: list[Observation], models: dict[str, CameraModel], reference: str,
                 lr: float = 0.01, max_iter: int = 1_000_000) -> ExtrinsicResult:
    """The paper's pipeline: depth-derived 3D corners, each camera aligned by gradient descent to
    a camera already placed (the reference first; cameras that never see the target together
    with the reference are chained through the neighbour they share most corners with)."""
    corners3d: dict[tuple[str, int], dict[int, np.ndarray]] = {}
    for o in observations:
        try:
            pts = depth_corners(o, models[o.camera])
        except ValueError:
            continue
        corners3d[(o.camera, o.view)] = dict(zip(o.detection.ids.tolist(), pts))

    def shared(a: str, b: str) -> tuple[np.ndarray, np.ndarray]:
        src, dst = [], []
        for (cam, view), pts in corners3d.items():
            if cam != a or (b, view) not in corners3d:
                continue
            other = corners3d[(b, view)]
            for cid in pts.keys() & other.keys():
                src.append(pts[cid])
                dst.append(other[cid])
        return np.asarray(src).reshape(-1, 3), np.asarray(dst).reshape(-1, 3)

    cameras = list(models)
    T_world = {reference: np.eye(4)}
    while len(T_world) < len(cameras):
        best = max(((len(shared(c, p)[0]), c, p) for c in cameras if c not in T_world for p in T_world),
                   default=(0, None, None))
        if best[0] < 3:
            raise CalibrationError('SED baseline: cameras share no depth corners with placed cameras',
                                   {c: 'no shared 3D corners' for c in cameras if c not in T_world})
        _, cam, parent = best
        X_i, X_ref = shared(cam, parent)
        T_parent_cam, _ = sed_gradient_descent(X_i, X_ref, lr=lr, max_iter=max_iter)
        T_world[cam] = T_world[parent] @ T_parent_cam
    reports = {}
    for c in cameras:
        obs = [o for o in observations if o.camera == c]
        reports[c] = CameraReport(len(obs), sum(o.corners for o in obs), float('nan'), None)
    return ExtrinsicResult(reference, T_world, {}, reports, 'paper_sed_gradient_descent')
