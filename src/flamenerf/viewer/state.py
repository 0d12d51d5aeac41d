"""What the viewer shows, apart from its widgets: the run's dataset, its tracks, the
expressions' limits and the rules an expression is shown by.

One part of `Viewer` (viewer/app.py): its panels, player and pages read and change these
same attributes from the GUI's and the player's threads (tests and benchmarks do too), so
the parts are mixins of one object rather than objects that would copy them."""

from __future__ import annotations

import numpy as np

from flamenerf.data.companions import dataset_companions
from flamenerf.data.expression_range import training_range
from flamenerf.rendering.cameras import rig_from_dataset
from flamenerf.rendering.edits import apply_edits
from flamenerf.rendering.filmed import filmed_codes_error
from flamenerf.viewer.camera import home_camera
from flamenerf.viewer.mask import FaceMasker
from flamenerf.viewer.options import ViewerOptions
from flamenerf.viewer.tracks import (Track, dataset_tracks, load_track_file, slider_range,
                                     tour_track)


class ViewerState:
    """The dataset's side of the viewer. The checkboxes that change the rules (`g_within`,
    `g_companions`) are viewer/panels.py's; before the GUI exists the rules hold as their
    defaults say."""

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
        # it opens on frame 0 whole, as `Frame 0 expression` returns to it: its camera,
        # codes and expression (all 0 is a face a tracked clip seldom shows)
        self.opening = self.shown(self.frame0_expression)
        self._slid = False  # an expression slider moved since a track frame was shown
        self._edits: list = []  # the Edit box's (rendering/edits.py)
        self._edit_text = ""  # ... as typed, for the render command
        self._edited: dict[tuple, np.ndarray] = {}  # tracks' frames with them applied

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
