"""Everything that is not the head: torso, neck and the room behind, with textures.

These primitives live in the *body frame*. World = head frame, so when the subject's head
sways in reality, here the body and the room move instead: `sway_pose` gives the
world-from-body rigid motion of each frame (identity when the sway amplitude is 0).
All intersections are analytic (planes, ellipsoids, vertical cylinders, boxes) and the
textures are procedural images sampled bilinearly.

The handheld variant (`Backdrop(..., handheld=True)`) keeps the torso and neck but puts
the room far away: a city skyline on a plane FAR_Z behind the head, and in front of it, to
one side of the head, a panel of leaves whose texture sways in the wind by itself (a
smooth displacement of its texture coordinates over time; `Leaves.wind`).
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
# the handheld variant: the skyline 4 m behind the head (4.6 m from the camera), wide and
# tall enough for the novel cameras too; the leaves 2 m from the camera, right of the
# head in the image (+x), beyond the head's reach under the camera's and the head's motion
FAR_Z = -4.0
FAR_EXTENT = (-7.5, 7.5, -4.0, 4.5)
LEAVES_Z = -1.4
LEAVES_RECT = (0.47, 1.05, -0.36, 1.25)  # x0, x1, y0, y1


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

    moves: bool = False  # its texture changes over time (albedo takes a time)

    def albedo(self, x, y, z, n) -> torch.Tensor:
        return self.sample(*self.texture_coords(x, y, z, n))

    def sample(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """The texture at texture coordinates a, b (n,) -> (3, n)."""
        a0, a1, b0, b1 = self.extent
        gx = (a - a0) * (2 / (a1 - a0)) - 1
        gy = (b1 - b) * (2 / (b1 - b0)) - 1
        g = torch.view_as_real(torch.complex(gx, gy)).reshape(1, 1, -1, 2)
        out = F.grid_sample(self.tex[None], g, mode="bilinear", padding_mode="border",
                            align_corners=False)
        return out.reshape(3, -1)


class Plane(Primitive):
    """The plane z = `z` facing +z; with `rect` = (x0, x1, y0, y1) only that rectangle."""

    def __init__(self, z: float, rect: tuple[float, float, float, float] | None = None):
        self.z, self.rect = float(z), rect
        if rect is not None:
            self.bounds = ((rect[0], rect[2], self.z - 1e-3), (rect[1], rect[3], self.z + 1e-3))

    def intersect(self, o, dx, dy, dz):
        t = (self.z - o[2]) / _safe(dz)
        ok = t > 0
        if self.rect is not None:
            x0, x1, y0, y1 = self.rect
            x, y = o[0] + t * dx, o[1] + t * dy
            ok = ok & (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
        return torch.where(ok, t, torch.full_like(t, math.inf)), None

    def normal(self, x, y, z, kind, dx, dy, dz):
        n = torch.zeros(3, x.shape[0])
        n[2] = 1
        return n

    def texture_coords(self, x, y, z, n):
        return x, y


class Leaves(Plane):
    """A rectangle of leaves swaying in the wind: its texture is displaced over time by a
    smooth field (`wind`), so its pixels change although nothing in the scene moves."""

    moves = True

    def __init__(self, z: float, rect, rng: np.random.Generator):
        super().__init__(z, rect)
        # three waves per axis, from a gust (~0.5 s at 30 fps) swaying the branch as a whole
        # to a flutter (~5 frames) over half a metre: together ~3.5 px per frame at 128 px and
        # 2 m (0.035 m); the wavelengths are long against the amplitudes (strain ~0.25 rms),
        # so the leaves move and bend but never fold over
        self.amp = np.array([0.06, 0.036, 0.012])[None, :] * rng.uniform(0.8, 1.2, (2, 3))
        self.period = np.array([[16.0, 9.0, 5.0]]) * rng.uniform(0.85, 1.15, (2, 3))
        ang = rng.uniform(0, 2 * np.pi, (2, 3))
        k = 2 * np.pi / (np.array([[2.5, 1.3, 0.45]]) * rng.uniform(0.8, 1.2, (2, 3)))
        self.kx, self.ky = k * np.cos(ang), k * np.sin(ang)
        self.phase = rng.uniform(0, 2 * np.pi, (2, 3))
        m = float(2 * self.amp.sum(1).max())  # the largest displacement the waves reach
        self.extent = (rect[0] - m, rect[1] + m, rect[2] - m, rect[3] + m)

    def wind(self, a: torch.Tensor, b: torch.Tensor, time: float | None):
        """Texture displacement (du, dv) (n,) each, metres, at texture coordinates a, b (n,)
        at capture frame `time`; zero at time 0 (and for None)."""
        if not time:
            return torch.zeros_like(a), torch.zeros_like(b)
        out = []
        for axis in range(2):
            d = torch.zeros_like(a)
            for j in range(self.amp.shape[1]):
                arg = a * float(self.kx[axis, j]) + b * float(self.ky[axis, j]) + float(
                    self.phase[axis, j])
                shift = 2 * math.pi * float(time) / float(self.period[axis, j])
                d = d + float(self.amp[axis, j]) * (torch.sin(arg + shift) - torch.sin(arg))
            out.append(d)
        return out[0], out[1]

    def albedo(self, x, y, z, n, time: float | None = None) -> torch.Tensor:
        a, b = self.texture_coords(x, y, z, n)
        du, dv = self.wind(a, b, time)
        return self.sample(a - du, b - dv)


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
    """Torso, neck and room, with textures chosen by `seed`. `person` and `moving` are the
    indices (into `prims`) of the person's primitives and of those that move by themselves."""

    def __init__(self, seed: int, skin: tuple[float, float, float], coarse: int = 1,
                 handheld: bool = False):
        """`coarse` divides every texture's resolution (for small images); `handheld`: the
        far skyline and the swaying leaves instead of the room."""
        self.seed = int(seed)
        c = int(coarse)
        rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([self.seed, 202])))
        nz = Noise(self.seed * 7 + 2)
        self.prims: list[Primitive] = []
        self.moving: tuple[int, ...] = ()

        if handheld:
            far = Plane(FAR_Z)  # first: every ray is tested against it (see trace)
            far.extent = FAR_EXTENT
            far.tex = _skyline(nz, _stream(self.seed, 212), far.extent, c)
            self.prims.append(far)
            _brick_base(rng)  # drawn, unused: a seed dresses the person alike in both variants
        else:
            wall = Plane(WALL_Z)
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
        self.person: tuple[int, ...] = (1, 2)

        if handheld:
            leaves = Leaves(LEAVES_Z, LEAVES_RECT, _stream(self.seed, 213))
            leaves.tex = _leaves(nz, leaves.extent, c)
            self.prims.append(leaves)
            self.moving = (len(self.prims) - 1,)
            return

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
        the body at world-from-body `pose` (4, 4). Every capture ray hits the wall (the far
        plane in the handheld variant), prims[0].

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

    def surface(self, tr: "Trace", idx: torch.Tensor, time: float | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """Albedo (3, n) and world-frame normal (3, n) where rays `idx` (n,) hit, at capture
        frame `time` (for the primitives that move by themselves)."""
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
            alb = prim.albedo(x, y, z, nb, time) if prim.moves else prim.albedo(x, y, z, nb)
            albedo.index_copy_(1, pos, alb)
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


def _stream(seed: int, key: int) -> np.random.Generator:
    """An independent random stream of `seed` (its own key, so adding one changes no other)."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), key])))


def _brick_base(rng) -> np.ndarray:
    """The wall's brick colour (3,)."""
    bases = [(0.62, 0.33, 0.25), (0.70, 0.62, 0.52), (0.55, 0.45, 0.42), (0.80, 0.76, 0.70)]
    return np.array(bases[rng.integers(len(bases))]) * rng.uniform(0.95, 1.05, 3)


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
    base = _brick_base(rng)
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


def _skyline(nz: Noise, rng, extent, c: int = 1) -> torch.Tensor:
    """A street of buildings with windows under a cloudy sky, for the far plane: 8 mm
    texels (16 mm coarse), so that at 4.6 m windows are a few pixels at 128-256 px and their
    corners (lit, dark, with blinds, each chosen by a hash) give a feature detector plenty."""
    x0, x1, y0, y1 = extent
    step = 0.008 * c
    w, h = round((x1 - x0) / step), round((y1 - y0) / step)
    x, y = _grid(h, w, *extent)
    edges = [x0]
    while edges[-1] < x1:
        edges.append(edges[-1] + float(rng.uniform(0.5, 1.4)))
    nb = len(edges) - 1
    e = torch.tensor(edges, dtype=torch.float32)
    b = (torch.bucketize(x.contiguous(), e) - 1).clamp(0, nb - 1)  # building of each texel
    par = lambda lo, hi: torch.from_numpy(rng.uniform(lo, hi, nb)).float()[b]  # noqa: E731
    top, sx, sy = par(0.3, 3.2), par(0.14, 0.26), par(0.20, 0.32)
    fw, fh = par(0.45, 0.7), par(0.45, 0.65)
    palette = torch.tensor([(0.62, 0.60, 0.56), (0.58, 0.32, 0.24), (0.78, 0.70, 0.55),
                            (0.86, 0.85, 0.82), (0.30, 0.33, 0.38)])
    base = (palette[torch.from_numpy(rng.integers(len(palette), size=nb))]
            * torch.from_numpy(rng.uniform(0.85, 1.1, (nb, 1))).float())[b].permute(2, 0, 1)
    lx, ly = x - e[b], top - y  # from the building's left edge; down from its roof
    width = e[b + 1] - e[b]
    col = torch.floor((lx - 0.06) / sx)
    row = torch.floor((ly - 0.12) / sy)
    fx, fy = (lx - 0.06) / sx - col, (ly - 0.12) / sy - row
    inside = (lx > 0.06) & (lx < width - 0.06) & (ly > 0.12)
    window = inside & (fx < fw) & (fy < fh)
    bi, ci, ri = b.to(torch.int32), col.to(torch.int32), row.to(torch.int32)
    lit, tint, blind = nz.hash(bi, ci, ri), nz.hash(bi + 101, ci, ri), nz.hash(bi + 202, ci, ri)
    glass = torch.stack([0.14 + 0.10 * tint, 0.18 + 0.10 * tint, 0.25 + 0.12 * tint])
    glass = glass + 0.12 * (fy / fh)  # the sky's reflection, brighter low in the pane
    warm = _rgb((0.95, 0.83, 0.52)) * (0.85 + 0.15 * tint)
    pane = torch.where((lit > 0.4)[None], warm, glass)
    shade_b = (blind > 0.1) & (fy / fh < 0.25 + 0.5 * (blind - 0.1))  # blinds half-drawn
    pane = torch.where(shade_b[None], _rgb((0.82, 0.78, 0.68)) * (0.9 + 0.1 * tint), pane)
    mullion = ((fx / fw - 0.5).abs() < 0.04) & window
    p = torch.stack([x, y], -1)
    xc, yc = _grid(h // 4, w // 4, *extent)
    blot = upsample(nz.fbm(torch.stack([xc, yc], -1) / 0.4 + 11.0, 3), (h, w))
    grain = nz.value(p / 0.02 + 13.0)
    storey = (fy > 0.97).float() * inside.float()  # a ledge under each row of windows
    facade = base * (1 + 0.10 * blot + 0.06 * grain - 0.25 * storey)
    facade = facade * (1 - 0.3 * ((ly < 0.05) & (ly > 0)).float())  # the roof's cornice
    bldg = torch.where(window[None] & ~mullion[None], pane, facade)
    bldg = torch.where(mullion[None], _rgb((0.2, 0.2, 0.2)), bldg)
    cloud = upsample(nz.fbm(torch.stack([xc * 0.6, yc * 1.5], -1) + 21.0, 4), (h, w))
    sky = (_rgb((0.55, 0.70, 0.90)) + 0.25 * ((y - 1.0) / 3.5).clamp(0, 1) * _rgb((-0.2, -0.15, 0))
           + 0.35 * (cloud - 0.1).clamp(0, 1))
    img = torch.where((ly > 0)[None], bldg, sky)
    haze = _rgb((0.75, 0.80, 0.88))
    return (0.88 * img + 0.12 * haze).clamp(0, 1).contiguous()


def _leaves(nz: Noise, extent, c: int = 1) -> torch.Tensor:
    """Two layers of pointed leaves (one per cell of a jittered grid, at random angles and
    sizes, the nearest leaf on top) over dark foliage: 3 mm texels (6 mm coarse), i.e. a
    leaf is a few pixels to a dozen at 2 m and 128-256 px."""
    x0, x1, y0, y1 = extent
    step = 0.003 * c
    w, h = round((x1 - x0) / step), round((y1 - y0) / step)
    x, y = _grid(h, w, *extent)
    img = _rgb((0.05, 0.09, 0.04)) * (1 + 0.3 * nz.value(torch.stack([x, y], -1) / 0.02 + 31.0))
    for layer, (s, green) in enumerate(((0.06, (0.16, 0.32, 0.10)), (0.045, (0.26, 0.48, 0.14)))):
        leaf, rel_v, depth = _leaf_cells(nz, x, y, s, layer)
        tone = nz.hash(*(torch.floor(v / s).to(torch.int32) + 3 * layer for v in (x, y)))
        colour = _rgb(green) * (1 + 0.25 * tone) * (0.75 + 0.25 * rel_v) * (0.9 + 0.2 * depth)
        colour = torch.where((rel_v.abs() < 0.08)[None], colour * 1.35, colour)  # midrib
        img = torch.where(leaf[None], colour, img)
    return img.clamp(0, 1).contiguous()


def _leaf_cells(nz: Noise, x: torch.Tensor, y: torch.Tensor, s: float, layer: int):
    """One layer of leaves on a grid of cell size `s` at texel positions x, y (h, w): each
    cell's leaf has a hashed centre, angle, length and width; where leaves overlap the one
    with the largest hashed depth wins. -> inside (h, w) bool, the position across the leaf
    in [-1, 1] and its depth in [-1, 1]."""
    ci, cj = torch.floor(x / s).to(torch.int32), torch.floor(y / s).to(torch.int32)
    best = torch.full(x.shape, -2.0)
    across = torch.zeros(x.shape)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            i, j = ci + di, cj + dj
            hv = [nz.hash(i + 7717 * k + 50021 * layer, j) for k in range(6)]
            cx = (i.float() + 0.5 + 0.45 * hv[0]) * s
            cy = (j.float() + 0.5 + 0.45 * hv[1]) * s
            ang = math.pi * hv[2]
            half_len = s * (0.85 + 0.3 * hv[3])
            half_w = half_len * (0.32 + 0.08 * hv[4])
            px, py = x - cx, y - cy
            u = px * torch.cos(ang) + py * torch.sin(ang)
            v = -px * torch.sin(ang) + py * torch.cos(ang)
            t = (u / half_len).clamp(-1, 1)
            # pointed at the tip (u = +half_len), rounder towards the stem
            wu = half_w * (1 - t * t) * (1 - 0.35 * t)
            inside = (u.abs() < half_len) & (v.abs() < wu)
            win = inside & (hv[5] > best)
            best = torch.where(win, hv[5], best)
            across = torch.where(win, v / wu.clamp(min=1e-6), across)
    return best > -2.0, across, best.clamp(min=-1.0)
