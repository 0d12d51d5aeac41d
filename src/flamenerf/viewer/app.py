"""The browser viewer (viser): a free camera, expression sliders, track playback, RGB /
depth, progressive quality. Rendering runs in `RenderWorker`'s thread; each finished image
becomes the browser's scene background."""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import io
import socket
import threading
import time

import numpy as np

from flamenerf.errors import UserError
from flamenerf.viewer.camera import HomeCamera, c2w_from_viser, home_camera
from flamenerf.viewer.mask import FaceMasker
from flamenerf.viewer.options import ViewerOptions
from flamenerf.viewer.renderer import Frame, RenderWorker
from flamenerf.viewer.tracks import (Track, dataset_tracks, load_track_file, slider_range,
                                     tour_track)
from flamenerf.data.companions import dataset_companions
from flamenerf.data.expression_range import training_range
from flamenerf.data.head_pose import HeadPoseKey, HeadRegion, control_transform
from flamenerf.gpu_kernels import fault_advice, first_line, gpu_faulted
from flamenerf.rendering.cameras import rig_from_dataset
from flamenerf.rendering.edits import apply_edits, describe, parse_edits
from flamenerf.rendering.filmed import FilmedClip, filmed_codes_error

STATUS_PREFIX = "Render"


def check_port_free(host: str, port: int) -> None:
    """A clear error now instead of viser silently moving to the next free port."""
    if not 0 < port < 65536:
        raise UserError(f"--port {port}: must be in 1..65535")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as e:
        raise UserError(f"--host {host}: cannot resolve it ({e.strerror})") from None
    family, _, _, _, addr = infos[0]
    s = socket.socket(family, socket.SOCK_STREAM)
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as asyncio's server does
        s.bind(addr)
    except OSError as e:
        if e.errno == errno.EADDRINUSE:
            raise UserError(f"port {port} on {host} is already in use "
                            f"(another viewer? pick a free one with --port)") from None
        if e.errno == errno.EADDRNOTAVAIL:
            raise UserError(f"--host {host}: not an address of this machine") from None
        if e.errno == errno.EACCES:
            raise UserError(f"port {port}: permission denied (use a port above 1023)") from None
        raise UserError(f"cannot listen on {host}:{port} ({e.strerror})") from None
    finally:
        s.close()


class Viewer:
    """`Viewer(run, opts).start()`; then `url`, `stop()`. Used by `flamenerf view`."""

    def __init__(self, run, opts: ViewerOptions):
        self.run = run
        self.opts = opts
        self.ds = run.dataset(opts.dataset)
        self.names = run.expression_names
        self.home = home_camera(self.ds)

        self.rig = rig_from_dataset(self.ds)  # where the capture filmed from (status line)
        self.masker = FaceMasker(self.ds, self.home.frame_position, run.model)
        self.lo, self.hi = slider_range(self.ds)
        fi = self.ds.frames[self.home.frame_position]
        self.frame0_expression = np.clip(fi.expression, self.lo, self.hi).astype(np.float32)
        self.neutral = np.clip(np.zeros(len(self.names), np.float32), self.lo, self.hi)

        same = self.ds.expression_names == self.names
        self.companions = dataset_companions(self.ds) if same else None
        self.range = training_range(self.ds, run.model.generic_controls) if same else None
        self.tracks: list[Track] = [load_track_file(p, self.names) for p in opts.track]
        tour = tour_track(self.ds, self.names, self.frame0_expression, self.companions)
        self.tracks += ([tour] if tour is not None else []) + dataset_tracks(self.ds)

        # tracks of the clip's own frames, which can play as filmed (their own codes)
        self.filmable = {t.name for t in self.tracks if t.clip and filmed_codes_error(
            run, self.ds, t.clip, opts.dataset) is None}
        self._filmed: dict[str, object] = {}  # their FilmedClips, made on first use
        h = opts.resolution or run.train_intrinsics(self.ds).h
        self.height = int(min(max(8, round(h / 8) * 8), opts.max_resolution))
        omega, phi = run.frame_codes(0)
        # it opens on frame 0 whole, as `Frame 0 expression` returns to it: its camera,
        # codes and expression (all 0 is a face a tracked clip seldom shows)
        self.opening = self.shown(self.frame0_expression)
        self.worker = RenderWorker(run.model, omega, phi, self.masker, self.opening,
                                   self._display, height=self.height, settle_s=opts.settle_s,
                                   on_error=self._render_failed)
        self.server = None
        self._clients: dict[int, object] = {}
        self._status: dict[int, object] = {}
        self._synced_after: dict[int, float] = {}
        self.sync_s = 10.0
        self._play = threading.Event()
        self._play_lock = threading.Lock()
        self._play_thread: threading.Thread | None = None
        self._play_t0 = 0.0
        self._play_frame0 = 0
        self._played: tuple[int, np.ndarray] | None = None  # the player's last frame and β
        self._slid = False  # an expression slider moved since a track frame was shown
        self._closing = False
        self._edits: list = []  # the Edit box's (rendering/edits.py)
        self._edit_text = ""  # ... as typed, for the render command
        self._edited: dict[tuple, np.ndarray] = {}  # tracks' frames with them applied

    # ------------------------------------------------------------------ lifecycle

    @property
    def url(self) -> str:
        host = self.opts.host
        shown = socket.gethostname() if host in ("0.0.0.0", "::", "") else host
        if ":" in shown:
            shown = f"[{shown}]"
        return f"http://{shown}:{self.port}"

    @property
    def port(self) -> int:
        return self.server.get_port() if self.server is not None else self.opts.port

    def start(self) -> "Viewer":
        import viser

        check_port_free(self.opts.host, self.opts.port)
        with contextlib.redirect_stdout(io.StringIO()) as banner:  # we print our own URL
            server = viser.ViserServer(host=self.opts.host, port=self.opts.port,
                                       label="flamenerf view", verbose=self.opts.verbose)
        if self.opts.verbose:
            print(banner.getvalue(), end="")
        if server.get_port() != self.opts.port:  # lost a race for the port
            server.stop()
            raise UserError(f"port {self.opts.port} on {self.opts.host} is already in use "
                            f"(pick a free one with --port)")
        self.server = server
        server.scene.set_up_direction(tuple(float(x) for x in self.home.up))
        server.scene.world_axes.visible = False
        cam = server.initial_camera
        cam.fov = self.home.fov_y
        cam.position = tuple(float(x) for x in self.home.position)
        cam.look_at = tuple(float(x) for x in self.home.look_at)
        cam.up = tuple(float(x) for x in self.home.up)
        self._build_gui()
        server.on_client_connect(self._on_connect)
        server.on_client_disconnect(self._on_disconnect)
        self.worker.start()
        self._play_thread = threading.Thread(target=self._player, name="flamenerf-play",
                                             daemon=True)
        self._play_thread.start()
        return self

    def stop(self) -> None:
        self._closing = True
        self._play.set()
        self.worker.stop()
        if self.server is not None:
            self.server.stop()

    # ------------------------------------------------------------------ GUI

    def _build_gui(self) -> None:
        gui = self.server.gui
        # the panel's order: the view, then the track (the clip, its frames, the Edit box: the
        # main way to change the clip) above the 52 sliders, which pushed it out of sight
        self.view_folder = gui.add_folder("View", order=0)
        with self.view_folder:
            self.g_mode = gui.add_dropdown("Show", ["RGB", "Depth"], initial_value="RGB",
                                           hint="Colour, or the expected depth (near = warm).")
            self.g_height = gui.add_slider(
                "Resolution", min=8, max=self.opts.max_resolution, step=8,
                initial_value=self.height,
                hint="Height in pixels of the refined image (the window's aspect ratio "
                     "sets the width).")
            self.g_prog = gui.add_checkbox(
                "Progressive", self.opts.progressive,
                hint="Render at 1/4 resolution while the camera moves (at 1/2 after any "
                     "other change), then refine to full once it is still.")
            self.g_reset_cam = gui.add_button("Reset camera", hint="Back to frame 0's camera.")
        self.expr_folder = gui.add_folder("Expression", order=3)
        with self.expr_folder:
            self.g_neutral = gui.add_button(
                "Reset to neutral", hint="Every control to 0 (no expression); within the "
                "clip's range, to the lowest value it shows.")
            self.g_frame0 = gui.add_button(
                "Frame 0 expression", hint="The capture's first frame: its expression, and "
                "its look and head again after a frame shown As filmed.")
            # options that exist only for datasets that have what they use; ticked by default
            self.g_within, self.g_companions = (
                gui.add_checkbox(label, True, hint=hint) if present else None
                for present, label, hint in (
                    (self.range is not None, "Stay within the clip's range",
                     "A slider stops at the largest (and smallest) value the training frames "
                     "show: beyond it the model has learnt nothing and the face breaks into "
                     "patches. Off: any value, as given."),
                    (self.companions is not None, "Move companions",
                     "A slider also moves the controls the tracker reads with it (same part "
                     "of the face and side; e.g. eyeBlinkLeft brings eyeLookDownLeft): "
                     "without them a blink alone barely closes the eye.")))
            self.g_sliders = []
            step = 0.01 if self.hi - self.lo <= 2 else 0.05
            for j, name in enumerate(self.names):
                s = gui.add_slider(name, min=self.lo, max=self.hi, step=step,
                                   initial_value=float(round(float(self.opening[j]), 4)))
                s.on_update(self._slider_cb(j))
                self.g_sliders.append(s)
        self.g_head: list = []
        if getattr(self.run.model, "follows_head", False):  # trained with head poses
            self.head_folder = gui.add_folder("Head pose", order=2)
            with self.head_folder:
                self.g_head_reset = gui.add_button(
                    "Frame 0 head pose", hint="Back to the capture's first pose (a frame "
                    "shown As filmed: to that frame's own).")
                for name, lim in (("yaw", 40), ("pitch", 25), ("roll", 25)):
                    s = gui.add_slider(name, min=-lim, max=lim, step=1, initial_value=0,
                                       hint=f"Head {name} in degrees, relative to frame 0's "
                                            "pose (independent of the camera).")
                    s.on_update(lambda e: self._head_changed())
                    self.g_head.append(s)
            self.g_head_reset.on_click(lambda e: self.set_head_pose(0, 0, 0))
        self.track_folder = gui.add_folder("Track", order=1)
        with self.track_folder:
            names = [t.name for t in self.tracks] or ["(none)"]
            self.g_track = gui.add_dropdown("Track", names, initial_value=names[0])
            self.g_play = gui.add_button("Play", disabled=not self.tracks)
            n = self.tracks[0].num_frames if self.tracks else 1
            self.g_frame = gui.add_slider("Frame", min=0, max=max(n - 1, 1), step=1,
                                          initial_value=0, disabled=not self.tracks)
            self.g_loop = gui.add_checkbox("Loop", True)
            self.g_filmed = None
            if self.filmable:
                self.g_filmed = gui.add_checkbox(
                    "As filmed", True,
                    hint="The capture's tracks show each frame with its own head motion, "
                    "look and face mesh, as `render --split capture` does (the clip itself, "
                    "with the expression the sliders or the Edit box give). Off: frame 0's "
                    "codes (its look), each frame's head and mesh: `--codes first`.",
                    disabled=names[0] not in self.filmable)
            self.g_frame_cam = None
            if any(t.clip for t in self.tracks):
                self.g_frame_cam = gui.add_button(
                    "Camera of this frame", hint="The view from where the clip filmed the "
                    "frame shown (tracks of the clip's frames); Reset camera: frame 0's.")
            self.g_edit = gui.add_text(
                "Edit", "", hint="Changes every frame of the track, as `render --edit` does: "
                "e.g. mouthSmile+=0.3 (both sides: the capture smiling more, as the clip "
                "smiles), jawOpen*=0 (mouth still), all*=1.5 (every control exaggerated). "
                "Empty: the track as it is. A model knows the expressions its clip shows.")
            self.g_edit_note = gui.add_markdown("")
            self.g_command = gui.add_markdown(self.command_markdown())

        self.g_mode.on_update(lambda e: self.worker.set_mode(e.target.value))
        self.g_height.on_update(lambda e: self.worker.set_quality(height=e.target.value))
        self.g_prog.on_update(lambda e: self.worker.set_quality(progressive=e.target.value))
        self.g_reset_cam.on_click(lambda e: e.client is not None and self.reset_camera(e.client))
        self.g_neutral.on_click(lambda e: self.set_expression(self.neutral))
        self.g_frame0.on_click(lambda e: self.show_frame0())
        self.g_track.on_update(self._on_track_change)
        self.g_play.on_click(lambda e: self.toggle_play())
        self.g_frame.on_update(self._on_frame_slider)
        self.g_edit.on_update(lambda e: self.set_edit(e.target.value))
        if self.g_filmed is not None:
            self.g_filmed.on_update(lambda e: self._show_current_frame())
        if self.g_frame_cam is not None:
            self.g_frame_cam.on_click(lambda e: self.frame_camera())
        if self.g_filmed is not None:
            self.g_filmed.on_update(lambda e: self._update_command())
        if self.g_within is not None:
            self.g_within.on_update(lambda e: self._edit_boxes_changed())
        if self.g_companions is not None:
            self.g_companions.on_update(lambda e: self._companions_changed())

    def set_head_pose(self, yaw: float, pitch: float, roll: float) -> None:
        """Turn the head (degrees relative to frame 0's pose) and move the sliders there."""
        for s, v in zip(self.g_head, (yaw, pitch, roll)):
            s.value = float(v)
        self._head_changed()

    def _head_changed(self) -> None:
        self._update_command()
        yaw, pitch, roll = (float(s.value) for s in self.g_head)
        if yaw == pitch == roll == 0:
            self.worker.set_head(None)
            return
        region = HeadRegion.from_dict(self.run.model.init_args["head_region"])
        self.worker.set_head(control_transform(HeadPoseKey(yaw, pitch, roll), region))

    def _slider_cb(self, j: int):
        def cb(event) -> None:
            if event.client is None:  # our own update (reset, playback)
                return
            self.pause()
            value = float(event.target.value)
            if not self._slid:  # the view is no longer the track's frame: Render it says so
                self._slid = True
                self._update_command()
            if self.within():
                value = float(np.clip(value, self.range.lo[j], self.range.hi[j]))
            if self.g_companions is not None and self.g_companions.value \
                    and self.companions.of(self.names[j]):
                self.set_expression(self.companions.complete(self.worker.expression(),
                                                             {j: value}))
            elif value != float(event.target.value):  # stopped at the range: show where
                self.set_expression(np.where(np.arange(len(self.names)) == j, value,
                                             self.worker.expression()))
            else:
                self.worker.set_expression_value(j, value)
        return cb

    def set_expression(self, values: np.ndarray, pause: bool = True) -> None:
        """Show this expression and move the sliders to it."""
        if pause:
            self.pause()
        v = self.shown(values)
        self.worker.set_expression(v)
        self._sync_sliders(v)

    def show_frame0(self) -> None:
        """Frame 0's expression, and frame 0's codes and head where a frame was shown as
        filmed: the view the viewer opens with."""
        self.pause()
        v = self.shown(self.frame0_expression)
        self.worker.set_filmed(None, v)
        self._sync_sliders(v)

    def shown(self, values: np.ndarray, clamp: bool = True) -> np.ndarray:
        """An expression as the viewer shows it: within the sliders' range, and with
        `clamp` the training frames' where that is kept (`within`)."""
        v = np.clip(np.asarray(values, np.float32), self.lo, self.hi)
        return self.range.clamp(v) if clamp and self.within() else v

    def within(self) -> bool:
        """Whether expressions are kept within the training frames' range (the checkbox;
        on by default, and before the GUI exists)."""
        if self.range is None:
            return False
        box = getattr(self, "g_within", None)
        return box is None or bool(box.value)

    def _sync_sliders(self, v: np.ndarray) -> None:
        if self.server is None:
            return
        with self.server.atomic():
            for s, x in zip(self.g_sliders, v):
                s.value = float(round(float(x), 4))

    def reset_camera(self, client, to: HomeCamera | None = None) -> None:
        """A page's camera to frame 0's (or `to`)."""
        to = self.home if to is None else to
        cam = client.camera
        with client.atomic():
            cam.fov = to.fov_y
            cam.up_direction = tuple(float(x) for x in to.up)
            cam.position = tuple(float(x) for x in to.position)
            cam.look_at = tuple(float(x) for x in to.look_at)

    def frame_camera(self) -> HomeCamera | None:
        """Every page's camera to the one the track's current frame was filmed from (a
        track of the clip's frames; None and nothing moved for another)."""
        t = self.current_track()
        if t is None or not t.clip:
            return None
        k = int(min(max(self.g_frame.value, 0), t.num_frames - 1))
        to = home_camera(self.ds, t.clip[k].position)
        for client in list(self._clients.values()):
            self.reset_camera(client, to)
        return to

    # ------------------------------------------------------------------ playback

    def current_track(self) -> Track | None:
        for t in self.tracks:
            if t.name == self.g_track.value:
                return t
        return None

    def set_edit(self, text: str) -> None:
        """Edit every track's frames (`render --edit`'s items; empty: none); a mistyped
        edit is shown under the box and leaves the last good one in force."""
        items = [text.replace(";", ",")] if text.strip() else []
        try:
            self._edits = parse_edits(items, self.names) if items else []
        except UserError as e:
            self.g_edit_note.content = f"*{e}*"
            return
        self._edited.clear()
        self.g_edit_note.content = f"editing {describe(items)}" if self._edits else ""
        self._edit_text = items[0] if items else ""
        self._update_command()
        self._show_current_frame()

    def render_command(self) -> str:
        """The `flamenerf render` command of the track shown, as the Track and Expression
        boxes set it (the video of it, from the source's own cameras for a split, frame 0's
        otherwise; the head sliders' turn is not in it: `command_markdown`); '' without a
        track."""
        import shlex

        t = self.current_track()
        if t is None or not t.render_args:
            return ""
        args = ["flamenerf", "render", str(self.run.run_dir), *t.render_args]
        if self.opts.dataset is not None:
            args += ["--dataset", str(self.opts.dataset)]
        if t.name in self.filmable and self.g_filmed is not None and not self.g_filmed.value:
            args += ["--codes", "first"]
        if self._edit_text:
            args += ["--edit", self._edit_text]
        if self.g_companions is not None and not self.g_companions.value:
            args.append("--no-companions")
        if self.range is not None and not self.within():
            args.append("--extrapolate")
        return shlex.join(args)

    def _companions_changed(self) -> None:
        """The tour again with or without companions (as render's with --no-companions),
        then as for the range box (`_edit_boxes_changed`)."""
        comp = self.companions if self.g_companions.value else None
        for t in self.tracks:
            if t.render_args == ("--expressions", "tour"):
                tour = tour_track(self.ds, self.names, self.frame0_expression, comp)
                if tour is not None:
                    t.frames = tour.frames  # the next frame shown (or played) is the new tour's
                self._edited.clear()
        self._edit_boxes_changed()

    def _edit_boxes_changed(self) -> None:
        """The command again; with an edit in force, the track's frame again, edited as
        the boxes now say (the picture kept the old edit while the command changed).
        Without one, the expression shown stays until a track frame is shown."""
        self._update_command()
        if self._edits:
            self._show_current_frame()

    def command_markdown(self) -> str:
        cmd = self.render_command()
        if not cmd:
            return ""
        turned = any(float(s.value) != 0 for s in self.g_head)
        # render's --head-pose eases through keyframes; a held turn is a .json file
        left = [what for what, out in (("the head sliders' turn", turned),
                                       ("the expression sliders' change", self._slid))
                if out]
        return f"Render it: `{cmd}`" + (f" ({' and '.join(left)} not in it: give an edit "
                                        "for an expression, docs/head_pose.md for a turn)"
                                        if left else "")

    def _update_command(self) -> None:
        if getattr(self, "g_command", None) is not None:
            self.g_command.content = self.command_markdown()

    def filmed_clip(self, t: Track):
        """The track's frames (rendering/filmed.FilmedClip) with their own codes where they
        have them (the capture's), frame 0's otherwise (a re-animation split's, as `render
        --split` shows them: each frame's own head pose and mesh); None: not a dataset's
        frames."""
        if not t.clip:
            return None
        clip = self._filmed.get(t.name)
        if clip is None:
            codes = None if t.name in self.filmable else (self.worker.omega, self.worker.phi)
            clip = self._filmed[t.name] = FilmedClip(self.run, self.ds, t.clip, codes)
        return clip

    def show_track_frame(self, t: Track, k: int, sync: bool = True) -> np.ndarray:
        """Show frame k of track t (edited; as filmed where it is the clip's) and, with
        `sync`, move the sliders and the frame slider there; -> the expression shown."""
        # as `render` does: the clip's own expressions as they are (an edit of them is
        # clamped by `track_frames`), anything else clamped to the training range
        v = self.shown(self.track_frames(t)[k], clamp=t.clip is None)
        clip = self.filmed_clip(t)
        frame = None if clip is None else clip.frame(k)
        if frame is not None and frame.own_codes and not self.g_filmed.value:
            # as `render --codes first`
            frame = dataclasses.replace(frame, omega=self.worker.omega, phi=self.worker.phi,
                                        own_codes=False)
        self.worker.set_filmed(frame, v)
        if self._slid:
            self._slid = False
            self._update_command()
        if sync:
            self._sync_sliders(v)
            if self.server is not None and int(self.g_frame.value) != k:
                self.g_frame.value = int(k)
        return v

    def _show_current_frame(self) -> None:
        t = self.current_track()
        if t is not None:
            self.show_track_frame(t, int(min(max(self.g_frame.value, 0), t.num_frames - 1)))

    def track_frames(self, t: Track) -> np.ndarray:
        """A track's expressions (T, E) with the edit applied as `render --edit` applies it
        (companions and the clip's range as the checkboxes say). Called from the GUI and
        the playback threads: the edit is part of the cache's key, and the result is the
        caller's even when the other thread clears the cache meanwhile."""
        edits = self._edits
        if not edits:
            return t.frames
        comp = (self.companions if self.g_companions is not None and self.g_companions.value
                else None)
        limits = self.range if self.within() else None
        key = (t.name, tuple(edits), comp is not None, limits is not None)
        v = self._edited.get(key)
        if v is None:
            # as render: a source that is not the clip's own frames is clamped first,
            # then edited (the edit clamped on its own)
            src = t.frames if t.clip or limits is None else limits.clamp(t.frames)
            v = apply_edits(src, edits, comp, limits)[0]
            self._edited[key] = v
        return v

    def _on_track_change(self, event) -> None:
        self.pause()
        t = self.current_track()
        if t is None:
            return
        self.g_frame.max = max(t.num_frames - 1, 1)
        self.g_frame.value = 0
        if self.g_filmed is not None:  # the box means nothing for another track's frames
            self.g_filmed.disabled = t.name not in self.filmable
        self.show_track_frame(t, 0)
        self._update_command()

    def _on_frame_slider(self, event) -> None:
        if event.client is None:
            return
        self.pause()
        t = self.current_track()
        if t is not None:
            self.show_track_frame(t, int(min(max(event.target.value, 0), t.num_frames - 1)))

    def toggle_play(self) -> None:
        if self._play.is_set():
            self.pause(show_last=True)
        else:
            self.play()

    def play(self) -> None:
        t = self.current_track()
        if t is None:
            return
        with self._play_lock:
            start = int(self.g_frame.value)
            if start >= t.num_frames - 1:
                start = 0
            self._play_frame0 = start
            self._play_t0 = time.monotonic()
            self._played = None
            self._play.set()
            self.g_play.label = "Pause"

    def pause(self, show_last: bool = False) -> None:
        """Stop playback. `show_last` (the Pause button): the Frame slider and the
        expression sliders to the frame last shown, which they follow only a few times a
        second while playing (they stayed a frame or two behind the picture). A slider's
        or the frame slider's own pause leaves them: the user's value is about to apply."""
        with self._play_lock:
            if self._play.is_set() and not self._closing:
                self._play.clear()
                self.g_play.label = "Play"
            played = self._played if show_last else None
        if played is not None:
            self._sync_sliders(played[1])
            self.g_frame.value = int(played[0])

    @property
    def playing(self) -> bool:
        return self._play.is_set()

    def _player(self) -> None:
        last_sync = 0.0
        while not self._closing:
            if not self._play.wait(timeout=0.5) or self._closing:
                continue
            t = self.current_track()
            if t is None:
                self.pause()
                continue
            self.filmed_clip(t)  # made before the lock: pause() does not wait for it
            # under the lock pause() takes, so that a frame decided before a pause (or a
            # change of track, which pauses) is not shown after it
            ended = False  # the track ran out (no loop): the player stopped itself
            with self._play_lock:
                if not self._play.is_set() or t is not self.current_track():
                    continue
                k, ended = t.frame_at(self._play_frame0, time.monotonic() - self._play_t0,
                                      bool(self.g_loop.value))
                if ended:
                    self._play.clear()
                    self.g_play.label = "Play"
                v = self.show_track_frame(t, k, sync=False)
                self._played = (k, v)
            now = time.monotonic()
            # the 52 sliders follow at a few Hz; the image follows every frame. Not after
            # a pause by a slider or the frame slider (the user's value is applying: the
            # Pause button syncs itself, `pause(show_last=True)`)
            if ended or (self._play.is_set() and now - last_sync > 0.2):
                self._sync_sliders(v)
                self.g_frame.value = int(k)
                last_sync = now
            time.sleep(max(0.005, 1.0 / min(t.fps, 60.0)))

    # ------------------------------------------------------------------ clients

    def _on_connect(self, client) -> None:
        self._clients[client.client_id] = client
        with self.view_folder:
            status = client.gui.add_markdown(f"{STATUS_PREFIX}: waiting for the first image",
                                             order=-1.0)
        self._status[client.client_id] = status
        # A new page reports three.js's default camera before the initial one applies:
        # put it at frame 0's camera, render that view right away, and ignore the page's
        # camera until it reports that pose (or for at most `sync_s`).
        self._synced_after[client.client_id] = time.monotonic() + self.sync_s

        def on_camera(cam) -> None:
            self._camera_changed(client)

        client.camera.on_update(on_camera)
        self.reset_camera(client)
        try:
            aspect = float(client.camera.aspect)
        except (AssertionError, ZeroDivisionError):
            aspect = self.ds.intrinsics.w / self.ds.intrinsics.h
        self.worker.set_camera(client.client_id, self.home.c2w, self.home.fov_y, aspect)

    def _camera_changed(self, client) -> None:
        cam = client.camera
        try:
            aspect = float(cam.aspect)
            if not np.isfinite(aspect) or aspect <= 0:
                return
            c2w = c2w_from_viser(cam.wxyz, cam.position)
            fov = float(cam.fov)
        except (AssertionError, ZeroDivisionError):  # no camera message yet
            return
        until = self._synced_after.get(client.client_id)
        if until is not None:
            at_home = (np.allclose(c2w, self.home.c2w, atol=1e-4)
                       and abs(fov - self.home.fov_y) < 1e-4)
            if not at_home and time.monotonic() < until:
                return  # still the page's default camera
            self._synced_after.pop(client.client_id, None)
        self.worker.set_camera(client.client_id, c2w, fov, aspect)

    def capture_note(self, client) -> str:
        """' · outside the capture (N cm)' when the browser's camera stands where no training
        camera filmed from (views there extrapolate: rendering/cameras.py), else ''."""
        try:
            eye = np.asarray(client.camera.position, np.float64)
        except (AssertionError, AttributeError):
            return ""
        if not np.all(np.isfinite(eye)) or self.rig.near_capture(eye[None])[0]:
            return ""
        d = np.linalg.norm(self.rig.captured_eyes() - eye, axis=1).min()
        return f" · outside the capture ({100 * d:.0f} cm from its cameras)"

    def _on_disconnect(self, client) -> None:
        self._clients.pop(client.client_id, None)
        self._status.pop(client.client_id, None)
        self._synced_after.pop(client.client_id, None)
        self.worker.remove_view(client.client_id)

    def _render_failed(self, key, err: BaseException) -> None:
        status = self._status.get(key)
        if status is not None:
            msg = first_line(err)[:160]
            # a lost CUDA context fails every image after it: say how to get going again
            after = ("the GPU cannot render in this process again: "
                     + fault_advice("restart the viewer") if gpu_faulted(err)
                     else "see the terminal")
            status.content = (f"{STATUS_PREFIX}: failed ({type(err).__name__}: {msg}); "
                              f"{after}")

    def _display(self, key, frame: Frame) -> None:
        client = self._clients.get(key)
        if client is None:
            return
        fmt = "png" if frame.final else "jpeg"
        client.scene.set_background_image(frame.image, format=fmt, jpeg_quality=90)
        status = self._status.get(key)
        if status is not None:
            state = "final" if frame.final else f"preview {frame.level + 1}"
            if frame.extras.get("filmed") is not None:
                state += f" · frame {frame.extras['filmed']} " + (
                    "as filmed" if frame.extras.get("own_codes") else "with frame 0's codes")
            status.content = (f"{STATUS_PREFIX}: {frame.seconds * 1000:.0f} ms · "
                              f"{frame.intr.w}×{frame.intr.h} px · {state} · "
                              f"#{frame.count}{self.capture_note(client)}")
        self.last_frame = frame
