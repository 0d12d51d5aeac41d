"""The synthetic head: a star-shaped surface with an ARKit-named expression model.

Geometry. The head surface is r = R(u, v) around the head-frame origin, with azimuth u
(0 looks along +z, positive towards +x, the subject's left) and elevation v (positive up):
direction w(u, v) = (sin u cos v, sin v, cos u cos v). R is stored on an equirectangular
grid (`GEO_STEP` degrees) and interpolated bilinearly; that interpolated surface *is* the
ground-truth geometry, so rays, depth maps and the face mesh all agree with it.

Expressions act as a map from canonical surface coordinates c = (u_c, v_c) (where the
texture lives) to deformed coordinates x, in two stages:
  1. the jaw "crack": y = (u_c, v_c - jawOpen * F(u_c, v_c)), a monotone vertical map per
     column that drops the lower face and stretches a thin band along the lip line into the
     open mouth (its position across the band says where the teeth and tongue are);
  2. smooth warps: x = y + D(y), D = sum_k e_k D_k (mouth corners, lips, brows), stored on a
     grid and sampled bilinearly (a blendshape of 2-D displacement fields).
On top, radial offsets dR = sum_k e_k dR_k(c) (cheeks, lips) and the eyelids (a function of
c and the blink/wide controls) change R. Every field has compact support inside the face
mesh's region, so an expression changes nothing outside it. Per frame the deformed maps
are computed on the grid by inverting the map (fixed-point iteration for D, bisection for
the crack), and the face mesh moves its canonical vertices forward through the same map.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from flamenerf.synthetic.noise import Noise, upsample

DEG = math.pi / 180.0

# ARKit blendshape names ("Left" = the subject's left = +x = +u).
CONTROLS: tuple[str, ...] = (
    "jawOpen",
    "mouthSmileLeft",
    "mouthSmileRight",
    "mouthFrownLeft",
    "mouthFrownRight",
    "mouthPucker",
    "cheekPuff",
    "browInnerUp",
    "browDownLeft",
    "browDownRight",
    "eyeBlinkLeft",
    "eyeBlinkRight",
    "eyeWideLeft",
    "eyeWideRight",
)
CONTROL_INDEX = {n: i for i, n in enumerate(CONTROLS)}

GEO_STEP = 0.4  # degrees per texel of the geometry / deformation maps
TEX_STEP = 0.2  # degrees per texel of the canonical albedo maps

# Face layout (degrees on the head sphere).
EYE_U, EYE_V, EYE_HW, EYE_UP, EYE_LO = 19.0, 4.0, 8.5, 3.6, 2.4
MOUTH_V, MOUTH_HALF = -36.0, 14.0
JAW_MAX = 10.0  # jaw drop at jawOpen = 1
JAW_C, JAW_R = (0.0, -48.0), (42.0, 34.0)  # jaw region ellipse (centre, radii)
# The face mesh covers the canonical ellipse ((u/FACE_R[0])^2 + ((v-FACE_C)/FACE_R[1])^2 <= 1)
FACE_C, FACE_R = -24.0, (62.0, 66.0)
MESH_STEP = 4.0
WARP_ITERS, JAW_BISECT = 6, 9  # fixed-point iterations / bisections inverting the expression map
# Head bounding shells for ray marching (metres).
R_OUTER, R_INNER = 0.145, 0.055


# ----------------------------------------------------------------------------- helpers


def smoothstep(e0: float, e1: float, x: torch.Tensor) -> torch.Tensor:
    t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0)
    return t * t * (3 - 2 * t)


def ell(u, v, cu, cv, ru, rv):
    return ((u - cu) / ru) ** 2 + ((v - cv) / rv) ** 2


def bump(r2: torch.Tensor) -> torch.Tensor:
    """Compactly supported bump (1 - r^2)^3 for r < 1, exactly 0 outside."""
    return (1 - r2).clamp(min=0.0) ** 3


def gauss(u, v, cu, cv, su, sv):
    return torch.exp(-0.5 * ell(u, v, cu, cv, su, sv))


def directions(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Unit directions for angles in degrees. -> (..., 3)."""
    ur, vr = u * DEG, v * DEG
    cv = torch.cos(vr)
    return torch.stack([torch.sin(ur) * cv, torch.sin(vr), torch.cos(ur) * cv], -1)


def angles(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor):
    """Point coordinates (contiguous tensors) -> azimuth u, elevation v (degrees), radius."""
    r = torch.sqrt(x * x + y * y + z * z)
    u = torch.atan2(x, z) * (1 / DEG)
    v = torch.asin((y / r.clamp(min=1e-9)).clamp(-1.0, 1.0)) * (1 / DEG)
    return u, v, r


def mouth_line(u: torch.Tensor) -> torch.Tensor:
    """Canonical lip-contact line v_m(u)."""
    return MOUTH_V + 1.0 * (u / MOUTH_HALF) ** 2


LIP_STEP = 0.15  # degrees: width of the jaw's step across the lip line
LIP_BAND = 4 * LIP_STEP  # canonical half-width of the band that opens into the mouth


def mouth_openness(u: torch.Tensor) -> torch.Tensor:
    """Share of the jaw drop that opens the lips (a step) rather than stretching skin (a
    ramp): 1 in the middle of the mouth, 0 at and beyond the corners."""
    return 1 - smoothstep(0.55 * MOUTH_HALF, MOUTH_HALF, u.abs())


def jaw_region(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """B(u, v): how much of the jaw drop a point takes; compact support."""
    r = torch.sqrt(ell(u, v, JAW_C[0], JAW_C[1], JAW_R[0], JAW_R[1]))
    return 1 - smoothstep(0.4, 1.0, r)


def jaw_drop(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """F(u, v) / jawOpen, degrees: the downward shift of canonical point (u, v).

    A sharp step at the lip line (weight `mouth_openness`) plus a smooth ramp over the lower
    face; F decreases with v, so v - jawOpen F is monotone and invertible per column."""
    vm = mouth_line(u)
    a = mouth_openness(u)
    step = torch.sigmoid((vm - v) / LIP_STEP)
    ramp = smoothstep(8.0, -12.0, v - vm)
    return JAW_MAX * jaw_region(u, v) * (a * step + (1 - a) * ramp)


def _invert_jaw(u: torch.Tensor, yv: torch.Tensor, jaw: float) -> torch.Tensor:
    """Solve v - jaw F(u, v) = yv for v (bisection; the map is increasing in v)."""
    # the u-dependent parts of F, once
    vm = mouth_line(u)
    a = mouth_openness(u)
    eu2 = ((u - JAW_C[0]) / JAW_R[0]) ** 2
    scale = jaw * JAW_MAX

    def g(v):
        r = torch.sqrt(eu2 + ((v - JAW_C[1]) / JAW_R[1]) ** 2)
        step = torch.sigmoid((vm - v) * (1 / LIP_STEP))
        ramp = smoothstep(8.0, -12.0, v - vm)
        return v - scale * (1 - smoothstep(0.4, 1.0, r)) * (a * (step - ramp) + ramp) - yv

    lo, hi = yv.clone(), yv + scale
    g_lo, g_hi = g(lo), g(hi)
    for _ in range(JAW_BISECT):
        mid = 0.5 * (lo + hi)
        gm = g(mid)
        m = (gm < 0).to(torch.float32)
        lo, g_lo = torch.lerp(lo, mid, m), torch.lerp(g_lo, gm, m)
        hi, g_hi = torch.lerp(mid, hi, m), torch.lerp(gm, g_hi, m)
    w = (-g_lo / (g_hi - g_lo).clamp(min=1e-12)).clamp(0, 1)
    return lo + (hi - lo) * w


def mouth_gap(uc: torch.Tensor, vc: torch.Tensor, yv: torch.Tensor, jaw: float):
    """Where a point lies in the open mouth. From canonical (uc, vc) and crack-space yv:
    band (1 inside the opening, 0 on the lips), degrees below the upper lip edge, degrees
    above the lower lip edge, and the opening (degrees) beyond the closed-lip band."""
    vm = mouth_line(uc)
    s = torch.sigmoid((vm - vc) / LIP_STEP)
    band = smoothstep(0.005, 0.05, s) * smoothstep(0.995, 0.95, s)
    band = band * smoothstep(MOUTH_HALF + 0.5, MOUTH_HALF - 1.0, uc.abs())
    upper = vm + LIP_BAND - jaw * jaw_drop(uc, vm + LIP_BAND)
    lower = vm - LIP_BAND - jaw * jaw_drop(uc, vm - LIP_BAND)
    return band, upper - yv, yv - lower, (upper - lower - 2 * LIP_BAND).clamp(min=0)


def eye_lids(u: torch.Tensor, side: float, blink, wide):
    """Lower lid line, upper lid line (after blink/wide) and the in-box mask for one eye."""
    a = (u - side * EYE_U) / EYE_HW
    shape = (1 - a * a).clamp(min=0.0).sqrt()
    lower = EYE_V - EYE_LO * shape
    upper = EYE_V + (EYE_UP + wide * 1.8 - blink * (EYE_UP + EYE_LO + 0.3)) * shape
    return lower, upper, a.abs() < 1


def eye_open(u: torch.Tensor, v: torch.Tensor, expr: torch.Tensor, soft: float = 0.0):
    """1 where the eyeball shows through the lids at canonical (u, v), else 0."""
    out = torch.zeros_like(u)
    for side, ib, iw in ((1.0, "eyeBlinkLeft", "eyeWideLeft"),
                         (-1.0, "eyeBlinkRight", "eyeWideRight")):
        blink = float(expr[CONTROL_INDEX[ib]])
        wide = float(expr[CONTROL_INDEX[iw]])
        lower, upper, inbox = eye_lids(u, side, blink, wide)
        if soft > 0:
            m = smoothstep(-soft, soft, v - lower) * smoothstep(-soft, soft, upper - v)
        else:
            m = ((v > lower) & (v < upper)).to(u.dtype)
        out = out + m * inbox.to(u.dtype)
    return out


# ----------------------------------------------------------------------------- expression fields


def _warp_fields(u: torch.Tensor, v: torch.Tensor) -> dict[str, tuple]:
    """Per control: (du, dv) smooth displacement (degrees) on crack-space coordinates."""
    z = torch.zeros_like(u)
    f: dict[str, tuple] = {}
    for name, s in (("Left", 1.0), ("Right", -1.0)):
        w = bump(ell(u, v, s * 15.0, -36.0, 12.0, 11.0))
        f["mouthSmile" + name] = (s * 3.0 * w, 4.0 * w)
        w = bump(ell(u, v, s * 15.0, -38.0, 13.0, 12.0))
        f["mouthFrown" + name] = (s * 1.0 * w, -5.5 * w)
        w = bump(ell(u, v, s * 17.0, 14.0, 15.0, 9.0))
        f["browDown" + name] = (-s * 1.5 * w, -3.0 * w)
    w = bump(ell(u, v, 0.0, -36.5, 24.0, 11.0))
    w2 = bump(ell(u, v, 0.0, -36.5, 40.0, 11.0))
    # lips pushed together sideways and rounded (upper lip up, lower lip down)
    f["mouthPucker"] = (-0.35 * u * w, 1.0 * torch.tanh((v - MOUTH_V) / 2.5) * w2)
    w = bump(ell(u, v, 9.0, 14.0, 14.0, 10.0)) + bump(ell(u, v, -9.0, 14.0, 14.0, 10.0))
    f["browInnerUp"] = (z, 4.0 * w)
    return f


def _radial_fields(u: torch.Tensor, v: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per control: radial offset (metres) on canonical coordinates."""
    f: dict[str, torch.Tensor] = {}
    for name, s in (("Left", 1.0), ("Right", -1.0)):
        f["mouthSmile" + name] = 0.004 * bump(ell(u, v, s * 25.0, -20.0, 11.0, 10.0))
        # the chin muscle bunches below a pulled-down mouth corner
        f["mouthFrown" + name] = 0.003 * bump(ell(u, v, s * 15.0, -46.0, 9.0, 7.0))
    f["mouthPucker"] = 0.009 * bump(ell(u, v, 0.0, -36.5, 15.0, 8.0))
    f["cheekPuff"] = 0.010 * (bump(ell(u, v, 30.0, -23.0, 15.0, 14.0))
                              + bump(ell(u, v, -30.0, -23.0, 15.0, 14.0)))
    return f


# ----------------------------------------------------------------------------- grids


@dataclass(frozen=True)
class Grid:
    """Equirectangular grid: row i at v = 90 - (i + .5) step, column j at u = -180 + (j + .5)."""

    step: float

    @property
    def shape(self) -> tuple[int, int]:
        return round(180 / self.step), round(360 / self.step)

    def uv(self) -> tuple[torch.Tensor, torch.Tensor]:
        h, w = self.shape
        v = 90.0 - (torch.arange(h, dtype=torch.float64) + 0.5) * self.step
        u = -180.0 + (torch.arange(w, dtype=torch.float64) + 0.5) * self.step
        vv, uu = torch.meshgrid(v, u, indexing="ij")
        return uu.float(), vv.float()


def sample(maps: torch.Tensor, u: torch.Tensor, v: torch.Tensor,
           box: tuple[float, float, float, float] | None = None) -> torch.Tensor:
    """Bilinear lookup of maps (C, H, W) at angles (degrees) -> (C, *u.shape).

    Without `box` the maps cover the whole sphere; with box = (u0, u1, v0, v1) they cover
    that window (edges of the outer texels) and read zero outside it."""
    if box is None:
        gx, gy = u * (1 / 180.0), v * (-1 / 90.0)
        pad = "border"
    else:
        u0, u1, v0, v1 = box
        gx = (u - u0) * (2 / (u1 - u0)) - 1
        gy = (v1 - v) * (2 / (v1 - v0)) - 1
        pad = "zeros"
    # interleave (x, y) pairs: complex packing is much faster than torch.stack on CPU
    g = torch.view_as_real(torch.complex(gx.reshape(-1), gy.reshape(-1))).reshape(1, 1, -1, 2)
    out = F.grid_sample(maps[None], g, mode="bilinear", padding_mode=pad, align_corners=False)
    return out.reshape(maps.shape[0], *u.shape)


def normals_from_radius(R: torch.Tensor, u: torch.Tensor, v: torch.Tensor,
                        Rl: torch.Tensor, Rr: torch.Tensor, Ru: torch.Tensor,
                        Rd: torch.Tensor, step: float) -> torch.Tensor:
    """Outward normals of r = R(u, v) from central differences (neighbours left, right, up,
    down on the grid). -> (..., 3)."""
    h = 2 * step * DEG
    dRu = (Rr - Rl) / h
    dRv = (Ru - Rd) / h
    ur, vr = u * DEG, v * DEG
    su, cu, sv, cv = torch.sin(ur), torch.cos(ur), torch.sin(vr), torch.cos(vr)
    w = torch.stack([su * cv, sv, cu * cv], -1)
    eu = torch.stack([cu, torch.zeros_like(cu), -su], -1)
    ev = torch.stack([-su * sv, cv, -cu * sv], -1)
    gu = (dRu / (R * cv.clamp(min=0.05)))[..., None]
    gv = (dRv / R)[..., None]
    n = w - gu * eu - gv * ev
    return n / n.norm(dim=-1, keepdim=True)


def map_normals(R: torch.Tensor, step: float) -> torch.Tensor:
    """Normals (3, H, W) of a whole-sphere radius map R (H, W)."""
    u, v = Grid(step).uv()
    Rl = torch.roll(R, 1, dims=1)
    Rr = torch.roll(R, -1, dims=1)
    Ru = torch.cat([R[:1], R[:-1]], 0)
    Rd = torch.cat([R[1:], R[-1:]], 0)
    return normals_from_radius(R, u, v, Rl, Rr, Ru, Rd, step).permute(2, 0, 1).contiguous()


# ----------------------------------------------------------------------------- the head


@dataclass
class HeadState:
    """A head deformed by one expression: what the renderer samples."""

    expression: torch.Tensor  # (num_controls,)
    radius: torch.Tensor  # (1, H, W) geometry map, metres
    aux: torch.Tensor  # (6, H, W): du_c, dv_c, dy_v (degrees, canonical/crack - texel), normal
    vertices: np.ndarray  # (V, 3) face-mesh vertices, world (= head) frame


class Head:
    """Static canonical maps of one head (appearance chosen by `seed`; albedo texels of
    `tex_step` degrees), and per-expression states."""

    def __init__(self, seed: int, tex_step: float = TEX_STEP):
        self.seed = int(seed)
        rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([self.seed, 101])))
        self.noise = Noise(self.seed * 7 + 1)
        self.palette = _choose_palette(rng)
        self.geo = Grid(GEO_STEP)
        self.tex = Grid(tex_step)
        u, v = self.geo.uv()
        self.R_static = self._radius(u, v)  # (H, W)
        # the ray marcher's shells must bound every expression's surface (cheeks and lips
        # add up to 1.2 cm, the open mouth cuts up to 2.4 cm into the lips)
        mouth = (u.abs() < MOUTH_HALF) & ((v - MOUTH_V).abs() < 3)
        assert float(self.R_static.max()) + 0.012 < R_OUTER
        assert float(self.R_static.min()) > R_INNER
        assert float(self.R_static[mouth].min()) - 0.025 > R_INNER
        self.N_static = map_normals(self.R_static, GEO_STEP)  # (3, H, W)
        self.albedo = self._albedo()  # (6, Ht, Wt): skin/lids/hair rgb, eyeball rgb
        self._build_expression_fields()
        self._build_mesh()

    # ------------------------------------------------------------------ static geometry

    def _radius(self, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Neutral head radius (metres), with lids closed over the eyes."""
        w = directions(u, v)
        ax = 0.074 * (1 - 0.12 * smoothstep(-10.0, -70.0, v))
        ay = torch.where(w[..., 1] > 0, 0.102, 0.112)
        az = torch.where(w[..., 2] > 0, 0.094, 0.102)
        R = 1 / torch.sqrt((w[..., 0] / ax) ** 2 + (w[..., 1] / ay) ** 2 + (w[..., 2] / az) ** 2)
        # flatten under the chin towards the neck
        R = R * (1 - 0.16 * smoothstep(-62.0, -88.0, v) * (torch.cos(u * DEG).clamp(min=0)))
        d = torch.zeros_like(R)
        # brow ridge, cheekbones
        d += 0.004 * bump(ell(u, v, 0.0, 13.0, 38.0, 7.0))
        for s in (1.0, -1.0):
            d += 0.005 * gauss(u, v, s * 33.0, -6.0, 11.0, 8.0)
            # eye socket, and the closed-lid dome over the eyeball
            d -= 0.007 * gauss(u, v, s * EYE_U, 3.0, 11.0, 8.0)
            d += 0.005 * (1 - ell(u, v, s * EYE_U, EYE_V, 10.0, 6.5)).clamp(min=0).sqrt()
            # nose wings
            d += 0.007 * gauss(u, v, s * 6.5, -14.5, 3.0, 2.8)
            # ears: rim bump with a hollow
            d += 0.016 * bump(ell(u, v, s * 88.0, -3.0, 7.0, 12.0))
            d -= 0.006 * bump(ell(u, v, s * 89.0, -4.0, 4.0, 7.0))
        # nose: a ridge growing from the bridge to the tip
        ridge = 0.004 + 0.018 * smoothstep(6.0, -10.0, v)
        ridge = ridge * smoothstep(-19.0, -11.5, v) * smoothstep(16.0, 6.0, v)
        width = 2.8 + 3.0 * smoothstep(2.0, -12.0, v)
        d += ridge * torch.exp(-0.5 * (u / width) ** 2)
        d += 0.004 * gauss(u, v, 0.0, -11.0, 4.0, 3.5)
        # lips, lip line, philtrum, chin
        vm = mouth_line(u)
        lipw = (1 - (u / 15.0) ** 2).clamp(min=0)
        d += 0.0045 * torch.exp(-0.5 * ((v - vm - 2.2) / 1.8) ** 2) * lipw
        d += 0.005 * torch.exp(-0.5 * ((v - vm + 2.8) / 2.2) ** 2) * lipw
        d -= 0.0015 * torch.exp(-0.5 * ((v - vm) / 0.6) ** 2) * lipw
        d -= 0.001 * gauss(u, v, 0.0, -27.0, 1.2, 4.0)
        d += 0.006 * gauss(u, v, 0.0, -60.0, 9.0, 6.0)
        d -= 0.002 * gauss(u, v, 0.0, -47.0, 10.0, 2.5)
        # hair: a shell over the scalp, thin at the hairline and fuller on top
        above = v - self._hairline(u)
        lumps = self.noise.fbm(torch.stack([u / 25.0, v / 25.0], -1) + 600.0, 3)
        d += self._hair_mask(u, v) * (0.003 + 0.010 * smoothstep(0.0, 14.0, above)
                                      + 0.003 * lumps)
        return R + d

    @staticmethod
    def _hairline(u: torch.Tensor) -> torch.Tensor:
        knots_u = [0, 30, 55, 75, 95, 112, 130, 181]
        knots_v = [37, 33, 22, 15, 16, -10, -38, -40]
        au = u.abs().double().numpy()
        return torch.from_numpy(np.interp(au, knots_u, knots_v)).float()

    def _hair_mask(self, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """1 on hair, with a ragged hairline."""
        jitter = 1.5 * self.noise.fbm(torch.stack([u / 3.0, v / 3.0], -1) + 700.0, 2)
        return smoothstep(-1.0, 1.5, v - self._hairline(u) + jitter)

    # ------------------------------------------------------------------ static albedo

    def _albedo(self) -> torch.Tensor:
        """Canonical albedo (6, H, W) on the texture grid: skin/lips/brows/hair, eyeballs."""
        grid = self.tex
        u, v = grid.uv()
        h, w = grid.shape
        pal = self.palette
        nz = self.noise
        # 2-D noise coordinates in degrees, roughly isometric on the sphere
        q = torch.stack([u * torch.cos(v * DEG), v], -1)
        uq, vq = Grid(grid.step * 4).uv()
        qq = torch.stack([uq * torch.cos(vq * DEG), vq], -1)
        blotch = upsample(nz.fbm(qq / 12.0, 3), (h, w))
        uh, vh = Grid(grid.step * 2).uv()
        qh = torch.stack([uh * torch.cos(vh * DEG), vh], -1)
        spots = upsample(smoothstep(0.45, 0.65, nz.fbm(qh / 1.8 + 50.0, 2)), (h, w))
        pores = nz.fbm(q / 0.7 + 100.0, 2)
        skin = torch.tensor(pal["skin"]).view(3, 1, 1) * (
            1 + 0.06 * blotch + 0.08 * pores - 0.10 * spots)
        red = torch.tensor([0.06, -0.02, -0.02]).view(3, 1, 1)
        for s in (1.0, -1.0):
            skin = skin + red * gauss(u, v, s * 30.0, -18.0, 12.0, 10.0)
            skin = skin * (1 - 0.14 * gauss(u, v, s * EYE_U, 5.0, 12.0, 7.0))
            skin = skin * (1 - 0.8 * smoothstep(1.0, 0.6, ell(u, v, s * 3.2, -16.8, 1.8, 1.0)))
            skin = skin * (1 - 0.25 * bump(ell(u, v, s * 89.0, -4.0, 4.0, 7.0)))
        # lips (box-restricted)
        rs, cs = _box(grid, -18.0, 18.0, -46.0, -28.0)
        bu, bv = u[rs, cs], v[rs, cs]
        vm = mouth_line(bu)
        shape = (1 - (bu / 15.0) ** 2).clamp(min=0).sqrt()
        up = smoothstep(-0.3, 0.3, bv - vm) * smoothstep(-0.4, 0.4, vm + 4.2 * shape - bv)
        lo = smoothstep(-0.3, 0.3, vm - bv) * smoothstep(-0.4, 0.4, bv - (vm - 5.2 * shape))
        lines = nz.fbm(torch.stack([bu * 1.5, bv * 0.15], -1) + 200.0, 2)
        lip = torch.tensor(pal["lip"]).view(3, 1, 1) * (1 + 0.10 * lines + 0.05 * pores[rs, cs])
        lm = (up + lo).clamp(max=1)
        skin[:, rs, cs] = skin[:, rs, cs] * (1 - lm) + lip * lm
        # eyebrows: hair strokes running sideways
        hair_c = torch.tensor(pal["hair"]).view(3, 1, 1)
        for s in (1.0, -1.0):
            rs, cs = _box(grid, min(s * 3.0, s * 36.0), max(s * 3.0, s * 36.0), 8.0, 20.0)
            bu, bv = u[rs, cs], v[rs, cs]
            t = ((s * bu - 5.0) / 28.0).clamp(0, 1)
            centre = 13.5 + 2.5 * torch.sin(math.pi * t)
            half = 1.4 - 0.7 * t
            bm = smoothstep(0.3, -0.3, (bv - centre).abs() - half)
            bm = bm * smoothstep(4.0, 6.0, s * bu) * smoothstep(34.0, 31.0, s * bu)
            strokes = nz.fbm(torch.stack([bu * 0.4, bv * 5.0], -1) + 300.0 + 10 * s, 2)
            dens = (0.75 + 0.5 * strokes).clamp(0, 1) * bm
            brow = hair_c * (1.2 + 0.3 * strokes)
            skin[:, rs, cs] = skin[:, rs, cs] * (1 - dens) + brow * dens
        # hair: strands running down from the crown (only where there is hair)
        hm = self._hair_mask(u, v)
        rows = (hm.amax(1) > 0).nonzero().flatten()
        rs = slice(int(rows[0]), int(rows[-1]) + 1)
        hu, hv = u[rs], v[rs]
        strands = nz.fbm(torch.stack([hu * 1.2, hv * 0.12], -1) + 400.0, 3)
        fine = nz.fbm(torch.stack([hu * 4.0, hv * 0.3], -1) + 500.0, 2)
        hair = hair_c * (1 + 0.45 * strands + 0.25 * fine)
        hmr = hm[rs]
        skin[:, rs] = skin[:, rs] * (1 - hmr) + hair * hmr
        # eyeballs
        eye = torch.tensor([0.93, 0.91, 0.87]).view(3, 1, 1) * (1 + 0.03 * pores)
        for s in (1.0, -1.0):
            rs, cs = _box(grid, s * EYE_U - 10.0, s * EYE_U + 10.0, EYE_V - 6.0, EYE_V + 7.0)
            bu, bv = u[rs, cs], v[rs, cs]
            du, dv = bu - s * EYE_U, bv - (EYE_V + 0.3)
            r = torch.sqrt(du * du + dv * dv)
            ang = torch.atan2(dv, du)
            streak = nz.fbm(torch.stack([torch.cos(ang) * 6, torch.sin(ang) * 6, r * 0.8], -1), 2)
            iris = torch.tensor(pal["iris"]).view(3, 1, 1) * (1 + 0.5 * streak)
            iris = iris * (1 - 0.5 * smoothstep(2.6, 3.4, r))
            im = smoothstep(3.55, 3.3, r)
            e = eye[:, rs, cs] * (1 - im) + iris * im
            pm = smoothstep(1.45, 1.25, r)
            e = e * (1 - pm) + 0.03 * pm
            cm = smoothstep(0.5, 0.35, torch.sqrt((du + 0.9) ** 2 + (dv - 1.0) ** 2))
            e = e * (1 - cm) + 0.97 * cm
            corner = gauss(bu, bv, s * (EYE_U - 7.5), EYE_V, 1.8, 1.5)
            pink = torch.tensor([0.85, 0.45, 0.45]).view(3, 1, 1)
            eye[:, rs, cs] = e * (1 - 0.3 * corner) + pink * 0.3 * corner
        return torch.cat([skin, eye], 0).clamp(0, 1).contiguous()

    # ------------------------------------------------------------------ expression fields

    def _build_expression_fields(self) -> None:
        h, w = self.geo.shape
        u, v = self.geo.uv()
        # window (whole texels) holding every expression field
        cols = ((u[0] > -66) & (u[0] < 66)).nonzero().flatten()
        rows = ((v[:, 0] > -90) & (v[:, 0] < 42)).nonzero().flatten()
        self.win_rows = (int(rows[0]), int(rows[-1]) + 1)
        self.win_cols = (int(cols[0]), int(cols[-1]) + 1)
        s = GEO_STEP
        r0, r1 = self.win_rows
        c0, c1 = self.win_cols
        self.win_box = (-180 + c0 * s, -180 + c1 * s, 90 - r1 * s, 90 - r0 * s)
        wu, wv = u[r0:r1, c0:c1], v[r0:r1, c0:c1]
        warps = _warp_fields(wu, wv)
        radial = _radial_fields(wu, wv)
        nk = len(CONTROLS)
        self.warp_basis = torch.zeros(nk, 2, r1 - r0, c1 - c0)
        self.radial_basis = torch.zeros(nk, 1, r1 - r0, c1 - c0)
        for name, (du, dv) in warps.items():
            self.warp_basis[CONTROL_INDEX[name], 0] = du
            self.warp_basis[CONTROL_INDEX[name], 1] = dv
        for name, dr in radial.items():
            self.radial_basis[CONTROL_INDEX[name], 0] = dr
        # active texels: where any field, the lids or the jaw can act (+ 2 texel margin)
        act = (self.warp_basis.abs().sum((0, 1)) > 0) | (self.radial_basis.abs().sum((0, 1)) > 0)
        act |= jaw_region(wu, wv) > 0
        for side in (1.0, -1.0):
            act |= (((wu - side * EYE_U) / (EYE_HW + 1)).abs() < 1) & (wv > EYE_V - EYE_LO - 1) & (
                wv < EYE_V + EYE_UP + 3)
        act = F.max_pool2d(act.float()[None, None], 5, 1, 2)[0, 0] > 0
        full = torch.zeros(h, w, dtype=torch.bool)
        full[r0:r1, c0:c1] = act
        self.active = full  # (H, W) bool: texels an expression may change
        self.active_idx = full.flatten().nonzero().flatten()
        # texels whose normal may change: one more texel around
        grown = F.max_pool2d(full.float()[None, None], 3, 1, 1)[0, 0] > 0
        self.normal_idx = grown.flatten().nonzero().flatten()
        # static lookups for `state`
        uf, vf = u.flatten(), v.flatten()
        self._act_u = uf.index_select(0, self.active_idx)
        self._act_v = vf.index_select(0, self.active_idx)
        nidx = self.normal_idx
        row, col = nidx // w, nidx % w
        self._normal_nbrs = torch.stack([
            nidx, row * w + (col - 1) % w, row * w + (col + 1) % w,
            (row - 1).clamp(min=0) * w + col, (row + 1).clamp(max=h - 1) * w + col])
        self._nrm_u, self._nrm_v = uf.index_select(0, nidx), vf.index_select(0, nidx)
        self._aux_static = torch.cat([torch.zeros(3, h, w), self.N_static])

    def _warp_at(self, warp: torch.Tensor, u: torch.Tensor, v: torch.Tensor):
        d = sample(warp, u, v, self.win_box)
        return d[0], d[1]

    # ------------------------------------------------------------------ face mesh

    def _build_mesh(self) -> None:
        uv, faces = mesh_layout()
        self.mesh_uv = torch.from_numpy(uv.copy())
        self.faces = faces

    # ------------------------------------------------------------------ per-expression state

    def state(self, expression) -> HeadState:
        """Deformed maps and face mesh for an expression vector (num_controls,) in [0, 1]."""
        e = torch.as_tensor(np.asarray(expression, np.float32)).clamp(0, 1)
        if e.shape != (len(CONTROLS),):
            raise ValueError(f"expression must have {len(CONTROLS)} values, got {tuple(e.shape)}")
        jaw = float(e[CONTROL_INDEX["jawOpen"]])
        warp = torch.einsum("k,kchw->chw", e, self.warp_basis)
        radial = torch.einsum("k,kchw->chw", e, self.radial_basis)
        idx, xu, xv = self.active_idx, self._act_u, self._act_v
        # 1. invert the smooth warp: y = x - D(y)
        yu, yv = xu, xv
        for _ in range(WARP_ITERS):
            du, dv = self._warp_at(warp, yu, yv)
            yu, yv = xu - du, xv - dv
        # 2. invert the jaw crack: find v_c with v_c - jaw F(u, v_c) = y_v (monotone in v_c)
        vc = yv.clone()
        if jaw > 0:
            sel = ((yu.abs() < JAW_R[0] + JAW_C[0]) & (yv < JAW_C[1] + JAW_R[1]))
            sel = sel.nonzero().flatten()
            vc.index_copy_(0, sel, _invert_jaw(yu.index_select(0, sel), yv.index_select(0, sel),
                                               jaw))
        uc = yu
        # 3. radius at the canonical point, lids, cheek/lip offsets, mouth pocket
        R = sample(self.R_static[None], uc, vc)[0] + sample(radial, uc, vc, self.win_box)[0]
        near_eye = (((uc.abs() - EYE_U).abs() < EYE_HW + 0.5) & (vc > EYE_V - EYE_LO - 1.0)
                    & (vc < EYE_V + EYE_UP + 3.0)).nonzero().flatten()
        if len(near_eye):
            ue, ve = uc.index_select(0, near_eye), vc.index_select(0, near_eye)
            R.index_add_(0, near_eye, -0.0012 * eye_open(ue, ve, e))
        near_mouth = (uc.abs() < MOUTH_HALF + 1.0) & ((vc - MOUTH_V).abs() < 2.5)
        near_mouth = near_mouth.nonzero().flatten()
        if jaw > 0 and len(near_mouth):
            sub = lambda x: x.index_select(0, near_mouth)  # noqa: E731
            R.index_add_(0, near_mouth, -self._pocket(sub(uc), sub(vc), sub(yv), jaw))
        radius = self.R_static.clone()
        radius.view(-1).index_copy_(0, idx, R)
        aux = self._aux_static.clone()
        aux_flat = aux.view(6, -1)
        aux_flat[:3].index_copy_(1, idx, torch.stack([uc - xu, vc - xv, yv - xv]))
        # normals where the radius (or a neighbour) changed
        Rf = radius.view(-1)
        nb = self._normal_nbrs  # (5, n): self, left, right, up, down
        n = normals_from_radius(Rf.index_select(0, nb[0]), self._nrm_u, self._nrm_v,
                                Rf.index_select(0, nb[1]), Rf.index_select(0, nb[2]),
                                Rf.index_select(0, nb[3]), Rf.index_select(0, nb[4]), GEO_STEP)
        aux_flat[3:].index_copy_(1, nb[0], n.T.contiguous())
        st = HeadState(expression=e, radius=radius[None], aux=aux, vertices=np.zeros((0, 3)))
        st.vertices = self.mesh_vertices(st, warp)
        return st

    @staticmethod
    def _pocket(uc, vc, yv, jaw: float) -> torch.Tensor:
        """How far (metres) the open mouth's surface lies inside the lip surface."""
        if jaw <= 0:
            return torch.zeros_like(uc)
        band, d_up, d_lo, opening = mouth_gap(uc, vc, yv, jaw)
        teeth_up = smoothstep(3.9, 3.5, d_up) * smoothstep(12.0, 10.0, uc.abs())
        teeth_lo = smoothstep(2.5, 2.1, d_lo) * smoothstep(10.0, 8.0, uc.abs())
        teeth = (teeth_up + teeth_lo).clamp(max=1)
        depth = 0.004 + (1 - teeth) * 0.020 * (opening / 3.0).clamp(max=1)
        return band * depth * (opening / 0.5).clamp(max=1)

    def mesh_vertices(self, st: HeadState, warp: torch.Tensor | None = None) -> np.ndarray:
        """Face-mesh vertices for a state: canonical grid points moved forward through the
        expression map and placed on the state's surface."""
        e = st.expression
        if warp is None:
            warp = torch.einsum("k,kchw->chw", e, self.warp_basis)
        uc, vc = self.mesh_uv[:, 0], self.mesh_uv[:, 1]
        jaw = float(e[CONTROL_INDEX["jawOpen"]])
        yv = vc - jaw * jaw_drop(uc, vc)
        du, dv = self._warp_at(warp, uc, yv)
        xu, xv = uc + du, yv + dv
        R = sample(st.radius, xu, xv)[0]
        return (directions(xu, xv) * R[:, None]).numpy().astype(np.float32)

    # ------------------------------------------------------------------ shading inputs

    def surface(self, st: HeadState, x: torch.Tensor, y: torch.Tensor,
                z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Albedo (3, N) and unit normal (3, N) at head-surface points (x, y, z each (N,))."""
        u, v, _ = angles(x, y, z)
        a = sample(st.aux, u, v)  # (6, N)
        uc, vc, yv = u + a[0], v + a[1], v + a[2]
        n = a[3:]
        n = n / torch.sqrt((n * n).sum(0, keepdim=True)).clamp(min=1e-9)
        alb = sample(self.albedo, uc, vc)  # (6, N)
        col = alb[:3].clone()
        e = st.expression
        # eyes: the eyeball through the lids, lashes along the lid edges
        near_eye = ((uc.abs() - EYE_U).abs() < EYE_HW) & (vc > EYE_V - EYE_LO - 0.6) & (
            vc < EYE_V + EYE_UP + 3.0)
        i = near_eye.nonzero().flatten()
        if len(i):
            eu, ev = uc[i], vc[i]
            open_ = eye_open(eu, ev, e, soft=0.12)
            lash = torch.zeros_like(eu)
            for side, ib, iw in ((1.0, "eyeBlinkLeft", "eyeWideLeft"),
                                 (-1.0, "eyeBlinkRight", "eyeWideRight")):
                lower, upper, inbox = eye_lids(eu, side, float(e[CONTROL_INDEX[ib]]),
                                               float(e[CONTROL_INDEX[iw]]))
                a_ = ((eu - side * EYE_U) / EYE_HW).abs()
                edge = smoothstep(-0.1, 0.1, ev - upper) * smoothstep(0.9, 0.5, ev - upper)
                low = smoothstep(-0.1, 0.1, lower - ev) * smoothstep(0.4, 0.2, lower - ev) * 0.5
                lash = lash + (edge + low) * inbox.float() * smoothstep(1.0, 0.8, a_)
            c = alb[:3, i] * (1 - open_) + alb[3:, i] * open_
            col[:, i] = c * (1 - 0.85 * lash.clamp(max=1))
        # the mouth: lip line, and inside the open mouth
        near_mouth = (uc.abs() < MOUTH_HALF + 1.0) & ((vc - MOUTH_V).abs() < 2.5)
        i = near_mouth.nonzero().flatten()
        if len(i):
            col[:, i] = self._mouth_colour(col[:, i], uc[i], vc[i], yv[i],
                                           float(e[CONTROL_INDEX["jawOpen"]]))
        return col, n

    @staticmethod
    def _mouth_colour(col, uc, vc, yv, jaw: float):
        band, d_up, d_lo, opening = mouth_gap(uc, vc, yv, jaw)
        cavity = torch.tensor([0.10, 0.025, 0.03]).view(3, 1)
        tongue = torch.tensor([0.55, 0.20, 0.22]).view(3, 1)
        tooth = torch.tensor([0.90, 0.88, 0.80]).view(3, 1)
        au = uc.abs()
        tm = smoothstep(1.5, 2.5, d_lo) * smoothstep(6.0, 4.0, d_lo) * smoothstep(9.0, 7.0, au)
        inner = cavity * (1 - tm) + tongue * tm
        gap_u = torch.remainder(uc + 1.5, 3.0)
        gaps = smoothstep(0.25, 0.0, gap_u) + smoothstep(2.75, 3.0, gap_u)
        t_up = smoothstep(0.1, 0.3, d_up) * smoothstep(3.9, 3.5, d_up) * smoothstep(12.0, 10.0, au)
        t_lo = smoothstep(0.1, 0.3, d_lo) * smoothstep(2.5, 2.1, d_lo) * smoothstep(10.0, 8.0, au)
        tm2 = (t_up + t_lo).clamp(max=1) * (1 - 0.6 * gaps.clamp(max=1))
        tm2 = tm2 * (opening / 0.8).clamp(max=1)
        inner = inner * (1 - tm2) + tooth * tm2
        return col * (1 - band) + inner * band


@functools.lru_cache(maxsize=1)
def mesh_layout() -> tuple[np.ndarray, np.ndarray]:
    """The face mesh's canonical vertices (V, 2) (u, v degrees, on a MESH_STEP grid inside
    the face ellipse) and triangles (F, 3) int32, counter-clockwise seen from outside."""
    us = np.arange(-64.0, 64.0 + 1e-6, MESH_STEP)
    vs = np.arange(40.0, -90.0 - 1e-6, -MESH_STEP)
    uu, vv = np.meshgrid(us, vs)
    keep = (uu / FACE_R[0]) ** 2 + ((vv - FACE_C) / FACE_R[1]) ** 2 <= 1.0
    index = -np.ones(keep.shape, np.int64)
    index[keep] = np.arange(keep.sum())
    faces = []
    for i in range(len(vs) - 1):
        for j in range(len(us) - 1):
            a, b, c, d = index[i, j], index[i, j + 1], index[i + 1, j], index[i + 1, j + 1]
            if min(a, b, c, d) < 0:
                continue
            faces.append((a, c, d))
            faces.append((a, d, b))
    uv = np.stack([uu[keep], vv[keep]], -1).astype(np.float32)
    uv.setflags(write=False)
    f = np.asarray(faces, np.int32)
    f.setflags(write=False)
    return uv, f


def mesh_landmarks() -> dict[str, list[int]]:
    """The face mesh's vertices at the eyes' and the mouth's centres (a dataset's
    `face_landmarks`, data/face_parts.py): the grid vertex nearest each."""
    uv, _ = mesh_layout()

    def nearest(u: float, v: float) -> list[int]:
        return [int(np.argmin((uv[:, 0] - u) ** 2 + (uv[:, 1] - v) ** 2))]

    return {"eye_left": nearest(EYE_U, EYE_V), "eye_right": nearest(-EYE_U, EYE_V),
            "mouth": nearest(0.0, MOUTH_V)}


def _box(grid: Grid, u0: float, u1: float, v0: float, v1: float) -> tuple[slice, slice]:
    """Row and column slices of the grid texels inside the angular box."""
    h, w = grid.shape
    c0 = max(0, int(math.floor((u0 + 180.0) / grid.step)))
    c1 = min(w, int(math.ceil((u1 + 180.0) / grid.step)))
    r0 = max(0, int(math.floor((90.0 - v1) / grid.step)))
    r1 = min(h, int(math.ceil((90.0 - v0) / grid.step)))
    return slice(r0, r1), slice(c0, c1)


def _choose_palette(rng: np.random.Generator) -> dict[str, tuple[float, float, float]]:
    skins = [(0.80, 0.60, 0.48), (0.72, 0.52, 0.40), (0.56, 0.38, 0.28), (0.86, 0.67, 0.56),
             (0.45, 0.30, 0.21), (0.76, 0.58, 0.42)]
    hairs = [(0.10, 0.07, 0.05), (0.24, 0.15, 0.08), (0.42, 0.28, 0.14), (0.66, 0.52, 0.30),
             (0.06, 0.05, 0.05), (0.45, 0.18, 0.08)]
    irises = [(0.33, 0.20, 0.10), (0.25, 0.42, 0.62), (0.30, 0.45, 0.25), (0.42, 0.33, 0.18)]
    skin = np.array(skins[rng.integers(len(skins))]) * rng.uniform(0.96, 1.04, 3)
    lip = skin * np.array([0.92, 0.55, 0.55]) + np.array([0.05, 0.0, 0.01])
    return {
        "skin": tuple(float(x) for x in skin),
        "lip": tuple(float(x) for x in lip),
        "hair": tuple(float(x) for x in hairs[rng.integers(len(hairs))]),
        "iris": tuple(float(x) for x in irises[rng.integers(len(irises))]),
    }
