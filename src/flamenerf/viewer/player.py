"""Tracks played in the viewer: a track's frame shown (edited; as filmed where it is the
clip's), and the player's thread, which shows the frames in time and keeps the sliders
following.

One part of `Viewer` (viewer/app.py; why mixins: viewer/state.py): the Track folder's
widgets (viewer/panels.py) start, pause and move it; the frames go to the RenderWorker
(`self.worker`)."""

from __future__ import annotations

import dataclasses
import threading
import time

import numpy as np

from flamenerf.rendering.filmed import FilmedClip
from flamenerf.viewer.tracks import Track


class ViewerPlayer:
    """Playback, under `_play_lock`: a frame decided before a pause is not shown after it."""

    def _init_player(self) -> None:
        self._play = threading.Event()
        self._play_lock = threading.Lock()
        self._play_thread: threading.Thread | None = None
        self._play_t0 = 0.0
        self._play_frame0 = 0
        self._played: tuple[int, np.ndarray] | None = None  # the player's last frame and β
        self._closing = False

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
