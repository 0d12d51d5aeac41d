"""Everything that is not the head: torso, neck and the room behind, with textures.

These primitives live in the *body frame*. World = head frame, so when the subject's head
sways in reality, here the body and the room move instead: `sway_pose` gives the
world-from-body rigid motion of each frame (identity when the sway amplitude is 0).
All intersections are analytic (planes, ellipsoids, vertical cylinders, boxes) and the
textures are procedural images sampled bilinearly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from flamenerf.synthetic.noise import Noise, upsample

WALL_Z = -0.55
NECK_PIVOT = np.array([0.0, -0.10, -0.03])  # the body sways about this point


def _grid(h: int, w: int, x0: float, x1: float, y0: float, y1: float):
    """Texel-centre coordinates of an image covering [x0, x1] x [y0, y1] (row 0 at y1)."""
    xs = x0 + (torch.arange(w, dtype=torch.float32) + 0.5) * (x1 - x0) / w
    ys = y1 - (torch.arange(h, dtype=torch.float32) + 0.5) * (y1 - y0) / h
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    return xx, yy


def _safe(d: torch.Tensor) -> torch.Tensor:
    """Direction component with exact zeros nudged away (avoids 0 * inf)."""
    return torch.where(d == 0, torch.full_like(d, 1e-20), d)


class Primitive:
    """One textured analytic shape in the body frame. Rays come as a scalar origin o
    (3 floats) and direction components dx, dy, dz (N,)."""

    tex: torch.Tensor
    extent: tuple[float, float, float, float]  # texture covers [a0, a1] x [b0, b1]
    bounds: tuple[tuple[float, ...], tuple[float, ...]] | None = None  # body-frame AABB

    def intersect(self, o, dx, dy, dz) -> tuple[torch.Tensor, torch.Tensor | None]:
        """-> t (N,) (inf where missed) and which part was hit (or None)."""
        raise NotImplementedError

    def normal(self, x, y, z, kind, dx, dy, dz) -> torch.Tensor:
        raise NotImplementedError

    def texture_coords(self, x, y, z, n) -> tuple[torch.Tensor, torch.Tensor]:
        raise NotImplementedError

    def albedo(self, x, y, z, n) -> torch.Tensor:
        a, b = self.texture_coords(x, y, z, n)
        a0, a1, b0, b1 = self.extent
        gx = (a - a0) * (2 / (a1 - a0)) - 1
        gy = (b1 - b) * (2 / (b1 - b0)) - 1
        g = torch.view_as_real(torch.complex(gx, gy)).reshape(1, 1, -1, 2)
        out = F.grid_sample(self.tex[None], g, mode="bilinear", padding_mode="border",
                            align_corners=False)
        return out.reshape(3, -1)


class Wall(Primitive):
    """The plane z = WALL_Z facing +z."""

    def intersect(self, o, dx, dy, dz):
        t = (WALL_Z - o[2]) / _safe(dz)
        return torch.where(t > 0, t, torch.full_like(t, math.inf)), None

    def normal(self, x, y, z, kind, dx, dy, dz):
        n = torch.zeros(3, x.shape[0])
        n[2] = 1
        return n

    def texture_coords(self, x, y, z, n):
        return x, y


class Ellipsoid(Primitive):
    def __init__(self, centre, radii):
        self.c = tuple(float(v) for v in centre)
        self.r = tuple(float(v) for v in radii)
        self.bounds = (tuple(c - r for c, r in zip(self.c, self.r)),
                       tuple(c + r for c, r in zip(self.c, self.r)))

    def intersect(self, o, dx, dy, dz):
        ox, oy, oz = ((o[i] - self.c[i]) / self.r[i] for i in range(3))
        ex, ey, ez = dx * (1 / self.r[0]), dy * (1 / self.r[1]), dz * (1 / self.r[2])
        a = ex * ex + ey * ey + ez * ez
        b = ex * ox + ey * oy + ez * oz
        c = ox * ox + oy * oy + oz * oz - 1
        disc = b * b - a * c
        sq = torch.sqrt(disc.clamp(min=0))
        t0 = (-b - sq) / a
        ok = (disc >= 0) & (t0 > 1e-6)  # the camera is never inside
        return torch.where(ok, t0, torch.full_like(t0, math.inf)), None

    def normal(self, x, y, z, kind, dx, dy, dz):
        n = torch.stack([(x - self.c[0]) / self.r[0] ** 2, (y - self.c[1]) / self.r[1] ** 2,
                         (z - self.c[2]) / self.r[2] ** 2])
        return n / torch.sqrt((n * n).sum(0, keepdim=True))

    def texture_coords(self, x, y, z, n):
        return torch.atan2(x - self.c[0], z - self.c[2]), y


class CylinderY(Primitive):
    """Vertical cylinder (axis through (cx, ., cz)) between y0 and y1, with a top cap."""

    def __init__(self, cx, cz, radius, y0, y1):
        self.cx, self.cz, self.rad, self.y0, self.y1 = cx, cz, radius, y0, y1
        self.bounds = ((cx - radius, y0, cz - radius), (cx + radius, y1, cz + radius))

    def intersect(self, o, dx, dy, dz):
        ox, oz = o[0] - self.cx, o[2] - self.cz
        a = (dx * dx + dz * dz).clamp(min=1e-12)
        b = dx * ox + dz * oz
        c = ox * ox + oz * oz - self.rad ** 2
        disc = b * b - a * c
        sq = torch.sqrt(disc.clamp(min=0))
        t_side = (-b - sq) / a
        y = o[1] + t_side * dy
        side_ok = (disc >= 0) & (t_side > 1e-6) & (y >= self.y0) & (y <= self.y1)
        t_side = torch.where(side_ok, t_side, torch.full_like(a, math.inf))
        t_cap = (self.y1 - o[1]) / _safe(dy)
        px, pz = ox + t_cap * dx, oz + t_cap * dz
        cap_ok = (t_cap > 1e-6) & (px * px + pz * pz <= self.rad ** 2) & (dy < 0)
        t_cap = torch.where(cap_ok, t_cap, torch.full_like(a, math.inf))
        return torch.minimum(t_side, t_cap), t_cap < t_side

    def normal(self, x, y, z, kind, dx, dy, dz):
        nx, nz = x - self.cx, z - self.cz
        ln = torch.sqrt(nx * nx + nz * nz).clamp(min=1e-9)
        cap = kind.to(torch.float32)
        return torch.stack([nx / ln * (1 - cap), cap, nz / ln * (1 - cap)])

    def texture_coords(self, x, y, z, n):
        return torch.atan2(x - self.cx, z - self.cz), y


class Box(Primitive):
    def __init__(self, lo, hi):
        self.lo = tuple(float(v) for v in lo)
        self.hi = tuple(float(v) for v in hi)
        self.bounds = (self.lo, self.hi)

    def intersect(self, o, dx, dy, dz):
        tn = tf = axis = None
        for i, di in enumerate((dx, dy, dz)):
            inv = 1.0 / _safe(di)
            ta = (self.lo[i] - o[i]) * inv
            tb = (self.hi[i] - o[i]) * inv
            near, far = torch.minimum(ta, tb), torch.maximum(ta, tb)
            if tn is None:
                tn, tf, axis = near, far, torch.zeros_like(near, dtype=torch.int8)
            else:
                axis = torch.where(near > tn, torch.full_like(axis, i), axis)
                tn, tf = torch.maximum(tn, near), torch.minimum(tf, far)
        ok = (tn <= tf) & (tn > 1e-6)
        return torch.where(ok, tn, torch.full_like(tn, math.inf)), axis

    def normal(self, x, y, z, kind, dx, dy, dz):
        n = torch.zeros(3, x.shape[0])
        for i, di in enumerate((dx, dy, dz)):
            n[i] = torch.where(kind == i, -torch.sign(di), torch.zeros_like(di))
        return n

    def texture_coords(self, x, y, z, n):
        # x-facing sides use (z, y); y-facing use (x, z); z-facing use (x, y)
        a = torch.where(n[0].abs() > 0.5, z, x)
        b = torch.where(n[1].abs() > 0.5, z, y)
        return a, b


class Backdrop:
    """Torso, neck and room, with textures chosen by `seed`."""

    def __init__(self, seed: int, skin: tuple[float, float, float], coarse: int = 1):
        """`coarse` divides every texture's resolution (for small images)."""
        self.seed = int(seed)
        c = int(coarse)
        rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([self.seed, 202])))
        nz = Noise(self.seed * 7 + 2)
        self.prims: list[Primitive] = []

        wall = Wall()
        wall.extent = (-1.2, 1.2, -1.2, 1.2)
        wall.tex = _bricks(nz, rng, wall.extent, 1200 // c)
        self.prims.append(wall)

        torso = Ellipsoid((0.0, -0.31, -0.035), (0.21, 0.15, 0.11))
        torso.extent = (-math.pi, math.pi, -0.50, -0.12)
        torso.tex = _cloth(nz, rng, torso.extent, skin, c)
        self.prims.append(torso)

        neck = CylinderY(0.0, -0.022, 0.056, -0.40, -0.02)
        neck.extent = (-math.pi, math.pi, -0.40, 0.0)
        neck.tex = _neck(nz, neck.extent, skin, c)
        self.prims.append(neck)

        vase = CylinderY(-0.25, -0.22, 0.055, -0.9, -0.05)
        vase.extent = (-math.pi, math.pi, -0.9, -0.05)
        vase.tex = _vase(nz, rng, vase.extent, c)
        self.prims.append(vase)

        lamp = Ellipsoid((-0.25, 0.02, -0.22), (0.07, 0.07, 0.07))
        lamp.extent = (-math.pi, math.pi, -0.05, 0.09)
        lamp.tex = _lamp(nz, lamp.extent, c)
        self.prims.append(lamp)

        shelf = Box((0.21, -0.95, -0.42), (0.50, 0.04, -0.21))
        shelf.extent = (0.21, 0.50, -0.95, 0.04)
        shelf.tex = _books(nz, rng, shelf.extent, c)
        self.prims.append(shelf)

        frame = Box((-0.52, 0.12, WALL_Z - 0.01), (-0.20, 0.36, WALL_Z + 0.025))
        frame.extent = (-0.52, -0.20, 0.12, 0.36)
        frame.tex = _painting(nz, rng, frame.extent, c)
        self.prims.append(frame)

    def trace(self, o, dx: torch.Tensor, dy: torch.Tensor, dz: torch.Tensor,
              pose: np.ndarray, candidates=None) -> "Trace":
        """Nearest hits of world rays from o (3 floats) along (dx, dy, dz) (N,) each, with
        the body at world-from-body `pose` (4, 4). Every capture ray hits the wall.

        `candidates(lo, hi)`, if given, returns the indices of the rays that may hit a
        body-frame box (or None for all); primitives are only tested against those.
        Shading inputs come from `surface(trace, indices)`."""
        R, tr = pose[:3, :3], pose[:3, 3]
        ob = tuple(float(v) for v in R.T @ (np.asarray(o) - tr))
        bx, by, bz = (float(R[0, i]) * dx + float(R[1, i]) * dy + float(R[2, i]) * dz
                      for i in range(3))
        N = dx.shape[0]
        t = torch.full((N,), math.inf)
        which = torch.zeros(N, dtype=torch.int8)
        kinds: list = []
        for k, prim in enumerate(self.prims):
            idx = None if (candidates is None or prim.bounds is None) else candidates(*prim.bounds)
            kind = None
            if idx is None:
                tk, kind = prim.intersect(ob, bx, by, bz)
                if k == 0:
                    t = tk
                else:
                    closer = (tk < t).nonzero().flatten()
                    t.index_copy_(0, closer, tk.index_select(0, closer))
                    which.index_fill_(0, closer, k)
            elif len(idx):
                tk, kind_sub = prim.intersect(ob, bx.index_select(0, idx), by.index_select(0, idx),
                                              bz.index_select(0, idx))
                closer = (tk < t.index_select(0, idx)).nonzero().flatten()
                ci = idx.index_select(0, closer)
                t.index_copy_(0, ci, tk.index_select(0, closer))
                which.index_fill_(0, ci, k)
                if kind_sub is not None:
                    kind = torch.zeros(N, dtype=kind_sub.dtype)
                    kind.index_copy_(0, idx, kind_sub)
            kinds.append(kind)
        return Trace(t=t, which=which, kinds=kinds, origin=ob, dirs=(bx, by, bz), rotation=R)

    def surface(self, tr: "Trace", idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Albedo (3, n) and world-frame normal (3, n) where rays `idx` (n,) hit."""
        n = len(idx)
        albedo, normal = torch.zeros(3, n), torch.zeros(3, n)
        which = tr.which.index_select(0, idx)
        ob, R = tr.origin, tr.rotation
        for k, prim in enumerate(self.prims):
            pos = (which == k).nonzero().flatten()
            if not len(pos):
                continue
            ids = idx.index_select(0, pos)
            tk = tr.t.index_select(0, ids)
            sx, sy, sz = (c.index_select(0, ids) for c in tr.dirs)
            x, y, z = ob[0] + tk * sx, ob[1] + tk * sy, ob[2] + tk * sz
            kind = None if tr.kinds[k] is None else tr.kinds[k].index_select(0, ids)
            nb = prim.normal(x, y, z, kind, sx, sy, sz)
            albedo.index_copy_(1, pos, prim.albedo(x, y, z, nb))
            normal.index_copy_(1, pos, torch.stack([
                float(R[i, 0]) * nb[0] + float(R[i, 1]) * nb[1] + float(R[i, 2]) * nb[2]
                for i in range(3)]))
        return albedo, normal


@dataclass
class Trace:
    """Background hits of a batch of rays (see Backdrop.trace)."""

    t: torch.Tensor  # (N,) inf where nothing is hit
    which: torch.Tensor  # (N,) int8 primitive index
    kinds: list  # per primitive: (N,) which part was hit, or None
    origin: tuple  # body-frame ray origin
    dirs: tuple  # body-frame directions (bx, by, bz)
    rotation: np.ndarray  # world-from-body rotation


# ----------------------------------------------------------------------------- sway


def sway_pose(frame: float, amplitude: float, seed: int) -> np.ndarray:
    """World-from-body 4x4 rigid motion at capture frame `frame` (float; smooth in time).

    Rotation about NECK_PIVOT of about `amplitude` degrees per axis and a translation of
    about 3 * `amplitude` mm, as slow sums of sinusoids. amplitude = 0 gives the identity."""
    if amplitude == 0:
        return np.eye(4)
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), 303])))
    periods = rng.uniform(45, 140, size=(6, 3))
    phases = rng.uniform(0, 2 * np.pi, size=(6, 3))
    weights = np.array([0.6, 0.3, 0.15])
    wave = (weights * np.sin(2 * np.pi * frame / periods + phases)).sum(-1) / weights.sum()
    ang = np.deg2rad(amplitude * np.array([1.0, 1.0, 0.8])) * wave[:3]
    trans = amplitude * np.array([0.003, 0.002, 0.003]) * wave[3:]
    R = _euler(*ang)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = NECK_PIVOT - R @ NECK_PIVOT + trans
    return T


def _euler(ax: float, ay: float, az: float) -> np.ndarray:
    cx, sx, cy, sy, cz, sz = np.cos(ax), np.sin(ax), np.cos(ay), np.sin(ay), np.cos(az), np.sin(az)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


# ----------------------------------------------------------------------------- textures


def _rgb(c) -> torch.Tensor:
    return torch.tensor(c, dtype=torch.float32).view(3, 1, 1)


def _bricks(nz: Noise, rng, extent, res: int) -> torch.Tensor:
    x, y = _grid(res, res, *extent)
    bw, bh, mortar = 0.21, 0.07, 0.010
    row = torch.floor(y / bh)
    xs = x + 0.5 * bw * torch.remainder(row, 2)
    col = torch.floor(xs / bw)
    fx = xs - col * bw
    fy = y - row * bh
    edge = torch.minimum(torch.minimum(fx, bw - fx), torch.minimum(fy, bh - fy))
    m = 1 - torch.clamp((edge - mortar / 2) / 0.0025 + 0.5, 0, 1)  # 1 in the mortar
    ri, ci = row.to(torch.int32), col.to(torch.int32)
    h1, h2 = nz.hash(ri, ci), nz.hash(ri + 7919, ci)
    bases = [(0.62, 0.33, 0.25), (0.70, 0.62, 0.52), (0.55, 0.45, 0.42), (0.80, 0.76, 0.70)]
    base = np.array(bases[rng.integers(len(bases))]) * rng.uniform(0.95, 1.05, 3)
    p = torch.stack([x, y], -1)
    grain = nz.fbm(p / 0.006, 2)
    xc, yc = _grid(res // 8, res // 8, *extent)
    blot = upsample(nz.fbm(torch.stack([xc, yc], -1) / 0.05 + 3.0, 3), (res, res))
    brick = _rgb(base) * (1 + 0.14 * h1 + 0.05 * blot + 0.10 * grain)
    brick = brick + _rgb((0.04, -0.01, -0.02)) * h2
    mort = _rgb((0.78, 0.76, 0.72)) * (1 + 0.06 * grain + 0.04 * blot)
    return (brick * (1 - m) + mort * m).clamp(0, 1).contiguous()


def _cloth(nz: Noise, rng, extent, skin, c: int = 1) -> torch.Tensor:
    w, h = 1000 // c, 300 // c
    a, y = _grid(h, w, *extent)
    cols = [(0.20, 0.30, 0.55), (0.55, 0.15, 0.15), (0.20, 0.42, 0.30), (0.35, 0.35, 0.38),
            (0.75, 0.65, 0.40)]
    c1 = np.array(cols[rng.integers(len(cols))])
    c2 = c1 * 0.55 + 0.35
    arc = a * 0.2  # ~metres around the torso
    stripe = 0.5 + 0.5 * torch.cos(2 * math.pi * arc / 0.025)
    band = 0.5 + 0.5 * torch.cos(2 * math.pi * y / 0.03)
    check = (stripe * band) ** 2
    p = torch.stack([arc, y], -1)
    weave = torch.cos(2 * math.pi * (arc + y) / 0.004) * 0.5 + 0.5
    cloth = _rgb(c1) * (1 - check) + _rgb(c2) * check
    cloth = cloth * (0.92 + 0.10 * weave + 0.06 * nz.fbm(p / 0.01, 3))
    # a V-neck opening showing skin
    vneck = (a.abs() * 0.2 < (y + 0.225) * 0.6).float() * (a.abs() < 1.2).float()
    skin_t = _rgb(skin) * (1 + 0.05 * nz.fbm(p / 0.002 + 2.0, 2)) * (0.9 + 0.1 * (y + 0.225) / 0.1)
    return (cloth * (1 - vneck) + skin_t * vneck).clamp(0, 1).contiguous()


def _neck(nz: Noise, extent, skin, c: int = 1) -> torch.Tensor:
    a, y = _grid(400 // c, 320 // c, *extent)
    p = torch.stack([a * 0.05, y], -1)
    t = _rgb(skin) * (1 + 0.05 * nz.fbm(p / 0.02 + 9.0, 3) + 0.08 * nz.fbm(p / 0.0012 + 4.0, 2))
    shade = 1 - 0.35 * ((y + 0.11) / 0.09).clamp(0, 1)  # darker up under the jaw
    return (t * shade).clamp(0, 1).contiguous()


def _vase(nz: Noise, rng, extent, c: int = 1) -> torch.Tensor:
    a, y = _grid(500 // c, 360 // c, *extent)
    p = torch.stack([a * 0.055, y], -1)
    base = np.array([(0.15, 0.35, 0.45), (0.55, 0.30, 0.15), (0.85, 0.82, 0.75)][rng.integers(3)])
    bands = 0.5 + 0.5 * torch.sin(2 * math.pi * y / 0.06 + 2 * torch.sin(a * 3))
    t = _rgb(base) * (0.7 + 0.35 * bands) * (1 + 0.08 * nz.fbm(p / 0.004 + 5.0, 3))
    return t.clamp(0, 1).contiguous()


def _lamp(nz: Noise, extent, c: int = 1) -> torch.Tensor:
    a, y = _grid(200 // c, 440 // c, *extent)
    p = torch.stack([a * 0.07, y], -1)
    fib = nz.fbm(torch.stack([a * 20, y * 150], -1) + 6.0, 3)
    t = _rgb((0.95, 0.88, 0.70)) * (0.9 + 0.1 * fib + 0.05 * nz.fbm(p / 0.01 + 7.0, 2))
    return t.clamp(0, 1).contiguous()


def _books(nz: Noise, rng, extent, c: int = 1) -> torch.Tensor:
    x0, x1, y0, y1 = extent
    w, h = 300 // c, 1000 // c
    x, y = _grid(h, w, *extent)
    grain = nz.fbm(torch.stack([x * 3, y * 60], -1) + 8.0, 3)
    img = _rgb((0.45, 0.30, 0.18)) * (1 + 0.15 * grain)
    shelf_h = 0.25
    xs = x[0]
    for level in range(4):
        yb = y1 - 0.03 - (level + 1) * shelf_h + 0.02
        edges, heights, colours = [x0 + 0.015], [], []
        while edges[-1] < x1 - 0.03:
            bw = float(rng.uniform(0.015, 0.04))
            heights.append(float(rng.uniform(0.14, 0.22)))
            colours.append(rng.uniform(0.1, 0.85, 3))
            edges.append(edges[-1] + bw + 0.002)
        e = torch.tensor(edges, dtype=torch.float32)
        idx = (torch.bucketize(xs, e) - 1).clamp(0, len(heights) - 1)  # book of each column
        left = e[idx]
        width = e[idx + 1] - 0.002 - left
        inbook = (xs >= left) & (xs < left + width) & (xs >= e[0]) & (xs < e[-1])
        top = torch.tensor(heights, dtype=torch.float32)[idx]
        col = torch.from_numpy(np.stack(colours)).float()[idx].T  # (3, w)
        m = ((y >= yb) & (y < yb + top) & inbook).float()
        rel = (xs - left) / width
        lettering = ((torch.remainder(y * 90, 1.0) < 0.25) & ((rel - 0.5).abs() < 0.2)).float()
        book = col[:, None, :] * (1 - 0.5 * lettering) * (0.9 + 0.1 * torch.cos(rel * math.pi * 2))
        img = img * (1 - m) + book * m
    return img.clamp(0, 1).contiguous()


def _painting(nz: Noise, rng, extent, c: int = 1) -> torch.Tensor:
    x0, x1, y0, y1 = extent
    w, h = 320 // c, 240 // c
    x, y = _grid(h, w, *extent)
    p = torch.stack([x, y], -1)
    a, b, c = (nz.fbm(p / 0.05 + k * 10.0, 4) for k in range(3))
    art = torch.stack([0.5 + 0.6 * a, 0.45 + 0.6 * b, 0.4 + 0.6 * c])
    border = ((x - x0 < 0.02) | (x1 - x < 0.02) | (y - y0 < 0.02) | (y1 - y < 0.02)).float()
    frame = _rgb((0.25, 0.17, 0.10)) * (1 + 0.2 * nz.fbm(p / 0.004 + 40.0, 2))
    return (art * (1 - border) + frame * border).clamp(0, 1).contiguous()
