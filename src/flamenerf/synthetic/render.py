"""Ray casting of the synthetic scene: the head (ray marching a star-shaped surface) in front
of the body and room (analytic primitives), with local Lambertian shading only (no shadows,
no inter-reflection), so the face never lights the background.

Each pixel's colour is the mean of a 2 x 2 grid of rays at quarter offsets; its depth is
the z-depth of a fifth ray through the pixel centre, cast exactly as `flamenerf.data.rays`
casts it (camera-space direction ((x - cx) / fx, -(y - cy) / fy, -1)), so reprojecting a
depth map with the dataset's cameras is exact.

Rays are kept as separate contiguous x, y, z tensors: elementwise torch ops on strided
views are several times slower on CPU.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from flamenerf.data.dataset import Intrinsics
from flamenerf.geometry import project
from flamenerf.synthetic.background import Backdrop, sway_pose
from flamenerf.synthetic.cameras import intrinsics
from flamenerf.synthetic.head import (CONTROLS, R_INNER, R_OUTER, TEX_STEP, Head, HeadState,
                                      mesh_layout)
from flamenerf.data.prior import rasterize_silhouette

LIGHT = tuple(float(x) for x in np.array([-0.5, 0.6, 0.65]) / np.linalg.norm([-0.5, 0.6, 0.65]))
AMBIENT, KEY, SKY = 0.30, 0.72, 0.10
# sub-pixel sample positions (x, y) from the pixel's top-left corner; the first is the centre
OFFSETS = ((0.5, 0.5), (0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75))
MARCH_STEPS, BISECT = 40, 7  # full march: samples through the head's shell, bisections
BISECT_SUB = 3  # bisections for sub-pixel rays (their depth is not output)
# guided rays: brackets around the interpolated depth (metres), tried in turn
TIGHT_BRACKET = (-0.0012, 0.0012)
WIDE_BRACKET = (-0.003, -0.001, 0.001, 0.003, 0.005)
GUESS_SPREAD = 0.01  # surrounding depths further apart than this: march their span
LOCAL_MARGIN, LOCAL_STEPS, LOCAL_STEP = 0.006, 14, 0.003  # marching the span: margin, max samples
INF = float("inf")


@dataclass
class View:
    """One rendered frame."""

    rgb: np.ndarray  # (H, W, 3) float32 in [0, 1]
    depth: np.ndarray  # (H, W) float32 z-depth (metres) of the pixel-centre ray
    mask: np.ndarray  # (H, W) bool: the face mesh's silhouette (dilated)
    face_vertices: np.ndarray  # (V, 3) float32, world (posed by the head pose)
    # (H, W) bool, from what any of a pixel's rays hit: the person (head, neck, torso), and
    # what moves by itself (the handheld scene's leaves; all False in the others)
    person: np.ndarray | None = None
    moving: np.ndarray | None = None


def shade(albedo: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """Lambertian key light + ambient + sky, world frame. albedo, normal (3, N) -> (3, N)."""
    lam = (normal[0] * LIGHT[0] + normal[1] * LIGHT[1] + normal[2] * LIGHT[2]).clamp(min=0)
    return albedo * (AMBIENT + KEY * lam + SKY * (0.5 + 0.5 * normal[1]))


class SyntheticScene:
    """The built-in portrait scene: one seed fixes appearance, camera path, sway and
    expressions. `render` gives ground truth for any camera, expression and body pose.
    `handheld`: the far skyline and swaying leaves instead of the room (background.py)."""

    names: tuple[str, ...] = CONTROLS

    def __init__(self, seed: int = 0, size: int = 256, sway: float = 1.0,
                 handheld: bool = False):
        self.seed, self.size, self.sway = int(seed), int(size), float(sway)
        self.handheld = bool(handheld)
        # small images get coarser textures (faster to build; finer detail would alias)
        self.head, self.backdrop = _parts(self.seed, 1 if self.size >= 160 else 2,
                                          self.handheld)
        self.intr: Intrinsics = intrinsics(self.size)
        self.mask_dilate = mask_dilation(self.intr)

    @property
    def faces(self) -> np.ndarray:
        """Face-mesh triangles (F, 3) int32."""
        return self.head.faces

    @staticmethod
    def mesh_faces() -> np.ndarray:
        """Face-mesh triangles (F, 3) int32, without building a scene."""
        return mesh_layout()[1]

    def body_pose(self, frame: float) -> np.ndarray:
        """World-from-body pose (4, 4) at capture frame `frame` (identity if sway = 0)."""
        return sway_pose(frame, self.sway, self.seed)

    def head_state(self, expression) -> HeadState:
        return self.head.state(expression)

    # ------------------------------------------------------------------ rendering

    def render(self, c2w: np.ndarray, expression, body_pose: np.ndarray | None = None,
               intr: Intrinsics | None = None, head_pose: np.ndarray | None = None,
               time: float | None = None) -> View:
        """Render one frame: camera-to-world c2w (4, 4, OpenGL axes), expression
        (num_controls,) in [0, 1], world-from-body pose (default identity), intrinsics
        (default the scene's), world-from-head pose (default identity: the head is the
        world, as in the paper's capture), time in capture frames (30 per second: capture
        frame t is time t) for what moves by itself (the handheld scene's leaves; None is
        time 0; the other scenes do not depend on it).

        The head is ray-marched in its own frame (the camera taken there by the inverse
        head pose) and shaded with its own-frame normals: its light turns with it, so a
        rigid head model can reproduce any head pose exactly (real heads' shading changes
        under a turn are not modelled)."""
        intr = intr or self.intr
        st = self.head.state(expression)
        c2w = np.asarray(c2w, np.float64)
        o = tuple(float(x) for x in c2w[:3, 3])
        d = _ray_dirs(intr, torch.tensor(c2w, dtype=torch.float32))  # (K, 3, N)
        K, _, N = d.shape
        if head_pose is None:
            o_h, d_h, verts = o, d, st.vertices
        else:  # rigid: the ray parameter t is the same in both frames
            hp = np.asarray(head_pose, np.float64)
            c2h = np.linalg.inv(hp) @ c2w
            o_h = tuple(float(x) for x in c2h[:3, 3])
            d_h = _ray_dirs(intr, torch.tensor(c2h, dtype=torch.float32))
            verts = (st.vertices @ hp[:3, :3].T + hp[:3, 3]).astype(np.float32)
        t_head = self._march_head(st, o_h, d_h, intr).reshape(-1)  # (K*N,)
        dx, dy, dz = (d[:, c].reshape(-1) for c in range(3))
        hx, hy, hz = (d_h[:, c].reshape(-1) for c in range(3))
        pose = np.eye(4) if body_pose is None else np.asarray(body_pose, np.float64)
        tr = self.backdrop.trace(o, dx, dy, dz, pose, candidates=_box_culler(intr, c2w, pose, K))
        # depth from the centre rays; colour from the 2 x 2 sub-pixel rays
        depth = torch.minimum(t_head[:N], tr.t[:N]).reshape(intr.h, intr.w)
        head_vis = t_head[N:] < tr.t[N:]
        colour = torch.zeros(3, (K - 1) * N)
        for vis, is_head in ((head_vis, True), (~head_vis, False)):
            pos = vis.nonzero().flatten()
            if not len(pos):
                continue
            ids = pos + N
            if is_head:
                th = t_head.index_select(0, ids)
                px = o_h[0] + th * hx.index_select(0, ids)
                py = o_h[1] + th * hy.index_select(0, ids)
                pz = o_h[2] + th * hz.index_select(0, ids)
                alb, n = self.head.surface(st, px, py, pz)
            else:
                alb, n = self.backdrop.surface(tr, ids, time)
            colour.index_copy_(1, pos, shade(alb, n))
        rgb = colour.clamp(0, 1).reshape(3, K - 1, intr.h, intr.w).mean(1).permute(1, 2, 0)
        dilate = self.mask_dilate if intr is self.intr else mask_dilation(intr)
        mask = rasterize_silhouette(verts, self.faces, intr, c2w, dilate)
        person, moving = self._seen(t_head < tr.t, tr.which, K, intr)
        return View(rgb=rgb.contiguous().numpy(), depth=depth.numpy().astype(np.float32),
                    mask=mask, face_vertices=verts, person=person, moving=moving)

    def _seen(self, head: torch.Tensor, which: torch.Tensor, K: int, intr: Intrinsics):
        """Pixels where any of their K rays sees the person, and where any sees what moves
        by itself, from whether each ray (K * H * W,) hits the head first and which
        background primitive it hits -> two (H, W) bool arrays. Any ray rather than the
        centre one: a pixel outside `moving` takes no colour from the leaves at all."""
        def on(prims) -> torch.Tensor:
            hit = torch.zeros_like(head)
            for k in prims:
                hit |= which == k
            return hit

        def pixels(rays: torch.Tensor) -> np.ndarray:
            return rays.reshape(K, intr.h, intr.w).any(0).numpy()

        return (pixels(head | on(self.backdrop.person)),
                pixels(~head & on(self.backdrop.moving)))

    # ------------------------------------------------------------------ head marching

    @staticmethod
    def _f(st: HeadState, x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """Signed radial distance |p| - R(direction of p), negative inside the head."""
        r = torch.sqrt(x * x + y * y + z * z)
        gx = torch.atan2(x, z) * (1 / math.pi)
        gy = torch.asin((y / r).clamp(-1.0, 1.0)) * (-2 / math.pi)
        g = torch.view_as_real(torch.complex(gx, gy)).reshape(1, 1, -1, 2)
        R = F.grid_sample(st.radius[None], g, mode="bilinear", padding_mode="border",
                          align_corners=False)
        return r - R.reshape(r.shape)

    def _f_at(self, st, o, d, t):
        """_f at o + t d; d = (dx, dy, dz) of shape (n,), t of shape (n,) or (n, S)."""
        if t.ndim == 2:
            d = tuple(c[:, None] for c in d)
        return self._f(st, o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2])

    def _crossing(self, st, o, d, ts):
        """First crossing into the head along samples ts (n, S) of rays d (tuples of (n,)).

        -> found (n,) bool (a crossing after an outside first sample), start_inside (n,)
        bool, and the bracket lo, hi, f_lo, f_hi (n,) (meaningful where found)."""
        f = self._f_at(st, o, d, ts)
        inside = f <= 0
        first = inside.to(torch.int8).argmax(1)
        start_inside = inside[:, 0]
        found = inside.any(1) & ~start_inside
        i1 = first[:, None]
        i0 = (first - 1).clamp(min=0)[:, None]
        return (found, start_inside, ts.gather(1, i0)[:, 0], ts.gather(1, i1)[:, 0],
                f.gather(1, i0)[:, 0], f.gather(1, i1)[:, 0])

    def _bisect(self, st, o, d, lo, hi, f_lo, f_hi, steps: int = BISECT) -> torch.Tensor:
        """Bisection on a bracket (f_lo > 0 >= f_hi), then one secant step."""
        for _ in range(steps):
            mid = 0.5 * (lo + hi)
            fm = self._f_at(st, o, d, mid)
            m = (fm <= 0).to(torch.float32)  # 1: mid is inside
            hi = torch.lerp(hi, mid, m)
            f_hi = torch.lerp(f_hi, fm, m)
            lo = torch.lerp(mid, lo, m)
            f_lo = torch.lerp(fm, f_lo, m)
        w = (f_lo / (f_lo - f_hi).clamp(min=1e-12)).clamp(0, 1)
        return lo + (hi - lo) * w

    def _solve(self, st, o, d, t0, t1, guess=None, lo_cs=None, hi_cs=None, near=None,
               use=None, bisect: int = BISECT):
        """Head hits of rays d (3 tensors (n,)) with shell span [t0, t1] (n,).

        Without a guess: march the whole shell (only rays with near=True, default all).
        With a guess (interpolated from surrounding rays whose depths span [lo_cs, hi_cs]):
        rays with `use` bracket the surface just around the guess, then a little wider;
        the rest of the rays `near` march the span of the surrounding depths (with a
        margin), then the whole shell. One bisection refines every bracket at the end.
        -> indices (into n) of the rays that hit, and their t."""
        n = t0.shape[0]
        found_ids, los, his, flos, fhis = [], [], [], [], []

        def take(ids, ts):
            dk = tuple(c.index_select(0, ids) for c in d)
            found, start_in, lo, hi, flo, fhi = self._crossing(st, o, dk, ts)
            k = found.nonzero().flatten()
            found_ids.append(ids.index_select(0, k))
            for acc, v in ((los, lo), (his, hi), (flos, flo), (fhis, fhi)):
                acc.append(v.index_select(0, k))
            return ids[~found], ids[start_in]

        full = torch.arange(n) if near is None else near.nonzero().flatten()
        if guess is not None:
            sel = use.nonzero().flatten()
            for offsets in (TIGHT_BRACKET, WIDE_BRACKET):
                if len(sel):
                    sel, _ = take(sel, guess.index_select(0, sel)[:, None] + torch.tensor(offsets))
            rest = torch.cat([(near & ~use).nonzero().flatten(), sel])
            a = torch.maximum(lo_cs.index_select(0, rest) - LOCAL_MARGIN, t0.index_select(0, rest))
            b = torch.minimum(hi_cs.index_select(0, rest) + LOCAL_MARGIN, t1.index_select(0, rest))
            short = (b - a < LOCAL_STEPS * LOCAL_STEP) & (b > a)
            loc = short.nonzero().flatten()
            full = rest[~short]
            if len(loc):
                k = torch.arange(LOCAL_STEPS + 1, dtype=torch.float32) / LOCAL_STEPS
                al, bl = a.index_select(0, loc), b.index_select(0, loc)
                _, start_in = take(rest.index_select(0, loc), al[:, None] + (bl - al)[:, None] * k)
                full = torch.cat([full, start_in])  # the span started inside: march it all
        if len(full):
            k = torch.arange(MARCH_STEPS + 1, dtype=torch.float32) / MARCH_STEPS
            a, b = t0.index_select(0, full), t1.index_select(0, full)
            take(full, a[:, None] + (b - a)[:, None] * k)  # t0 is on the outer sphere: outside
        ids = torch.cat(found_ids)
        if not len(ids):
            return ids, torch.zeros(0)
        dk = tuple(c.index_select(0, ids) for c in d)
        t = self._bisect(st, o, dk, torch.cat(los), torch.cat(his), torch.cat(flos),
                         torch.cat(fhis), bisect)
        return ids, t

    def _guided(self, st, o, d, t0, t1, ok, cs, wx, wy, bisect: int):
        """_solve for rays `ok` guided by the depths cs (4, n) of the surrounding rays
        (bilinear weights wx, wy); rays none of whose surrounding rays hit are misses (the
        head has no feature thinner than the spacing of those rays)."""
        guess = (1 - wy) * ((1 - wx) * cs[0] + wx * cs[1]) + wy * ((1 - wx) * cs[2] + wx * cs[3])
        # misses are +inf: min over all = min over hits; max over hits via inf -> -1
        lo_cs = cs.amin(0)
        hi_cs = cs.nan_to_num(posinf=-1.0).amax(0)
        near = ok & (lo_cs < INF)
        use = near & torch.isfinite(guess) & (hi_cs - lo_cs < GUESS_SPREAD)
        return self._solve(st, o, d, t0, t1, guess, lo_cs, hi_cs, near, use, bisect)

    def _march_head(self, st: HeadState, o, d: torch.Tensor, intr: Intrinsics) -> torch.Tensor:
        """Head hits t (K, N) of all rays (inf where they miss the head).

        Centre rays on a coarse pixel grid march the whole shell; the centre rays of each
        finer grid, then the sub-pixel rays, search around depths interpolated from the
        grid before, and march only where that fails."""
        K, _, N = d.shape
        h, w = intr.h, intr.w
        t = torch.full((K, N), INF)
        t0, t1, ok = _shell(o, d)
        tc = t[0]
        stride = 4 if min(h, w) >= 192 else 2 if min(h, w) >= 96 else 1
        pix = torch.arange(N).reshape(h, w)
        # 1. coarse centre rays: the whole shell
        ids = pix[::stride, ::stride].reshape(-1)
        ids = ids[ok[0].index_select(0, ids)]
        if len(ids):
            sub = lambda x: x.index_select(-1, ids)  # noqa: E731, B023 (used at once)
            hit, th = self._solve(st, o, tuple(sub(d[0, c]) for c in range(3)), sub(t0[0]),
                                  sub(t1[0]))
            tc.index_copy_(0, ids.index_select(0, hit), th)
        # 2. finer centre-ray grids, each guided by the one before
        while stride > 1:
            fine = stride // 2
            prev = tc.reshape(h, w)[::stride, ::stride]
            ii = torch.arange(0, h, fine, dtype=torch.float32) / stride
            jj = torch.arange(0, w, fine, dtype=torch.float32) / stride
            cs, wx, wy = _corners(prev, ii, jj)
            ids = pix[::fine, ::fine].reshape(-1)
            keep = (((ids // w) % stride != 0) | ((ids % w) % stride != 0)).nonzero().flatten()
            ids = ids.index_select(0, keep)
            sub = lambda x: x.index_select(-1, ids)  # noqa: E731, B023 -- used within this iteration
            hit, th = self._guided(st, o, tuple(sub(d[0, c]) for c in range(3)), sub(t0[0]),
                                   sub(t1[0]), sub(ok[0]), cs.index_select(1, keep),
                                   wx.index_select(0, keep), wy.index_select(0, keep), BISECT)
            tc.index_copy_(0, ids.index_select(0, hit), th)
            stride = fine
        # 3. all sub-pixel rays at once, guided by the centre rays; they only colour the
        # pixel, so a coarser solve is plenty
        tf = tc.reshape(h, w)
        parts = []
        for k in range(1, K):
            ox, oy = OFFSETS[k]
            ii = torch.arange(h, dtype=torch.float32) + (oy - 0.5)
            jj = torch.arange(w, dtype=torch.float32) + (ox - 0.5)
            parts.append(_corners(tf, ii, jj))
        cs = torch.cat([p[0] for p in parts], 1)
        wx = torch.cat([p[1] for p in parts])
        wy = torch.cat([p[2] for p in parts])
        flat = lambda x: x[1:].reshape(-1)  # noqa: E731
        hit, th = self._guided(st, o, tuple(flat(d[:, c]) for c in range(3)), flat(t0),
                               flat(t1), flat(ok), cs, wx, wy, BISECT_SUB)
        t[1:].view(-1).index_copy_(0, hit, th)
        return t


def mask_dilation(intr: Intrinsics) -> int:
    """Pixels by which face masks are dilated: 1 up to 191 px, 2 at 256, ..."""
    return max(1, round(min(intr.w, intr.h) / 128))


@functools.lru_cache(maxsize=4)
def _parts(seed: int, coarse: int, handheld: bool = False) -> tuple[Head, Backdrop]:
    """Head and backdrop of a seed (read-only after construction, so scenes share them)."""
    head = _head(seed, coarse)
    return head, Backdrop(seed, head.palette["skin"], coarse, handheld)


@functools.lru_cache(maxsize=4)
def _head(seed: int, coarse: int) -> Head:
    """The head of a seed, the slow part, shared by the scene's variants."""
    return Head(seed, TEX_STEP * coarse)


def _box_culler(intr: Intrinsics, c2w: np.ndarray, pose: np.ndarray, K: int):
    """A function (lo, hi) -> indices (into the K * H * W rays) of the pixels that a
    body-frame box projects onto (1 pixel margin), or None when the box reaches behind
    the camera. Depends only on the camera and the body pose."""
    w2c = np.linalg.inv(c2w)

    def candidates(lo, hi):
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])])
        world = corners @ pose[:3, :3].T + pose[:3, 3]
        cam = world @ w2c[:3, :3].T + w2c[:3, 3]
        zc = -cam[:, 2]
        if (zc < 1e-3).any():
            return None
        px, py = project(cam, intr.fx, intr.fy, intr.cx, intr.cy).T
        c0, c1 = max(0, int(np.floor(px.min())) - 1), min(intr.w, int(np.ceil(px.max())) + 1)
        r0, r1 = max(0, int(np.floor(py.min())) - 1), min(intr.h, int(np.ceil(py.max())) + 1)
        if c0 >= c1 or r0 >= r1:
            return torch.zeros(0, dtype=torch.long)
        rows = torch.arange(r0, r1)[:, None] * intr.w + torch.arange(c0, c1)[None, :]
        n = intr.h * intr.w
        return (torch.arange(K)[:, None] * n + rows.reshape(1, -1)).reshape(-1)

    return candidates


def _corners(grid: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor):
    """The 4 grid values around fractional positions (ii[r], jj[c]) of a (h, w) grid, for
    every (r, c) -> values (4, R*C) (order 00, 01, 10, 11) and weights wx, wy (R*C,)."""
    h, w = grid.shape
    i0 = ii.floor().clamp(0, h - 1)
    j0 = jj.floor().clamp(0, w - 1)
    wy = (ii - i0).clamp(0, 1)
    wx = (jj - j0).clamp(0, 1)
    i0l, j0l = i0.long(), j0.long()
    i1l, j1l = (i0l + 1).clamp(max=h - 1), (j0l + 1).clamp(max=w - 1)
    r0, r1 = grid.index_select(0, i0l), grid.index_select(0, i1l)
    vals = torch.stack([r0.index_select(1, j0l), r0.index_select(1, j1l),
                        r1.index_select(1, j0l), r1.index_select(1, j1l)]).reshape(4, -1)
    WX = wx[None, :].expand(len(ii), len(jj)).reshape(-1)
    WY = wy[:, None].expand(len(ii), len(jj)).reshape(-1)
    return vals, WX, WY


def _ray_dirs(intr: Intrinsics, c2w: torch.Tensor) -> torch.Tensor:
    """World directions (K, 3, H*W), one set per sub-pixel offset; camera-space z = -1."""
    ys, xs = torch.meshgrid(torch.arange(intr.h, dtype=torch.float32),
                            torch.arange(intr.w, dtype=torch.float32), indexing="ij")
    R = c2w[:3, :3]
    out = []
    for ox, oy in OFFSETS:
        cx = ((xs + ox - intr.cx) / intr.fx).reshape(-1)
        cy = (-(ys + oy - intr.cy) / intr.fy).reshape(-1)
        out.append(torch.stack([R[i, 0] * cx + R[i, 1] * cy - R[i, 2] for i in range(3)]))
    return torch.stack(out)


def _shell(o, d: torch.Tensor):
    """For rays from o (3 floats) along d (K, 3, N): entry into the outer bounding sphere,
    entry into the inner one (or exit from the outer one), and whether the outer one is hit."""
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    a = dx * dx + dy * dy + dz * dz
    b = dx * o[0] + dy * o[1] + dz * o[2]
    oo = o[0] ** 2 + o[1] ** 2 + o[2] ** 2
    disc_o = b * b - a * (oo - R_OUTER ** 2)
    disc_i = b * b - a * (oo - R_INNER ** 2)
    sq_o = torch.sqrt(disc_o.clamp(min=0))
    sq_i = torch.sqrt(disc_i.clamp(min=0))
    t0 = ((-b - sq_o) / a).clamp(min=0)
    t_exit = (-b + sq_o) / a
    t_in = (-b - sq_i) / a
    inner = ((disc_i > 0) & (t_in > 0)).to(torch.float32)
    t1 = torch.lerp(t_exit, t_in, inner)
    return t0, t1, (disc_o > 0) & (t_exit > 0)
