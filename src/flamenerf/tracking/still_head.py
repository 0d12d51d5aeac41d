"""The still-head hypothesis for the background's cameras: a joint adjustment of the
background's feature tracks and the cameras, started from (and softly held to) the cameras
the face gives when the head is the world.

Why: over a short baseline with a distant, defocused background, incremental SfM could
settle in the mirror-image basin (the camera's sideways motion reversed, its turn explaining
the rest), and the composed world would then have a still head moving centimetres. The
question is whether a world with a still head explains the background about as well.
COLMAP's own tools do not answer it from the face's start: strict triangulation from the
face's cameras (1–2° off the background's) keeps a handful of points, and a free bundle
adjustment of a loose one drifts away from the face's cameras. Holding every camera to the
face's pose with a prior (σ 1°, 1 cm) while the tracks pull it onto the background does,
with the points started in front of the cameras and those that end behind them counted as
not fitting (a point behind them projects to the same pixels up to sign, and a first
version "fitted" the orbit clip that way).

    SfM tracks -> points triangulated from the face's cameras (DLT; behind them: far along
    their ray) -> robust joint adjustment (soft-L1 reweighted Levenberg-Marquardt, analytic
    sparse Jacobian) -> accepted when it explains the background about as well as SfM with
    the cameras still near the face's, or, when SfM's world contradicts the face (the
    least-squares metric scale that composes them is not positive: the face says the
    camera travels the other way), when it explains the background acceptably

The second rule came from the shared orbit clip (a still head): SfM's world fits its
background better (0.94 against 1.40 source px) but composes into a head that slides 20 cm,
more than the camera travels; trained on the adjusted world instead, `fast` scored 30.7 dB
driven against 27.3 (face 35.7 against 31.9, background 30.0 against 26.7; docs/head_pose.md).
The adjusted world is not a still head imposed: the head's own motion is composed from it
as from SfM's (for a synthetic head that turned 10°, the adjusted cameras turn away from the
face's: tests/tracking/test_still_head.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flamenerf.geometry import cayley, cayley_grad
from flamenerf.tracking.world import metric_scale


RULE_AS_GOOD = "as good as SfM"
"""`info["rule"]` when the adjusted world explains the background about as well as SfM's."""
RULE_CONTRADICTED = "SfM contradicts the face"
"""`info["rule"]` when it was kept because SfM's world has the camera travel against the
face's account (the report then says so, and may point to the field of view)."""


@dataclass
class StillHeadOptions:
    rot_sigma_deg: float = 1.0
    """Prior: how far (1σ) a camera may turn from the face's camera."""
    pos_sigma_m: float = 0.01
    """Prior: how far (1σ) a camera centre may move from the face's (metres)."""
    robust_px: float = 2.0
    """Soft-L1 scale of the reprojection residuals (COLMAP's pixels: the frames as given to
    it, downscaled from the source's; so are the other pixel figures here)."""
    inlier_px: float = 4.0
    """Observations within this many pixels count as inliers (COLMAP's own filter)."""
    min_inliers: float = 0.95
    """Accepted only if this fraction of the observations are inliers ..."""
    max_error_ratio: float = 1.25
    """... their mean error is at most this times SfM's mean error ..."""
    max_turn_deg: float = 2.0
    """... and the cameras turned at most this far from the face's (median over frames);
    further, the head moved against the background and the hypothesis is wrong."""
    contradicted_min_inliers: float = 0.9
    """Where SfM's world contradicts the face: accepted if this fraction are inliers ..."""
    contradicted_error_ratio: float = 2.0
    """... and their mean error is at most this times SfM's."""
    max_iterations: int = 100


def tracks(rec, names: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]:
    """The observations of a pycolmap Reconstruction's points. -> frame index (K,) into
    `names`, point index (K,), pixel (K, 2), the point ids (M,)."""
    pos = {n: k for k, n in enumerate(names)}
    point_ids = list(rec.points3D.keys())
    obs = []
    for j, pid in enumerate(point_ids):
        for el in rec.points3D[pid].track.elements:
            im = rec.images[el.image_id]
            u, v = im.points2D[el.point2D_idx].xy
            obs.append((pos[im.name], j, u, v))
    obs = np.asarray(obs, np.float64).reshape(-1, 4)
    return obs[:, 0].astype(int), obs[:, 1].astype(int), obs[:, 2:], point_ids


def reconstruction_c2w(rec, names: list[str]) -> np.ndarray:
    """The camera-to-world of each named image in a pycolmap reconstruction (OpenCV axes,
    its units), NaN where it has no pose. -> (len(names), 4, 4)"""
    pos = {n: k for k, n in enumerate(names)}
    c2w = np.full((len(names), 4, 4), np.nan)
    for im in rec.images.values():
        if im.has_pose and im.name in pos:
            w2c = np.eye(4)
            w2c[:3] = im.cam_from_world().matrix()
            c2w[pos[im.name]] = np.linalg.inv(w2c)
    return c2w


def triangulate(K: np.ndarray, w2c: np.ndarray, fi: np.ndarray, pj: np.ndarray,
                uv: np.ndarray, num_points: int) -> np.ndarray:
    """Linear (DLT) triangulation of each track: K (3, 3), w2c (N, 3, 4) OpenCV cameras,
    observations fi/pj (K,), uv (K, 2). -> points (M, 3)"""
    P = np.einsum("ab,nbc->nac", K, w2c)[fi]  # (K, 3, 4)
    rows = np.concatenate([uv[:, :1] * P[:, 2] - P[:, 0], uv[:, 1:] * P[:, 2] - P[:, 1]], 1)
    X = np.zeros((num_points, 3))
    order = np.argsort(pj, kind="stable")
    starts = np.searchsorted(pj[order], np.arange(num_points + 1))
    for j in range(num_points):
        A = rows[order[starts[j]:starts[j + 1]]].reshape(-1, 4)
        V = np.linalg.svd(A)[2][-1]
        X[j] = V[:3] / V[3] if abs(V[3]) > 1e-12 else np.nan
    return X


def _in_front(X: np.ndarray, K: np.ndarray, w2c: np.ndarray, fi: np.ndarray, pj: np.ndarray,
              uv: np.ndarray) -> np.ndarray:
    """Points (M, 3) the linear triangulation put behind their cameras (a distant point seen
    with little parallax lands "beyond infinity") or nowhere -> far along their first
    observation's ray (100x the median depth of the others), for the adjustment to pull in."""
    R, t = w2c[:, :, :3], w2c[:, :, 3]
    bad = ~np.isfinite(X).all(1)
    Xs = np.where(bad[:, None], 0.0, X)
    depth = np.einsum("kb,kb->k", R[fi, 2], Xs[pj]) + t[fi, 2]
    behind = np.bincount(pj, depth <= 0, len(X)) > 0
    bad |= behind
    if not bad.any():
        return X
    far = 100 * float(np.median(depth[~bad[pj]])) if (~bad[pj]).any() else 100.0
    first = np.full(len(X), -1)
    first[pj[::-1]] = np.arange(len(pj))[::-1]
    k = first[bad]
    ray = np.linalg.solve(K, np.concatenate([uv[k], np.ones((len(k), 1))], 1).T).T
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    centre = -np.einsum("kba,kb->ka", R[fi[k]], t[fi[k]])
    out = X.copy()
    out[bad] = centre + far * np.einsum("kba,kb->ka", R[fi[k]], ray)
    return out


@dataclass
class Adjusted:
    w2c: np.ndarray  # (N, 3, 4) OpenCV cameras
    points: np.ndarray  # (M, 3)
    errors: np.ndarray  # (K,) reprojection error of every observation, px
    turn_deg: np.ndarray  # (N,) each camera's turn from its prior
    shift_m: np.ndarray  # (N,) each camera centre's distance from its prior


def adjust(K: np.ndarray, w2c0: np.ndarray, fi: np.ndarray, pj: np.ndarray, uv: np.ndarray,
           opts: StillHeadOptions) -> Adjusted:
    """Jointly adjust cameras and points: K (3, 3); w2c0 (N, 3, 4) the prior cameras
    (OpenCV, metres), also the start; observations fi/pj (K,), uv (K, 2)."""
    from scipy.sparse import csr_matrix

    N, M = len(w2c0), int(pj.max()) + 1
    R0, C0 = w2c0[:, :, :3], -np.einsum("nba,nb->na", w2c0[:, :, :3], w2c0[:, :, 3])
    X0 = _in_front(triangulate(K, w2c0, fi, pj, uv, M), K, w2c0, fi, pj, uv)
    f, cx, cy = K[0, 0], K[0, 2], K[1, 2]
    wr = 1.0 / np.tan(np.radians(opts.rot_sigma_deg) / 2)  # Cayley |r| = tan(angle / 2)
    wt = 1.0 / opts.pos_sigma_m
    n_obs = len(fi)

    def unpack(x):
        return x[:3 * N].reshape(N, 3), x[3 * N:6 * N].reshape(N, 3), x[6 * N:].reshape(M, 3)

    def cam_points(x):
        r, c, X = unpack(x)
        R = cayley(r) @ R0
        d = X[pj] - c[fi]
        return r, R, d, np.einsum("kab,kb->ka", R[fi], d)

    def residuals(x):
        r, R, d, p = cam_points(x)
        z = np.where(np.abs(p[:, 2]) < 1e-9, 1e-9, p[:, 2])
        e = (np.stack([f * p[:, 0] / z + cx, f * p[:, 1] / z + cy], 1) - uv).ravel()
        return np.concatenate([e, (r * wr).ravel(), ((unpack(x)[1] - C0) * wt).ravel()])

    def jacobian(x):
        r, R, d, p = cam_points(x)
        z = np.where(np.abs(p[:, 2]) < 1e-9, 1e-9, p[:, 2])
        # d(pixel)/d(camera point): (K, 2, 3)
        J = np.zeros((n_obs, 2, 3))
        J[:, 0, 0] = J[:, 1, 1] = f / z
        J[:, 0, 2], J[:, 1, 2] = -f * p[:, 0] / z ** 2, -f * p[:, 1] / z ** 2
        dR = np.einsum("nabk,nbc->nack", cayley_grad(r), R0)  # (N, 3, 3, 3)
        Jr = np.einsum("kij,kjlm,kl->kim", J, dR[fi], d)  # (K, 2, 3)
        JX = np.einsum("kij,kjl->kil", J, R[fi])
        rows = np.repeat(np.arange(2 * n_obs).reshape(n_obs, 2, 1), 9, axis=2)
        cols = np.concatenate([3 * fi[:, None] + np.arange(3), 3 * N + 3 * fi[:, None]
                               + np.arange(3), 6 * N + 3 * pj[:, None] + np.arange(3)], 1)
        cols = np.repeat(cols[:, None, :], 2, axis=1)
        vals = np.concatenate([Jr, -JX, JX], 2)
        prior = np.arange(6 * N)
        return csr_matrix((np.concatenate([vals.ravel(), np.full(3 * N, wr), np.full(3 * N, wt)]),
                           (np.concatenate([rows.ravel(), 2 * n_obs + prior]),
                            np.concatenate([cols.ravel(), prior]))),
                          shape=(2 * n_obs + 6 * N, 6 * N + 3 * M))

    x = np.concatenate([np.zeros(3 * N), C0.ravel(), X0.ravel()])
    x = _levenberg_marquardt(residuals, jacobian, x, n_obs, 6 * N, opts)
    r, c, X = unpack(x)
    R = cayley(r) @ R0
    w2c = np.concatenate([R, -np.einsum("nab,nb->na", R, c)[..., None]], 2)
    errors = np.linalg.norm(residuals(x)[:2 * n_obs].reshape(-1, 2), axis=1)
    errors[cam_points(x)[3][:, 2] <= 0] = np.inf  # behind the camera: not seen there
    turn = np.degrees(2 * np.arctan(np.linalg.norm(r, axis=1)))
    return Adjusted(w2c, X, errors, turn, np.linalg.norm(c - C0, axis=1))


def _robust_weights(e: np.ndarray, n_obs: int, scale: float) -> np.ndarray:
    """Square roots of the soft-L1 IRLS weights, one per observation (on its 2-D error) and
    1 for the priors: e (2K + P,) -> (2K + P,)"""
    err2 = (e[:2 * n_obs].reshape(-1, 2) ** 2).sum(1) / scale ** 2
    w = np.repeat((1.0 + err2) ** -0.25, 2)
    return np.concatenate([w, np.ones(len(e) - 2 * n_obs)])


def _robust_cost(e: np.ndarray, n_obs: int, scale: float) -> float:
    err2 = (e[:2 * n_obs].reshape(-1, 2) ** 2).sum(1) / scale ** 2
    return float(2 * scale ** 2 * (np.sqrt(1 + err2) - 1).sum() + (e[2 * n_obs:] ** 2).sum())


def _schur_solve(A, g: np.ndarray, n_cam: int) -> np.ndarray:
    """Solve A x = g for normal equations A (sparse, symmetric) whose unknowns are n_cam
    camera parameters followed by 3-D points that no observation couples to each other
    (A's point block is block-diagonal, 3x3): eliminate the points (Schur complement), solve
    the small dense camera system, back-substitute. A direct sparse solve of the whole
    system took seconds per step from a few thousand points on (its fill-in grows with the
    points each frame sees); this stays at the camera system's size."""
    from scipy.sparse import bsr_matrix

    A = A.tocsr()
    m = (A.shape[0] - n_cam) // 3
    Acc, Acp = A[:n_cam, :n_cam].toarray(), A[:n_cam, n_cam:]
    r = n_cam + 3 * np.arange(m)[:, None, None] + np.arange(3)[None, :, None]
    c = n_cam + 3 * np.arange(m)[:, None, None] + np.arange(3)[None, None, :]
    r, c = np.broadcast_arrays(r, c)
    blocks = np.asarray(A[r.ravel(), c.ravel()]).reshape(m, 3, 3)
    inv = bsr_matrix((np.linalg.inv(blocks), np.arange(m), np.arange(m + 1)),
                     shape=(3 * m, 3 * m))
    gc, gp = g[:n_cam], g[n_cam:]
    AcpI = (Acp @ inv).tocsr()
    S = Acc - (AcpI @ Acp.T).toarray()
    xc = np.linalg.solve(S, gc - AcpI @ gp)
    xp = inv @ (gp - Acp.T @ xc)
    return np.concatenate([xc, xp])


def _levenberg_marquardt(residuals, jacobian, x: np.ndarray, n_obs: int, n_cam: int,
                         opts: StillHeadOptions) -> np.ndarray:
    """Iteratively reweighted Levenberg-Marquardt on the normal equations, points
    eliminated per step (`_schur_solve`; scipy's trust-region solver with an iterative
    inner solve needed hundreds of steps)."""
    from scipy.sparse import diags

    lam, e = 1e-3, residuals(x)
    cost = _robust_cost(e, n_obs, opts.robust_px)
    for _ in range(opts.max_iterations):
        w = _robust_weights(e, n_obs, opts.robust_px)
        J = diags(w) @ jacobian(x)
        A, g = (J.T @ J).tocsr(), J.T @ (w * e)
        d = A.diagonal() + 1e-9
        while True:
            try:
                step = _schur_solve(A + diags(lam * d), -g, n_cam)
            except np.linalg.LinAlgError:
                step = np.full_like(x, np.nan)
            x_new = x + step
            e_new = residuals(x_new)
            cost_new = _robust_cost(e_new, n_obs, opts.robust_px)
            if np.isfinite(cost_new) and cost_new < cost:
                lam = max(lam / 3, 1e-9)
                break
            lam *= 4
            if lam > 1e8:
                return x
        done = cost - cost_new < 1e-7 * cost
        x, e, cost = x_new, e_new, cost_new
        if done:
            break
    return x


def sfm_metric_scale(rec, w2c_face: np.ndarray, names: list[str]) -> float:
    """The least-squares metric scale (`world.metric_scale`) that composes SfM's cameras
    with the face's: not positive when the face says the camera travels against SfM's
    path; NaN when too few frames are registered."""
    c2w = reconstruction_c2w(rec, names)
    ok = np.isfinite(c2w[:, 0, 0])
    if ok.sum() < 2:
        return float("nan")
    cam_from_head = np.tile(np.eye(4), (int(ok.sum()), 1, 1))
    cam_from_head[:, :3] = w2c_face[ok]
    return metric_scale(c2w[ok], cam_from_head)


def still_head_hypothesis(rec, w2c_face: np.ndarray, names: list[str],
                          opts: StillHeadOptions | None = None):
    """rec: COLMAP's reconstruction (pycolmap); w2c_face (len(names), 3, 4) the face's
    cameras, head as world, OpenCV axes like COLMAP's, metres. -> (the reconstruction to use:
    `rec` or the adjusted copy, a dict of what was compared for the report)"""
    import pycolmap

    opts = opts or StillHeadOptions()
    fi, pj, uv, point_ids = tracks(rec, names)
    e_sfm = float(rec.compute_mean_reprojection_error())
    info = {"sfm_error_px": e_sfm, "sfm_points": len(point_ids), "chosen": "sfm"}
    if len(point_ids) < 10:
        info["why"] = "too few background points"
        return rec, info
    cam = next(iter(rec.cameras.values()))
    f, cx, cy = (float(v) for v in cam.params[:3])
    K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1]])
    w2c0 = w2c_face
    seen = np.unique(fi)  # frames that see a background point; the rest get no pose
    remap = np.full(len(names), -1)
    remap[seen] = np.arange(len(seen))
    adj = adjust(K, w2c0[seen], remap[fi], pj, uv, opts)
    inl = adj.errors < opts.inlier_px
    e_alt = float(adj.errors[inl].mean()) if inl.any() else float("inf")
    turn = float(np.median(adj.turn_deg))
    scale = sfm_metric_scale(rec, w2c_face, names)
    info.update(still_head_error_px=e_alt, still_head_inliers=float(inl.mean()),
                still_head_turn_deg=turn, still_head_turn_max_deg=float(adj.turn_deg.max()),
                still_head_shift_m=float(np.median(adj.shift_m)),
                sfm_metric_scale=scale)
    plain = (inl.mean() >= opts.min_inliers and e_alt <= opts.max_error_ratio * e_sfm
             and turn <= opts.max_turn_deg)
    contradicted = (np.isfinite(scale) and scale <= 0
                    and inl.mean() >= opts.contradicted_min_inliers
                    and e_alt <= opts.contradicted_error_ratio * e_sfm)
    if not (plain or contradicted):
        return rec, info
    info["rule"] = RULE_AS_GOOD if plain else RULE_CONTRADICTED
    alt = pycolmap.Reconstruction(rec)
    pos = {n: k for k, n in enumerate(names)}
    for im in alt.images.values():
        if not im.has_pose:
            continue
        k = remap[pos[im.name]]
        if k >= 0:
            alt.frame(im.frame_id).rig_from_world = pycolmap.Rigid3d(adj.w2c[k])
        else:  # a pose in SfM's world and scale would not fit this one: unregistered
            alt.deregister_frame(im.frame_id)
    for j, pid in enumerate(point_ids):
        alt.point3D(pid).xyz = adj.points[j]
    # COLMAP's own filter: observations that do not fit are not part of the track
    for k in np.flatnonzero(~inl):
        pid = point_ids[pj[k]]
        if alt.exists_point3D(pid):
            im = next(e.image_id for e in alt.point3D(pid).track.elements
                      if pos[alt.images[e.image_id].name] == fi[k])
            idx = next(e.point2D_idx for e in alt.point3D(pid).track.elements
                       if e.image_id == im)
            alt.delete_observation(im, idx)
    alt.update_point_3d_errors()
    info.update(chosen="still head", still_head_points=int(alt.num_points3D()))
    return alt, info
