"""One stable square crop for the whole clip, and the intrinsics that go with it.

A NeRF of a moving camera needs one pinhole camera for every frame, so the crop is the
same window in every frame (a per-frame crop would be a per-frame principal point). It is
centred on the union of the tracked face boxes and `scale` times the largest face box, grown
to hold the union when the face wanders, and limited to (and kept inside) the frame.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from PIL import Image

from flamenerf.data.dataset import Intrinsics


@dataclass
class Crop:
    x0: int
    y0: int
    size: int  # side of the square, source pixels
    out_size: int  # side after resizing

    @property
    def scale(self) -> float:
        return self.out_size / self.size

    def to_dict(self) -> dict:
        return {**asdict(self), "scale": self.scale}

    def intrinsics(self, focal: float, cx: float, cy: float) -> Intrinsics:
        """Intrinsics of the cropped, resized image (continuous pixel coordinates)."""
        s = self.scale
        return Intrinsics(self.out_size, self.out_size, focal * s, focal * s,
                          (cx - self.x0) * s, (cy - self.y0) * s)

    def points(self, uv: np.ndarray) -> np.ndarray:
        """Source-pixel points (..., 2) -> output pixels."""
        return (uv - np.array([self.x0, self.y0])) * self.scale

    def apply(self, rgb: np.ndarray) -> np.ndarray:
        """Cut the window out of a source frame and resize it (Lanczos, antialiased)."""
        win = rgb[self.y0 : self.y0 + self.size, self.x0 : self.x0 + self.size]
        if self.size == self.out_size:
            return np.ascontiguousarray(win)
        img = Image.fromarray(np.ascontiguousarray(win))
        return np.asarray(img.resize((self.out_size, self.out_size), Image.Resampling.LANCZOS))


    def mask(self, mask: np.ndarray, scale: float) -> np.ndarray:
        """A mask (h, w) bool made at `scale` of the source's pixels -> (out, out) bool:
        the crop's pixels, each the mask's nearest sample at its centre."""
        c = (np.arange(self.out_size) + 0.5) / self.scale
        xs = np.clip(((c + self.x0) * scale).astype(int), 0, mask.shape[1] - 1)
        ys = np.clip(((c + self.y0) * scale).astype(int), 0, mask.shape[0] - 1)
        return mask[np.ix_(ys, xs)]


def face_boxes(landmarks: np.ndarray) -> np.ndarray:
    """(N, L, ≥2) pixel landmarks -> (N, 4) boxes x0, y0, x1, y1."""
    lo, hi = landmarks[..., :2].min(1), landmarks[..., :2].max(1)
    return np.concatenate([lo, hi], -1)


def stable_square_crop(boxes: np.ndarray, width: int, height: int, out_size: int,
                       scale: float = 2.0) -> tuple[Crop, dict]:
    """The clip's crop window. Returns it and facts for the report (face coverage)."""
    lo, hi = boxes[:, :2].min(0), boxes[:, 2:].max(0)  # union of face boxes
    face = float((boxes[:, 2:] - boxes[:, :2]).max())
    union = float((hi - lo).max())
    side = max(scale * face, 1.1 * union)
    limit = min(width, height)
    size = int(round(min(side, limit)))
    centre = (lo + hi) / 2
    x0 = int(round(np.clip(centre[0] - size / 2, 0, width - size)))
    y0 = int(round(np.clip(centre[1] - size / 2, 0, height - size)))
    crop = Crop(x0, y0, size, out_size)
    inside = ((boxes[:, 0] >= x0) & (boxes[:, 1] >= y0) & (boxes[:, 2] <= x0 + size)
              & (boxes[:, 3] <= y0 + size))
    facts = {"face_box_px_max": face, "union_box": [*lo.tolist(), *hi.tolist()],
             "limited_by_frame": bool(side > limit), "frames_face_inside": int(inside.sum())}
    return crop, facts
