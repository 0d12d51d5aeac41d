"""The viewer's panel in the browser: the View, Track, Head pose and Expression folders'
widgets (viser handles, `g_*`) and what each does when it changes.

One part of `Viewer` (viewer/app.py; why mixins: viewer/state.py): the callbacks change
what viewer/state.py holds, pause and show frames through viewer/player.py, and give the
RenderWorker (`self.worker`) the expression, mode and quality."""

from __future__ import annotations

import shlex

import numpy as np

from flamenerf.data.head_pose import HeadPoseKey, HeadRegion, control_transform
from flamenerf.errors import UserError
from flamenerf.rendering.edits import describe, parse_edits
from flamenerf.viewer.tracks import Track, tour_track


class ViewerPanels:
    """The widgets, made by `_build_gui` once the server runs (`Viewer.start`)."""

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

    def _sync_sliders(self, v: np.ndarray) -> None:
        if self.server is None:
            return
        with self.server.atomic():
            for s, x in zip(self.g_sliders, v):
                s.value = float(round(float(x), 4))

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
