"""FLAME backend: load the user's FLAME model files, pose the model (linear blend skinning),
and fit shape, expression, jaw and neck pose to the tracked MediaPipe landmarks through
FLAME's MediaPipe landmark embedding.

Files (in `--flame-dir`; FLAME's licence forbids redistribution, so we never download them):
- the model pickle: `generic_model.pkl` (FLAME 2020) or `flame2023*.pkl` or any single
  `*.pkl` with v_template (V, 3), shapedirs (V, 3, K), posedirs (V, 3, 36), J_regressor
  (5, V; dense or scipy.sparse), weights (V, 5), kintree_table (2, 5), f (F, 3);
  the first 300 of the K components are shape and the rest expression when K > 300 (FLAME),
  otherwise the first half.
- the landmark embedding: `mediapipe_landmark_embedding.npz` (as distributed with FLAME
  2023 / MICA) with lmk_face_idx (L,), lmk_b_coords (L, 3) and landmark_indices (L,)
  (the MediaPipe landmark each barycentric point corresponds to).

Pickles can run arbitrary code when loaded. We only read the path the user gives, and we
unpickle with an allow-list (numpy arrays, scipy sparse matrices, chumpy arrays read as
plain numpy) that refuses every other class.
"""

from __future__ import annotations

import io
import os
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from flamenerf.errors import UserError
from flamenerf.geometry import matrix_to_rotvec, project, so3_exp, umeyama
from flamenerf.runtime import torch_threads
from flamenerf.tracking.cameras import MIN_DEPTH, _lbfgs, cauchy

NUM_FLAME_SHAPE = 300  # FLAME's shape components precede its expression components


# ----------------------------------------------------------------------------- loading


class _ChumpyArray:
    """Stand-in for chumpy.ch.Ch objects inside FLAME pickles: keeps their state, whose
    'x' entry is the numpy array."""

    def __init__(self, *args, **kwargs):
        pass

    def __setstate__(self, state):
        if isinstance(state, dict):
            self.__dict__.update(state)
        else:
            self.__dict__["_state"] = state


_ALLOWED = {
    ("numpy", "ndarray"), ("numpy", "dtype"), ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"), ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"), ("copyreg", "_reconstructor"),
    ("builtins", "object"), ("collections", "OrderedDict"), ("_codecs", "encode"),
}
_SPARSE = {"csc_matrix", "csr_matrix", "coo_matrix"}
_PY2_MODULES = {"copy_reg": "copyreg", "__builtin__": "builtins"}


class _SafeUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        module = _PY2_MODULES.get(module, module)  # FLAME's pickles come from Python 2
        if (module, name) in _ALLOWED:
            import importlib

            return getattr(importlib.import_module(module), name)
        if module.startswith("scipy.sparse") and name in _SPARSE:
            import scipy.sparse

            return getattr(scipy.sparse, name)
        if module.startswith("chumpy"):
            return _ChumpyArray
        raise pickle.UnpicklingError(f"refusing to load {module}.{name} (not an array type)")


def _plain(x) -> np.ndarray:
    if isinstance(x, _ChumpyArray):
        x = x.__dict__.get("x", x.__dict__.get("_state"))
    if hasattr(x, "toarray"):
        x = x.toarray()
    return np.asarray(x)


def load_pickle(path: Path) -> dict:
    try:
        with open(path, "rb") as f:
            data = _SafeUnpickler(io.BytesIO(f.read()), encoding="latin1").load()
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError,
            ImportError, IndexError) as e:
        raise UserError(f"{path}: not a readable FLAME model pickle ({e})") from None
    if not isinstance(data, dict):
        raise UserError(f"{path}: expected a dict of arrays, got {type(data).__name__}")
    return data


@dataclass
class FlameModel:
    v_template: np.ndarray  # (V, 3)
    shapedirs: np.ndarray  # (V, 3, S) shape components
    exprdirs: np.ndarray  # (V, 3, E) expression components
    posedirs: np.ndarray  # (V, 3, 36)
    J_regressor: np.ndarray  # (5, V)
    weights: np.ndarray  # (V, 5)
    parents: np.ndarray  # (5,) int, -1 for the root
    faces: np.ndarray  # (F, 3) int32
    lmk_faces: np.ndarray  # (L,) face index per embedded landmark
    lmk_bary: np.ndarray  # (L, 3)
    lmk_mediapipe: np.ndarray  # (L,) MediaPipe landmark index
    path: Path
    embedding_path: Path

    @property
    def num_vertices(self) -> int:
        return len(self.v_template)


def _find_one(d: Path, patterns: list[str], what: str) -> Path:
    for pat in patterns:
        hits = sorted(d.glob(pat))
        if len(hits) == 1:
            return hits[0]
        if len(hits) > 1:
            names = ", ".join(h.name for h in hits)
            raise UserError(f"{d}: several {what} files ({names}); keep one")
    raise UserError(f"{d}: no {what} file ({' or '.join(patterns)})")


def load_flame_dir(flame_dir: str | os.PathLike | None) -> FlameModel:
    """Load and validate FLAME's files from the user's folder (see the module docstring)."""
    if flame_dir is None:
        raise UserError("--face-model flame needs --flame-dir DIR (FLAME's model files)")
    d = Path(flame_dir).expanduser()
    if not d.is_dir():
        raise UserError(f"{d}: FLAME directory does not exist")
    model_path = (d / "generic_model.pkl" if (d / "generic_model.pkl").is_file()
                  else _find_one(d, ["flame2023*.pkl", "*.pkl"], "FLAME model (.pkl)"))
    emb_path = _find_one(d, ["mediapipe_landmark_embedding.npz", "*embedding*.npz"],
                         "MediaPipe landmark embedding (.npz)")
    raw = load_pickle(model_path)
    need = ["v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table",
            "f"]
    missing = [k for k in need if k not in raw]
    if missing:
        raise UserError(f"{model_path}: missing {', '.join(missing)} (not a FLAME model?)")
    v = _plain(raw["v_template"]).astype(np.float64)
    sd = _plain(raw["shapedirs"]).astype(np.float64)
    pd = _plain(raw["posedirs"]).astype(np.float64)
    J = _plain(raw["J_regressor"]).astype(np.float64)
    W = _plain(raw["weights"]).astype(np.float64)
    kt = _plain(raw["kintree_table"]).astype(np.int64)
    f = _plain(raw["f"]).astype(np.int64)
    V = v.shape[0] if v.ndim == 2 else -1
    bad = []
    if v.ndim != 2 or v.shape[1] != 3:
        bad.append(f"v_template {v.shape}")
    if sd.ndim != 3 or sd.shape[:2] != (V, 3) or sd.shape[2] < 2:
        bad.append(f"shapedirs {sd.shape}")
    if pd.ndim != 3 or pd.shape[:2] != (V, 3) or pd.shape[2] != 36:
        bad.append(f"posedirs {pd.shape}")
    if J.shape != (5, V):
        bad.append(f"J_regressor {J.shape}")
    if W.shape != (V, 5):
        bad.append(f"weights {W.shape}")
    if kt.shape != (2, 5):
        bad.append(f"kintree_table {kt.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or (f.size and (f.min() < 0 or f.max() >= V)):
        bad.append(f"f {f.shape}")
    if bad:
        raise UserError(f"{model_path}: unexpected array shapes ({'; '.join(bad)})")
    K = sd.shape[2]
    ns = NUM_FLAME_SHAPE if K > NUM_FLAME_SHAPE else K // 2
    parents = kt[0].copy()
    parents[parents > 4] = -1  # the root's parent is stored as 2**32 - 1
    try:
        with np.load(emb_path, allow_pickle=False) as z:
            lf = np.asarray(z["lmk_face_idx"]).astype(np.int64).ravel()
            lb = np.asarray(z["lmk_b_coords"]).astype(np.float64).reshape(-1, 3)
            li = np.asarray(z["landmark_indices"]).astype(np.int64).ravel()
    except KeyError as e:
        raise UserError(f"{emb_path}: missing array {e} (need lmk_face_idx, lmk_b_coords, "
                        "landmark_indices)") from None
    except (OSError, ValueError) as e:
        raise UserError(f"{emb_path}: not a readable .npz ({e})") from None
    if not (len(lf) == len(lb) == len(li)) or len(lf) < 6:
        raise UserError(f"{emb_path}: lmk_face_idx, lmk_b_coords and landmark_indices must "
                        "have the same length (at least 6)")
    if lf.min() < 0 or lf.max() >= len(f) or li.min() < 0 or li.max() >= 478:
        raise UserError(f"{emb_path}: indices out of range for this FLAME model / MediaPipe")
    return FlameModel(v, sd[:, :, :ns], sd[:, :, ns:], pd, J, W, parents, f.astype(np.int32),
                      lf, lb, li, model_path, emb_path)


# ----------------------------------------------------------------------------- the model


class FlameLayer(torch.nn.Module):
    """FLAME's forward model restricted to a subset of vertices (all by default).

    vertices(shape (S,), expr (N, E), pose (N, 5, 3) axis-angle per joint: global, neck,
    jaw, left eye, right eye) -> (N, V_subset, 3), in FLAME's own frame (metres).
    """

    def __init__(self, m: FlameModel, num_shape: int, num_expr: int,
                 subset: np.ndarray | None = None, dtype=torch.float64):
        super().__init__()
        idx = np.arange(m.num_vertices) if subset is None else np.asarray(subset)
        t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=dtype)  # noqa: E731
        S, E = min(num_shape, m.shapedirs.shape[2]), min(num_expr, m.exprdirs.shape[2])
        self.num_shape, self.num_expr = S, E
        dirs = np.concatenate([m.shapedirs[:, :, :S], m.exprdirs[:, :, :E]], 2)
        # joints depend linearly on the shaped template: regress once for all components
        self.J_template = t(m.J_regressor @ m.v_template)  # (5, 3)
        self.J_dirs = t(np.einsum("jv,vck->jck", m.J_regressor, dirs))  # (5, 3, S+E)
        self.v_template = t(m.v_template[idx])
        self.dirs = t(dirs[idx])
        self.posedirs = t(m.posedirs[idx])
        self.weights = t(m.weights[idx])
        self.parents = [int(p) for p in m.parents]

    def forward(self, shape: torch.Tensor, expr: torch.Tensor, pose: torch.Tensor
                ) -> torch.Tensor:
        N = expr.shape[0]
        coeff = torch.cat([shape[None].expand(N, -1), expr], -1)  # (N, S+E)
        v = self.v_template + torch.einsum("vck,nk->nvc", self.dirs, coeff)
        J = self.J_template + torch.einsum("jck,nk->njc", self.J_dirs, coeff)  # (N, 5, 3)
        R = so3_exp(pose)  # (N, 5, 3, 3)
        eye = torch.eye(3, dtype=v.dtype)
        pose_feat = (R[:, 1:] - eye).reshape(N, 36)
        v = v + torch.einsum("vck,nk->nvc", self.posedirs, pose_feat)
        # kinematic chain: world transform of every joint
        G = []
        for k, p in enumerate(self.parents):
            t_local = J[:, k] - (J[:, p] if p >= 0 else 0)
            Tk = torch.cat([torch.cat([R[:, k], t_local[..., None]], -1),
                            torch.tensor([0, 0, 0, 1], dtype=v.dtype).expand(N, 1, 4)], 1)
            G.append(Tk if p < 0 else G[p] @ Tk)
        G = torch.stack(G, 1)  # (N, 5, 4, 4)
        # remove the rest pose: skinning transforms act on rest-pose vertices
        rest = torch.einsum("nkab,nkb->nka", G[..., :3, :3], J)
        G = torch.cat([G[..., :3, :3], (G[..., :3, 3] - rest)[..., None]], -1)  # (N,5,3,4)
        T = torch.einsum("vk,nkab->nvab", self.weights, G)  # (N, V, 3, 4)
        return torch.einsum("nvab,nvb->nva", T[..., :3], v) + T[..., 3]


def embedded_vertices(m: FlameModel) -> np.ndarray:
    """Indices of the vertices the landmark embedding touches."""
    return np.unique(m.faces[m.lmk_faces].ravel())


# ----------------------------------------------------------------------------- fitting


JAW_NAMES = ("flame_jaw_rx", "flame_jaw_ry", "flame_jaw_rz")
"""The jaw pose's controls, after the expression coefficients in a FLAME β."""


@dataclass
class FlameFit:
    expressions: np.ndarray  # (N, E + 3) float32: FLAME expression coefficients, then the
    # jaw pose (axis-angle, radians): in FLAME the mouth opens mostly through the jaw, so an
    # expression vector without it could not open the mouth
    names: list[str]
    vertices: np.ndarray  # (N, V, 3) float32, world (head) frame
    shape: np.ndarray  # (S,)
    jaw: np.ndarray  # (N, 3)
    neck: np.ndarray  # (N, 3)
    to_world: np.ndarray  # (4, 4) similarity FLAME -> world
    median_error_px: float
    errors_px: np.ndarray  # (N,) per frame, source pixels
    model_info: dict


def fit_flame(m: FlameModel, clip, sol, num_expr: int = 50, num_shape: int = 100,
              iters: int = 200, reg_shape: float = 1e-3, reg_expr: float = 1e-4,
              reg_pose: float = 1e-2, smooth: float = 1e-3) -> FlameFit:
    """Fit FLAME to the landmarks of every frame, cameras fixed to the solve's.

    Unknowns: shape β (shared), per-frame expression ψ_i, jaw and neck pose, and one
    similarity transform FLAME -> world (initialised by Umeyama on the template).
    Loss: Cauchy reprojection error of the embedded landmarks (face-size units) + L2 priors
    + temporal smoothness of ψ and jaw. L-BFGS over all frames, float64.
    """
    with torch_threads(1):  # small tensors: as in the camera solve
        return _fit(m, clip, sol, num_expr, num_shape, iters, reg_shape, reg_expr, reg_pose,
                    smooth)


def _fit(m, clip, sol, num_expr, num_shape, iters, reg_shape, reg_expr, reg_pose, smooth):
    dt = torch.float64
    sub = embedded_vertices(m)
    local = {int(v): k for k, v in enumerate(sub)}
    tri = torch.as_tensor(np.vectorize(local.get)(m.faces[m.lmk_faces]), dtype=torch.long)
    bary = torch.as_tensor(m.lmk_bary, dtype=dt)
    layer = FlameLayer(m, num_shape, num_expr, sub)
    N, E, S = len(sol.w2c), layer.num_expr, layer.num_shape
    obs = torch.as_tensor(clip.landmarks[:, m.lmk_mediapipe, :2], dtype=dt)  # (N, L, 2)
    w2c = torch.as_tensor(sol.w2c, dtype=dt)
    f = torch.tensor(sol.focal, dtype=dt)

    def landmarks(verts: torch.Tensor) -> torch.Tensor:  # (N, Vs, 3) -> (N, L, 3)
        return (verts[:, tri] * bary[None, :, :, None]).sum(2)

    # initial similarity: FLAME's neutral landmarks onto the solve's template
    zeros = torch.zeros
    with torch.no_grad():
        lm0 = landmarks(layer(zeros(S, dtype=dt), zeros(1, E, dtype=dt),
                              zeros(1, 5, 3, dtype=dt)))[0].numpy()
    s0, R0, t0 = umeyama(lm0, sol.template[m.lmk_mediapipe])

    # unknowns are scaled so that one unit moves the landmarks by similar amounts (L-BFGS
    # converges slowly otherwise): translation in cm, angles and log-scale in 0.1 units
    r0 = torch.tensor(matrix_to_rotvec(R0), dtype=dt)
    g_rot = zeros(3, dtype=dt, requires_grad=True)
    g_t = torch.tensor(t0 / 0.01, dtype=dt, requires_grad=True)
    g_logs = zeros((), dtype=dt, requires_grad=True)
    shape = zeros(S, dtype=dt, requires_grad=True)
    expr = zeros(N, E, dtype=dt, requires_grad=True)
    jaw_s = zeros(N, 3, dtype=dt, requires_grad=True)
    neck_s = zeros(N, 3, dtype=dt, requires_grad=True)
    c = 0.01
    fs = sol.face_size
    # consecutive frames of one shot: an expression may change at once across a cut
    shots = clip.shots
    pairs = (torch.ones(max(N - 1, 0), dtype=torch.bool) if shots is None
             else torch.as_tensor(shots[1:] == shots[:-1]))

    def world(verts: torch.Tensor) -> torch.Tensor:
        R = so3_exp(0.1 * g_rot) @ so3_exp(r0)
        return s0 * torch.exp(0.1 * g_logs) * verts @ R.T + 0.01 * g_t

    def posed(layer_, shape_, expr_, jaw_s_, neck_s_):
        z = torch.zeros_like(jaw_s_)
        return layer_(shape_, expr_, torch.stack([z, 0.1 * neck_s_, 0.1 * jaw_s_, z, z], 1))

    def loss_fn() -> torch.Tensor:
        P = world(landmarks(posed(layer, shape, expr, jaw_s, neck_s)))
        Pc = torch.einsum("nab,nlb->nla", w2c[:, :3, :3], P) + w2c[:, None, :3, 3]
        r2 = ((project(Pc, f, f, sol.cx, sol.cy, MIN_DEPTH) - obs) ** 2).sum(-1) / fs**2
        loss = cauchy(r2, c).mean() / c**2
        loss = loss + reg_shape * shape.pow(2).sum() + reg_expr * expr.pow(2).sum(-1).mean()
        loss = loss + reg_pose * (jaw_s.pow(2).sum(-1).mean() + neck_s.pow(2).sum(-1).mean())
        if N >= 2 and smooth > 0 and bool(pairs.any()):
            loss = loss + smooth * ((expr[1:] - expr[:-1])[pairs].pow(2).sum(-1).mean()
                                    + (jaw_s[1:] - jaw_s[:-1])[pairs].pow(2).sum(-1).mean())
        return loss

    _lbfgs([g_rot, g_t, g_logs], loss_fn, 30)  # place the neutral head first
    _lbfgs([g_rot, g_t, g_logs, shape, expr, jaw_s, neck_s], loss_fn, iters)

    with torch.no_grad():
        P = world(landmarks(posed(layer, shape, expr, jaw_s, neck_s)))
        Pc = torch.einsum("nab,nlb->nla", w2c[:, :3, :3], P) + w2c[:, None, :3, 3]
        err = (project(Pc, f, f, sol.cx, sol.cy, MIN_DEPTH) - obs).norm(dim=-1).median(-1).values.numpy()
        full = FlameLayer(m, num_shape, num_expr)
        verts = np.concatenate([world(posed(full, shape, expr[k:k + 32], jaw_s[k:k + 32],
                                            neck_s[k:k + 32])).numpy().astype(np.float32)
                                for k in range(0, N, 32)])
        T = np.eye(4)
        T[:3, :3] = (s0 * float(torch.exp(0.1 * g_logs))
                     * (so3_exp(0.1 * g_rot) @ so3_exp(r0)).numpy())
        T[:3, 3] = 0.01 * g_t.numpy()
    jaw = 0.1 * jaw_s.detach().numpy()
    return FlameFit(
        expressions=np.concatenate([expr.detach().numpy(), jaw], 1).astype(np.float32),
        names=[f"flame_expr_{k:03d}" for k in range(E)] + list(JAW_NAMES),
        vertices=verts, shape=shape.detach().numpy(),
        jaw=jaw, neck=0.1 * neck_s.detach().numpy(), to_world=T,
        median_error_px=float(np.median(err)), errors_px=err,
        model_info={"model": m.path.name, "embedding": m.embedding_path.name,
                    "num_shape": S, "num_expr": E, "vertices": m.num_vertices,
                    "landmarks": int(len(m.lmk_faces))},
    )
