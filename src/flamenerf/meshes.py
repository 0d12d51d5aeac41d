"""Face-mesh helpers shared by the model, rendering and evaluation: points on a mesh, the
per-subject linear expression model β -> mesh (optionally limited per control to parts of
the face), the displacement a mesh change induces on nearby space, and the nearest vertex
of many points (the per-control prior's gates).

The expression model is what lets a commanded β move the face: fitted on the training
frames' tracked meshes, it gives the mesh of any β (re-animation, the viewer's sliders, the
spatial prior's silhouette of the driven expression), and the mesh-guided deformation
(`mesh_displacement`) carries points near the face from the expression's mesh to the
neutral one, as RigNeRF does with its 3DMM. The model takes its two steps separately
(`nearest_vertices`, `displacement_of_neighbours`) so that one query also gives the
per-control gates their nearest vertex.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from flamenerf import gpu_kernels
from flamenerf.cpu_kernels import kernel_library


def surface_points(vertices: Tensor, faces: Tensor, tri: Tensor, uv: Tensor,
                   which: Tensor | None = None) -> Tensor:
    """Points on triangles by barycentric coordinates.

    vertices (V, 3), or (M, V, 3) several meshes of one topology with `which` (B,) long
    saying whose mesh each point is on (default: the i-th point on mesh i); faces (F, 3)
    long; tri (B,) long triangle ids; uv (B, 2) uniform in [0, 1]^2 (folded into the
    triangle here). -> (B, 3).
    """
    u = uv.clone()
    flip = u.sum(-1) > 1
    u[flip] = 1 - u[flip]
    idx = faces[tri]  # (B, 3)
    if vertices.dim() == 2:
        v = vertices[idx]  # (B, 3, 3)
    else:
        if which is None:
            which = torch.arange(len(tri), device=vertices.device)
        v = vertices[which[:, None], idx]
    return v[:, 0] + u[:, :1] * (v[:, 1] - v[:, 0]) + u[:, 1:] * (v[:, 2] - v[:, 0])


def expression_model_system(expressions: Tensor, vertices: Tensor, ridge: float = 1e-3,
                            weights: Tensor | None = None
                            ) -> tuple[Tensor, Tensor, Tensor]:
    """The normal equations of `fit_expression_model`, one small system per vertex, float64.

    Vertex v's coefficients c_v (1+E, 3) (its neutral position, then one offset per control)
    solve gram[v] c_v = rhs[v]; the model's row e of vertex v is c_v[e] * scale[v, e].
    -> gram (V, 1+E, 1+E), or (1, 1+E, 1+E) shared by every vertex without `weights` (a
    FLAME mesh's 5023 copies would take ~120 MB); rhs (V, 1+E, 3); scale (V, 1+E) (ones
    without `weights`)."""
    n, e = expressions.shape
    v = vertices.shape[1]
    x = torch.cat([torch.ones(n, 1, dtype=torch.float64),
                   expressions.to(torch.float64)], 1)  # (N, 1+E)
    y = vertices.to(torch.float64)  # (N, V, 3)
    reg = torch.eye(e + 1, dtype=torch.float64) * ridge * max(float((x[:, 1:] ** 2).mean()), 1e-12) * n
    reg[0, 0] = 0.0  # the neutral mesh is not shrunk
    wt = torch.ones(v, e + 1, dtype=torch.float64)
    if weights is not None:
        wt[:, 1:] = weights.to(torch.float64)
    # per vertex, the design x·diag(w̃_v) with w̃_v = (1, weights[v]): its normal equations
    # are the shared ones scaled by w̃_v w̃_vᵀ
    gram = (x.T @ x)[None] + reg
    if weights is not None:
        gram = (x.T @ x)[None] * (wt[:, :, None] * wt[:, None, :]) + reg  # (V, 1+E, 1+E)
    rhs = torch.einsum("ne,nvc->vec", x, y) * wt[:, :, None]  # (V, 1+E, 3)
    return gram, rhs, wt


def fit_expression_model(expressions: Tensor, vertices: Tensor, ridge: float = 1e-3,
                         weights: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Least-squares linear model mesh(β) = neutral + Σ_k β_k basis_k over frames.

    expressions (N, E); vertices (N, V, 3). `ridge` (relative to the mean squared control
    value) keeps controls that barely vary in the frames from getting wild shapes.
    `weights` (V, E) in [0, 1] limits where each control may move the mesh
    (data/face_parts.py): vertex v is fitted on the controls scaled by weights[v], so a
    control with weight 0 there leaves it still and the others explain its motion.
    -> neutral (V, 3), basis (E, V, 3).
    """
    gram, rhs, scale = expression_model_system(expressions, vertices, ridge, weights)
    return model_from_coefficients(torch.linalg.solve(gram, rhs), scale)


def model_from_coefficients(coef: Tensor, scale: Tensor) -> tuple[Tensor, Tensor]:
    """`expression_model_system`'s unknowns coef (V, 1+E, 3) and scale (V, 1+E) -> neutral
    (V, 3), basis (E, V, 3) float32."""
    c = (coef * scale[:, :, None]).permute(1, 0, 2).to(torch.float32)
    return c[0].contiguous(), c[1:].contiguous()


def expression_mesh(neutral: Tensor, basis: Tensor, expression: Tensor) -> Tensor:
    """neutral (V, 3), basis (E, V, 3), expression (..., E) -> mesh (..., V, 3)."""
    return neutral + torch.einsum("...e,evc->...vc", expression.to(basis), basis)


GUIDE_CUTOFF = 4.0
"""Points farther than this many falloffs from the mesh do not move (their motion would be
below exp(-16) ≈ 1e-7 of the vertices')."""


def mesh_displacement(x: Tensor, mesh: Tensor, target: Tensor, falloff: float, k: int = 4,
                      which: Tensor | None = None) -> Tensor:
    """The displacement that carries space near `mesh` along with its vertices to `target`.

    x (P, 3) points; mesh (V, 3), or (M, V, 3) several meshes with `which` (P,) long saying
    whose mesh each point moves with; target (V, 3) the same vertices in the common pose;
    `falloff` the distance at which the motion has faded to 1/e (points far from the face
    stay put). Each point moves by the inverse-square-distance blend of its k nearest
    vertices' motions (on its own mesh), scaled by exp(-(d_min / falloff)^2), and not at
    all beyond GUIDE_CUTOFF falloffs. -> (P, 3).
    """
    if x.shape[0] == 0:
        return torch.zeros_like(x)
    meshes = mesh if mesh.dim() == 3 else mesh[None]
    if which is None:
        which = torch.zeros(len(x), dtype=torch.long, device=x.device)
    k = min(k, meshes.shape[1])
    d2k, idx = nearest_vertices(x, meshes, k, GUIDE_CUTOFF * falloff, which)  # inf: none
    return displacement_of_neighbours(d2k, idx, meshes, target, falloff)


def displacement_of_neighbours(d2k: Tensor, idx: Tensor, meshes: Tensor, target: Tensor,
                               falloff: float) -> Tensor:
    """`mesh_displacement` from the points' k nearest vertices found already: d2k (P, k)
    squared distances (inf: none), idx (P, k) into the M·V stacked vertices of meshes
    (M, V, 3); target (V, 3). Neighbours beyond GUIDE_CUTOFF falloffs do not count. -> (P, 3)."""
    d2k = d2k.masked_fill(d2k > (GUIDE_CUTOFF * falloff) ** 2, float("inf"))
    w = 1.0 / (d2k + 1e-10)  # 0 for the missing (d² = inf)
    w = w / w.sum(-1, keepdim=True).clamp_min(1e-30)  # rows with none: 0, not 0/0
    motion = (target[None] - meshes).reshape(-1, 3)[idx]  # (P, k, 3)
    fade = torch.exp(-d2k[:, :1] / (falloff * falloff))  # (P, 1): 0 where none is near
    return (w[..., None] * motion).sum(1) * fade


def nearest_vertices(pts: Tensor, verts: Tensor, k: int, bound: float,
                     which: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Squared distances to, and indices of, the k nearest of verts (V, 3) for pts (P, 3),
    nearest first; neighbours farther than `bound` get d² = inf and index 0. With several
    meshes verts (M, V, 3) and `which` saying whose mesh each point is on, indices run into
    the M·V stacked vertices: pts (P, 3) with which (P,), or the samples of rays pts
    (R, S, 3) with which (R,) (a ray's samples share its mesh). On a CPU with AVX-512 the
    compiled kernel (kernels/knn.c: each point walks its mesh's vertices, seeded by the
    previous point's neighbours; 41 -> 13 ms for a 128 px viewer update's queries, the same
    answer), on other CPUs a k-d tree (brute-force distances in PyTorch were over a third
    of a mesh-guided frame's time); distance blocks elsewhere. -> (P, k) or (R·S, k), and the
    same shape long."""
    if verts.dim() == 3 and which is None:
        raise ValueError("nearest_vertices: several meshes need `which`")
    if pts.device.type != "cpu":
        return nearest_vertices_off_cpu(pts, verts, k, bound, which)
    if pts.dim() == 3:
        which = which.repeat_interleave(pts.shape[1])
        pts = pts.reshape(-1, 3)

    lib = kernel_library()
    if lib is not None and lib.knn_vectorised() and 1 <= k <= KNN_MAX_K:
        return _nearest_vertices_kernel(lib, pts, verts, k, bound, which)
    from scipy.spatial import cKDTree

    v = verts.double().reshape(-1, 3).numpy()
    p = pts.double().numpy()
    if verts.dim() == 3:
        # one tree for all the meshes (a training batch has ~100 distinct β; a tree and
        # a query each cost more in overhead than in work): a fourth coordinate, far
        # apart for different meshes, keeps every point's neighbours on its own mesh
        gap = 2.0 * bound + 1.0
        m = np.repeat(np.arange(verts.shape[0], dtype=np.float64), verts.shape[1])
        v = np.concatenate([v, (m * gap)[:, None]], 1)
        p = np.concatenate([p, which.double().numpy()[:, None] * gap], 1)
    d, i = cKDTree(v).query(p, k=k, distance_upper_bound=bound,
                            workers=_threads_for(len(pts)))
    d, i = d.reshape(len(pts), k), i.reshape(len(pts), k)
    far = ~np.isfinite(d)
    i[far] = 0
    return torch.from_numpy(np.square(d)).to(pts.dtype), torch.from_numpy(i).long()


KNN_MAX_K = 16
"""The most neighbours the compiled kernel keeps (kernels/knn.c)."""


def _nearest_vertices_kernel(lib, pts: Tensor, verts: Tensor, k: int, bound: float,
                             which: Tensor | None) -> tuple[Tensor, Tensor]:
    """`nearest_vertices` on a CPU through kernels/knn.c: pts (P, 3), verts (V, 3) or
    (M, V, 3) with which (P,)."""
    meshes = verts[None] if verts.dim() == 2 else verts
    p = pts.detach().float().contiguous()
    v = meshes.detach().float().contiguous()
    w = None if verts.dim() == 2 else which.to(torch.int64).contiguous()
    if w is not None and len(w) and (int(w.min()) < 0 or int(w.max()) >= v.shape[0]):
        raise ValueError(f"nearest_vertices: mesh indices outside 0..{v.shape[0] - 1}")
    d2 = torch.empty(len(p), k)
    idx = torch.empty(len(p), k, dtype=torch.int64)
    rc = lib.knn_forward(p.data_ptr(), len(p), None if w is None else w.data_ptr(),
                         v.data_ptr(), v.shape[0], v.shape[1], k, float(bound),
                         d2.data_ptr(), idx.data_ptr(), _threads_for(len(p)))
    if rc != 0:
        raise RuntimeError(f"knn_forward failed ({rc})")
    return d2.to(pts.dtype), idx


def nearest_vertices_off_cpu(pts: Tensor, verts: Tensor, k: int, bound: float,
                             which: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """`nearest_vertices` as it runs off the CPU (distance blocks or the GPU's kernel), on
    any device: one mesh (V, 3) is taken as a stack of one."""
    if verts.dim() == 2:
        verts, which = verts[None], torch.zeros(len(pts), dtype=torch.long, device=pts.device)
    return nearest_vertices_brute(pts, verts, k, bound, which)


def nearest_vertices_brute(pts: Tensor, meshes: Tensor, k: int, bound: float, which: Tensor,
                           block_elements: int = 1 << 25) -> tuple[Tensor, Tensor]:
    """`nearest_vertices` of several meshes (M, V, 3) by distances to every vertex of each
    point's own mesh: the path off the CPU. pts (P, 3) with which (P,), or (R, S, 3) with
    which (R,). In blocks of rays whose (B, S, V) distances hold at most `block_elements`
    numbers, every block one batched `cdist` (a loop over the meshes launched ~15 kernels
    and a synchronisation per mesh, ~100 meshes per training batch: an H200 trained
    `fast-gpu` at 5 steps/s; one (P, V, 3) gather of each point's mesh was gigabytes).
    Where Triton runs (GPUs), one kernel instead (gpu_kernels.knn: `topk` over the
    distances was over a third of a guided 256 px frame on an H200)."""
    x = pts if pts.dim() == 3 else pts[:, None]  # (R, S, 3)
    M, V = meshes.shape[:2]
    if which.shape != x.shape[:1]:  # the kernel would read past its end
        raise ValueError(f"nearest_vertices_brute: which {tuple(which.shape)} for points "
                         f"{tuple(pts.shape)}: one mesh index per point (or per ray)")
    k = min(k, V)

    def nearest(d: Tensor) -> tuple[Tensor, Tensor]:
        if k == 1:  # a reduction: topk's radix select was 15 % of an H100's 256 px frame
            return d.min(-1, keepdim=True)
        return torch.topk(d, k, dim=-1, largest=False)

    found = (gpu_kernels.knn(x.reshape(-1, 3), meshes, which.repeat_interleave(x.shape[1]), k)
             if k <= 8 and gpu_kernels.available(pts.device) else None)
    if found is not None:
        d2, idx = found
    elif M == 1:  # one mesh (an image, a viewer update): blocks of points, no gathers
        flat = x.reshape(-1, 3)
        step = max(1, block_elements // V)
        parts = [nearest(torch.cdist(flat[lo:lo + step], meshes[0]).square())
                 for lo in range(0, len(flat), step)]
        d2, idx = torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])
    else:  # blocks of rays, each against its own ray's mesh: (B, S, V) distances
        step = max(1, block_elements // (x.shape[1] * V))
        parts = []
        for lo in range(0, len(x), step):
            w = which[lo:lo + step]
            dk, ik = nearest(torch.cdist(x[lo:lo + step], meshes[w]).square())
            parts.append((dk.reshape(-1, k), (ik + (w * V)[:, None, None]).reshape(-1, k)))
        d2, idx = torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])
    far = d2 > bound * bound
    return d2.masked_fill(far, float("inf")), idx.masked_fill(far, 0)


def _threads_for(n: int) -> int:
    # threads pay from a few thousand points: a training step's one query of ~50k points
    # took 49 ms with 2 threads against 87 ms with one (the k-d tree); small queries (a
    # viewer's few rays) stay on one
    return max(1, torch.get_num_threads()) if n >= 8192 else 1
