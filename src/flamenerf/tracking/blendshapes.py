"""MediaPipe's blendshape stage on its own: the 52 scores as a function of the face's
landmarks in the image.

FaceLandmarker scores an expression in two stages: a network finds the 478 landmarks in the
image, and a second, small network (`face_blendshapes.tflite`, inside the same
`face_landmarker.task`) reads the scores from 146 of those landmarks' image positions alone.
Run on the landmarker's own landmarks, this module gives its scores to the bit (tested).
What it adds is the second stage without an image: the scores of any face mesh projected
into a camera, and their derivatives, which is how the β -> mesh model is made to mean what
the tracker means by each control (tracking/expression_model.py). LiteRT
(`ai-edge-litert` on PyPI, Google's runtime for these files) runs it on the CPU.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from flamenerf.errors import UserError
from flamenerf.tracking.landmarker import NUM_LANDMARKS, blendshape_names, find_model

MEMBER = "face_blendshapes.tflite"

INPUT_LANDMARKS = (
    0, 1, 4, 5, 6, 7, 8, 10, 13, 14, 17, 21, 33, 37, 39, 40, 46, 52, 53, 54, 55, 58, 61, 63,
    65, 66, 67, 70, 78, 80, 81, 82, 84, 87, 88, 91, 93, 95, 103, 105, 107, 109, 127, 132, 133,
    136, 144, 145, 146, 148, 149, 150, 152, 153, 154, 155, 157, 158, 159, 160, 161, 162, 163,
    168, 172, 173, 176, 178, 181, 185, 191, 195, 197, 234, 246, 249, 251, 263, 267, 269, 270,
    276, 282, 283, 284, 285, 288, 291, 293, 295, 296, 297, 300, 308, 310, 311, 312, 314, 317,
    318, 321, 323, 324, 332, 334, 336, 338, 356, 361, 362, 365, 373, 374, 375, 377, 378, 379,
    380, 381, 382, 384, 385, 386, 387, 388, 389, 390, 397, 398, 400, 402, 405, 409, 415, 454,
    466, 468, 469, 470, 471, 472, 473, 474, 475, 476, 477)
"""The landmarks the blendshape network reads, in its input order: the model's interface as
MediaPipe's face_blendshapes_graph.cc defines it (Apache-2.0), irises included."""


class BlendshapeStage:
    """The blendshape network of a `face_landmarker.task` (default: the one `preprocess`
    uses, tracking/landmarker.find_model)."""

    def __init__(self, task: str | Path | None = None):
        from ai_edge_litert.interpreter import Interpreter

        path = find_model(task)
        try:
            with zipfile.ZipFile(path) as z:
                blob = z.read(MEMBER)
        except (OSError, KeyError, zipfile.BadZipFile) as e:
            raise UserError(f"{path}: cannot read its blendshape model ({e})") from None
        self._net = Interpreter(model_content=blob, num_threads=1)
        self._net.allocate_tensors()
        self._in = self._net.get_input_details()[0]["index"]
        self._out = self._net.get_output_details()[0]["index"]
        self.names = blendshape_names()
        self._subset = np.asarray(INPUT_LANDMARKS)

    def scores(self, points: np.ndarray) -> np.ndarray:
        """points (478, 2) image pixels (x right, y down) -> (52,) scores, `names` order."""
        if points.shape != (NUM_LANDMARKS, 2):
            raise ValueError(f"expected ({NUM_LANDMARKS}, 2) landmarks, got {points.shape}")
        self._net.set_tensor(self._in, np.asarray(points, np.float32)[self._subset][None])
        self._net.invoke()
        return self._net.get_tensor(self._out).astype(np.float64).reshape(-1)

    def jacobian(self, points: np.ndarray, eps: float = 0.05) -> np.ndarray:
        """d scores / d points at `points` (478, 2) pixels by central differences of `eps`
        pixels -> (52, 478, 2); zero for the landmarks the network does not read."""
        jac = np.zeros((len(self.names), NUM_LANDMARKS, 2))
        p = np.array(points, np.float64)
        for j in self._subset:
            for c in range(2):
                keep = p[j, c]
                p[j, c] = keep + eps
                hi = self.scores(p)
                p[j, c] = keep - eps
                lo = self.scores(p)
                p[j, c] = keep
                jac[:, j, c] = (hi - lo) / (2 * eps)
        return jac
