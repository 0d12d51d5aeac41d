"""`flamenerf view` end to end: a tiny run, the viewer on a free port, headless Chromium
moving an expression slider and pressing Play in the page (DOM mouse events via the
DevTools protocol)."""

from __future__ import annotations

import json
import re
import os
import socket
import sys
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from cdp import INSTALL_HINT, Browser, find_chromium  # noqa: E402

from flamenerf.cli import main as cli_main  # noqa: E402

pytestmark = pytest.mark.slow  # a browser against a live viewer, end to end

SLIDER = "jawOpen"
RES = 48  # refined image height in the test (pixels)
STATUS_JS = ("(() => { const b = document.body; const m = (b ? b.innerText : '')"
             ".match(/Render: [^\\n]*#(\\d+)/); return m ? m[0] : ''; })()")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def chromium():
    exe = find_chromium()
    if exe is None:
        where = os.environ.get("FLAMENERF_CHROMIUM")
        where = f"FLAMENERF_CHROMIUM={where} is not an executable" if where else \
            "found none on PATH"
        pytest.fail(f"the viewer test needs headless Chromium and {where} "
                    f"({INSTALL_HINT}; or set FLAMENERF_CHROMIUM=/path/to/chromium)")
    return exe


@pytest.fixture
def viewer(tiny_run):
    from flamenerf.training.run import load_run
    from flamenerf.viewer.app import Viewer
    from flamenerf.viewer.options import ViewerOptions

    run = load_run(tiny_run, device="cpu")
    v = Viewer(run, ViewerOptions(port=_free_port(), resolution=RES, verbose=False)).start()
    yield v
    v.stop()


def _panel_rect(b: Browser) -> dict:
    """Bounding box of the smallest element holding the whole control panel."""
    return json.loads(b.eval(f"""(() => {{
        let best = null;
        for (const el of document.querySelectorAll('div')) {{
            const t = el.innerText || '';
            if (!t.includes('flamenerf view') || !t.includes('{SLIDER}')) continue;
            const r = el.getBoundingClientRect();
            if (r.width === 0) continue;
            if (!best || r.width * r.height < best.width * best.height) best = r;
        }}
        return JSON.stringify({{x: best.x, y: best.y, width: best.width, height: best.height}});
    }})()"""))


def _wait_final(b: Browser, after: int, timeout: float = 40.0) -> int:
    s = b.wait_for(f"""(() => {{ const s = {STATUS_JS};
        const m = s.match(/final · #(\\d+)/); return m && +m[1] > {after} ? s : '' }})()""",
                   timeout)
    return int(re.search(r"final · #(\d+)", s).group(1))


def _rect(b: Browser, js_element: str) -> dict:
    return json.loads(b.eval(f"""(() => {{ const r = ({js_element}).getBoundingClientRect();
        return JSON.stringify({{x: r.x, y: r.y, width: r.width, height: r.height}}); }})()"""))


def _texel_centres(rect: dict, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Screen pixel of each render pixel's centre (the image spans the canvas)."""
    ys = rect["y"] + (np.arange(h) + 0.5) / h * rect["height"]
    xs = rect["x"] + (np.arange(w) + 0.5) / w * rect["width"]
    return ys.astype(int), xs.astype(int)


def _covered(ys: np.ndarray, xs: np.ndarray, rects: list[dict], pad: float = 4) -> np.ndarray:
    out = np.zeros(np.broadcast(ys, xs).shape, bool)
    for r in rects:
        out |= ((xs >= r["x"] - pad) & (xs <= r["x"] + r["width"] + pad)
                & (ys >= r["y"] - pad) & (ys <= r["y"] + r["height"] + pad))
    return out


def _wait_shown(b: Browser, viewer, canvas: dict, covers: list[dict], timeout: float = 30.0):
    """Screenshot once the page shows the viewer's last image (painting lags the
    status text, by seconds with software WebGL). -> (screenshot, frame)."""
    end = time.monotonic() + timeout
    err = None
    while time.monotonic() < end:
        frame = viewer.last_frame
        shot = b.screenshot()
        h, w = frame.image.shape[:2]
        ys, xs = _texel_centres(canvas, h, w)
        seen = shot[ys[:, None], xs[None, :]].astype(int)
        free = ~_covered(ys[:, None], xs[None, :], covers)
        err = np.abs(seen - frame.image.astype(int)).max(-1)[free]
        if frame is viewer.last_frame and np.median(err) <= 2 and np.mean(err > 8) < 0.05:
            return shot, frame
        time.sleep(0.25)
    raise AssertionError(f"the page never showed the rendered image (median error "
                         f"{np.median(err)}, {np.mean(err > 8):.1%} of pixels off by > 8)")


def test_slider_changes_the_face_and_only_the_face(chromium, viewer):
    t0 = time.monotonic()
    # the two-step model answers β faintly: the slider goes to its far end (0.9), past the
    # scene's training range, where the viewer would otherwise stop it (tested without a
    # browser in test_viewer_parts)
    viewer.range = None
    with Browser(chromium, width=1100, height=1100) as b:
        # a square viewport: the view is then exactly frame 0's camera
        b.call("Emulation.setDeviceMetricsOverride", width=1100, height=1100,
               deviceScaleFactor=1, mobile=False)
        b.goto(viewer.url)
        n1 = _wait_final(b, 0, 60)
        assert viewer.worker.wait_idle(30)
        canvas = _rect(b, "document.querySelector('canvas')")
        # what covers the canvas: the control panel, notifications (hidden), and the
        # orientation gizmo in the bottom-left corner
        b.eval("""(() => { const s = document.createElement('style');
            s.textContent = '.mantine-Notifications-root {display: none !important}';
            document.head.appendChild(s); })()""")
        covers = [_panel_rect(b), dict(x=canvas["x"], y=canvas["y"] + canvas["height"] - 90,
                                       width=90, height=90)]
        before, shown = _wait_shown(b, viewer, canvas, covers)
        assert shown.final and abs(shown.intr.w / shown.intr.h - 1) < 0.05
        # the slider: the Mantine slider whose <label for=...> reads SLIDER; click near
        # its right end (a real mouse press/release in the page)
        r = _rect(b, f"""document.getElementById([...document.querySelectorAll('label')]
            .find(e => e.textContent === '{SLIDER}').htmlFor)""")
        b.click(r["x"] + 0.9 * r["width"], r["y"] + r["height"] / 2)
        _wait_final(b, n1)
        assert viewer.worker.wait_idle(30)
        after, final = _wait_shown(b, viewer, canvas, covers)
        j = viewer.names.index(SLIDER)
        assert viewer.worker.expression()[j] > 0.5, "the click did not move the slider"
        assert viewer.g_sliders[j].value > 0.5
        assert not viewer.worker.errors, (viewer.worker.errors, viewer.worker.error_views)

    # camera unchanged; the prior's mask follows the expression's mesh, so β may reach any
    # pixel of either silhouette and "the face" is their union
    assert final.final and final.intr == shown.intr
    assert final.extras["mask"].shape == shown.extras["mask"].shape
    mask = final.extras["mask"] | shown.extras["mask"]
    H, W = mask.shape

    # screen pixels -> render pixels (the background image spans the whole canvas)
    sh, sw = before.shape[:2]
    ys, xs = np.mgrid[0:sh, 0:sw]
    u = (xs + 0.5 - canvas["x"]) / canvas["width"]
    v = (ys + 0.5 - canvas["y"]) / canvas["height"]
    on_canvas = (u >= 0) & (u < 1) & (v >= 0) & (v < 1)
    in_panel = _covered(ys, xs, covers)
    rx = np.clip((u * W).astype(int), 0, W - 1)
    ry = np.clip((v * H).astype(int), 0, H - 1)
    # distance in render pixels from the face mask (upscaling blurs about one pixel)
    from scipy import ndimage

    dist = ndimage.distance_transform_edt(~mask)[ry, rx]
    inside = on_canvas & ~in_panel & mask[ry, rx]
    outside = on_canvas & ~in_panel & (dist > 2.0)
    assert inside.sum() > 500 and outside.sum() > inside.sum()

    diff = np.abs(after.astype(int) - before.astype(int)).max(-1)
    if os.environ.get("FLAMENERF_VIEWER_TEST_DUMP"):  # debugging aid
        from PIL import Image

        d = Path(os.environ["FLAMENERF_VIEWER_TEST_DUMP"])
        d.mkdir(parents=True, exist_ok=True)
        Image.fromarray(before).save(d / "before.png")
        Image.fromarray(after).save(d / "after.png")
        vis = np.stack([np.clip(diff * 8, 0, 255), inside * 255, outside * 128], -1)
        Image.fromarray(vis.astype(np.uint8)).save(d / "diff.png")
    changed = diff > 12
    frac_in = changed[inside].mean()
    frac_out = changed[outside].mean()
    print(f"changed: {frac_in:.1%} of the face (max {diff[inside].max()}), {frac_out:.3%} "
          f"elsewhere (max {diff[outside].max()}); "
          f"render {W}x{H}, test took {time.monotonic() - t0:.1f} s")
    assert frac_in > 0.2, f"moving {SLIDER} changed only {frac_in:.1%} of the face"
    assert frac_out < 0.002, f"moving {SLIDER} changed {frac_out:.3%} of the image off the face"


def test_play_in_the_page_plays_the_capture_as_filmed(chromium, viewer):
    """Play pressed in the page: the images keep coming while the track plays (each one's
    frame passes before it is rendered), each a frame of the clip as filmed."""
    capture = next(t for t in viewer.tracks if t.name.startswith("capture"))
    with Browser(chromium, width=900, height=700) as b:
        b.goto(viewer.url)
        n = _wait_final(b, 0, 60)
        viewer.g_track.value = capture.name  # the track menu (a viser dropdown)
        b.wait_for(f"""(() => {{ const s = {STATUS_JS};
            const m = s.match(/final · frame 0 as filmed · #(\\d+)/);
            return m && +m[1] > {n} ? s : '' }})()""", 40)
        b.eval("""[...document.querySelectorAll('button')]
            .find(e => e.textContent.trim() === 'Play').scrollIntoView()""")
        r = _rect(b, """[...document.querySelectorAll('button')]
            .find(e => e.textContent.trim() === 'Play')""")
        b.click(r["x"] + r["width"] / 2, r["y"] + r["height"] / 2)
        b.wait_for("[...document.querySelectorAll('button')]"
                   ".some(e => e.textContent.trim() === 'Pause')", 10)
        seen = []  # (image count, frame as filmed) the status line shows, while playing
        end = time.monotonic() + 4.0
        while time.monotonic() < end:
            m = re.search(r"frame (\d+) as filmed · #(\d+)", b.eval(STATUS_JS) or "")
            if m:
                seen.append((int(m.group(2)), int(m.group(1))))
            time.sleep(0.1)
        assert viewer.playing
        viewer.pause()
    counts, frames = {c for c, _ in seen}, {k for _, k in seen}
    assert len(counts) >= 4 and len(frames) >= 3, seen  # images arrive, of different frames
    assert not viewer.worker.errors


def test_port_taken_is_one_line_error(tiny_run, capsys):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        rc = cli_main(["view", str(tiny_run), "--port", str(port)])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.strip().count("\n") == 0 and f"port {port}" in err and "in use" in err


def test_not_a_run_is_one_line_error(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    for d in (tmp_path / "empty", tmp_path / "missing"):
        rc = cli_main(["view", str(d)])
        err = capsys.readouterr().err
        assert rc == 2 and err.strip().count("\n") == 0 and str(d) in err, err
