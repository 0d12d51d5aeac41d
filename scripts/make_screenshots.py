"""Screenshots of `flamenerf view` for docs/viewer.md (not a test).

    python scripts/make_screenshots.py RUN [--out docs] [--resolution 160]

Starts the viewer on RUN, opens it in headless Chromium and saves
viewer_rgb.png (frame 0's camera, an expression set with the sliders), viewer_depth.png
(the same in depth) and viewer_orbit.png (the camera dragged sideways).
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import time
from pathlib import Path

# the headless-Chromium client the viewer test uses
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "viewer"))
from cdp import Browser, find_chromium  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path)
    ap.add_argument("--out", type=Path, default=Path("docs"))
    ap.add_argument("--resolution", type=int, default=160)
    ap.add_argument("--size", type=int, nargs=2, default=(1280, 720))
    ap.add_argument("--orbit-px", type=int, default=40)
    ap.add_argument("--expression", default="jawOpen=0.8,mouthSmileLeft=0.7,"
                                            "mouthSmileRight=0.7,browInnerUp=0.6")
    args = ap.parse_args()

    import numpy as np
    import torch
    from PIL import Image

    torch.set_num_threads(1)
    from flamenerf.training.run import load_run
    from flamenerf.viewer.app import Viewer
    from flamenerf.viewer.options import ViewerOptions

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    v = Viewer(load_run(args.run), ViewerOptions(port=port, resolution=args.resolution,
                                                 verbose=False)).start()
    w, h = args.size
    args.out.mkdir(parents=True, exist_ok=True)

    def settle(b: Browser) -> None:
        time.sleep(0.5)
        assert v.worker.wait_idle(600)
        b.wait_for("document.body.innerText.includes('final')", 60)
        time.sleep(2.0)  # software WebGL paints late

    def shot(b: Browser, name: str) -> None:
        Image.fromarray(b.screenshot()).save(args.out / name, optimize=True)
        print("wrote", args.out / name)

    try:
        with Browser(find_chromium(), width=w, height=h) as b:
            b.call("Emulation.setDeviceMetricsOverride", width=w, height=h,
                   deviceScaleFactor=1, mobile=False)
            b.goto(v.url)
            b.wait_for("document.body && document.body.innerText.includes('final')", 600)
            b.eval("""(() => { const s = document.createElement('style');
                s.textContent = '.mantine-Notifications-root {display: none !important}';
                document.head.appendChild(s); })()""")
            # set the expression by clicking the sliders in the page
            for item in args.expression.split(","):
                name, val = item.split("=")
                r = json.loads(b.eval(f"""(() => {{
                    const l = [...document.querySelectorAll('label')]
                        .find(e => e.textContent === '{name}');
                    const el = document.getElementById(l.htmlFor);
                    el.scrollIntoView({{block: 'center'}});  // below the Track folder
                    const r = el.getBoundingClientRect();
                    return JSON.stringify({{x: r.x, y: r.y, w: r.width, h: r.height}}); }})()"""))
                b.click(r["x"] + float(val) * r["w"], r["y"] + r["h"] / 2)
                # viser's page throttles all GUI updates through one 50 ms sender: an
                # update to another control within 50 ms replaces this one
                time.sleep(0.3)
            settle(b)
            shot(b, "viewer_rgb.png")
            v.g_mode.value = "Depth"  # the dropdown, set from the server
            settle(b)
            shot(b, "viewer_depth.png")
            v.g_mode.value = "RGB"
            # orbit: a short drag on the canvas, left of the panel
            b.drag(w * 0.40, h * 0.5, w * 0.40 + args.orbit_px, h * 0.5, steps=8)
            settle(b)
            shot(b, "viewer_orbit.png")
            print("expression:", np.round(v.worker.expression(), 2).tolist())
    finally:
        v.stop()


if __name__ == "__main__":
    main()
