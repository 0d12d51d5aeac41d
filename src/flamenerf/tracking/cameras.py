"""Joint camera solve: shared focal length, per-frame camera poses and a per-subject face
template, refined against the tracked 2D landmarks of every frame.

Model (the head is still, the camera moves, so the world frame is the head's)::

    x_ij = K (R_i (X_j + Δ_ij) + t_i)          j = 0..467 face-mesh landmarks, frame i

with OpenGL camera axes (x right, y up, the camera looks down -z), so a world point p maps to
pixels u = cx + f·p_x/(-p_z), v = cy - f·p_y/(-p_z) (as `flamenerf.geometry.project`).
`X = X0 + δ` is the per-subject template (MediaPipe's canonical mesh X0, metres, refined by
a regularised offset δ); `Δ_ij` is a per-frame non-rigid offset for expressions, solved in a
second stage with the cameras held fixed.

Stage A (rigid) minimises, over every (R_i, t_i) and δ (the focal length f fixed),
    Σ w_j ρ(‖x̂_ij − x_ij‖ / s)              robust (Cauchy) reprojection, s = face size in px
  + λ_smooth Σ ‖accel of camera centre and rotation‖²       temporal smoothness
  + λ_template (‖δ‖² + ‖L δ‖²)                              template priors
with w_j = 1 on MediaPipe's expression-stable Procrustes landmarks and `other_weight` on the
rest. Because the error is nearly flat along the focal-length / distance direction (a face
is shallow), f comes from a scan: poses are fitted at several fields of view on a subset of
frames and the best is refined by a parabola (`_scan_focal`). The poses start from
MediaPipe's per-frame head pose and are fitted by robust Levenberg-Marquardt per frame
(batched over frames), alternated with robust Gauss-Newton per template vertex (batched over
vertices); an L-BFGS pass then polishes everything jointly with the smoothness term.
Stage B fits Δ_i per frame and vertex (least squares on the landmark, plus MediaPipe's
relative depth, weakly, and a small prior), the cameras fixed. docs/preprocessing.md has
the details and the numbers on the reference clips.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from flamenerf.geometry import matrix_to_rotvec, project, skew, so3_exp
from flamenerf.runtime import torch_threads

# Depths are clamped to at least this in the solve: points that stray behind the camera
# while the optimiser searches must not flip their projection.
MIN_DEPTH = 1e-6
# MediaPipe's geometry pipeline assumes this vertical field of view for its head pose.
MEDIAPIPE_VFOV_DEG = 63.0


@dataclass
class SolveConfig:
    """Knobs of the camera solve (defaults tuned on the two reference clips)."""

    fov_deg: float | None = None
    """Fix the horizontal field of view (degrees) instead of estimating the focal length."""
    fov_scan_deg: tuple[float, ...] = (15.0, 22.0, 30.0, 40.0, 50.0, 60.0, 75.0, 95.0)
    """Horizontal fields of view tried (on a subset of frames) to initialise the focal length;
    the landmark error is flat along the focal/distance direction, so L-BFGS alone stays
    wherever it starts."""
    fov_prior_deg: float = 60.0
    """Centre of the weak focal prior that breaks near-ties in the scan (a phone's main
    camera is ~65-70°, a face-cropped clip narrower)."""
    focal_prior: float = 0.02
    """Weight of the weak prior on log-focal (loss units: 1 ≈ every landmark off by the
    robust scale)."""
    scan_frames: int = 32
    """Frames used by the focal scan."""
    robust_scale: float = 0.01
    """Cauchy scale, as a fraction of the face size in pixels."""
    other_weight: float = 0.3
    """Weight of landmarks outside MediaPipe's expression-stable set in the rigid stage."""
    smooth: float = 0.5
    """Weight of the temporal smoothness of camera centres and rotations (1 ≈ an isolated
    jitter of the camera centre costs as much as half the landmark misfit it causes)."""
    template_prior: float = 1.0
    """Weight of the prior keeping the template close to MediaPipe's canonical face."""
    template_sigma: float = 0.004
    """Template offsets of this size (metres) cost as much as 1 face-size of residual."""
    refine_focal: bool = False
    """Also refine the focal length in the joint stage (the template's depth and the focal
    length trade off, so this mostly drifts; the scan's value is the default)."""
    lm_iters: int = 10
    alternations: int = 4
    """Rounds of per-frame pose fitting <-> per-vertex template fitting before the joint
    L-BFGS polish."""
    joint_iters: int = 60
    mesh_iters: int = 5
    mesh_prior: float = 0.1
    """Weight of the prior keeping the per-frame mesh near the template (per mesh_sigma)."""
    mesh_depth_weight: float = 0.05
    """Weight of MediaPipe's relative depth in the per-frame mesh stage."""
    mesh_sigma: float = 0.006
    """Per-frame mesh offsets of this size (metres) cost 1 face-size² of residual."""


@dataclass
class SolveResult:
    focal: float  # pixels of the input frames (fx = fy)
    cx: float
    cy: float
    w2c: np.ndarray  # (N, 4, 4) world -> OpenGL camera
    c2w: np.ndarray  # (N, 4, 4)
    template: np.ndarray  # (468, 3) world (= head) coordinates, metres
    vertices: np.ndarray  # (N, 468, 3) per-frame face mesh, world
    rigid_error: np.ndarray  # (N,) median px reprojection error of the rigid template
    mesh_error: np.ndarray  # (N,) median px reprojection error of the per-frame mesh
    face_size: float  # median face size in px
    history: dict = field(default_factory=dict)  # loss curves, focal scan


# ----------------------------------------------------------------------------- math


def cauchy(r2: torch.Tensor, c: float) -> torch.Tensor:
    """Cauchy robust loss of squared residuals: c² log(1 + r²/c²)."""
    return c * c * torch.log1p(r2 / (c * c))


def mesh_laplacian(faces: np.ndarray, num_vertices: int) -> torch.Tensor:
    """Uniform graph Laplacian (V, V): (L x)_j = x_j − mean of j's neighbours."""
    A = np.zeros((num_vertices, num_vertices))
    for a, b in ((0, 1), (1, 2), (2, 0)):
        A[faces[:, a], faces[:, b]] = 1
        A[faces[:, b], faces[:, a]] = 1
    deg = A.sum(1, keepdims=True)
    deg[deg == 0] = 1
    return torch.from_numpy(np.eye(num_vertices) - A / deg)


def _lbfgs(params: list[torch.Tensor], closure_loss, iters: int) -> list[float]:
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=iters, history_size=20,
                            line_search_fn="strong_wolfe", tolerance_grad=1e-10,
                            tolerance_change=1e-12)
    hist: list[float] = []

    def closure():
        opt.zero_grad()
        loss = closure_loss()
        loss.backward()
        hist.append(float(loss.detach()))
        return loss

    opt.step(closure)
    return hist


def _smooth_terms(x: torch.Tensor, times: torch.Tensor, step: float,
                  shots: torch.Tensor | None = None) -> torch.Tensor:
    """Squared discrete accelerations of a sequence x (N, D) sampled at `times` (N,) seconds,
    times step² (the source video's frame step): the same physical motion costs the same
    whether or not frames were subsampled. `shots` (N,): the shot of each frame; an
    acceleration across a cut (its three frames not of one shot) is left out."""
    if x.shape[0] < 3:
        return x.new_zeros(())
    dt = (times[1:] - times[:-1]).clamp_min(1e-6)
    vel = (x[1:] - x[:-1]) / dt[:, None]
    acc = (vel[1:] - vel[:-1]) / (0.5 * (dt[1:] + dt[:-1]))[:, None]
    terms = ((acc * step * step) ** 2).sum(-1)
    if shots is not None:
        within = (shots[:-2] == shots[1:-1]) & (shots[1:-1] == shots[2:])
        if not bool(within.all()):
            return terms[within].mean() if bool(within.any()) else x.new_zeros(())
    return terms.mean()


# ----------------------------------------------------------------------------- the solve


def solve_cameras(
    landmarks: np.ndarray,
    times: np.ndarray,
    template0: np.ndarray,
    faces: np.ndarray,
    stable_weights: np.ndarray,
    width: int,
    height: int,
    init_transforms: np.ndarray | None = None,
    cfg: SolveConfig | None = None,
    frame_step: float | None = None,
    shots: np.ndarray | None = None,
) -> SolveResult:
    """landmarks (N, >=468, 3) pixels (+ MediaPipe relative depth); times (N,) seconds;
    template0 (468, 3) metres; faces (F, 3); stable_weights (468,) (>0 = expression-stable);
    init_transforms (N, 4, 4) MediaPipe head poses (canonical cm -> camera) or None for a
    frontal guess; frame_step: the source's 1/fps (default: the smallest gap in `times`);
    shots (N,): each frame's shot (tracking/shots.py; None: one), the cameras are not
    smoothed across a cut. The principal point is the image centre. See the module
    docstring for the model."""
    cfg = cfg or SolveConfig()
    if landmarks.shape[0] < 2:
        raise ValueError("the camera solve needs at least 2 frames")
    if frame_step is None:
        gaps = np.diff(np.asarray(times, np.float64))
        frame_step = float(gaps[gaps > 0].min()) if np.any(gaps > 0) else 1.0
    # these tensors are small: thread-pool synchronisation costs more than it saves, and
    # ~10x more when other processes compete for the cores
    with torch_threads(1):
        return _solve(landmarks, times, template0, faces, stable_weights, width, height,
                      init_transforms, cfg, frame_step, shots)


class _Problem:
    """Observations and fixed quantities shared by every stage."""

    def __init__(self, landmarks, times, template0, faces, stable_weights, width, height,
                 init_transforms, cfg: SolveConfig, step: float,
                 shots: np.ndarray | None = None):
        dt = torch.float64
        self.cfg, self.step = cfg, step
        self.N, self.V = landmarks.shape[0], template0.shape[0]
        V = self.V
        self.obs = torch.from_numpy(np.ascontiguousarray(landmarks[:, :V, :2])).to(dt)
        self.zrel = torch.from_numpy(np.ascontiguousarray(landmarks[:, :V, 2])).to(dt)
        self.times = torch.from_numpy(np.asarray(times, np.float64))
        self.shots = None if shots is None else torch.from_numpy(np.asarray(shots, np.int64))
        self.X0 = torch.from_numpy(np.asarray(template0, np.float64))
        self.width, self.height = width, height
        self.cx, self.cy = width / 2.0, height / 2.0
        lo, hi = self.obs.amin(1), self.obs.amax(1)
        self.face_size = float((hi - lo).amax(-1).median())
        w = torch.from_numpy(np.where(stable_weights > 0, 1.0, cfg.other_weight)).to(dt)
        self.w = w / w.sum()
        self.lap = mesh_laplacian(faces, V).to(dt)
        e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        self.edges = torch.from_numpy(np.unique(np.sort(e, 1), axis=0).astype(np.int64))
        self.radius = float((self.X0 - self.X0.mean(0)).norm(dim=-1).pow(2).mean().sqrt())
        self.init_transforms = init_transforms

    def subset(self, idx: np.ndarray) -> "_Problem":
        p = object.__new__(_Problem)
        p.__dict__.update(self.__dict__)
        p.N = len(idx)
        p.obs, p.zrel, p.times = self.obs[idx], self.zrel[idx], self.times[idx]
        p.shots = None if self.shots is None else self.shots[idx]
        if self.init_transforms is not None:
            p.init_transforms = self.init_transforms[idx]
        return p

    def focal_of_fov(self, fov_deg: float) -> float:
        return 0.5 * max(self.width, self.height) / np.tan(np.radians(fov_deg) / 2)

    def initial_poses(self, f0: float) -> tuple[np.ndarray, np.ndarray]:
        """From MediaPipe's head pose (assumes a 63° vertical FOV; rescaled to f0)."""
        if self.init_transforms is not None:
            f_mp = 0.5 * self.height / np.tan(np.radians(MEDIAPIPE_VFOV_DEG) / 2)
            U, _, Vt = np.linalg.svd(self.init_transforms[:, :3, :3])
            rvec0 = matrix_to_rotvec(U @ Vt)
            # same image size at focal f0: scale the depth, keep x/y (cm -> m)
            tvec0 = self.init_transforms[:, :3, 3] / 100.0
            tvec0[:, 2] *= f0 / f_mp
            return rvec0, tvec0
        X0 = self.X0.numpy()
        size_m = float(np.ptp(X0[:, :2], axis=0).max())
        depth = f0 * size_m / self.face_size
        ctr = self.obs.mean(1).numpy()
        tvec0 = np.stack([(ctr[:, 0] - self.cx) * depth / f0,
                          -(ctr[:, 1] - self.cy) * depth / f0, -np.full(self.N, depth)], -1)
        return np.zeros((self.N, 3)), tvec0


def _cam_points(rvec, tvec, X):
    """World points X (V, 3) or (N, V, 3) -> OpenGL camera space (N, V, 3)."""
    R = so3_exp(rvec)
    if X.dim() == 2:
        return torch.einsum("nab,vb->nva", R, X) + tvec[:, None]
    return torch.einsum("nab,nvb->nva", R, X) + tvec[:, None]


def _proj_jacobian(Pc: torch.Tensor, f: float) -> torch.Tensor:
    """d(pixel)/d(camera point) of `project`: (*, 3) -> (*, 2, 3)."""
    x, y, zz = Pc[..., 0], Pc[..., 1], (-Pc[..., 2]).clamp_min(1e-6)
    zero = torch.zeros_like(x)
    return torch.stack([
        torch.stack([f / zz, zero, f * x / zz**2], -1),
        torch.stack([zero, -f / zz, -f * y / zz**2], -1),
    ], -2)


def _lm_poses(P: _Problem, X: torch.Tensor, f: float, rvec: torch.Tensor,
              tvec: torch.Tensor, iters: int) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Robust (Cauchy IRLS) Levenberg-Marquardt over each frame's pose independently,
    batched over frames: a fast PnP with analytic Jacobians (rotation updated on the left,
    R <- exp(ω) R). Returns the poses and the final data loss (the joint stage's units)."""
    c = P.cfg.robust_scale
    f_t = torch.tensor(f, dtype=torch.float64)
    R = so3_exp(rvec)
    t = tvec.clone()

    def resid(R: torch.Tensor, t: torch.Tensor):
        Pc = torch.einsum("nab,vb->nva", R, X) + t[:, None]
        return Pc, (project(Pc, f_t, f_t, P.cx, P.cy, MIN_DEPTH) - P.obs) / P.face_size

    def cost(r: torch.Tensor) -> torch.Tensor:  # per frame
        return (cauchy((r * r).sum(-1), c) * P.w).sum(-1) / (c * c)

    lam = torch.full((P.N,), 1e-3, dtype=torch.float64)
    Pc, r = resid(R, t)
    cur = cost(r)
    for _ in range(iters):
        Jp = _proj_jacobian(Pc, f) / P.face_size  # (N, V, 2, 3)
        dP = torch.cat([-skew(Pc - t[:, None]), torch.eye(3, dtype=Pc.dtype).expand(
            *Pc.shape[:2], 3, 3)], -1)  # (N, V, 3, 6): d Pc / d (ω, dt)
        J = Jp @ dP  # (N, V, 2, 6)
        wr = P.w / (1 + (r * r).sum(-1) / (c * c))  # IRLS weights (N, V)
        H = torch.einsum("nvak,nv,nval->nkl", J, wr, J)
        g = torch.einsum("nvak,nv,nva->nk", J, wr, r)
        Hd = H + lam[:, None, None] * torch.diag_embed(torch.diagonal(H, dim1=1, dim2=2) + 1e-12)
        step = -torch.linalg.solve(Hd, g)
        R_new = so3_exp(step[:, :3]) @ R
        t_new = t + step[:, 3:]
        Pc_new, r_new = resid(R_new, t_new)
        new = cost(r_new)
        ok = new < cur
        R = torch.where(ok[:, None, None], R_new, R)
        t = torch.where(ok[:, None], t_new, t)
        Pc = torch.where(ok[:, None, None], Pc_new, Pc)
        r = torch.where(ok[:, None, None], r_new, r)
        cur = torch.where(ok, new, cur)
        lam = torch.where(ok, lam * 0.3, lam * 10).clamp(1e-12, 1e9)
    rv = torch.from_numpy(matrix_to_rotvec(R.numpy()))
    return rv, t, float(cur.mean())


def _gn_template(P: _Problem, f: float, rvec: torch.Tensor, tvec: torch.Tensor,
                 delta: torch.Tensor, iters: int) -> torch.Tensor:
    """Robust Levenberg-Marquardt over each template vertex's offset independently, batched
    over vertices (a triangulation from every frame with a Gaussian prior towards the
    canonical face), the poses held fixed. The objective is the joint stage's without the
    smoothness and Laplacian terms. Returns the new offset (V, 3)."""
    cfg, c = P.cfg, P.cfg.robust_scale
    s = cfg.template_sigma
    f_t = torch.tensor(f, dtype=torch.float64)
    R = so3_exp(rvec)
    wv = P.w * P.V  # per-vertex weight; the prior below is per vertex too

    def resid(d: torch.Tensor):
        Pc = torch.einsum("nab,vb->nva", R, P.X0 + d) + tvec[:, None]
        return Pc, (project(Pc, f_t, f_t, P.cx, P.cy, MIN_DEPTH) - P.obs) / P.face_size

    def cost(r: torch.Tensor, d: torch.Tensor) -> torch.Tensor:  # per vertex
        data = cauchy((r * r).sum(-1), c).mean(0) * wv / (c * c)
        return data + cfg.template_prior * ((d / s) ** 2).sum(-1)

    d = delta.clone()
    eye = torch.eye(3, dtype=torch.float64)
    lam = torch.full((P.V,), 1e-3, dtype=torch.float64)
    Pc, r = resid(d)
    cur = cost(r, d)
    for _ in range(iters):
        J = (_proj_jacobian(Pc, f) / P.face_size) @ R[:, None]  # (N, V, 2, 3)
        wr = 1 / (1 + (r * r).sum(-1) / (c * c))  # (N, V)
        scale = wv / (P.N * c * c)
        H = torch.einsum("nvak,nv,nval->vkl", J, wr, J) * scale[:, None, None]
        g = torch.einsum("nvak,nv,nva->vk", J, wr, r) * scale[:, None]
        H = H + cfg.template_prior * eye / s**2
        g = g + cfg.template_prior * d / s**2
        Hd = H + lam[:, None, None] * torch.diag_embed(torch.diagonal(H, dim1=1, dim2=2))
        d_new = d - torch.linalg.solve(Hd, g)
        Pc_new, r_new = resid(d_new)
        new = cost(r_new, d_new)
        ok = new < cur
        d = torch.where(ok[:, None], d_new, d)
        Pc = torch.where(ok[None, :, None], Pc_new, Pc)
        r = torch.where(ok[None, :, None], r_new, r)
        cur = torch.where(ok, new, cur)
        lam = torch.where(ok, lam * 0.3, lam * 10).clamp(1e-12, 1e9)
    return d


def _gn_mesh(P: _Problem, f: float, rvec: torch.Tensor, tvec: torch.Tensor,
             X: torch.Tensor, D_target: torch.Tensor, iters: int) -> torch.Tensor:
    """Stage B: per-frame, per-vertex offsets Δ (N, V, 3) so that the mesh follows every
    landmark (least squares, not robust: expressions move landmarks far from the rigid
    template on purpose), plus MediaPipe's relative depth (weight mesh_depth_weight) and a
    small prior towards the template. Each vertex is a 3-unknown Gauss-Newton problem;
    all N x V of them are solved at once."""
    cfg, c, s_m = P.cfg, P.cfg.robust_scale, P.cfg.mesh_sigma
    f_t = torch.tensor(f, dtype=torch.float64)
    R = so3_exp(rvec)  # (N, 3, 3)
    eye = torch.eye(3, dtype=torch.float64)
    d = torch.zeros((P.N, P.V, 3), dtype=torch.float64)
    Rz = R[:, 2, :][:, None, :]  # d(cam z)/dΔ, (N, 1, 3)
    H_depth = cfg.mesh_depth_weight * (Rz[..., :, None] * Rz[..., None, :]) / s_m**2
    for _ in range(iters):
        Pc = torch.einsum("nab,nvb->nva", R, X[None] + d) + tvec[:, None]
        r = (project(Pc, f_t, f_t, P.cx, P.cy, MIN_DEPTH) - P.obs) / P.face_size  # (N,V,2)
        J = (_proj_jacobian(Pc, f) / P.face_size) @ R[:, None]  # (N, V, 2, 3)
        H = J.transpose(-1, -2) @ J / c**2 + H_depth + cfg.mesh_prior * eye / s_m**2
        dz = (-Pc[..., 2] - D_target)[..., None]  # (N, V, 1); d(-z)/dΔ = -Rz
        g = ((J.transpose(-1, -2) @ r[..., None])[..., 0] / c**2
             - cfg.mesh_depth_weight * dz * Rz / s_m**2 + cfg.mesh_prior * d / s_m**2)
        d = d - torch.linalg.solve(H, g[..., None])[..., 0]
    return d


def _joint(P: _Problem, f: float, rvec0: torch.Tensor, tvec0: torch.Tensor,
           delta0: torch.Tensor, refine_focal: bool, iters: int):
    """Stage A, joint part: poses, template offset (and optionally the focal length) with the
    temporal smoothness term. Returns (rvec, tvec, delta, focal, history)."""
    cfg, dt, c = P.cfg, torch.float64, P.cfg.robust_scale
    # parameters are scaled to similar sensitivities so that L-BFGS converges: translations
    # in units of the mean camera distance, template offsets in units of template_sigma
    d0 = float(tvec0.norm(dim=-1).mean())
    s = cfg.template_sigma
    rvec = rvec0.detach().clone().requires_grad_(True)
    that = (tvec0 / d0).detach().clone().requires_grad_(True)
    log_f = torch.tensor(np.log(f), dtype=dt, requires_grad=refine_focal)
    dhat = (delta0 / s).detach().clone().requires_grad_(True)

    def loss_fn() -> torch.Tensor:
        tvec = that * d0
        f_cur = log_f.exp()
        uv = project(_cam_points(rvec, tvec, P.X0 + dhat * s), f_cur, f_cur, P.cx, P.cy,
                     MIN_DEPTH)
        r2 = ((uv - P.obs) ** 2).sum(-1) / P.face_size**2
        loss = (cauchy(r2, c) * P.w).sum(-1).mean() / (c * c)
        if cfg.smooth > 0 and P.N >= 3:
            C = -torch.einsum("nba,nb->na", so3_exp(rvec), tvec)  # centres, c = -R^T t
            # rotation accelerations weighted as the motion they cause at the face's radius
            loss = loss + cfg.smooth * (
                _smooth_terms(C / d0, P.times, P.step, P.shots)
                + _smooth_terms(rvec * (P.radius / d0), P.times, P.step, P.shots)) / (c * c)
        loss = loss + cfg.template_prior * (
            dhat.pow(2).sum(-1).mean() + (P.lap @ dhat).pow(2).sum(-1).mean())
        if refine_focal:
            loss = loss + cfg.focal_prior * (log_f - np.log(f)) ** 2
        return loss

    params = [rvec, that, dhat] + ([log_f] if refine_focal else [])
    hist = _lbfgs(params, loss_fn, iters)
    return (rvec.detach(), (that * d0).detach(), (dhat * s).detach(),
            float(log_f.detach().exp()), hist)


def _scan_focal(P: _Problem) -> tuple[float, list[tuple[float, float]]]:
    """Fit poses (template fixed to the canonical face) for each FOV of cfg.fov_scan_deg on a
    subset of frames; return the focal minimising the loss plus the weak prior (parabola
    through the best three, in log-focal), and the scan."""
    cfg = P.cfg
    k = min(P.N, cfg.scan_frames)
    sub = P.subset(np.unique(np.round(np.linspace(0, P.N - 1, k)).astype(np.int64)))
    f_prior = P.focal_of_fov(cfg.fov_prior_deg)
    scores = []
    for fov in cfg.fov_scan_deg:
        f = P.focal_of_fov(fov)
        r0, t0 = sub.initial_poses(f)
        *_, loss = _lm_poses(sub, sub.X0, f, torch.from_numpy(r0), torch.from_numpy(t0),
                             cfg.lm_iters)
        scores.append((float(fov), loss + cfg.focal_prior * np.log(f / f_prior) ** 2))
    logs = np.log([P.focal_of_fov(fv) for fv, _ in scores])
    vals = np.array([v for _, v in scores])
    b = int(np.argmin(vals))
    best = logs[b]
    if 0 < b < len(vals) - 1:
        x, y = logs[b - 1 : b + 2], vals[b - 1 : b + 2]
        a2, a1, _ = np.polyfit(x, y, 2)
        if a2 > 0:
            best = float(np.clip(-a1 / (2 * a2), x.min(), x.max()))
    return float(np.exp(best)), scores


def _solve(landmarks, times, template0, faces, stable_weights, width, height,
           init_transforms, cfg: SolveConfig, step: float,
           shots: np.ndarray | None = None) -> SolveResult:
    P = _Problem(landmarks, times, template0, faces, stable_weights, width, height,
                 init_transforms, cfg, step, shots)
    history: dict = {}
    if cfg.fov_deg is not None:
        f0 = P.focal_of_fov(cfg.fov_deg)
    else:
        f0, history["focal_scan"] = _scan_focal(P)
    r0, t0 = P.initial_poses(f0)
    rvec, tvec = torch.from_numpy(r0), torch.from_numpy(t0)
    delta = torch.zeros_like(P.X0)
    history["alternation"] = []
    for _ in range(cfg.alternations):  # resection <-> triangulation, both robust and batched
        rvec, tvec, loss = _lm_poses(P, P.X0 + delta, f0, rvec, tvec, cfg.lm_iters)
        history["alternation"].append(loss)
        delta = _gn_template(P, f0, rvec, tvec, delta, cfg.lm_iters)
    rvec, tvec, delta, f, history["joint"] = _joint(
        P, f0, rvec, tvec, delta, cfg.refine_focal and cfg.fov_deg is None, cfg.joint_iters)
    f_t = torch.tensor(f, dtype=torch.float64)
    Xt = P.X0 + delta
    with torch.no_grad():
        Pc = _cam_points(rvec, tvec, Xt)
        uv = project(Pc, f_t, f_t, P.cx, P.cy, MIN_DEPTH)
        rigid_err = (uv - P.obs).norm(dim=-1).median(-1).values
        # MediaPipe's relative depth, as a depth target anchored on the template's mean depth
        D = -Pc[..., 2]
        D_target = D.mean(1, keepdim=True) * (1 + (P.zrel - P.zrel.mean(1, keepdim=True)) / f)

    # --- stage B: per-frame non-rigid offsets, cameras fixed
    dper = _gn_mesh(P, f, rvec, tvec, Xt, D_target, cfg.mesh_iters)

    with torch.no_grad():
        verts = Xt[None] + dper
        uv = project(_cam_points(rvec, tvec, verts), f_t, f_t, P.cx, P.cy, MIN_DEPTH)
        mesh_err = (uv - P.obs).norm(dim=-1).median(-1).values.numpy()
        w2c = np.tile(np.eye(4), (P.N, 1, 1))
        w2c[:, :3, :3] = so3_exp(rvec).numpy()
        w2c[:, :3, 3] = tvec.numpy()
    return SolveResult(
        focal=f, cx=P.cx, cy=P.cy, w2c=w2c, c2w=np.linalg.inv(w2c), template=Xt.numpy(),
        vertices=verts.numpy(), rigid_error=rigid_err.numpy(), mesh_error=mesh_err,
        face_size=P.face_size, history=history,
    )
