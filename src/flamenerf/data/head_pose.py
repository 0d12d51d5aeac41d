"""The head's rigid pose: from the dataset's per-frame `head_pose` (world-from-head) to
what the model needs, and head poses given as controls.

Canonical frame: the world as it is at the reference frame (frame 0): a point x seen in
frame f is at T_f x in the canonical frame, with T_f = P_ref P_f⁻¹ (P: world-from-head).
A head that never moves gives T_f = identity, and so does a dataset without head poses.
Each T_f travels as its twist ξ_f = log(T_f) (6 numbers: rotation vector, then v; see
`geometry.se3_log`), so that the model can move points part of the way (exp(w ξ)) where
the head blends into the static background (docs/head_pose.md).

The head's region is an ellipsoid around the reference frame's face mesh in the head's own
axes (x: the subject's left, y: up, z: out of the face), grown from the face to the whole
head: the face mesh covers brows to chin and cheek to cheek, the head extends behind it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flamenerf.data.dataset import Dataset, Frame, reference_position
from flamenerf.errors import UserError
from flamenerf.geometry import euler_head, se3_log
from flamenerf.io import read_json
from flamenerf.keyvalues import parse_assignments


@dataclass
class HeadRegion:
    """An ellipsoid in canonical (= world at the reference frame) coordinates."""

    centre: np.ndarray  # (3,)
    axes: np.ndarray  # (3, 3) columns: the head's x, y, z axes in the world
    radii: np.ndarray  # (3,) semi-axes along those columns, metres

    def to_dict(self) -> dict:
        return {"centre": self.centre.tolist(), "axes": self.axes.tolist(),
                "radii": self.radii.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "HeadRegion":
        return cls(*(np.asarray(d[k], np.float64) for k in ("centre", "axes", "radii")))

    def inside(self, points: np.ndarray) -> np.ndarray:
        """Points (*bs, 3) -> ellipsoidal radius (*bs,): < 1 inside."""
        q = (np.asarray(points, np.float64) - self.centre) @ self.axes / self.radii
        return np.linalg.norm(q, axis=-1)


def reference_pose(ds: Dataset) -> np.ndarray:
    """P_ref (4, 4): frame 0's world-from-head pose (identity without head poses)."""
    p = ds.frames[reference_position(ds)].head_pose
    return np.eye(4) if p is None else p


def canonical_from_world(ds: Dataset, frames: list[Frame]) -> np.ndarray | None:
    """T_f = P_ref P_f⁻¹ (N, 4, 4) of each frame, or None when the dataset has no head
    poses."""
    if not ds.has_head_poses:
        return None
    ref = reference_pose(ds)
    return np.stack([ref @ np.linalg.inv(f.head_pose) for f in frames])


def head_twists(ds: Dataset, frames: list[Frame]) -> np.ndarray | None:
    """log(T_f) (N, 6) float32 of each frame, or None without head poses."""
    T = canonical_from_world(ds, frames)
    return None if T is None else se3_log(T).astype(np.float32)


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Rigid T (4, 4) or (N, 4, 4) applied to points (..., 3) or (N, ..., 3)."""
    T = np.asarray(T, np.float64)
    p = np.asarray(points, np.float64)
    if T.ndim == 2:
        return p @ T[:3, :3].T + T[:3, 3]
    return np.einsum("nij,n...j->n...i", T[:, :3, :3], p) + T[:, None, :3, 3].reshape(
        len(T), *([1] * (p.ndim - 2)), 3)


def canonical_vertices(ds: Dataset, frames: list[Frame]) -> np.ndarray:
    """The frames' face meshes (N, V, 3) in the canonical frame (the world's own without
    head poses): what the expression model is fitted on, since β does not turn the head."""
    v = ds.face_vertices[[f.position for f in frames]]
    T = canonical_from_world(ds, frames)
    return v if T is None else transform_points(T, v).astype(np.float32)


def posed_vertices(canonical: np.ndarray, T: np.ndarray | None) -> np.ndarray:
    """Face meshes in the canonical frame posed into the world by the inverse of their head
    transform (`canonical_vertices` undone): (n, V, 3) with T (n, 4, 4), or (V, 3) with
    T (4, 4); unchanged when T is None."""
    if T is None:
        return canonical
    return transform_points(np.linalg.inv(T), canonical).astype(np.float32)


def head_region(ds: Dataset, scale: float = 1.0) -> HeadRegion:
    """The head's ellipsoid around the reference frame's face mesh (see the module doc);
    `scale` grows it about its centre."""
    pos = reference_position(ds)
    axes = reference_pose(ds)[:3, :3].copy()
    v = ds.face_vertices[pos].astype(np.float64)
    local = v @ axes  # coordinates along the head's axes
    lo, hi = local.min(0), local.max(0)
    width, height, depth = hi - lo
    if depth > width:  # a whole-head mesh (e.g. all of FLAME): its own bounding box
        c_local, radii = (lo + hi) / 2, 0.55 * (hi - lo)
    else:  # a face mesh (brows to chin, cheek to cheek), as the built-in scene's: a head
        # is about 1.3 face-widths wide and 1.4 face-heights tall and deep, centred a
        # little above mid-face and a radius behind the tip of the nose
        radii = np.array([0.64 * width, 0.69 * height, 0.69 * height])
        c_local = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2 + 0.1 * height,
                            hi[2] - 1.05 * radii[2]])
    radii = radii * scale
    return HeadRegion(axes @ c_local, axes, radii)


# ----------------------------------------------------------------------------- controls


@dataclass
class HeadPoseKey:
    """A head pose relative to frame 0's, in the head's own axes: degrees and metres."""

    yaw: float = 0.0
    pitch: float = 0.0
    roll: float = 0.0
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0


def control_transform(key: HeadPoseKey, region: HeadRegion) -> np.ndarray:
    """T (4, 4) canonical-from-world of the head turned by `key` about its region's centre
    (the head at frame 0's pose: identity)."""
    A, c = region.axes, region.centre
    M = np.eye(4)  # the motion of the head in the world
    M[:3, :3] = A @ euler_head(key.yaw, key.pitch, key.roll) @ A.T
    M[:3, 3] = c - M[:3, :3] @ c + A @ np.array([key.x, key.y, key.z])
    return np.linalg.inv(M)


def parse_head_key(item: str, where: str = "--head-pose") -> HeadPoseKey:
    """`yaw=20,pitch=-5` (degrees; x, y, z in metres) -> a HeadPoseKey."""
    key = HeadPoseKey(**parse_assignments(item, list(HeadPoseKey.__dataclass_fields__),
                                          where))
    # a head turned more than a full turn or moved a metre has left the scene it was filmed in
    for name, v in vars(key).items():
        top, unit = (360, "degrees") if name in ("yaw", "pitch", "roll") else (1, "m")
        if not abs(v) <= top:
            raise UserError(f"{where}: {name}={v:g} is beyond +-{top} {unit}")
    return key


def key_array(key: HeadPoseKey) -> np.ndarray:
    return np.array([getattr(key, n) for n in HeadPoseKey.__dataclass_fields__])


def head_pose_items(items: list[str]) -> tuple[np.ndarray, bool]:
    """`--head-pose` values -> rows (K, 6) of (yaw, pitch, roll, x, y, z), and whether they
    are keyframes (to ease through, as expression keyframes are) rather than one FILE's
    per-frame poses (.json: a list of {yaw, pitch, ...} objects, or {"head_pose": [...]})."""
    from pathlib import Path

    if not items:
        raise UserError("--head-pose: give yaw=..,pitch=.. keyframes or a .json file")
    if len(items) == 1 and (items[0].lower().endswith(".json") or Path(items[0]).is_file()):
        path = Path(items[0])
        d = read_json(path, "head-pose file")
        rows = d.get("head_pose") if isinstance(d, dict) else d
        if not isinstance(rows, list) or not rows or not all(isinstance(r, dict) for r in rows):
            raise UserError(f"{path}: expected a non-empty list of {{yaw, pitch, roll, x, y, "
                            "z}} objects")
        return np.stack([key_array(parse_head_key(",".join(f"{k}={v}" for k, v in r.items()),
                                                  str(path))) for r in rows]), False
    return np.stack([key_array(parse_head_key(it)) for it in items]), True
