"""The background's cameras of the built-in handheld scene (`synth --handheld`, small):
a phone's shake with little parallax, the head moving on its own, leaves that sway."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from flamenerf.geometry import rotation_angle_deg
from flamenerf.synthetic.scene import handheld_capture
from flamenerf.tracking.background import BackgroundOptions, register_background
from flamenerf.tracking.world import compose_world




@pytest.mark.slow
def test_the_shake_is_recovered_the_head_separated_and_the_leaves_flagged():
    frames = list(handheld_capture(seed=0, size=96, frames=24, workers=1))
    reg = register_background(((k, f.rgb, f.person) for k, f in enumerate(frames)),
                              BackgroundOptions(), focal=float(frames[0].intrinsics.fx))
    assert reg.status == "registered" and reg.camera_model == "rotation", reg.reason
    assert reg.registered.all()
    c2w = np.stack([f.c2w for f in frames])
    head = np.stack([f.head_pose for f in frames])
    world = compose_world(np.linalg.inv(c2w) @ head, reg, np.zeros(3))
    assert world.case == "both moving"
    G = Rotation.from_matrix(np.einsum("nab,ncb->nac", c2w[:, :3, :3],
                                       world.c2w[:, :3, :3])).mean().as_matrix()
    assert np.median(rotation_angle_deg(G @ world.c2w[:, :3, :3], c2w[:, :3, :3])) < 0.3
    assert np.median(rotation_angle_deg(G @ world.head_pose[:, :3, :3],
                                        head[:, :3, :3])) < 1.0
    # the head turned on its own by far more than that
    assert rotation_angle_deg(head[:, :3, :3], head[:1, :3, :3]).max() > 3.0
    est = np.stack([np.asarray(Image.fromarray(m.astype(np.uint8) * 255).resize(
        (96, 96), Image.Resampling.NEAREST)) > 0 for m in reg.moving])
    truth = np.stack([f.moving for f in frames])
    # recall is low this small (0.21: the leaves' texture is a few pixels; the benchmark
    # measures 0.68 at 128 px and 0.93 at 256), precision is not
    assert (est & truth).sum() / truth.sum() > 0.15
    assert (est & truth).sum() / max(est.sum(), 1) > 0.9  # precision
