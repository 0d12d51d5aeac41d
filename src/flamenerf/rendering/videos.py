"""The re-animation videos of `flamenerf render`: options, the expression source, the camera
path, the output paths, then rendering and writing (result, depth, side by side).

`render_videos(opts)` is the whole job; the pieces are separate so that each choice (which
source, which cameras, how many frames) can be read and tested on its own.
"""

from __future__ import annotations

# imported to build `flamenerf --help` (RenderOptions): what only rendering needs (the run,
# the renderer, edits, filmed clips, frame folders) is imported inside the functions that use it

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import tyro

from flamenerf.data.dataset import Dataset, Intrinsics, reference_position
from flamenerf.data.head_pose import canonical_vertices, posed_vertices
from flamenerf.errors import UserError
from flamenerf.model.inference import FAST, REFERENCE, RenderSettings
from flamenerf.rendering import cameras as C
from flamenerf.rendering import expressions as X
from flamenerf.rendering import soundtrack as S
from flamenerf.data.video import VideoWriter, check_fps
from flamenerf.runtime import set_threads
from flamenerf.data import head_pose as H
from flamenerf.data.companions import dataset_companions
from flamenerf.data.expression_range import ExpressionRange, training_expressions, training_range
from flamenerf.geometry import se3_log
from flamenerf.images import (expression_panel, resize_to_height, text_strip, text_width,
                              titled_row, vstack)
from flamenerf.outdir import folders_kept_only_on_success, writable_dir

MAX_FRAMES = 1_000_000


@dataclass
class RenderOptions:
    """Options of `flamenerf render` (its flags, same names; the help text below is
    their --help).

    Attributes:
        run: Run directory (made by `flamenerf train`).
        out: Output video (default: RUN/renders/SOURCE_CAMERA.mp4; with --edit
            SOURCE_EDIT_CAMERA.mp4, e.g. capture_mouthSmile+0.3_split.mp4).
        expressions: An expression file, name=value[,name=value] keyframes (a pair's
            stem, e.g. mouthSmile, sets both sides), or `tour` (each control the training
            frames show, in turn). Repeated, its items add up.
        split: Take expressions, cameras and face meshes from this dataset split (with
            `capture`: the clip as filmed, every frame in order).
        drive: Track the expressions of this driving video.
        edit: Change controls in every frame of the source, e.g. `--split capture --edit
            mouthSmileLeft+=0.3,mouthSmileRight+=0.3`: `name=V` sets a control,
            items `name+=D` / `name-=D` raise or lower it, `name*=S` scales it (0 stills
            it, 1.5 exaggerates); a name `all` is every control no other item names, as
            in `all*=0,jawOpen*=1` (only the jaw moves); a pair's stem moves both sides,
            as in `mouthSmile+=0.3`. Companions move
            along and the edited controls are clamped to the training range in each frame
            as for keyframes (a note says in how many). Repeated, its items add up.
        edit_during: Apply --edit only between START:END seconds of the video as rendered,
            at its --fps (as in 2:4.5; the end left out: to the end, the start: from the
            start), eased in and out over 0.3 s inside them; the other frames as the source
            has them.
        codes: Each frame's deformation and appearance codes: own (with --split of
            capture frames: a training frame's trained codes, a held-out frame's between
            its neighbours', so the clip's own small motions and light stay), first (the
            codes of frame 0 for every frame, as every other source renders), or auto: own
            with a split of capture frames of the run's own dataset (or of the one given
            with --dataset where the run's has moved), else first.
        camera: static, orbit, spiral, dolly, split (a --split's own cameras), a JSON
            file of poses, or auto (split with --split, else static).
        head_pose: Head pose relative to frame 0's, independent of --camera: `drive` (the
            driving video's head turns, with --drive), `take` (a Live Link Face take's
            HeadYaw/HeadPitch/HeadRoll, with --expressions take.csv), keyframes like
            `yaw=20,pitch=-5` in degrees (roll too; x/y/z in metres), eased through like
            expression keyframes, or a .json list of such objects (one per frame). Needs
            a run trained with head poses. Default: a split's own head poses, else
            frame 0's.
        frames: Number of frames when the source does not fix it (keyframes, a tour, the
            held expression; a named camera path follows). Unset: 60, a tour 24 a control.
        fps: Frames per second (default: the source's; a split of frames outside the
            capture, such as reanimate, 4; else 30). With --drive the video
            is sampled at this rate.
        size: Render width in pixels (default: the run's training width).
        amplitude: Path amplitude: degrees for orbit/spiral, a fraction of the distance
            for dolly (default: from the training cameras; dolly 0.2).
        expression_base: What keyframes start from and return to, and which controls
            they leave unchanged: frame 0's expression (reference) or all zeros.
        depth: Also write a colour-mapped depth video.
        side_by_side: Also write driving | result | depth, each under its title (the
            filmed frame with --split, the expression as bars when there is no driving
            image).
        dataset: Dataset with the face mesh and cameras (default: the run's own).
        dilate_px: Dilation of the prior's mask in dataset pixels (default: the
            dataset's own, estimated from its masks where it does not store one).
        max_frames: Render at most this many frames (with --drive: this many spread over
            the clip).
        relative: With --drive on a dataset of the same expression model, transfer
            expressions relative to each subject's neutral face.
        match_range: With --drive and --relative: also scale each control's motion so that
            the furthest the driver takes it (its 99th percentile) lands on the furthest the
            subject's own frames take it (a broad smile gives the subject's broadest, a
            small jaw the subject's own reach); controls either face moves by less than 0.1
            are left as transferred.
        gain: With --drive: scale the named controls' motion from the subject's neutral,
            as in `jawOpen=1.5,mouthSmile=0.5` (a pair's stem sets both sides; 0 to 10).
        companions: Keyframes, the tour and --edit also move the controls the tracker
            reads with the named ones (same part of the face and side, by a regression on
            the training frames:
            e.g. eyeBlinkLeft brings eyeLookDownLeft, without which the eye barely
            closes). ARKit-named datasets from `preprocess`; others have none.
        extrapolate: Render keyframes, files, driving videos and edits as given. By default
            each control is clamped to the range the training frames cover (with a note): past
            it the model has learnt nothing, and a control pushed far beyond (a smile at 1
            on a clip whose largest is 0.3) breaks the face into patches.
        landmarker: face_landmarker.task for --drive (default: as for preprocess).
        chunk: Rays per forward pass (0: the renderer's choice, `RenderSettings.chunk`;
            lower it if memory runs out).
        captured_directions: Colour at cameras beyond the capture as the nearest captured
            view saw it (a ray more than 2 degrees from every captured view is turned back
            to 2 degrees; data/captured_views.py): outside the captured range the view
            direction's encoding extrapolates (pale faces, lips without their red). Off:
            at the direction asked.
        sound: Carry the source's sound in the video and the side by side: with --split
            capture of a clip played at its own pace, the clip's (from its first frame's
            time, where the video `preprocess` read is still there); with --drive, the
            driving video's, in step with its frames (the frame before a gap without a
            face held for the gap's time).
        audio: Lay this sound file (wav, mp3, m4a, or a video's sound) under the render,
            from its start, cut or padded with silence to the video's length (a note says
            which); it replaces the source's sound.
        frames_dir: Also write the result as numbered PNG frames in this folder (one per
            frame of the video, at its rate), with frames.json (rate, count, size) and the
            sound as sound.wav where the video has one: for editing further without the
            video codec's loss.
        baked: Render the run's bake (RUN/baked.npz, made by `flamenerf bake`) instead of
            the NeRF: splats drawn as the web export draws them, frame 0's codes and head
            pose, in milliseconds a frame.
        exact: Render with the training forward pass (what `flamenerf eval`'s PSNR uses)
            instead of the inference path, which is several times faster on a CPU and
            within 0.05 dB of it on the built-in scene (docs/bench/render.md).
        device: `auto` (CUDA when present), `cpu` or `cuda`.
        threads: CPU threads for torch (0 = default).
        overwrite: Replace existing output videos.
    """

    run: Annotated[Path, tyro.conf.Positional]
    out: Path | None = None
    expressions: list[str] | None = None
    split: str | None = None
    drive: Path | None = None
    edit: list[str] | None = None
    edit_during: str | None = None
    codes: Literal["auto", "first", "own"] = "auto"
    camera: str = "auto"
    head_pose: list[str] | None = None
    frames: int | None = None
    fps: float | None = None
    size: int | None = None
    amplitude: float | None = None
    expression_base: Literal["reference", "zero"] = "reference"
    depth: bool = False
    side_by_side: bool = False
    dataset: Path | None = None
    dilate_px: int | None = None
    max_frames: int | None = None
    relative: bool = True
    match_range: bool = False
    gain: list[str] | None = None
    companions: bool = True
    extrapolate: bool = False
    landmarker: Path | None = None
    chunk: int = 0
    captured_directions: bool = True
    sound: bool = True
    audio: Path | None = None
    frames_dir: Path | None = None
    baked: bool = False
    exact: bool = False
    device: str = "auto"
    threads: int = 0
    overwrite: bool = False

    def check(self) -> None:
        """One-line errors for options that cannot work, before anything is loaded."""
        given = [n for n, v in (("--expressions", self.expressions), ("--split", self.split),
                                ("--drive", self.drive)) if v]
        if len(given) > 1:
            raise UserError(f"give one expression source, not {' and '.join(given)}")
        if self.frames is not None and self.frames < 1:
            raise UserError(f"--frames {self.frames}: must be at least 1")
        if self.max_frames is not None and self.max_frames < 1:
            raise UserError(f"--max-frames {self.max_frames}: must be at least 1")
        if self.threads < 0:
            set_threads(self.threads)  # its one-line error, before anything is loaded
        if self.chunk < 0:
            raise UserError(f"--chunk {self.chunk}: must be positive (or 0: automatic)")
        if self.fps is not None:
            check_fps(self.fps, "--fps")
        if self.frames is not None and self.frames > MAX_FRAMES:
            raise UserError(f"--frames {self.frames}: at most {MAX_FRAMES} (a video of "
                            f"{MAX_FRAMES // 30 // 3600} hours at 30 fps)")
        if self.dilate_px is not None and self.dilate_px < 0:
            raise UserError(f"--dilate-px {self.dilate_px}: must be >= 0")
        if self.edit_during is not None:
            from flamenerf.rendering.edits import EditWindow

            if not self.edit:
                raise UserError("--edit-during: limits an --edit in time; give one")
            EditWindow.parse(self.edit_during)  # its one-line error, before anything loads
        if self.audio is not None:
            if not self.sound:
                raise UserError("--audio: lays a sound under the video; --no-sound leaves "
                                "sound out: give one of them")
            S.check_audio(self.audio)  # its one-line error, before anything is loaded
        if (self.gain or self.match_range) and not self.drive:
            raise UserError(f"--{'gain' if self.gain else 'match-range'}: scales a driving "
                            "video's expressions; give one with --drive")
        if self.baked and self.head_pose:
            raise UserError("--baked: a bake holds the head at frame 0's pose; --head-pose "
                            "needs the run itself (leave out --baked)")
        if self.baked and self.exact:
            raise UserError("--baked and --exact: give one (--exact is the NeRF's training "
                            "forward, --baked its bake)")
        if self.baked and self.codes == "own":
            raise UserError("--baked: a bake has frame 0's codes only; --codes own needs the "
                            "run itself (leave out --baked)")
        if self.codes == "own" and not self.split:
            raise UserError("--codes own: takes each frame's codes from a split of the run's "
                            "dataset; give --split (e.g. --split capture)")


@dataclass
class RenderSummary:
    paths: dict[str, Path]  # "rgb", and "depth" / "sbs" when asked for
    frames: int
    width: int
    height: int
    fps: float
    source: str  # the expression source's label
    camera: str  # the camera path's label
    dilate_px: int

    def describe(self) -> str:
        return (f"wrote {', '.join(str(p) for p in self.paths.values())}: {self.frames} "
                f"frames at {self.width}x{self.height}, {self.fps:g} fps (expressions: "
                f"{self.source}; camera: {self.camera}; prior mask dilation "
                f"{self.dilate_px} px)")


@dataclass
class RenderPlan:
    """What `render` draws, every choice made: the run, its dataset and the render size;
    per frame the camera (T, 4, 4), the expression (T, E), the prior's face mesh (T, V, 3),
    the head's twist (T, 6) or None and the codes ω (T, code_dim), φ (T, appearance_dim)
    or None (frame 0's); the videos to write and their frame rate."""

    run: Any
    ds: Dataset
    intr: Intrinsics
    poses: np.ndarray
    values: np.ndarray
    verts: np.ndarray
    heads: np.ndarray | None
    dilate_px: int
    settings: RenderSettings
    fps: float
    paths: dict[str, Path]
    seq: X.ExpressionSequence
    label: str  # the expression source's, the edit's `file_tag` added
    camera: str
    codes: tuple[Any, Any] | None = None
    edited: np.ndarray | None = None  # (T,) bool: the frames --edit changed; None: no edit
    sound: Any = None  # data/video.Soundtrack: for the video and side by side (soundtrack.py)
    shown: np.ndarray | None = None  # (T,) int: times each frame is shown (clip_pace); None: once
    frames_dir: Path | None = None  # --frames-dir: the result as PNG frames too
    caption: str | None = None  # under the side by side: what the clip cannot give
    baked: Any = None  # splats.avatar.BakedAvatar: drawn instead of the run's NeRF

    def frames(self):
        """The frames, rendered one at a time (an iterator of
        rendering.reanimate.RenderedFrame)."""
        from flamenerf.rendering.reanimate import baked_sequence, render_sequence

        if self.baked is not None:
            return baked_sequence(self.baked, self.ds, self.intr, self.poses, self.values,
                                  self.verts, self.dilate_px)
        omega, phi = self.codes if self.codes is not None else self.run.frame_codes(0)
        return render_sequence(self.run.model, self.ds, self.intr, self.poses, self.values,
                               self.verts, omega, phi, self.dilate_px, heads=self.heads,
                               settings=self.settings)


def render_intrinsics(run, ds: Dataset, size: int | None) -> Intrinsics:
    """The run's training resolution, or `size` pixels wide."""
    if size is None:
        return run.train_intrinsics(ds)
    if not 8 <= size <= 8192:
        raise UserError(f"--size {size}: must be between 8 and 8192")
    return ds.intrinsics.scaled(size / ds.intrinsics.w)


def expression_source(opts: RenderOptions, ds: Dataset, names: list[str], intr: Intrinsics,
                      base: np.ndarray, log=print, companions=None,
                      training: np.ndarray | None = None) -> X.ExpressionSequence:
    """The sequence --split, --drive or --expressions name (keyframes with `companions`, a
    tour from the `training` expressions); else `base` held."""
    if opts.split:
        return X.from_split(ds, opts.split, (intr.h, intr.w))
    if opts.drive:
        seq = X.from_video(opts.drive, ds, names, relative=opts.relative, fps=opts.fps,
                           max_frames=opts.max_frames, panel_height=intr.h,
                           landmarker=opts.landmarker, match_range=opts.match_range,
                           gains=X.parse_gains(opts.gain, names))
        if opts.max_frames is not None and opts.fps is None:
            log(f"note: --max-frames spreads the {len(seq)} frames over the clip; the video "
                f"plays at their rate ({seq.fps:.3g} fps) unless --fps is given")
        return seq
    if opts.expressions:
        return X.from_items(opts.expressions, names, base, opts.frames, companions, training,
                            fps=opts.fps)
    return held_expression(base, opts.frames or X.KEYFRAME_FRAMES, "reference")


def tour_training(opts: RenderOptions, ds: Dataset, names: list[str]) -> np.ndarray | None:
    """What `--expressions tour` reads: the training frames' expressions (N, E), where a
    tour is asked for and the dataset's controls are the run's; else None."""
    if opts.expressions != ["tour"] or ds.expression_names != names:
        return None
    return training_expressions(ds)


def keyframe_companions(opts: RenderOptions, ds: Dataset, names: list[str]):
    """The dataset's companions for --expressions keyframes, unless --no-companions."""
    if not opts.companions or ds.expression_names != names:
        return None
    return dataset_companions(ds)


def within_training_range(opts: RenderOptions, ds: Dataset, names: list[str],
                          values: np.ndarray, log=print, generic: list[int] = ()
                          ) -> np.ndarray:
    """What the user asked for (keyframes, a file, a driving video), each control clamped
    to the training frames' range unless --extrapolate (data/expression_range.py); a
    split's own expressions are taken as they are (an edit of them is clamped by
    `apply_edits`); `generic`: the run's generic shapes' controls, which reach 1."""
    rng = training_limits(opts, ds, names, generic)
    if opts.split or rng is None:
        return values
    over = rng.beyond(values)
    if over:
        log(clamp_note(over))
    return rng.clamp(values) if over else values


def training_limits(opts: RenderOptions, ds: Dataset, names: list[str],
                    generic: list[int] = ()):
    """The training frames' range (data/expression_range.ExpressionRange) that what the
    user asks for is clamped to (`generic` controls up to 1); None with --extrapolate or
    another expression model."""
    if opts.extrapolate or ds.expression_names != names:
        return None
    return training_range(ds, generic)


def clamp_note(over: list[str]) -> str:
    return f"note: {ExpressionRange.note(over)}"


def held_expression(base: np.ndarray, num: int, label: str) -> X.ExpressionSequence:
    return X.ExpressionSequence(np.repeat(base[None], num, 0), label=label, resizable=True)


def camera_poses(opts: RenderOptions, seq: X.ExpressionSequence, rig: C.CameraRig,
                 names: list[str], base: np.ndarray, log=print, companions=None,
                 training: np.ndarray | None = None
                 ) -> tuple[np.ndarray, str, X.ExpressionSequence]:
    """--camera -> poses (T, 4, 4), the path's label, and the expression sequence (re-made
    when a pose file fixes the length of a keyframe, tour or held sequence; `training`: the
    training expressions a tour reads)."""
    camera = opts.camera
    if camera in ("auto", "split"):
        if seq.cameras is not None:
            return seq.cameras, "split", seq
        if camera == "split":
            raise UserError("--camera split: needs --split")
        return C.camera_path("static", len(seq), rig), "static", seq
    if camera in C.PATH_KINDS:
        return C.camera_path(camera, len(seq), rig, opts.amplitude), camera, seq
    if not Path(camera).exists():  # most likely a mistyped path name, not a missing file
        raise UserError(f"--camera {camera!r}: neither a camera path ({', '.join(C.PATH_KINDS)}, "
                        "auto, split) nor an existing JSON file of poses")
    poses = C.load_poses(Path(camera))
    if seq.resizable and len(poses) != len(seq):
        seq = (X.from_items(opts.expressions, names, base, len(poses), companions, training)
               if opts.expressions
               else held_expression(base, len(poses), seq.label))
    elif len(poses) != len(seq):
        log(f"note: {camera} has {len(poses)} poses for {len(seq)} frames; resampled")
        poses = C.resample(poses, len(seq))
    return poses, Path(camera).stem, seq


def own_codes(opts: RenderOptions, run, ds: Dataset, frames: list) -> bool:
    """Whether the split's `frames` render with their own codes (--codes). `auto`: where
    they have codes in this run (capture frames, `Run.codes_error`) of its own dataset, or
    of the one given with --dataset where the run's is no longer where it trained (moved);
    `own` needs only the codes."""
    from flamenerf.rendering.filmed import filmed_codes_error

    if opts.codes == "first" or not opts.split:
        return False
    why = run.codes_error(ds, frames)
    if why is not None:
        if opts.codes == "own":
            raise UserError(f"--codes own: --split {opts.split}: {why}")
        return False
    return opts.codes == "own" or filmed_codes_error(run, ds, frames, opts.dataset) is None


def output_paths(opts: RenderOptions, source: str, camera: str, tag: str = ""
                 ) -> dict[str, Path]:
    """The videos to write (by default RUN/renders/SOURCE_CAMERA{tag}.mp4), refusing to
    replace existing ones without --overwrite."""
    out = (opts.out if opts.out is not None
           else Path(opts.run) / "renders" / f"{source}_{camera}{tag}.mp4")
    if out.suffix.lower() != ".mp4":
        raise UserError(f"{out}: the output must be an .mp4 file")
    paths = {"rgb": out}
    if opts.depth:
        paths["depth"] = out.with_name(f"{out.stem}_depth.mp4")
    if opts.side_by_side:
        paths["sbs"] = out.with_name(f"{out.stem}_sbs.mp4")
    for p in paths.values():
        if p.exists() and not opts.overwrite:
            raise UserError(f"{p}: already exists (pass --overwrite to replace it, or --out "
                            "to name another)")
        if p.is_dir():
            raise UserError(f"{p}: is a folder, not a video file")
    return paths


def head_transforms(opts: RenderOptions, run, ds: Dataset, n: int, log=print,
                    seq: X.ExpressionSequence | None = None) -> np.ndarray | None:
    """Each frame's canonical-from-world head transform (n, 4, 4): --head-pose (`drive` /
    `take`: the driving video's / the ARKit take's head turns, from `seq`), else a split's
    own head poses; None: the head at frame 0's pose."""
    if opts.head_pose:
        if not getattr(run.model, "follows_head", False):
            raise UserError(f"--head-pose: {opts.run} was not trained on a dataset with head "
                            "poses, so its head cannot be turned apart from the scene")
        region = H.HeadRegion.from_dict(run.model.init_args["head_region"])
        if opts.head_pose in (["drive"], ["take"]):
            rows, keyframes = X.source_head_pose(opts.head_pose[0], seq, log)[:n], False
        else:
            rows, keyframes = H.head_pose_items(opts.head_pose)
        if keyframes:
            rows = X.keyframe_sequence(rows, np.zeros(6), n)
        elif len(rows) != n:
            log(f"note: {opts.head_pose[0]} has {len(rows)} head poses for {n} frames; "
                "resampled")
            u = np.linspace(0, len(rows) - 1, n)
            rows = np.stack([np.interp(u, np.arange(len(rows)), rows[:, j])
                             for j in range(6)], -1)
        return np.stack([H.control_transform(H.HeadPoseKey(*map(float, r)), region)
                         for r in rows])
    if opts.split and ds.has_head_poses:
        return H.canonical_from_world(ds, ds.split(opts.split))[:n]
    return None


def write_videos(plan: RenderPlan) -> None:
    """Render the plan and write the result, and with "depth"/"sbs" in its paths the depth
    video and driving | result | depth side by side (the expression as bars when the source
    has no driving image)."""
    import contextlib

    from tqdm import tqdm

    from flamenerf.rendering.reanimate import depth_image, depth_range

    intr, values, seq = plan.intr, plan.values, plan.seq
    near, far = plan.run.model.near, plan.run.model.far
    left_title = (("filmed" if seq.cameras is not None else "driving")
                  if seq.driving is not None else "expression")
    with contextlib.ExitStack() as stack:
        if plan.frames_dir is not None:  # entered first: named after the videos are
            from flamenerf.rendering.frame_folder import FrameFolder

            frames_out = stack.enter_context(FrameFolder(plan.frames_dir, plan.fps,
                                                         plan.sound))
        writers = {k: stack.enter_context(VideoWriter(
            p, plan.fps, sound=plan.sound if k in ("rgb", "sbs") else None))
            for k, p in plan.paths.items()}
        lo = hi = None
        for i, fr in enumerate(tqdm(plan.frames(), total=len(values), desc="render",
                                    unit="frame")):
            # a frame before a gap in the clip stays for the gap's time (clip_pace)
            times = 1 if plan.shown is None else int(plan.shown[i])
            for _ in range(times):
                writers["rgb"].write(fr.rgb)
                if plan.frames_dir is not None:
                    frames_out.write(fr.rgb)
            if lo is None:
                lo, hi = depth_range(fr, near, far)
            if "depth" in writers or "sbs" in writers:
                dimg = depth_image(fr, lo, hi)
            if "depth" in writers:
                for _ in range(times):
                    writers["depth"].write(dimg)
            if "sbs" in writers:
                if seq.driving is not None:
                    left = resize_to_height(seq.driving(i), intr.h)
                else:
                    # what moved since the first frame shows first (a keyframe's, a tour's)
                    left = expression_panel(values[i], plan.run.expression_names, intr.h,
                                            intr.w, ref=values[0])
                edited = plan.edited is not None and plan.edited[i]
                row = titled_row([left, fr.rgb, dimg],
                                 [left_title, "edited" if edited else "render", "depth"], gap=2)
                if plan.caption:
                    row = vstack([row, caption_strip(plan.caption, row.shape[1])])
                for _ in range(times):
                    writers["sbs"].write(row)


def render_videos(opts: RenderOptions, log=print) -> RenderSummary:
    """The whole of `flamenerf render` (see its --help)."""
    opts.check()
    with folders_kept_only_on_success(opts.out.parent if opts.out is not None
                                      else Path(opts.run) / "renders"):
        return _render_videos(opts, log)


def _render_videos(opts: RenderOptions, log) -> RenderSummary:
    p = plan_render(opts, log)
    write_videos(p)
    paths = p.paths if p.frames_dir is None else {**p.paths, "frames": p.frames_dir}
    return RenderSummary(paths, len(p.values), p.intr.w, p.intr.h, p.fps, p.label, p.camera,
                         p.dilate_px)


def plan_render(opts: RenderOptions, log=print) -> RenderPlan:
    """Everything `flamenerf render` decides before it renders (see its --help); checks
    that the outputs can be written, writes nothing."""
    from flamenerf.data.prior import dataset_dilation, mesh_function
    from flamenerf.training.run import load_run

    set_threads(opts.threads)
    if opts.out is not None:  # fail before loading and tracking, not after rendering
        writable_dir(opts.out.parent, "video")
    run = load_run(opts.run, opts.device)
    ds = run.dataset(opts.dataset, opts.captured_directions)
    names = run.expression_names
    intr = render_intrinsics(run, ds, opts.size)
    ref = reference_position(ds)
    base = (ds.frames[ref].expression.astype(np.float32) if opts.expression_base == "reference"
            else np.zeros(len(names), np.float32))

    comp = keyframe_companions(opts, ds, names)
    edits = []
    if opts.edit:  # before a driving video is tracked, so that a typo fails at once
        from flamenerf.rendering.edits import parse_edits

        edits = parse_edits(opts.edit, names)
    training = tour_training(opts, ds, names)
    seq = expression_source(opts, ds, names, intr, base, log, comp, training)
    for note in seq.notes:
        log(f"note: {note}")
    poses, cam_label, seq = camera_poses(opts, seq, C.rig_from_dataset(ds), names, base, log,
                                         comp, training)
    n = len(seq) if opts.max_frames is None else min(len(seq), opts.max_frames)
    if seq.label == "tour" and n < len(seq):
        log(f"note: --max-frames {n} keeps the tour's first {n} of {len(seq)} frames, so only "
            f"its first controls (--frames sets the tour's whole length)")
    values, poses, label = seq.values[:n], poses[:n], seq.label
    fps = opts.fps or seq.fps or 30.0
    generic = run.model.generic_controls
    caption = lacking_caption(*not_covered(opts, ds, names, values, edits, log, generic))
    # the source as the model has learnt it, then the edit of it (clamped on its own), so
    # that `jawOpen-=0.3` lowers a drive's jaw from where the render shows it
    values = within_training_range(opts, ds, names, values, log, generic)
    changed = None  # the frames the edit changes (the side by side's titles say which)
    if edits:
        from flamenerf.rendering.edits import describe, edit_sequence

        source = values
        ed = edit_sequence(values, edits, opts.edit, names, comp,
                           training_limits(opts, ds, names, generic), opts.edit_during,
                           fps)
        values, changed, label = ed.values, ed.changed, f"{label}_{ed.tag}"
        held = not (opts.split or opts.drive or opts.expressions)
        log(f"note: edited {describe(opts.edit)} {ed.where}"
            + (" of frame 0's expression, held (give --split capture, --drive or "
               "--expressions for a sequence to edit)" if held else "")
            + (f", moving with them {', '.join(ed.moved)} (--no-companions to leave them)"
               if ed.moved else ""))
        if ed.over:
            log(clamp_note(ed.over))
    T = head_transforms(opts, run, ds, n, log, seq)
    if seq.vertices is not None and not opts.head_pose and not edits:
        verts = seq.vertices[:n]  # a split's own (posed) meshes
    elif seq.vertices is not None:  # the split's meshes, turned by --head-pose, edited
        canon = canonical_vertices(ds, ds.split(opts.split))[:n]
        if edits:  # the tracked mesh, moved as the expression model moves it for the edit
            from flamenerf.rendering.filmed import changed_meshes

            canon = changed_meshes(canon, mesh_function(run.model, ds), values, source)
        verts = posed_vertices(canon, T)
    else:  # the prior's silhouette follows the driven expression's mesh, not frame 0's
        mesh_of = mesh_function(run.model, ds)  # canonical: the head at frame 0's pose
        verts = posed_vertices(np.stack([mesh_of(v) for v in values]), T)
    heads = None
    if T is not None:
        heads = se3_log(T).astype(np.float32)
    if opts.head_pose:
        cam_label = f"{cam_label}_head"
    dil = dataset_dilation(ds) if opts.dilate_px is None else opts.dilate_px

    # a split with frame 0's codes is named apart from the default (its own codes)
    paths = output_paths(opts, label, cam_label,
                         ("_first" if opts.split and opts.codes == "first" else "")
                         + ("_baked" if opts.baked else ""))
    writable_dir(paths["rgb"].parent, "video")
    if opts.frames_dir is not None:
        from flamenerf.rendering.frame_folder import check_frames_dir

        check_frames_dir(opts.frames_dir, opts.overwrite)
        writable_dir(opts.frames_dir.absolute().parent, "frames")
    settings = dataclasses.replace(REFERENCE if opts.exact else FAST,
                                   chunk=opts.chunk or (REFERENCE.chunk if opts.exact else 0))
    codes, frames = None, ds.split(opts.split)[:n] if opts.split else []
    baked = None
    if opts.baked:
        from flamenerf.splats.avatar import load_avatar

        baked = load_avatar(Path(opts.run) / "baked.npz")
        if baked.names != names:
            raise UserError(f"{Path(opts.run) / 'baked.npz'}: baked with other controls "
                            "than this run's; bake again (`flamenerf bake RUN`)")
        if opts.split and opts.codes == "auto":
            log("note: --baked renders every frame with frame 0's codes (the bake's)")
    elif own_codes(opts, run, ds, frames):
        from flamenerf.rendering.filmed import own_codes_settings

        codes = run.clip_codes(ds, frames)
        settings = own_codes_settings(settings)
        trained = {f.frame_index for f in ds.training_frames()}
        between = sum(f.frame_index not in trained for f in frames)
        log("note: each frame renders with its own codes"
            + (f" ({between} held-out frame{'s' if between > 1 else ''} with "
               f"{'their' if between > 1 else 'its'} neighbours')" if between else "")
            + "; --codes first renders all with frame 0's")
    shown, sound = plan_sound(opts, ds, frames, seq, n, fps, log)
    return RenderPlan(run, ds, intr, poses, values, verts, heads, dil, settings, fps, paths,
                      seq, label, cam_label, codes, changed, sound, shown, opts.frames_dir,
                      caption, baked)


def plan_sound(opts: RenderOptions, ds: Dataset, frames: list, seq: X.ExpressionSequence,
               n: int, fps: float, log=print):
    """How many times each of the `n` frames is shown, and the sound under them
    (rendering/soundtrack.py): the clip's for --split capture at its pace, the driving
    video's for --drive, or --audio's file for any source. -> (shown (n,) or None, a
    data/video.Soundtrack or None)."""
    if opts.drive:
        times = None if seq.times is None else seq.times[:n]
        shown = S.drive_pace(times, fps)
        sound = S.drive_sound(opts, times, shown, fps, log) if opts.audio is None else None
    else:
        shown = S.clip_pace(opts, ds, frames, fps, log)
        sound = S.clip_sound(opts, ds, frames, fps, log, shown) if opts.audio is None else None
    if opts.audio is not None:
        sound = S.audio_sound(opts.audio, S.shown_duration(n, shown, fps), log)
    return shown, sound


def not_covered(opts: RenderOptions, ds: Dataset, names: list[str], values: np.ndarray,
                edits: list, log=print, generic: list[int] = ()
                ) -> tuple[list[str], list[str]]:
    """Say which of the controls a drive, a file, keyframes or an edit ask for the
    training frames never move (a clip without a blink has no blink to give), and which
    of them a generic shape stands in for (`generic`). -> (those with nothing to give,
    those with a generic shape)."""
    if ds.expression_names != names or not (opts.drive or opts.expressions or edits):
        return [], []
    rng = training_range(ds)
    asked = None if opts.split and not (opts.drive or opts.expressions) else values
    missing = rng.uncovered(asked, [e.index for e in edits])
    shaped = [n for n in missing if names.index(n) in generic]
    if shaped:
        log(f"note: {ExpressionRange.generic_note(shaped)}")
    missing = [n for n in missing if n not in shaped]
    if missing:
        what = ("the drive" if opts.drive else "the edit" if edits and asked is None
                else "the render")
        log(f"note: {ExpressionRange.not_covered_note(missing, what)}")
    return missing, shaped


def short_names(names: list[str]) -> str:
    """Control names with their Left / Right pairs folded: eyeBlink L/R, jawOpen."""
    out, seen = [], set(names)
    for n in names:
        for side, other in (("Left", "Right"), ("Right", "Left")):
            if n.endswith(side) and n[:-len(side)] + other in seen:
                stem = n[:-len(side)]
                if stem + " L/R" not in out:
                    out.append(stem + " L/R")
                break
        else:
            out.append(n)
    return ", ".join(out)


def caption_strip(caption: str, width: int) -> np.ndarray:
    """The caption as a strip `width` wide; where it does not fit, a shorter line that
    points at the command's note, which names them all."""
    for text in (caption, "not every control asked for is in the clip (see the note)",
                 "see the note"):
        if text_width(text) + 4 <= width:
            break
    return text_strip(text, width)


def lacking_caption(missing: list[str], shaped: list[str]) -> str | None:
    """The side by side's caption for what the clip cannot give (`not_covered`), or None."""
    parts = ([f"never in the clip: {short_names(missing)}"] if missing else []) + (
        [f"generic shape: {short_names(shaped)}"] if shaped else [])
    return "; ".join(parts) or None
