import subprocess
import sys

import pytest

from flamenerf.data.dataset import load_dataset
from flamenerf.data.video import read_frames


@pytest.mark.slow
def test_demo_end_to_end_at_tiny_size(tmp_path):
    out = tmp_path / "demo"
    r = subprocess.run([sys.executable, "-m", "flamenerf.cli", "demo", "--out", str(out),
                        "--size", "32", "--frames", "20", "--steps", "4", "--train-size", "32",
                        "--batch-rays", "256"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    frames = read_frames(out / "reanimation.mp4")
    n = len(load_dataset(out / "scene").splits["reanimate"])  # one video frame each
    assert n > 0 and len(frames) == n and frames[0].shape == (32, 32, 3)
    tour = read_frames(out / "expressions.mp4")  # the expression tour: a few controls
    assert len(tour) >= 3 * 24 and len(tour) % 24 == 1 and tour[0].shape == (32, 32, 3)
    for extra in ("reanimation_depth.mp4", "reanimation_sbs.mp4", "expressions_depth.mp4",
                  "expressions_sbs.mp4"):
        assert (out / extra).stat().st_size > 0
