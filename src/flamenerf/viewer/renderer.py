"""Progressive rendering in a background thread.

Every browser (view) has a camera; all views share the expression, the display mode and
the quality. Whenever any of these changes the view's *key* changes and the worker renders
it again, coarse to fine: after a camera move first at 1/4 of the chosen height (fast, so
dragging the camera stays interactive), after any other change at 1/2, then - once nothing
has changed for `settle_s` - at the levels above, up to the full height. The first image
of a change is always finished and shown; a refinement is rendered in bands of rows and
abandoned as soon as the key changes again, so the worker never sits on a stale image.

When only the expression changes (a slider, a track playing) and the view's camera, head
pose, codes and height are those of its last full-height image, only the pixels inside the
spatial prior's silhouette before or after the change are rendered again, at the full
height at once: β reaches no other ray (the prior), so every other pixel is the one shown.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from flamenerf.data.dataset import Intrinsics
from flamenerf.model.inference import VIEWER, RenderSettings
from flamenerf.model.render_image import StillCamera
from flamenerf.rendering.filmed import FilmedFrame, own_codes_settings
from flamenerf.viewer.camera import view_intrinsics
from flamenerf.geometry import se3_log
from flamenerf.images import colorize_depth, to_uint8


@dataclass
class Shared:
    """State common to every view. Mutate only through RenderWorker's setters."""

    expression: np.ndarray
    mode: str = "RGB"  # or "Depth"
    height: int = 128  # pixels of the refined image
    progressive: bool = True
    version: int = 0
    changed_at: float = 0.0
    # head pose (head-following runs): canonical-from-world (4, 4); None = frame 0's pose
    # (or, with `filmed`, that frame's own)
    head: np.ndarray | None = None
    # a frame of the clip shown as filmed (its codes, head pose and mesh); None: frame 0's
    # codes
    filmed: FilmedFrame | None = None


@dataclass
class View:
    """One browser's camera and what has been shown in it."""

    c2w: np.ndarray
    fov_y: float
    aspect: float
    version: int = 0
    changed_at: float = 0.0
    shown_key: tuple | None = None
    shown_level: int = -1
    depth_range: tuple[float, float] | None = None
    renders: int = 0
    # the renderer of the last full-height image (the worker thread's alone)
    cache: StillCamera | None = None


@dataclass
class Frame:
    """A finished image, handed to the display callback."""

    image: np.ndarray  # (H, W, 3) uint8
    intr: Intrinsics
    seconds: float
    level: int  # 0 = coarsest
    final: bool  # the full-quality image of the current state
    count: int  # images finished for this view so far
    mode: str
    extras: dict = field(default_factory=dict)


DisplayFn = Callable[[object, Frame], None]


class _Stale(Exception):
    pass


class RenderWorker:
    def __init__(self, model, deform_code: torch.Tensor, appearance_code: torch.Tensor,
                 masker, expression: np.ndarray, display: DisplayFn, height: int = 128,
                 settle_s: float = 0.25, band_rays: int = 16384,
                 on_error: Callable[[object, BaseException], None] | None = None,
                 settings: RenderSettings = VIEWER):
        self.model = model
        self.settings = settings  # the inference path: ω is fixed, its warp bake is reused
        self.omega, self.phi = deform_code, appearance_code
        self.masker = masker
        self.display = display
        self.on_error = on_error
        self.settle_s = settle_s
        # rays per band: each band pays the per-image work once (the silhouette's mesh and
        # the setup of its nearest-vertex queries) and is split among the CPU's threads
        # (render_image); 16384 (a whole 128 px update) made it 0.31 -> 0.26 s on the
        # 2-core CPU (8192 before, 4096 before that), still abandoning a stale image within
        # ~0.25 s
        self.band_rays = band_rays
        # the full-height image at once after a change of expression alone when the face's
        # silhouette covers at most this share of it: an expression is invisible in the
        # coarse level's 32 px, and the silhouette's rays alone cost less than a whole
        # image (at 128 px on the 2-core CPU, 14 % of the pixels: 78 against 204 ms, 37 %:
        # 147 against 238 ms; benchmarks/bench_render.py's viewer rows). A face that fills
        # more of the view goes coarse to fine, as a camera move does, and its last level
        # still renders only the silhouette again.
        self.partial_max = 0.5
        self.shared = Shared(expression=np.asarray(expression, np.float32).copy(),
                             height=int(height))
        self.views: dict[object, View] = {}
        self._cv = threading.Condition()
        self._stop = False
        self._thread = threading.Thread(target=self._loop, name="flamenerf-render", daemon=True)
        self.errors: list[BaseException] = []
        self.error_views: list[dict] = []  # the view each error happened in

    # ------------------------------------------------------------------ state changes

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        with self._cv:
            self._stop = True
            self._cv.notify_all()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout)

    def _touch_shared(self) -> None:
        self.shared.version += 1
        self.shared.changed_at = time.monotonic()
        self._cv.notify_all()

    def set_expression(self, values: np.ndarray) -> None:
        v = np.asarray(values, np.float32)
        with self._cv:
            if np.array_equal(v, self.shared.expression):
                return
            self.shared.expression = v.copy()
            self._touch_shared()

    def set_expression_value(self, index: int, value: float) -> None:
        with self._cv:
            if float(self.shared.expression[index]) == float(value):
                return
            self.shared.expression = self.shared.expression.copy()
            self.shared.expression[index] = value
            self._touch_shared()

    def set_filmed(self, filmed: FilmedFrame | None, expression: np.ndarray) -> None:
        """Show a frame of the clip as filmed (None: frame 0's codes) at `expression`, in
        one change (no image of the one without the other)."""
        v = np.asarray(expression, np.float32)
        with self._cv:
            old = self.shared.filmed
            same = old is None if filmed is None else filmed.same(old)
            if same and np.array_equal(v, self.shared.expression):
                return
            self.shared.filmed, self.shared.expression = filmed, v.copy()
            self._touch_shared()

    def filmed(self) -> FilmedFrame | None:
        with self._cv:
            return self.shared.filmed

    def set_head(self, transform: np.ndarray | None) -> None:
        """The head's pose: canonical-from-world (4, 4) (data/head_pose.control_transform),
        or None for frame 0's."""
        with self._cv:
            self.shared.head = None if transform is None else np.array(transform, np.float64)
            self._touch_shared()

    def expression(self) -> np.ndarray:
        with self._cv:
            return self.shared.expression.copy()

    def set_mode(self, mode: str) -> None:
        with self._cv:
            if mode != self.shared.mode:
                self.shared.mode = mode
                for v in self.views.values():
                    v.depth_range = None
                self._touch_shared()

    def set_quality(self, height: int | None = None, progressive: bool | None = None) -> None:
        with self._cv:
            if height is not None and int(height) != self.shared.height:
                self.shared.height = max(1, int(height))
                self._touch_shared()
            if progressive is not None and bool(progressive) != self.shared.progressive:
                self.shared.progressive = bool(progressive)
                self._touch_shared()

    def set_camera(self, key: object, c2w: np.ndarray, fov_y: float, aspect: float) -> None:
        c2w = np.asarray(c2w, np.float64)
        with self._cv:
            v = self.views.get(key)
            if v is None:
                self.views[key] = View(c2w, float(fov_y), float(aspect), 1, time.monotonic())
            elif (np.allclose(v.c2w, c2w, rtol=0, atol=1e-6) and abs(v.fov_y - fov_y) < 1e-6
                  and abs(v.aspect - aspect) < 1e-6):
                return
            else:
                v.c2w, v.fov_y, v.aspect = c2w, float(fov_y), float(aspect)
                v.version += 1
                v.changed_at = time.monotonic()
            self._cv.notify_all()

    def refresh(self, key: object) -> None:
        """Show `key`'s current state again from the coarsest level."""
        with self._cv:
            v = self.views.get(key)
            if v is not None:
                v.version += 1
                v.changed_at = time.monotonic()
                v.cache = None
                self._cv.notify_all()

    def remove_view(self, key: object) -> None:
        with self._cv:
            self.views.pop(key, None)

    # ------------------------------------------------------------------ the worker

    def levels(self, height: int, progressive: bool) -> list[int]:
        if not progressive:
            return [height]
        hs = [max(8, height // 4), max(8, height // 2), height]
        out: list[int] = []
        for h in hs:
            if h <= height and (not out or h > out[-1]):
                out.append(h)
        return out

    def _next_job(self):
        """-> (key, level, heights, snapshot) or (None, wait_seconds)."""
        now = time.monotonic()
        s = self.shared
        heights = self.levels(s.height, s.progressive)
        wait = None
        # views whose state changed first, then refinements
        best = None
        for key, v in self.views.items():
            state = (v.version, s.version)
            if v.shown_key != state:
                # a new camera starts at the coarsest level (a drag wants many images a
                # second); a new expression, frame or quality under the same camera one
                # level up, where a track played as filmed still shows ~3 images a second
                # on the 2-core CPU (a 16:9 view of 128 px; benchmarks/bench_playback.py)
                # and a face is recognisable, which at 1/4 it is not
                moved = v.shown_key is None or v.shown_key[0] != v.version
                cand = (0, -v.changed_at, key, 0 if moved else max(len(heights) - 2, 0))
            elif v.shown_level < len(heights) - 1:
                idle = now - max(v.changed_at, s.changed_at)
                if idle < self.settle_s:
                    w = self.settle_s - idle
                    wait = w if wait is None else min(wait, w)
                    continue
                cand = (1, v.shown_level, key, v.shown_level + 1)
            else:
                continue
            if best is None or cand[:2] < best[:2]:
                best = cand
        if best is None:
            return None, wait
        key, level = best[2], best[3]
        v = self.views[key]
        # the first image of a new state always finishes and is shown, however soon the
        # state changes again (a player, a drag): abandoning it could leave the view
        # frozen on a long since stale image; refinements are abandoned
        snap = dict(key=key, first=best[0] == 0, state=(v.version, s.version),
                    c2w=v.c2w.copy(), fov_y=v.fov_y,
                    aspect=v.aspect, expression=s.expression.copy(), mode=s.mode,
                    height=heights[-1], final=True, depth_range=v.depth_range, head=s.head,
                    filmed=s.filmed)
        if s.head is None and s.filmed is not None:  # the frame's own pose
            snap["head"] = s.filmed.head
        if level < len(heights) - 1 and not (self._reusable(v, snap) and
                                             v.cache.last[1].mean() <= self.partial_max):
            snap.update(height=heights[level], final=False)
        else:  # the whole image at once, or only the pixels a new expression reaches
            level = len(heights) - 1
        return (key, level, heights, snap), None

    @staticmethod
    def _view(snap) -> tuple[Intrinsics, np.ndarray, torch.Tensor | None]:
        """A snapshot's intrinsics, camera and head twist (or None)."""
        head = None
        if snap["head"] is not None:
            head = torch.from_numpy(se3_log(snap["head"]).astype(np.float32))
        return view_intrinsics(snap["fov_y"], snap["aspect"], snap["height"]), snap["c2w"], head

    def _reusable(self, v: View, snap) -> bool:
        """Whether the view's last full image holds every pixel of `snap` that its
        expression does not reach."""
        return (v.cache is not None and self.model.expression.confined
                and v.cache.same_view(*self._view(snap))
                and v.cache.same_codes(*self._codes(snap)))

    def _codes(self, snap) -> tuple[torch.Tensor, torch.Tensor]:
        f = snap["filmed"]
        return (self.omega, self.phi) if f is None else (f.omega, f.phi)

    def _loop(self) -> None:
        while True:
            with self._cv:
                while True:
                    if self._stop:
                        return
                    job, wait = self._next_job()
                    if job is not None:
                        break
                    self._cv.wait(timeout=wait if wait is not None else 1.0)
            key, level, heights, snap = job
            try:
                frame = self._render(snap, level, cancellable=not snap["first"])
            except _Stale:
                continue
            except Exception as e:  # noqa: BLE001 - keep serving this state no more
                if not self.errors or repr(self.errors[-1]) != repr(e):
                    import traceback

                    traceback.print_exc()
                self.errors.append(e)
                del self.errors[:-10]
                self.error_views.append({k: snap[k] for k in ("c2w", "fov_y", "aspect",
                                                              "height", "mode")})
                del self.error_views[:-10]
                with self._cv:
                    v = self.views.get(key)
                    if v is not None:
                        v.shown_key, v.shown_level = snap["state"], len(heights) - 1
                if self.on_error is not None:
                    try:
                        self.on_error(key, e)
                    except Exception:  # noqa: BLE001
                        pass
                continue
            with self._cv:
                v = self.views.get(key)
                if v is None:
                    continue
                if (v.version, self.shared.version) != snap["state"] and not snap["first"]:
                    continue
                v.shown_key, v.shown_level = snap["state"], level
                v.renders += 1
                frame.count = v.renders
                if snap["mode"] == "Depth" and v.depth_range is None:
                    v.depth_range = frame.extras["depth_range"]
            try:
                self.display(key, frame)
            except Exception:  # noqa: BLE001 - a client that went away
                pass

    def _stale(self, snap) -> bool:
        v = self.views.get(snap["key"])
        return v is None or (v.version, self.shared.version) != snap["state"] or self._stop

    def _render(self, snap, level: int, cancellable: bool) -> Frame:
        t0 = time.perf_counter()
        intr, c2w, head = self._view(snap)
        # head pose: the masker poses the mesh, render_image moves the head's points
        mask = self.masker(intr, c2w, snap["expression"], snap["head"], snap["filmed"])
        expr = torch.from_numpy(snap["expression"])
        with self._cv:
            v = self.views.get(snap["key"])
        if v is not None and snap["final"] and self._reusable(v, snap):
            still = v.cache  # only the pixels a new expression reaches
        else:
            f = snap["filmed"]  # a frame's own ω is not baked, as in render
            settings = (own_codes_settings(self.settings) if f is not None and f.own_codes
                        else self.settings)
            still = StillCamera(self.model, intr, c2w, *self._codes(snap), head=head,
                                settings=settings)

        def check() -> None:
            if cancellable and self._stale(snap):
                raise _Stale

        out = still(expr, mask, band=self.band_rays, check=check)
        rgb, depth, rays = out["rgb"].numpy(), out["depth"].numpy(), still.rays
        if snap["final"] and v is not None:
            with self._cv:
                v.cache = still
        extras: dict = {"mask": mask, "rays": rays,
                        "filmed": None if snap["filmed"] is None else snap["filmed"].index,
                        "own_codes": snap["filmed"] is not None and snap["filmed"].own_codes}
        if snap["mode"] == "Depth":
            rng = snap["depth_range"]
            if rng is None:
                rng = (float(np.percentile(depth, 1)), float(np.percentile(depth, 99)))
            extras["depth_range"] = rng
            img = colorize_depth(depth, rng[0], rng[1])
        else:
            img = rgb
        return Frame(to_uint8(img), intr, time.perf_counter() - t0, level, snap["final"], 0,
                     snap["mode"], extras)

    def wait_idle(self, timeout: float = 30.0) -> bool:
        """Block until every view shows its final image of the current state (tests)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            with self._cv:
                s = self.shared
                top = len(self.levels(s.height, s.progressive)) - 1
                if self.views and all(v.shown_key == (v.version, s.version)
                                      and v.shown_level == top for v in self.views.values()):
                    return True
            time.sleep(0.02)
        return False
