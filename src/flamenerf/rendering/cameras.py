"""Camera paths for re-animation videos, built around the capture's cameras.

Conventions (the dataset's): camera-to-world 4x4 matrices with OpenGL camera axes (x right,
y up, the camera looks down -z).

Every path starts from the reference camera (the camera of frame 0, whose codes ω_0, φ_0
re-animation uses) and keeps the head where that camera sees it: the centroid of frame 0's
face mesh stays at the same pixel, however the camera moves (a crop of the video can put the
face off the image's centre). Its scale comes from the capture: by default a path stays
within the azimuths the training cameras covered about the capture's mean up vector, where
the model has seen the scene (a still camera gives a still path: views beyond the capture
extrapolate, ask for them with an explicit amplitude). An orbit also keeps to the
capture's distance and height at each azimuth: a handheld capture films the scene from one
curve, and a model is only sure of it near that curve (on the shared orbit clip an arc at frame 0's distance, 5 cm
further back and 2 cm lower than the capture at its far end, showed the chin twice). Where
the dataset has head poses, a path holds the head at frame 0's pose, so the face is seen
from where each camera stood relative to the head, not in the room: the default range is
the part of the room's azimuths that the head's also cover (a head that turned with the
camera was never seen from the room's far end).

Kinds:
  static  the reference camera itself, every frame;
  orbit   around the head, swinging +-amplitude deg in azimuth (one back-and-forth over
          the video) at the capture's distance and height for each azimuth (held at the
          ends of the captured range beyond them); by default from the reference out to
          each end of the captured azimuths;
  spiral  an LLFF/Nerfies-style spiral: the camera circles in the image plane from the
          reference position towards the capture's cameras (radius = tan(amplitude/2) x
          distance) while moving 10 % in and out; by default shrunk until every camera is
          one the capture covers (`CameraRig.near_capture`: near a training camera, or
          between the passes of one that sweeps an area);
  dolly   along the line to the head, in to (1 - amplitude) times the reference distance
          and back (default amplitude 0.2); never further than the reference camera, whose
          view the far plane was set for;
  FILE    a JSON file of poses: a list of 4x4 matrices, {"poses": [...]}, {"c2w": [...]} or a
          transforms.json-style {"frames": [{"transform_matrix": ...}, ...]}.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flamenerf.data.dataset import Dataset, reference_position
from flamenerf.data.dataset_checks import CAMERA_TOL, MAX_METRES, too_far
from flamenerf.data.head_pose import canonical_from_world, transform_points
from flamenerf.errors import UserError
from flamenerf.geometry import is_rigid, rotation_between
from flamenerf.io import read_json

PATH_KINDS = ("static", "orbit", "spiral", "dolly")


@dataclass
class CameraRig:
    """Where the capture looked from: what every path is built around."""

    center: np.ndarray  # (3,) the head: centroid of frame 0's face mesh
    up: np.ndarray  # (3,) unit, mean camera up vector of the training cameras
    reference: np.ndarray  # (4, 4) frame 0's camera
    swing_deg: float  # half-range of the training cameras' azimuths about `up`
    min_distance: float = 0.0  # closer to `center` than this, the face crosses the near plane
    azimuth_range: tuple[float, float] | None = None
    """(lowest, highest) training-camera azimuth in degrees, relative to the reference
    camera (so lowest <= 0 <= highest), in the room and, with head poses, relative to the
    head too; None: +-swing_deg."""
    captured: np.ndarray | None = None
    """(N, 3) the training cameras about the head: azimuth (degrees, as azimuth_range),
    distance from the `up` axis through `center`, and height along it; None: an arc at the
    reference camera's distance and height."""

    def clamp(self, eye: np.ndarray) -> np.ndarray:
        """Push an eye position out to `min_distance` from the head if it is closer."""
        v = eye - self.center
        d = np.linalg.norm(v)
        return eye if d >= self.min_distance else self.center + v * (self.min_distance / d)

    @property
    def eye(self) -> np.ndarray:
        return self.reference[:3, 3].copy()

    def basis(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit vectors (3,), (3,) perpendicular to `up`: towards the reference camera, and
        the direction of increasing azimuth."""
        e0 = self.eye - self.center
        e0 = e0 - self.up * (e0 @ self.up)
        e0 = e0 / max(np.linalg.norm(e0), 1e-12)
        return e0, np.cross(self.up, e0)

    def aim(self, eye: np.ndarray) -> np.ndarray:
        """Camera-to-world (4, 4) at `eye` that sees `center` where the reference camera
        does: the reference orientation turned by the smallest rotation between the two
        directions to the head."""
        R = rotation_between(self.center - self.eye, self.center - eye)
        c2w = self.reference.copy()
        c2w[:3, :3] = R @ self.reference[:3, :3]
        c2w[:3, 3] = eye
        return c2w

    def captured_eyes(self) -> np.ndarray | None:
        """The training cameras' centres (N, 3) (from `captured`), or None."""
        if self.captured is None:
            return None
        e0, e1 = self.basis()
        a = np.radians(self.captured[:, :1])
        return (self.center + self.captured[:, 1:2] * (np.cos(a) * e0 + np.sin(a) * e1)
                + self.captured[:, 2:3] * self.up)

    def capture_tolerance(self) -> float:
        """How far (metres) a path's camera may stand from the nearest training camera: 3 %
        of the reference camera's distance from the head (the orbit clip's renders were
        clean up to 1.7 cm at 0.57 m and ghosted from ~3 cm: docs/head_pose.md), or the
        capture's own spacing (90th percentile of its nearest-neighbour distances) where its
        cameras are sparser."""
        d = 0.03 * float(np.linalg.norm(self.eye - self.center))
        eyes = self.captured_eyes()
        if eyes is None or len(eyes) < 2:
            return d
        nn = np.linalg.norm(eyes[:, None] - eyes[None], axis=-1)
        np.fill_diagonal(nn, np.inf)
        return max(d, float(np.percentile(nn.min(1), 90)))

    def near_capture(self, points: np.ndarray) -> np.ndarray:
        """Which eye positions (N, 3) the capture covers (N,) bool: within
        `capture_tolerance` of a training camera, or between them: inside the hull of their
        centres seen along the reference camera's axis and within their spread along it
        (a capture that sweeps up and down as well as across covers the area between its
        passes; one that moves along a line covers only the line)."""
        from scipy.spatial import Delaunay, QhullError

        eyes = self.captured_eyes()
        points = np.asarray(points, np.float64)
        if eyes is None:
            return np.ones(len(points), bool)
        tol = self.capture_tolerance()
        ok = np.linalg.norm(points[:, None] - eyes[None], axis=-1).min(1) <= tol
        axes = self.reference[:3, :3]  # right, up, back columns
        q, e = (points - self.eye) @ axes, (eyes - self.eye) @ axes
        try:
            inside = Delaunay(e[:, :2]).find_simplex(q[:, :2]) >= 0
        except (QhullError, ValueError):  # cameras along a line (or too few): no area
            return ok
        depth = (q[:, 2] >= e[:, 2].min() - tol) & (q[:, 2] <= e[:, 2].max() + tol)
        return ok | (inside & depth)

    def fit_to_capture(self, path, steps: int = 12) -> float:
        """The largest scale in [0, 1] at which every camera of `path(scale)` (a list of eye
        positions, the reference's at scale 0) is one the capture covers (`near_capture`;
        bisection); 1 without a recorded capture."""
        if self.captured is None:
            return 1.0

        def fits(scale: float) -> bool:
            return bool(self.near_capture(np.asarray(path(scale))).all())

        if fits(1.0):
            return 1.0
        lo, hi = 0.0, 1.0
        for _ in range(steps):
            mid = (lo + hi) / 2
            lo, hi = (mid, hi) if fits(mid) else (lo, mid)
        return lo

    def orbit_eye(self, azimuth_deg: float) -> np.ndarray:
        """Where an orbit's camera stands at an azimuth: the reference camera turned about
        the head, then moved in or out and up or down by as much as the capture's cameras
        at that azimuth differ, on average, from those at the reference's (a Gaussian
        kernel over their azimuths)."""
        e0, e1 = self.basis()
        v = self.eye - self.center
        h0 = float(v @ self.up)
        r0 = float(np.linalg.norm(v - h0 * self.up))
        dr = dh = 0.0
        if self.captured is not None and len(self.captured) > 1:
            az, r, h = self.captured.T
            lo, hi = float(az.min()), float(az.max())
            width = max(2.0, (hi - lo) / 10)

            def smooth(a: float) -> tuple[float, float]:
                w = np.exp(-0.5 * ((az - np.clip(a, lo, hi)) / width) ** 2) + 1e-12
                return float(w @ r / w.sum()), float(w @ h / w.sum())

            (ra, ha), (rz, hz) = smooth(azimuth_deg), smooth(0.0)
            dr, dh = ra - rz, ha - hz
        a = np.radians(azimuth_deg)
        return self.center + (r0 + dr) * (np.cos(a) * e0 + np.sin(a) * e1) + (h0 + dh) * self.up


def rig_from_dataset(ds: Dataset) -> CameraRig:
    ref = reference_position(ds)
    center = ds.face_vertices[ref].astype(np.float64).mean(0)
    train = ds.split("train")
    c2ws = np.stack([f.c2w for f in train])
    up = c2ws[:, :3, 1].mean(0)
    up = up / max(np.linalg.norm(up), 1e-12)
    eyes = c2ws[:, :3, 3]
    # azimuths about `up`, measured from the reference camera's direction
    ref_c2w = ds.frames[ref].c2w.astype(np.float64)
    rig = CameraRig(center, up, ref_c2w, 0.0)
    e0, e1 = rig.basis()

    def azimuths(points: np.ndarray) -> np.ndarray:
        v = points - center
        return np.degrees(np.arctan2(v @ e1, v @ e0))

    az = azimuths(eyes)
    lo, hi = min(0.0, float(az.min())), max(0.0, float(az.max()))
    T = canonical_from_world(ds, train)
    if T is not None:  # the cameras as the head (held at frame 0's pose) saw them
        az_head = azimuths(transform_points(T, eyes[:, None])[:, 0])
        lo, hi = max(lo, min(0.0, float(az_head.min()))), min(hi, max(0.0, float(az_head.max())))
    height = (eyes - center) @ up
    dist = np.linalg.norm(eyes - center - height[:, None] * up, axis=1)
    swing = (hi - lo) / 2
    # how far the face reaches out towards the reference camera, plus 10 % of near
    verts = ds.face_vertices[ref].astype(np.float64) - center
    to_cam = (ref_c2w[:3, 3] - center) / max(np.linalg.norm(ref_c2w[:3, 3] - center), 1e-12)
    reach = max(0.0, float((verts @ to_cam).max()))
    return CameraRig(center, up, ref_c2w, swing, 1.1 * ds.near + reach, (lo, hi),
                     np.stack([az, dist, height], 1))


def camera_path(kind: str, num: int, rig: CameraRig, amplitude: float | None = None
                ) -> np.ndarray:
    """`num` camera-to-world matrices (num, 4, 4) of a named path (see the module doc);
    `amplitude`: degrees for orbit/spiral, a fraction of the distance for dolly."""
    if num < 1:
        raise UserError(f"a camera path needs at least 1 frame, got {num}")
    s = np.arange(num) / num  # one period over the video, so it loops seamlessly
    if kind == "static":
        return np.repeat(rig.reference[None], num, axis=0)
    target = rig.center
    eye0 = rig.eye
    if kind == "orbit":
        wave = np.sin(2 * np.pi * s)
        if amplitude is not None or rig.azimuth_range is None:
            ang = np.radians(rig.swing_deg if amplitude is None else amplitude) * wave
        else:  # out to each end of the captured range, however far off-centre frame 0 is
            lo, hi = np.radians(rig.azimuth_range)
            ang = np.where(wave >= 0, hi * wave, -lo * wave)
        return np.stack([rig.aim(rig.clamp(rig.orbit_eye(np.degrees(a)))) for a in ang])
    if kind == "spiral":
        amp = np.radians(rig.swing_deg if amplitude is None else amplitude)
        base = rig.reference
        right, up, back = base[:3, 0], base[:3, 1], base[:3, 2]
        dist = np.linalg.norm(eye0 - target)
        towards = -right  # the circle's centre from the reference: towards the capture's cameras
        eyes = rig.captured_eyes()
        if eyes is not None:
            m = eyes.mean(0) - eye0
            m = (m @ right) * right + (m @ up) * up
            if np.linalg.norm(m) > 1e-3 * dist:
                towards = m / np.linalg.norm(m)
        side = np.cross(back, towards)  # in the image plane, perpendicular to `towards`

        def spiral(scale: float) -> list[np.ndarray]:
            r = scale * np.tan(amp / 2) * dist
            return [rig.clamp(eye0 + r * (1 - np.cos(2 * np.pi * t)) * towards
                              + r * np.sin(2 * np.pi * t) * side
                              + scale * 0.1 * dist * np.sin(4 * np.pi * t) * back) for t in s]

        scale = 1.0 if amplitude is not None else rig.fit_to_capture(spiral)
        return np.stack([rig.aim(e) for e in spiral(scale)])
    if kind == "dolly":
        amp = 0.2 if amplitude is None else float(amplitude)
        if not 0 <= amp < 1:
            raise UserError(f"--amplitude {amp}: a dolly's amplitude is a fraction in [0, 1)")
        d = eye0 - target
        return np.stack([rig.aim(rig.clamp(target + d * (1 - amp * (1 - np.cos(2 * np.pi * t))
                                                          / 2))) for t in s])
    raise UserError(f"unknown camera path {kind!r} (choose from {', '.join(PATH_KINDS)}, or "
                    "give a JSON file of poses)")


def load_poses(path: str | Path) -> np.ndarray:
    """Camera-to-world matrices (N, 4, 4) from a JSON file (see the module doc)."""
    path = Path(path)
    d = read_json(path, "camera path file")
    if isinstance(d, dict):
        if "frames" in d and isinstance(d["frames"], list):
            try:
                d = [f["transform_matrix"] for f in d["frames"]]
            except (TypeError, KeyError):
                raise UserError(f"{path}: every entry of 'frames' needs a 'transform_matrix'") \
                    from None
        elif "poses" in d:
            d = d["poses"]
        elif "c2w" in d:
            d = d["c2w"]
        else:
            raise UserError(f"{path}: expected a list of 4x4 matrices, or an object with "
                            "'poses', 'c2w' or 'frames'")
    try:
        poses = np.asarray(d, np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{path}: poses must be 4x4 (or 3x4) number matrices") from None
    if poses.ndim == 2:
        poses = poses[None]
    if poses.ndim != 3 or poses.shape[1:] not in ((4, 4), (3, 4)) or len(poses) == 0:
        raise UserError(f"{path}: poses must be a non-empty list of 4x4 (or 3x4) matrices, "
                        f"got shape {poses.shape}")
    if not np.all(np.isfinite(poses)):
        raise UserError(f"{path}: poses contain non-finite values")
    if poses.shape[1] == 3:
        poses = np.concatenate([poses, np.tile([[[0, 0, 0, 1.0]]], (len(poses), 1, 1))], 1)
    bad = np.flatnonzero(~is_rigid(poses, CAMERA_TOL))
    if len(bad):
        raise UserError(f"{path}: pose {bad[0]} is not rigid (a rotation, a translation and a "
                        "last row 0 0 0 1)")
    far = np.flatnonzero(too_far(poses))
    if len(far):
        raise UserError(f"{path}: pose {far[0]} is more than {MAX_METRES:g} m from the origin "
                        "(positions are metres)")
    return poses


def resample(poses: np.ndarray, num: int) -> np.ndarray:
    """Nearest-neighbour resampling of a pose sequence to `num` frames."""
    if len(poses) == num:
        return poses
    idx = np.minimum((np.arange(num) * len(poses)) // max(num, 1), len(poses) - 1)
    return poses[idx]
