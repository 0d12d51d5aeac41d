"""The scene's world: cameras from the background, the head's rigid pose from the face.

Inputs: the face solve's camera-from-head per frame (metres; `SolveResult.w2c`, whose world
is the head) and the background registration (`flamenerf.tracking.background`). Output: per
frame a camera-to-world and a world-from-head matrix in one metric world, and which case the
clip is:

  moving camera, still head   the paper's capture: the head pose is constant;
  still camera, moving head   a tripod or a selfie held still: the camera is constant;
  both moving                 a handheld clip of a moving head;
  both still                  nothing moves: only one view of anything (a warning);
  head as world (fallback)    no usable background: today's cameras, the head fixed in
                              the world, every head turn taken as a camera motion.

A handheld clip with little parallax registers as rotations about one centre
(`flamenerf.tracking.rotation_cameras`): its cameras need no scale, the head's pose is
the rotation times the face's camera-from-head.

Metric scale: COLMAP's world has none. The head's position in it is
    h_i = s c_i + R_i p_i           (camera centre c_i, rotation R_i, head in camera p_i, m)
and s (metres per COLMAP unit) is the one that makes the head move least: least squares over
s of Σ |h_i − mean h|², exact for a still head, and for a moving one the assumption that
the head moves less than the camera. The world is finally put at the head's mean pose, so a
still head has the identity pose and the world is the head frame of today's datasets.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flamenerf.geometry import rotation_angle_deg

CASES = ("moving camera, still head", "still camera, moving head", "both moving",
         "both still", "head as world (fallback)")


@dataclass
class MotionThresholds:
    """When a camera or a head counts as moving, and when a camera move is too small."""

    camera_deg: float = 2.0
    """The camera moves when it turns more than this, or its centre moves by more than
    this angle seen from the head."""
    head_deg: float = 3.0
    """The head moves when it turns more than this..."""
    head_m: float = 0.015
    """... or moves more than this (metres) from its mean position."""
    shake_deg: float = 0.5
    """A camera registered as rotations about one centre moves when it turns more than
    this: a hand's shake, measured to about a tenth of a degree."""
    small_baseline_deg: float = 5.0
    """Warn when the camera centres span less than this angle seen from the head: views
    away from the captured ones extrapolate."""


@dataclass
class World:
    case: str
    c2w: np.ndarray  # (N, 4, 4) camera-to-world, OpenGL axes, metres
    head_pose: np.ndarray | None  # (N, 4, 4) world-from-head; None in the fallback
    scale: float | None  # metres per COLMAP unit (registered background only)
    camera_motion: dict
    head_motion: dict
    warnings: list[str] = field(default_factory=list)


def mean_pose(T: np.ndarray) -> np.ndarray:
    """Rigid mean of poses (N, 4, 4): chordal mean rotation, mean translation."""
    from scipy.spatial.transform import Rotation

    out = np.eye(4)
    out[:3, :3] = Rotation.from_matrix(T[:, :3, :3]).mean().as_matrix()
    out[:3, 3] = T[:, :3, 3].mean(0)
    return out


def pose_spread(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each pose's rotation angle (deg) and distance (same units) from the mean pose:
    T (N, 4, 4) -> (N,), (N,)."""
    M = mean_pose(T)
    return (rotation_angle_deg(T[:, :3, :3], M[:3, :3]),
            np.linalg.norm(T[:, :3, 3] - M[:3, 3], axis=1))


def motion_stats(c2w: np.ndarray, head_pose: np.ndarray | None, head_centre: np.ndarray
                 ) -> tuple[dict, dict]:
    """How much the cameras and the head move. head_centre (3,): the face's centre in head
    coordinates (where head translation is measured and what camera baselines are seen
    from)."""
    n = len(c2w)
    hp = head_pose if head_pose is not None else np.tile(np.eye(4), (n, 1, 1))
    H = hp[:, :3, :3] @ head_centre + hp[:, :3, 3]  # the face's centre in the world
    cam_rot, _ = pose_spread(c2w)
    C = c2w[:, :3, 3]
    dist = np.linalg.norm(C - H, axis=1)
    # the camera centres' spread seen from the (mean) head: max angle between any camera
    # and the mean camera direction
    v = C - H.mean(0)
    u = v / np.linalg.norm(v, axis=1, keepdims=True)
    m = u.mean(0) / np.linalg.norm(u.mean(0))
    span = np.degrees(np.arccos(np.clip(u @ m, -1, 1)))
    head_rot, _ = pose_spread(hp)
    head_t = np.linalg.norm(H - H.mean(0), axis=1)
    cam = {"rotation_max_deg": float(cam_rot.max()),
           "centre_spread_m": float(np.linalg.norm(C - C.mean(0), axis=1).max()),
           "baseline_deg": float(2 * span.max()),
           "distance_to_head_m": [float(dist.min()), float(dist.max())]}
    head = {"rotation_max_deg": float(head_rot.max()), "translation_max_m": float(head_t.max())}
    return cam, head


def classify(cam: dict, head: dict, th: MotionThresholds, shake: bool = False) -> str:
    """The case; shake: the camera was registered as rotations (its own threshold)."""
    turn = th.shake_deg if shake else th.camera_deg
    cam_moves = cam["rotation_max_deg"] > turn or cam["baseline_deg"] > th.camera_deg
    head_moves = head["rotation_max_deg"] > th.head_deg or head["translation_max_m"] > th.head_m
    return CASES[{(True, False): 0, (False, True): 1, (True, True): 2,
                  (False, False): 3}[(cam_moves, head_moves)]]


def metric_scale(c2w: np.ndarray, cam_from_head: np.ndarray) -> float:
    """s minimising Σ |s c_i + R_i p_i − mean|² (see the module doc): c2w (N, 4, 4) in
    COLMAP units, cam_from_head (N, 4, 4) metres. NaN when the cameras do not move."""
    c = c2w[:, :3, 3]
    q = np.einsum("nab,nb->na", c2w[:, :3, :3], cam_from_head[:, :3, 3])
    dc, dq = c - c.mean(0), q - q.mean(0)
    den = float((dc * dc).sum())
    return -float((dc * dq).sum()) / den if den > 0 else float("nan")


def _scale_floor(reg, cam_from_head: np.ndarray) -> float:
    """The smallest metric scale at which the near background (5th percentile of its point
    depths) is no nearer than the head: NaN without points."""
    near = getattr(reg, "near_depth", None)
    if near is None or not near > 0:
        return float("nan")
    return float(np.median(-cam_from_head[:, 2, 3])) / near


def compose_world(cam_from_head: np.ndarray, reg, head_centre: np.ndarray,
                  th: MotionThresholds | None = None, head_asked: bool = False) -> World:
    """cam_from_head (N, 4, 4) OpenGL camera-from-head, metres, of the frames `reg`
    (a background Registration of the same frames in the same order, or None) has; frames
    it did not register must have been dropped by the caller. `head_asked`: the user asked
    for the head as the world (`--cameras head`), so its fallback is no warning."""
    th = th or MotionThresholds()
    n = len(cam_from_head)
    warnings: list[str] = []
    scale = None
    if reg is not None and reg.status == "still":
        c2w = np.tile(np.eye(4), (n, 1, 1))  # the camera's own frame, for now
        head = cam_from_head.copy()
    elif (reg is not None and reg.status == "registered"
          and getattr(reg, "camera_model", None) == "rotation"):
        # turns about one centre: metric already, the hand's few centimetres of travel go
        # to the head's pose (the far background cannot tell them apart)
        c2w = reg.c2w.copy()
        head = c2w @ cam_from_head
    elif reg is not None and reg.status == "registered":
        c2w = reg.c2w.copy()
        scale = metric_scale(c2w, cam_from_head)
        floor = _scale_floor(reg, cam_from_head)
        if not np.isfinite(scale) or scale < floor:
            if not np.isfinite(floor) or floor <= 0:
                warnings.append("the background registered, but no metric scale makes the "
                                "head stay put: falling back to the head as the world")
                return _fallback(cam_from_head, head_centre, th, warnings)
            warnings.append(
                f"the face does not fix the metric scale of the camera's motion (the head "
                f"moves with or against it; least-squares scale {scale:.3g}): the smallest "
                f"scale that keeps the background behind the head is used ({floor:.3g} m "
                f"per unit), so camera translation, and head motion, may be underestimated")
            scale = floor
        c2w[:, :3, 3] *= scale
        head = c2w @ cam_from_head
    elif head_asked and reg is None:
        return _fallback(cam_from_head, head_centre, th, warnings)
    else:
        why = reg.reason if reg is not None else "no background registration"
        warnings.append(f"cameras could not be solved from the background ({why}): the head "
                        "is taken as the world, so every head turn becomes a camera motion "
                        "and the background will not register across frames")
        return _fallback(cam_from_head, head_centre, th, warnings)

    cam, hm = motion_stats(c2w, head, head_centre)
    shake = reg.status == "registered" and getattr(reg, "camera_model", None) == "rotation"
    case = classify(cam, hm, th, shake)
    # the special cases are exactly special: their fixed part is its mean
    if case in (CASES[0], CASES[3]):
        head = np.repeat(mean_pose(head)[None], n, axis=0)
    # a shake measured as rotations stays: snapped still, the background would slide
    if case == CASES[1] and reg.status != "still" and not shake:
        fixed = mean_pose(c2w)
        head = fixed @ np.linalg.inv(c2w) @ head
        c2w = np.repeat(fixed[None], n, axis=0)
    to_head = np.linalg.inv(mean_pose(head))  # the world is the head's mean pose
    c2w, head = to_head @ c2w, to_head @ head
    cam, hm = motion_stats(c2w, head, head_centre)
    warnings += _motion_warnings(case, cam, th, hm)
    return World(case, c2w, head, scale, cam, hm, warnings)


def _fallback(cam_from_head, head_centre, th, warnings) -> World:
    c2w = np.linalg.inv(cam_from_head)
    cam, hm = motion_stats(c2w, None, head_centre)
    warnings += _motion_warnings(CASES[4], cam, th)
    return World(CASES[4], c2w, None, None, cam, hm, warnings)


def _motion_warnings(case: str, cam: dict, th: MotionThresholds,
                     head: dict | None = None) -> list[str]:
    if cam["baseline_deg"] < th.small_baseline_deg:
        what = ("the camera does not move" if case in (CASES[1], CASES[3])
                else "the camera barely moves")
        # a head that turns before a still camera is seen from other sides all the same:
        # what novel views extrapolate is the room's
        turns = head is not None and head["rotation_max_deg"] > th.head_deg
        of = (f" of the room (the head's own turns, up to {head['rotation_max_deg']:.0f} deg "
              "from its mean pose, show it from other sides)" if turns else "")
        return [f"{what} ({cam['baseline_deg']:.1f} deg of baseline seen from the head): "
                f"novel views will extrapolate beyond what the clip shows{of}; default "
                "camera paths stay within the captured range"]
    return []
