"""Which part of the face each named control may move.

A tracker's expression scores co-vary: in a surprised face MediaPipe raises jawOpen,
browOuterUp and eyeWide together, and a blink comes with eyeLookDown. A β -> mesh model
fitted by least squares on such frames spreads the jaw's motion over the brow controls
(measured on a real clip: browInnerUp's largest vertex motion was on the chin), and the
per-control spatial prior built from it lets a brow control open the mouth, so that
commanding jawOpen alone opens it a fraction. Anatomy settles what the data cannot: a brow
control moves the brows, a jaw or mouth control the lower face. This module gives, for
ARKit-named controls on a face mesh whose eyes and mouth it can find, a soft weight per
vertex and control; the β -> mesh fit (meshes.fit_expression_model) only lets control k
move vertex v by as much as that weight.

The eyes and mouth are MediaPipe's landmarks on its topology (what `flamenerf preprocess`
writes), or the vertices a dataset names in `face_landmarks` (the built-in scene's mesh).
The built-in scene needs them too although its controls are uncorrelated by construction:
its mesh's lip vertices slide into the open mouth (not linear in jawOpen), and a free fit
spread that residual over the rarely used controls (eyeBlinkLeft's largest motion was 5 mm
on the lips, eyeWideLeft's 48 mm), so that a commanded blink opened the mouth. FLAME's PCA
components get no weights: they are the model's own basis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# MediaPipe's canonical face mesh (468 landmarks; 478 with the irises): the eye corners,
# the lip centres and the mouth corners, which place the eyes and the mouth on any face
MEDIAPIPE_LANDMARKS = {
    "eye_left": (263, 362),    # the subject's left eye, outer and inner corner
    "eye_right": (33, 133),
    "mouth": (13, 14, 61, 291),
}
MEDIAPIPE_VERTEX_COUNTS = (468, 478)
LANDMARK_KEYS = tuple(MEDIAPIPE_LANDMARKS)
PART_KINDS = ("arkit", "synthetic")
"""Expression kinds whose controls are ARKit-named blendshapes (the tracker's scores, the
built-in rig's controls)."""

# (lower, upper) bounds of a part along the face's vertical axis h (0 at the mouth, 1 at the
# eyes), with a soft edge of _EDGE on each side; the eyes are a distance from either eye.
_EDGE = 0.1
_LOWER_FACE = (-np.inf, 0.45)     # chin, jaw, lips, up to under the nose
_MID_FACE = (-0.1, 1.15)          # cheeks and nose
_UPPER_FACE = (0.9, np.inf)       # brows and forehead
_EYE_RADIUS = (0.35, 0.5)         # full weight within, none beyond (units of eye-mouth distance)
# ... and up to the upper lid only (h 1.05 on MediaPipe's mesh of a real face; the brows sit
# at h 1.13-1.32, within the eyes' radius): the eye controls' scores co-vary with the brow
# raisers' on real faces, and with the brows in both parts a fit gave the brows' motion to
# eyeLookDown and eyeBlink and left browInnerUp +0.2 mm of it (the shared expressions clip)
_EYE_TOP = 1.05
# "Left" is the subject's left, MediaPipe's left eye (checked on a real clip: a free fit
# moves the left eye's lid most under eyeBlinkLeft, the right brow under browDownRight);
# a sided control fades out over ±_MIDLINE across the face's midline. jawLeft/Right and
# mouthLeft/Right move the whole jaw or mouth sideways: not sided.
_MIDLINE = 0.1
_UNSIDED = ("jawLeft", "jawRight", "mouthLeft", "mouthRight")


def _part_of(name: str) -> str | None:
    """The part an ARKit blendshape name belongs to; None for unknown names (no limit)."""
    if name == "_neutral":
        return "none"  # MediaPipe's overall 'no expression' score: no place on the face
    for prefix, part in (("brow", "upper"), ("eye", "eye"), ("cheek", "mid"),
                         ("nose", "mid"), ("jaw", "lower"), ("mouth", "lower"),
                         ("tongue", "lower")):
        if name.startswith(prefix):
            return part
    return None


def part_and_side(name: str) -> tuple[str | None, str]:
    """An ARKit control's part of the face (None: unknown name, "none": no place) and side
    ("Left", "Right", or "" for controls that act on both sides)."""
    part = _part_of(name)
    if part is None or name in _UNSIDED:
        return part, ""
    return part, next((s for s in ("Left", "Right") if name.endswith(s)), "")


def _band(h: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """1 on [lo, hi], fading linearly to 0 over _EDGE outside it."""
    below = np.clip((h - (lo - _EDGE)) / _EDGE, 0, 1) if np.isfinite(lo) else 1.0
    above = np.clip(((hi + _EDGE) - h) / _EDGE, 0, 1) if np.isfinite(hi) else 1.0
    return np.minimum(below, above) * np.ones_like(h)


def applies(kind: str, names: list[str], num_vertices: int) -> bool:
    """Whether the dataset is a tracked clip with face parts (MediaPipe's ARKit scores on
    its own mesh): its scores co-vary, which the companions (data/companions.py) answer,
    and the per-control prior's wider fade radius was measured on such clips. The built-in
    scene's face parts do not count here (its controls are independent); whether any
    dataset has face parts at all (and so the mesh guide): `has_parts`."""
    return (kind == "arkit" and num_vertices in MEDIAPIPE_VERTEX_COUNTS
            and any(_part_of(n) is not None for n in names))


def has_parts(kind: str, names: list[str], num_vertices: int, landmarks: dict | None = None
              ) -> bool:
    """Whether `control_weights` gives such a dataset face parts (tracked clips, the
    built-in scene; not FLAME's components, nor a mesh whose eyes and mouth are unknown)."""
    return (kind in PART_KINDS and mesh_landmarks(num_vertices, landmarks) is not None
            and any(_part_of(n) is not None for n in names))


def mesh_landmarks(num_vertices: int, given: dict | None = None
                   ) -> dict[str, tuple[int, ...]] | None:
    """Vertex indices of the eyes and the mouth on a face mesh: `given` (a dataset's
    `face_landmarks`), else MediaPipe's on its topology, else None."""
    if given is not None:
        return {k: tuple(int(i) for i in given[k]) for k in LANDMARK_KEYS}
    return MEDIAPIPE_LANDMARKS if num_vertices in MEDIAPIPE_VERTEX_COUNTS else None


@dataclass(frozen=True)
class FaceFrame:
    """Where each vertex of a face mesh lies on the face, in units of the distance `scale`
    from the mouth to the eyes' midpoint (`face_frame`)."""

    scale: float
    """The mouth-to-eyes distance, the mesh's units."""
    up: np.ndarray
    """(3,) unit vector from the mouth to the eyes' midpoint."""
    across: np.ndarray
    """(3,) unit vector towards the subject's left, orthogonal to `up`."""
    h: np.ndarray
    """(V,) height: 0 at the mouth, 1 at the eyes."""
    s: np.ndarray
    """(V,) across: > 0 on the subject's left."""
    d_eye: np.ndarray
    """(V,) distance to the nearer eye."""
    eyes: dict[str, np.ndarray]
    """"Left" / "Right" -> (3,) the eye's centre."""


def face_frame(vertices: np.ndarray, marks: dict[str, tuple[int, ...]]) -> FaceFrame:
    """The frame of a face mesh (V, 3) from its eyes' and mouth's vertices (`mesh_landmarks`)."""
    v = np.asarray(vertices, np.float64)
    eye_l = v[list(marks["eye_left"])].mean(0)
    eye_r = v[list(marks["eye_right"])].mean(0)
    mouth = v[list(marks["mouth"])].mean(0)
    up = (eye_l + eye_r) / 2 - mouth
    scale = float(np.linalg.norm(up))
    h = (v - mouth) @ (up / scale) / scale
    across = eye_l - eye_r
    across -= (across @ up) / scale ** 2 * up
    across /= np.linalg.norm(across)
    d_eye = np.minimum(np.linalg.norm(v - eye_l, axis=1),
                       np.linalg.norm(v - eye_r, axis=1)) / scale
    return FaceFrame(scale, up / scale, across, h, (v - mouth) @ across / scale, d_eye,
                     {"Left": eye_l, "Right": eye_r})


def control_weights(kind: str, names: list[str], vertices: np.ndarray,
                    landmarks: dict | None = None) -> np.ndarray | None:
    """Soft per-vertex limits of each control, or None where none apply (not ARKit names,
    no eyes and mouth known on the mesh, or no name this module knows).

    kind: the dataset's expression kind (`arkit` for MediaPipe's blendshape scores,
    `synthetic` for the built-in rig's); names (E,); vertices (V, 3) a typical mesh of the
    subject (e.g. the mean training mesh), any units; landmarks: the dataset's
    `face_landmarks` (`mesh_landmarks`). -> (V, E) float32 in [0, 1].
    """
    if not has_parts(kind, names, vertices.shape[0], landmarks):
        return None
    parts = [_part_of(n) for n in names]
    f = face_frame(vertices, mesh_landmarks(vertices.shape[0], landmarks))
    h, s, d_eye = f.h, f.s, f.d_eye
    lo, hi = _EYE_RADIUS
    eye = np.clip((hi - d_eye) / (hi - lo), 0, 1) * _band(h, -np.inf, _EYE_TOP)
    weight = {
        "lower": _band(h, *_LOWER_FACE),
        "mid": _band(h, *_MID_FACE),
        # the brows' part stops where the eyes' begins: a clip raises its brows with its
        # eyes wide open, and a brow control that could move the lids (and, through the
        # per-control prior, repaint the eyes) learnt wide eyes, which a brow edit over a
        # squint or a blink blended into glassy, see-through eyes (the shared expressions
        # clip). The mid face's part still reaches the eyes: untested, the clip's cheek and
        # nose scores stay under 0.001
        "upper": _band(h, *_UPPER_FACE) * (1 - eye),
        "eye": eye,
        "none": np.zeros(len(h)),
        None: np.ones(len(h)),
    }
    side = {"Left": np.clip((s + _MIDLINE) / (2 * _MIDLINE), 0, 1),
            "Right": np.clip((_MIDLINE - s) / (2 * _MIDLINE), 0, 1)}
    cols = []
    for name, part in zip(names, parts):
        sided = part_and_side(name)[1]
        cols.append(weight[part] * side[sided] if sided else weight[part])
    return np.stack(cols, 1).astype(np.float32)
