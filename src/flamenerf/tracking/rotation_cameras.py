"""Cameras of a clip filmed with little parallax: each frame's rotation about one fixed
centre, from the background's matches, and the criterion that chooses between this model
and structure from motion.

A phone held in the hand mostly turns: a few degrees, while its centre moves a few
centimetres. Against a far background that translation moves nothing measurably, so the
background's matches fix the rotations and nothing else, and incremental SfM has no pair
with parallax enough to start from (or triangulates noise). Under a pure rotation a
background point seen in frame i is seen in frame j at

    x_j = π(K R_j R_iᵀ K⁻¹ x̃_i)        (R: camera-from-world, OpenCV axes; K: the face's focal)

so the rotations follow from a robust least-squares fit of every verified match (frame 0
fixed), started from the chained rotations of consecutive frames (orthogonal Procrustes of
their bearings). The hand's few centimetres are not lost: the face solve gives each frame's
camera-from-head, so they end up in the head's pose in this world, where the background
cannot see them.

Which model explains the background better is Torr's GRIC (geometric robust information
criterion) over the same matches: the rotation model constrains a match to a point
(d = 2 of its 4 dimensions, 3 parameters per frame), SfM to its epipolar line (d = 3, 6 per
frame): GRIC = Σ min(e²/σ², 2(4 − d)) + ln4·d·n + ln(4n)·k, the lower wins. A far
background or a still camera centre make the rotation model's residuals as small as the
epipolar ones and it wins by its fewer dimensions; parallax leaves residuals along the
epipolar lines that only SfM explains.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from flamenerf.geometry import skew

# GRIC's constants for matches in two images (r = 4 data dimensions)
_R = 4
_LAMBDA1, _LAMBDA3 = np.log(_R), 2.0


@dataclass
class Matches:
    """Verified background matches of frame pairs, stacked: pixel positions in the frames as
    matched (x right, y down)."""

    i: np.ndarray  # (M,) int: first frame's position
    j: np.ndarray  # (M,) int: second frame's position
    xi: np.ndarray  # (M, 2) float
    xj: np.ndarray  # (M, 2) float

    def __len__(self) -> int:
        return len(self.i)

    def where(self, keep: np.ndarray) -> "Matches":
        return Matches(self.i[keep], self.j[keep], self.xi[keep], self.xj[keep])


@dataclass
class RotationSolve:
    """Rotations of the frames about one centre, with how well they explain the matches."""

    R: np.ndarray  # (N, 3, 3) camera-from-world, OpenCV axes; identity for frame 0
    connected: np.ndarray  # (N,) bool: frames with enough matches to fix their rotation
    residual: np.ndarray  # (M,) transfer error |x_j − π(K R_j R_iᵀ K⁻¹ x̃_i)|, pixels
    cost_seconds: float = 0.0


def bearings(x: np.ndarray, f: float, c: np.ndarray) -> np.ndarray:
    """Pixel positions (M, 2) -> unit viewing rays (M, 3) in the camera (OpenCV axes)."""
    b = np.concatenate([(x - c) / f, np.ones((len(x), 1))], 1)
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def project(b: np.ndarray, f: float, c: np.ndarray) -> np.ndarray:
    """Rays (M, 3) in the camera -> pixels (M, 2); rays behind the camera land far away."""
    z = np.where(b[:, 2] > 1e-6, b[:, 2], 1e-6)
    return f * b[:, :2] / z[:, None] + c


def transfer(m: Matches, R: np.ndarray, f: float, c: np.ndarray) -> np.ndarray:
    """Where each match's first point lands in its second frame under rotations R (N, 3, 3):
    -> (M, 2) pixels."""
    rel = np.einsum("mab,mcb->mac", R[m.j], R[m.i])  # R_j R_iᵀ
    return project(np.einsum("mab,mb->ma", rel, bearings(m.xi, f, c)), f, c)


def _chain(m: Matches, n: int, f: float, c: np.ndarray, min_matches: int
           ) -> tuple[np.ndarray, np.ndarray]:
    """Starting rotations: each frame from the nearest earlier frame it shares enough
    matches with (Procrustes of their rays). -> R (n, 3, 3), connected (n,)."""
    R = np.tile(np.eye(3), (n, 1, 1))
    ok = np.zeros(n, bool)
    ok[0] = True
    for j in range(1, n):
        for i in range(j - 1, -1, -1):
            sel = (m.i == i) & (m.j == j)
            if ok[i] and sel.sum() >= min_matches:
                # Kabsch: the rotation taking frame i's rays onto frame j's
                rel, _ = Rotation.align_vectors(bearings(m.xj[sel], f, c),
                                                bearings(m.xi[sel], f, c))
                R[j], ok[j] = rel.as_matrix() @ R[i], True
                break
    return R, ok


def solve_rotations(m: Matches, n: int, f: float, c: np.ndarray, robust_px: float = 1.0,
                    min_matches: int = 15, iterations: int = 15) -> RotationSolve:
    """Rotations of n frames from their matches (frame positions in m.i < m.j), focal f and
    principal point c (2,) in the matches' pixels: a Cauchy-robust fit of the transfer
    errors (outliers: what moves by itself, mismatches) by iteratively reweighted
    Gauss-Newton on local rotation increments. Frames not connected to frame 0 through
    pairs of at least `min_matches` keep the identity and are reported."""
    t0 = time.perf_counter()
    R, connected = _chain(m, n, f, c, min_matches)
    use = connected[m.i] & connected[m.j]
    mu = m.where(use)
    col = np.full(n, -1)
    free = np.flatnonzero(connected[1:]) + 1  # frame 0 fixes the world's orientation
    col[free] = 3 * np.arange(len(free))
    if len(free) and len(mu):
        b_i = bearings(mu.xi, f, c)
        for _ in range(iterations):
            step = _gauss_newton_step(mu, b_i, R, f, c, col, 3 * len(free), robust_px)
            R[free] = Rotation.from_rotvec(step.reshape(-1, 3)).as_matrix() @ R[free]
            if np.abs(step).max() < 1e-7:
                break
    residual = np.full(len(m), np.inf)
    residual[use] = np.linalg.norm(transfer(mu, R, f, c) - mu.xj, axis=1)
    return RotationSolve(R, connected, residual, time.perf_counter() - t0)


def _gauss_newton_step(m: Matches, b_i: np.ndarray, R: np.ndarray, f: float, c: np.ndarray,
                       col: np.ndarray, dim: int, robust_px: float) -> np.ndarray:
    """One reweighted Gauss-Newton step for increments δ_k (R_k <- exp([δ_k]) R_k) of the
    frames with col >= 0: -> (dim,). With p = R_j R_iᵀ b_i: ∂p/∂δ_j = −[p]×,
    ∂p/∂δ_i = R_j R_iᵀ [b_i]×; ∂π/∂p = f/z [[1, 0, −x/z], [0, 1, −y/z]]."""
    rel = np.einsum("mab,mcb->mac", R[m.j], R[m.i])
    p = np.einsum("mab,mb->ma", rel, b_i)
    z = np.maximum(p[:, 2], 1e-6)
    r = f * p[:, :2] / z[:, None] + c - m.xj  # (M, 2)
    dpi = np.zeros((len(m), 2, 3))
    dpi[:, 0, 0] = dpi[:, 1, 1] = f / z
    dpi[:, :, 2] = -f * p[:, :2] / z[:, None] ** 2
    blocks = ((m.i, dpi @ rel @ skew(b_i)), (m.j, -dpi @ skew(p)))
    w = 1.0 / (1.0 + (r ** 2).sum(1) / robust_px ** 2)  # Cauchy's IRLS weights
    A, g = np.zeros((dim, dim)), np.zeros(dim)
    for fa, Ja in blocks:
        ca = col[fa]
        ka = ca >= 0
        g_a = np.einsum("m,mab,ma->mb", w[ka], Ja[ka], r[ka])
        for d in range(3):
            np.add.at(g, ca[ka] + d, g_a[:, d])
        for fb, Jb in blocks:
            cb = col[fb]
            kk = ka & (cb >= 0)
            H = np.einsum("m,mab,mac->mbc", w[kk], Ja[kk], Jb[kk])
            for d in range(3):
                for e in range(3):
                    np.add.at(A, (ca[kk] + d, cb[kk] + e), H[:, d, e])
    A[np.diag_indices(dim)] += 1e-6 * (1 + A.diagonal())  # Levenberg's damping, tiny
    return -np.linalg.solve(A, g)


def sampson(m: Matches, w2c: np.ndarray, f: float, c: np.ndarray) -> np.ndarray:
    """Sampson distance (pixels) of each match to its epipolar line under the cameras
    w2c (N, 3, 4) camera-from-world, OpenCV axes: -> (M,); NaN where a frame has no pose."""
    K = np.array([[f, 0, c[0]], [0, f, c[1]], [0, 0, 1.0]])
    Ki = np.linalg.inv(K)
    Ri, ti, Rj, tj = w2c[m.i, :, :3], w2c[m.i, :, 3], w2c[m.j, :, :3], w2c[m.j, :, 3]
    rel = np.einsum("mab,mcb->mac", Rj, Ri)
    t = tj - np.einsum("mab,mb->ma", rel, ti)
    F = Ki.T @ np.einsum("mab,mbc->mac", skew(t), rel) @ Ki
    a = np.concatenate([m.xi, np.ones((len(m), 1))], 1)
    b = np.concatenate([m.xj, np.ones((len(m), 1))], 1)
    Fa, Ftb = np.einsum("mab,mb->ma", F, a), np.einsum("mba,mb->ma", F, b)
    num = np.einsum("ma,ma->m", b, Fa)
    den = Fa[:, 0] ** 2 + Fa[:, 1] ** 2 + Ftb[:, 0] ** 2 + Ftb[:, 1] ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.abs(num) / np.sqrt(den)


def gric(e2: np.ndarray, sigma: float, d: int, k: int) -> float:
    """Torr's GRIC of a model of dimension d with k parameters whose squared distances to
    its manifold are e2 (n,), noise σ (pixels)."""
    n = len(e2)
    rho = np.minimum(e2 / sigma ** 2, _LAMBDA3 * (_R - d)).sum()
    return float(rho + _LAMBDA1 * d * n + np.log(_R * n) * k)


def noise_sigma(e: np.ndarray, floor: float = 0.3) -> float:
    """The matches' noise (pixels) from distances to the best model: robust (MAD) scale."""
    e = e[np.isfinite(e)]
    return max(floor, 1.4826 * float(np.median(np.abs(e)))) if len(e) else floor


def compare_models(rot_residual: np.ndarray, sfm_sampson: np.ndarray | None,
                   frames: int) -> dict:
    """GRIC of the rotation model and of SfM on the matches both explain (lower wins).
    rot_residual: transfer errors (the manifold distance is half of it squared: both
    points are noisy), sfm_sampson: Sampson distances, or None without an SfM solution."""
    ok = np.isfinite(rot_residual)
    if sfm_sampson is not None:
        ok &= np.isfinite(sfm_sampson)
    e_rot2 = rot_residual[ok] ** 2 / 2
    out = {"matches": int(ok.sum()),
           "rotation_median_px": float(np.median(np.sqrt(e_rot2))) if ok.any() else None}
    if sfm_sampson is None or not ok.any():
        out["sigma_px"] = noise_sigma(np.sqrt(e_rot2)) if ok.any() else None
        return out
    e_sfm2 = sfm_sampson[ok] ** 2
    sigma = noise_sigma(np.sqrt(e_sfm2))
    g_rot = gric(e_rot2, sigma, 2, 3 * (frames - 1))
    g_sfm = gric(e_sfm2, sigma, 3, 6 * (frames - 1) - 1)
    out.update(sigma_px=sigma, sfm_median_px=float(np.median(np.sqrt(e_sfm2))),
               gric_rotation=g_rot, gric_sfm=g_sfm,
               gric_per_match=(g_sfm - g_rot) / max(int(ok.sum()), 1),
               chosen="rotation" if g_rot < g_sfm else "sfm")
    return out
