"""Cameras from the static background: COLMAP (pycolmap) structure-from-motion on the frames
with the person masked out, one shared pinhole camera.

    frames + person masks -> SIFT outside the person -> sequential matching (1, 2, 4, 8...
    frames apart) -> background flow -> [still camera] or incremental mapping, and the
    rotation-only model (`flamenerf.tracking.rotation_cameras`) on the same matches; the
    one that explains them better by GRIC is kept (rotation alone when the mapping
    cannot start) -> what moves by itself (`flamenerf.tracking.moving_background`)

The result is in COLMAP's own world and scale (`flamenerf.tracking.world` makes it metric
from the face and puts the head in it). Three outcomes, each with a reason for the report:
  registered    cameras solved for (most of) the frames: by structure from motion
                (`camera_model` "sfm") or as rotations about one centre ("rotation": a
                handheld clip with little parallax, a far background);
  still         the background does not move in the image (tripod, a selfie held still):
                the camera is fixed, there is nothing to solve; also a background too
                plain to register whose pixels do not change over the clip;
  failed        too little texture, too few matches, or the mapping did not register
                enough frames: the caller falls back to head-as-world cameras.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flamenerf.runtime import quiet_native_stderr
from flamenerf.tracking.moving_background import MovingOptions, PairResidual, detect_moving
from flamenerf.tracking.rotation_cameras import (Matches, compare_models, sampson,
                                                 solve_rotations, transfer)
from flamenerf.tracking.still_head import reconstruction_c2w, still_head_hypothesis

# COLMAP / OpenCV camera axes (x right, y down, z forward) -> OpenGL (x right, y up, -z fwd)
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class BackgroundOptions:
    """Knobs of the background registration (defaults tuned on the two reference clips)."""

    max_side: int = 960
    """Frames are downscaled to at most this many pixels on their long side for COLMAP."""
    max_features: int = 4096
    """SIFT features per frame."""
    peak_threshold: float | None = None
    """SIFT's contrast threshold; None: 0.004 for frames of 640 px and more (COLMAP's
    default 0.0067 finds too little in the soft, defocused backgrounds of portrait clips),
    COLMAP's default below (with the upsampled first octave it finds plenty)."""
    first_octave: int | None = None
    """SIFT's first octave: -1 (COLMAP's default) doubles the image first, 4x the time;
    None: -1 for frames under 640 px (they need it), else 0."""
    min_features: int = 60
    """Median SIFT features per frame outside the person below which the background counts
    as textureless (no registration is attempted)."""
    still_flow: float = 0.004
    """The camera counts as still when background features move less than this fraction of
    the image's long side (90th percentile over matched frame pairs)."""
    still_change: float = 4.0
    """A textureless background counts as a still camera's when its pixels change by less
    than this (mean |Δ| in 0-255 over the background, 90th percentile over frames against
    the first); more and the registration failed."""
    min_registered: float = 0.8
    """Fraction of the frames that must register; fewer and the registration failed."""
    max_reprojection_px: float = 2.0
    """Mean reprojection error (source pixels) above which the registration failed."""
    overlap: int = 8
    """Sequential matching: each frame against the next `overlap` ones, plus 2^k apart."""
    init_min_tri_angle: float = 4.0
    """Degrees; COLMAP's default (16) rejects the small baselines of handheld clips."""
    refine_focal: bool = True
    """Refine the given focal length in a final bundle adjustment."""
    max_focal_change: float = 0.3
    """Keep the given focal length if the refinement moves it by more than this fraction."""
    camera_models: tuple[str, ...] = ("sfm", "rotation")
    """The camera models tried: structure from motion, rotations about one centre."""
    rotation_min_inliers: float = 0.5
    """The rotation-only model is usable when at least this share of the background's
    verified matches lands within `inlier_px` of where it predicts."""
    inlier_px: float = 3.0
    """Matches within this many pixels (COLMAP's downscaled frames) of a model's prediction
    count as explained by it."""
    moving: MovingOptions = field(default_factory=MovingOptions)
    """What counts as background that moves by itself."""
    num_threads: int = 2
    """Threads of the feature extraction. Matching, mapping and bundle adjustment run on
    one: with two, the matches' geometric checks (and, by float sums, the adjustment)
    differed from run to run, and the orbit clip's cameras by up to 1 mm."""
    seed: int = 0


@dataclass
class Registration:
    """Cameras of the frames in COLMAP's world (OpenGL axes, arbitrary scale)."""

    status: str  # "registered" | "still" | "failed"
    reason: str
    ids: np.ndarray  # (N,) the caller's frame ids, in the order given
    registered: np.ndarray  # (N,) bool
    c2w: np.ndarray  # (N, 4, 4) camera-to-world, NaN where not registered
    focal: float | None  # source pixels, when registered
    reprojection_error_px: float | None  # mean over observations, source pixels
    num_points: int = 0
    near_depth: float | None = None  # 5th percentile of background point depths, COLMAP units
    features_median: float = 0.0  # SIFT features per frame outside the person
    flow_p90: float = 0.0  # background flow, fraction of the long side (90th pct of pairs)
    seconds: float = 0.0
    details: dict = field(default_factory=dict)
    camera_model: str | None = None  # "sfm" | "rotation" when registered
    moving: np.ndarray | None = None  # (N, h, w) bool: background moving by itself
    moving_scale: float = 1.0  # the moving masks' pixels per source pixel

    def subset(self, ids: np.ndarray) -> "Registration":
        """The same registration restricted to (and ordered as) the frames `ids`."""
        pos = {int(i): k for k, i in enumerate(self.ids)}
        idx = np.array([pos[int(i)] for i in ids], np.int64)
        out = Registration(**self.__dict__)
        out.ids, out.registered, out.c2w = self.ids[idx], self.registered[idx], self.c2w[idx]
        if self.moving is not None:
            out.moving = self.moving[idx]
        return out

    def summary(self) -> dict:
        """The report's view: everything but the per-frame arrays."""
        return {"status": self.status, "reason": self.reason,
                "frames": int(len(self.ids)), "registered": int(self.registered.sum()),
                "focal_px_source": self.focal,
                "reprojection_error_px_source": self.reprojection_error_px,
                "points": self.num_points, "features_per_frame_median": self.features_median,
                "background_flow_p90": self.flow_p90, "seconds": self.seconds,
                "camera_model": self.camera_model, **self.details}


def person_mask(landmarks: np.ndarray, width: int, height: int, grow: float = 1.0
                ) -> np.ndarray:
    """Where the person may be in a frame, generously: an ellipse around the face (hair,
    ears, a turned head) and everything below the chin a little wider than the shoulders.
    landmarks (L, >=2) pixels -> (H, W) bool. Feature detection skips these pixels, so
    erring large only costs background features."""
    x0, y0 = landmarks[:, 0].min(), landmarks[:, 1].min()
    x1, y1 = landmarks[:, 0].max(), landmarks[:, 1].max()
    fw, fh = x1 - x0, y1 - y0
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1) - 0.15 * fh  # the skull sits above the face
    ax, ay = grow * 1.1 * fw, grow * 1.1 * fh
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    head = ((xx - cx) / max(ax, 1.0)) ** 2 + ((yy - cy) / max(ay, 1.0)) ** 2 <= 1.0
    below = yy >= cy
    # neck and shoulders: a widening trapezoid from the chin down to the frame's bottom
    half = grow * (0.9 * fw + 1.2 * fw * np.clip((yy - y1) / max(fh, 1.0), 0, None))
    body = below & (np.abs(xx - cx) <= half)
    return head | body


def register_background(frames: Iterable[tuple[int, np.ndarray, np.ndarray]],
                        opts: BackgroundOptions | None = None,
                        focal: float | None = None, still_head_c2w: np.ndarray | None = None
                        ) -> Registration:
    """frames: (id, (H, W, 3) uint8 RGB, (H, W) bool person mask) in time order; focal:
    the face solve's focal length (source px; None: COLMAP estimates it); still_head_c2w
    (N, 4, 4): the face solve's cameras (head as world), the still-head hypothesis that
    is tried against COLMAP's own solution (see `flamenerf.tracking.still_head`).
    Everything COLMAP writes lives in a temporary folder, removed afterwards."""
    opts = opts or BackgroundOptions()
    t0 = time.perf_counter()
    tmp = Path(tempfile.mkdtemp(prefix="flamenerf_colmap_"))
    try:
        reg = _register(frames, opts, tmp, focal, still_head_c2w)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    reg.seconds = time.perf_counter() - t0
    return reg


def _write_frames(frames, opts: BackgroundOptions, img_dir: Path, mask_dir: Path):
    from PIL import Image

    ids, names, size, scale = [], [], None, 1.0
    for k, (fid, rgb, person) in enumerate(frames):
        h, w = rgb.shape[:2]
        if size is None:
            size = (w, h)
            scale = min(1.0, opts.max_side / max(w, h))
        img = Image.fromarray(rgb)
        keep = Image.fromarray(np.where(person, 0, 255).astype(np.uint8))
        if scale < 1.0:
            sz = (round(w * scale), round(h * scale))
            img = img.resize(sz, Image.Resampling.LANCZOS)
            keep = keep.resize(sz, Image.Resampling.NEAREST)
        name = f"{k:06d}.jpg"
        img.save(img_dir / name, quality=95)  # JPEG: PNG encoding took as long as SIFT
        keep.save(mask_dir / f"{name}.png")  # COLMAP: features only where the mask is > 0
        ids.append(int(fid))
        names.append(name)
    return np.asarray(ids, np.int64), names, size, scale


def _load_grey(img_dir: Path, mask_dir: Path, name: str, side: int
               ) -> tuple[np.ndarray, np.ndarray]:
    """One frame as COLMAP saw it, resized to `side` pixels on its long side: grey (h, w)
    uint8 and where the background is (h, w) bool (outside the person mask)."""
    from PIL import Image

    img = Image.open(img_dir / name).convert("L")
    s = side / max(img.size)
    sz = (max(1, round(img.width * s)), max(1, round(img.height * s)))
    keep = Image.open(mask_dir / f"{name}.png").resize(sz, Image.Resampling.NEAREST)
    return np.asarray(img.resize(sz, Image.Resampling.BILINEAR)), np.asarray(keep) > 0


def _background_change(img_dir: Path, mask_dir: Path, names: list[str], side: int = 160,
                       max_frames: int = 40) -> float | None:
    """How much the background's pixels change over the clip: mean |Δ| (0-255, grey) over
    the pixels outside the person in both frames, each frame against the first, 90th
    percentile over up to `max_frames` frames; None when too little background is seen."""
    def load(name):
        img, keep = _load_grey(img_dir, mask_dir, name, side)
        return img.astype(np.float32), keep

    pick = np.unique(np.linspace(0, len(names) - 1, min(max_frames, len(names))).astype(int))
    ref, ref_keep = load(names[pick[0]])
    changes = []
    for k in pick[1:]:
        img, keep = load(names[k])
        both = keep & ref_keep
        if both.sum() < 100:  # a close-up leaves little outside the (generous) person mask
            continue
        changes.append(float(np.abs(img - ref)[both].mean()))
    return float(np.percentile(changes, 90)) if changes else None


def _empty(ids, status, reason, **kw) -> Registration:
    n = len(ids)
    return Registration(status, reason, ids, np.zeros(n, bool), np.full((n, 4, 4), np.nan),
                        None, None, **kw)


def _register(frames, opts: BackgroundOptions, tmp: Path, focal: float | None,
              still_head_c2w: np.ndarray | None) -> Registration:
    import pycolmap

    pycolmap.set_random_seed(opts.seed)
    pycolmap.logging.minloglevel = 2  # errors only: COLMAP logs every frame and pair
    img_dir, mask_dir, db_path = tmp / "images", tmp / "masks", tmp / "database.db"
    img_dir.mkdir()
    mask_dir.mkdir()
    ids, names, size, scale = _write_frames(frames, opts, img_dir, mask_dir)
    if len(ids) < 2:
        return _empty(ids, "failed", "fewer than 2 frames")
    W, H = size
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_PINHOLE"  # the dataset's cameras are pinholes
    if focal is not None:
        reader.camera_params = f"{focal * scale},{W * scale / 2},{H * scale / 2}"
    reader.mask_path = mask_dir
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = opts.num_threads
    extraction.sift.max_num_features = opts.max_features
    small = max(W, H) * scale < 640
    extraction.sift.peak_threshold = (opts.peak_threshold if opts.peak_threshold is not None
                                      else 0.0067 if small else 0.004)
    extraction.sift.first_octave = (opts.first_octave if opts.first_octave is not None
                                    else -1 if small else 0)
    extraction.use_gpu = False
    with quiet_native_stderr():
        pycolmap.extract_features(db_path, img_dir, image_names=names,
                                  camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction,
                                  device=pycolmap.Device.cpu)
    db = pycolmap.Database.open(db_path)
    try:
        image_ids = {im.name: im.image_id for im in db.read_all_images()}
        feats = np.array([db.num_keypoints_for_image(image_ids[n]) for n in names])
    finally:
        db.close()
    features_median = float(np.median(feats))
    if features_median < opts.min_features:
        why = (f"background has too little texture (median {features_median:.0f} features "
               f"per frame outside the person, need {opts.min_features})")
        change = _background_change(img_dir, mask_dir, names)
        kw = dict(features_median=features_median, details={"background_change": change})
        if change is not None and change < opts.still_change:
            # nothing to register, and the background's pixels stay put: a still camera
            # (were it moving, a wall this plain would look the same from anywhere near)
            # said as the finding it is, not as the failure to register that led to it
            return _empty(ids, "still", f"the background's pixels do not change between "
                          f"frames (mean |Δ| {change:.1f}/255), so the camera stood still; "
                          f"too little texture to register ({features_median:.0f} features per "
                          f"frame outside the person, median), which a still camera does not "
                          f"need",
                          **kw)
        return _empty(ids, "failed", why, **kw)

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = 1  # reproducible (num_threads)
    matching.use_gpu = False
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = opts.overlap
    pairing.quadratic_overlap = True
    with quiet_native_stderr():
        pycolmap.match_sequential(db_path, matching_options=matching,
                                  pairing_options=pairing, device=pycolmap.Device.cpu)
    flow, n_pairs = _background_flow(db_path, image_ids, names)
    long_side = max(W, H) * scale
    flow_p90 = float(np.percentile(flow, 90) / long_side) if len(flow) else 0.0
    if n_pairs == 0 and flow_p90 >= opts.still_flow:
        return _empty(ids, "failed", "no frame pairs of the background verified",
                      features_median=features_median, flow_p90=flow_p90)
    kw = dict(features_median=features_median, flow_p90=flow_p90,
              details={"verified_pairs": n_pairs, "image_scale": scale})
    if len(flow) == 0:
        return _empty(ids, "failed", "no frame pairs of the background matched", **kw)
    ctx = _Context(img_dir, mask_dir, names, scale, max(W, H) * scale,
                   np.array([W * scale / 2, H * scale / 2]),
                   (focal if focal is not None else 1.2 * max(W, H)) * scale)
    if flow_p90 < opts.still_flow:
        still = _empty(ids, "still", f"the background does not move (90% of frame pairs "
                       f"move < {100 * flow_p90:.2f}% of the image)", **kw)
        _add_moving(still, ctx, _still_residual, opts)
        return still

    matches = _verified_matches(db_path, image_ids, names)
    rot = solve_rotations(matches, len(names), ctx.focal, ctx.centre)
    sfm = (_structure_from_motion(db_path, img_dir, tmp, opts, focal, scale, names, ids,
                                  still_head_c2w, kw)
           if "sfm" in opts.camera_models else (None, "structure from motion not tried", None))
    return _choose(ctx, ids, matches, rot, sfm, opts, kw)


@dataclass
class _Context:
    """What the camera models and the moving-background check share: the frames COLMAP
    saw, their scale against the source, and the face's intrinsics in their pixels."""

    img_dir: Path
    mask_dir: Path
    names: list[str]
    scale: float
    long_side: float  # of COLMAP's frames, pixels
    centre: np.ndarray  # (2,) principal point
    focal: float  # the face solve's (or a guess), pixels of COLMAP's frames


def _structure_from_motion(db_path, img_dir, tmp, opts, focal, scale, names, ids,
                           still_head_c2w, kw) -> tuple[Registration | None, str, object]:
    """COLMAP's incremental mapping (with the focal refinement and the still-head check as
    before) -> (its registration or None, why not, the reconstruction)."""
    import pycolmap

    mapping = pycolmap.IncrementalPipelineOptions()
    # one thread: the multi-threaded mapper is not reproducible, and on short clips its
    # outcome varied from run to run (all frames or a handful); it is not the slow part
    mapping.num_threads = 1
    mapping.random_seed = opts.seed
    mapping.multiple_models = False
    mapping.min_model_size = 3
    mapping.ba_refine_principal_point = False
    mapping.extract_colors = False
    # the focal length stays at the face solve's while the map grows: refined from the first
    # few frames (little parallax) it collapses and the reconstruction with it
    mapping.ba_refine_focal_length = focal is None
    mapping.mapper.abs_pose_refine_focal_length = focal is None
    mapping.mapper.init_min_tri_angle = opts.init_min_tri_angle
    mapping.mapper.init_min_num_inliers = 50
    mapping.mapper.num_threads = 1
    mapping.mapper.random_seed = opts.seed
    with quiet_native_stderr():  # "Failed to create any sparse model" is ours to say
        recs = pycolmap.incremental_mapping(db_path, img_dir, tmp / "sparse", mapping)
    if not recs:
        return None, ("structure from motion found no initial pair to start from (too "
                      "little parallax or too few matches)"), None
    rec = max(recs.values(), key=lambda r: r.num_reg_images())
    if focal is not None and opts.refine_focal:
        rec = _refine_focal(rec, focal * scale, opts)
    details = {}
    if still_head_c2w is not None:
        rec, hyp = still_head_hypothesis(rec, np.linalg.inv(still_head_c2w @ CV_TO_GL)[:, :3],
                                         names)
        # the report's errors are in source pixels, COLMAP's in its downscaled frames'
        details["still_head_hypothesis"] = {
            k: v / scale if k.endswith("_px") else v for k, v in hyp.items()}
    c2w = reconstruction_c2w(rec, names) @ CV_TO_GL
    registered = np.isfinite(c2w[:, 0, 0])
    cam = next(iter(rec.cameras.values()))
    f_sfm = float(cam.params[0]) / scale
    err = float(rec.compute_mean_reprojection_error()) / scale
    out = _registered(f"{registered.sum()} of {len(ids)} frames registered against the "
                      "background by structure from motion", ids, registered, c2w, f_sfm,
                      err, "sfm", kw, details, num_points=int(rec.num_points3D()),
                      near_depth=_near_depth(rec))
    why = ""
    frac = registered.mean()
    if frac < opts.min_registered:
        why = (f"structure from motion registered only {registered.sum()} of {len(ids)} "
               f"frames (need {100 * opts.min_registered:.0f}%)")
    elif err > opts.max_reprojection_px:
        why = (f"structure from motion's reprojection error {err:.2f} px > "
               f"{opts.max_reprojection_px} px")
    return out, why, rec


def _registered(reason: str, ids, registered, c2w, focal: float, err: float | None,
                model: str, kw: dict, details: dict, **more) -> Registration:
    """A registration by `model`, with the clip's shared figures (kw: features, flow and
    their details) and the model's own details added to a copy of them."""
    shared = {k: v for k, v in kw.items() if k != "details"}
    return Registration("registered", reason, ids, registered, c2w, focal, err,
                        camera_model=model, details={**kw["details"], **details},
                        **shared, **more)


def _verified_matches(db_path: Path, image_ids: dict[str, int], names: list[str]) -> Matches:
    """Every geometrically verified background match (COLMAP's two-view geometries'
    inliers), as frame positions i < j and pixels of COLMAP's frames."""
    import pycolmap

    pos = {image_ids[n]: k for k, n in enumerate(names)}
    db = pycolmap.Database.open(db_path)
    try:
        kps = {i: db.read_keypoints(i)[:, :2] for i in image_ids.values()}
        pair_ids, geoms = db.read_two_view_geometries()
    finally:
        db.close()
    first, second = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    XI, XJ = [np.zeros((0, 2))], [np.zeros((0, 2))]
    for pid, g in zip(pair_ids, geoms):
        m = np.asarray(g.inlier_matches)
        if len(m) < 15:
            continue
        a, b = pycolmap.pair_id_to_image_pair(pid)
        if pos[a] > pos[b]:
            a, b, m = b, a, m[:, ::-1]
        first.append(np.full(len(m), pos[a]))
        second.append(np.full(len(m), pos[b]))
        XI.append(kps[a][m[:, 0]].astype(np.float64))
        XJ.append(kps[b][m[:, 1]].astype(np.float64))
    return Matches(*(np.concatenate(v) for v in (first, second, XI, XJ)))


def _rotation_registration(ctx: _Context, ids, rot, opts: BackgroundOptions, kw
                           ) -> tuple[Registration, str]:
    """The rotation-only model as a registration (camera centres at the origin) -> (it,
    why it is not usable or "")."""
    R = rot.R
    c2w = np.tile(np.eye(4), (len(ids), 1, 1))
    c2w[:, :3, :3] = np.transpose(R, (0, 2, 1))
    c2w = c2w @ CV_TO_GL
    c2w[~rot.connected] = np.nan
    fin = np.isfinite(rot.residual)
    inl = fin & (rot.residual <= opts.inlier_px)
    share = float(inl.sum() / max(fin.sum(), 1))
    # per point, as SfM's reprojection errors are: a transfer error holds both points' noise
    err = float(np.mean(rot.residual[inl]) / np.sqrt(2) / ctx.scale) if inl.any() else None
    out = _registered(f"{rot.connected.sum()} of {len(ids)} frames registered against the "
                      "background as rotations about one centre", ids, rot.connected.copy(),
                      c2w, ctx.focal / ctx.scale, err, "rotation", kw,
                      {"rotation_inliers": share})
    why = ""
    if rot.connected.mean() < opts.min_registered:
        why = (f"the rotation model connects only {rot.connected.sum()} of {len(ids)} "
               f"frames (need {100 * opts.min_registered:.0f}%)")
    elif share < opts.rotation_min_inliers:
        why = (f"the rotation model explains only {100 * share:.0f}% of the background's "
               f"matches (need {100 * opts.rotation_min_inliers:.0f}%): the camera moves "
               "with parallax")
    return out, why


def _choose(ctx: _Context, ids, matches: Matches, rot, sfm, opts: BackgroundOptions, kw
            ) -> Registration:
    """SfM or rotations, by GRIC where both are usable, else whichever is; then what moves
    by itself, and (for rotations) the solve again without it."""
    sfm_reg, sfm_why, rec = sfm
    rot_reg, rot_why = _rotation_registration(ctx, ids, rot, opts, kw)
    if "rotation" not in opts.camera_models:
        rot_why = "rotations about one centre not tried"
    w2c = None
    if rec is not None:
        w2c = np.full((len(ids), 3, 4), np.nan)
        ok = sfm_reg.registered
        w2c[ok] = np.linalg.inv(sfm_reg.c2w[ok] @ CV_TO_GL)[:, :3]
    verdict = compare_models(rot.residual, None if w2c is None else
                             sampson(matches, w2c, sfm_reg.focal * ctx.scale, ctx.centre),
                             len(ids))
    verdict = {k: (v / ctx.scale if k.endswith("_px") and v is not None else v)
               for k, v in verdict.items()}
    if not sfm_why and not rot_why:
        more = rot_reg.registered.sum() >= sfm_reg.registered.sum()
        pick = "rotation" if verdict.get("chosen") == "rotation" and more else "sfm"
        why = (f"GRIC {verdict['gric_rotation']:.0f} (rotations) against "
               f"{verdict['gric_sfm']:.0f} (structure from motion) over {verdict['matches']} "
               f"background matches; median distance {verdict['rotation_median_px']:.2f} "
               f"against {verdict['sfm_median_px']:.2f} source px")
        if pick == "rotation":
            why = "the background shows no parallax that structure from motion needs: " + why
    elif not rot_why:
        pick, why = "rotation", f"{sfm_why}; rotations about one centre explain " \
            f"{100 * rot_reg.details['rotation_inliers']:.0f}% of the background's matches"
    elif not sfm_why:
        pick, why = "sfm", f"{rot_why}"
    else:
        out = sfm_reg if sfm_reg is not None else rot_reg
        out.status, out.reason = "failed", f"{sfm_why}; {rot_why}"
        out.details["camera_model_choice"] = verdict
        return out
    out = rot_reg if pick == "rotation" else sfm_reg
    out.details["camera_model_choice"] = {**verdict, "chosen": pick, "why": why}
    residual = (_rotation_residual(rot.R, ctx.focal, ctx.centre) if pick == "rotation"
                else _epipolar_residual(w2c, sfm_reg.focal * ctx.scale, ctx.centre))
    _add_moving(out, ctx, residual, opts)
    if pick == "rotation" and out.moving is not None and out.moving.any():
        # the rotations again, without the matches that moved by themselves
        ratio = out.moving_scale / ctx.scale
        still = ~(_in_mask(out.moving, matches.i, matches.xi, ratio)
                  | _in_mask(out.moving, matches.j, matches.xj, ratio))
        rot2 = solve_rotations(matches.where(still), len(ids), ctx.focal, ctx.centre)
        again, again_why = _rotation_registration(ctx, ids, rot2, opts, kw)
        if not again_why:
            out.details["moving_left_out_of_solve"] = True
            out.c2w, out.registered = again.c2w, again.registered
            out.reprojection_error_px = again.reprojection_error_px
            out.details["rotation_inliers"] = again.details["rotation_inliers"]
    return out


def _rotation_residual(R: np.ndarray, f: float, c: np.ndarray) -> PairResidual:
    """Distance of a flow's end point to where the rotations R (N, 3, 3) take its start."""
    def residual(a: int, b: int, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
        m = Matches(np.full(len(x0), a), np.full(len(x0), b), x0, x1)
        return np.linalg.norm(transfer(m, R, f, c) - x1, axis=1)
    return residual


def _epipolar_residual(w2c: np.ndarray, f: float, c: np.ndarray) -> PairResidual:
    """Sampson distance of a flow to the epipolar geometry of the cameras w2c (N, 3, 4)."""
    def residual(a: int, b: int, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
        return sampson(Matches(np.full(len(x0), a), np.full(len(x0), b), x0, x1), w2c, f, c)
    return residual


def _still_residual(a: int, b: int, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """A still camera predicts no motion at all."""
    return np.linalg.norm(x1 - x0, axis=1)


def _add_moving(reg: Registration, ctx: _Context, residual, opts: BackgroundOptions) -> None:
    """Detect the background that moves by itself and record it on `reg` (masks, and the
    share of the background they cover in the report)."""
    # small frames are upsampled: the flow needs a few pixels of texture either side
    grey, keep = zip(*(_load_grey(ctx.img_dir, ctx.mask_dir, name, opts.moving.side)
                       for name in ctx.names))
    s = opts.moving.side / ctx.long_side
    moving = detect_moving(np.stack(grey), np.stack(keep), residual, s, opts.moving)
    reg.moving, reg.moving_scale = moving, s * ctx.scale
    share = float(moving.sum() / max(sum(k.sum() for k in keep), 1))
    reg.details["moving_background_share"] = share
    reg.details["moving_background_frames"] = int(moving.any((1, 2)).sum())


def _in_mask(masks: np.ndarray, frame: np.ndarray, x: np.ndarray, ratio: float
             ) -> np.ndarray:
    """Whether points x (M, 2) in COLMAP's pixels of frames `frame` (M,) lie in masks
    (N, h, w) made at `ratio` of those pixels."""
    n, h, w = masks.shape
    u = np.clip((x[:, 0] * ratio).astype(int), 0, w - 1)
    v = np.clip((x[:, 1] * ratio).astype(int), 0, h - 1)
    return masks[frame, v, u]


def _bundle_adjust(rec, refine_focal: bool, opts: BackgroundOptions) -> None:
    """Global bundle adjustment in place: poses and points, the focal length only when
    asked, a robust (Cauchy) loss against background outliers."""
    import pycolmap

    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = refine_focal
    ba.refine_principal_point = False
    ba.refine_extra_params = False
    ba.print_summary = False
    ba.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    ba.ceres.solver_options.num_threads = 1  # reproducible (num_threads)
    # its binding sets its own log level: its INFO lines went into preprocess's output
    with quiet_native_stderr():
        pycolmap.bundle_adjustment(rec, ba)


def _refine_focal(rec, focal0: float, opts: BackgroundOptions):
    """One global bundle adjustment with the focal length free, now that every frame's
    parallax constrains it. -> the refined reconstruction, or `rec` unchanged if the focal
    moved by more than max_focal_change (a weakly constrained focal wanders) or the
    reprojection error did not improve."""
    import pycolmap

    out = pycolmap.Reconstruction(rec)
    _bundle_adjust(out, refine_focal=True, opts=opts)
    f = float(next(iter(out.cameras.values())).params[0])
    e0, e1 = rec.compute_mean_reprojection_error(), out.compute_mean_reprojection_error()
    ok = (abs(np.log(f / focal0)) <= np.log(1 + opts.max_focal_change) and np.isfinite(e1)
          and e1 <= e0)  # a diverged adjustment (seen once on a tiny clip) is dropped
    return out if ok else rec


def _near_depth(rec) -> float | None:
    """5th percentile over all observations of the observed background point's depth."""
    depths = []
    for im in rec.images.values():
        if not im.has_pose:
            continue
        P = im.cam_from_world().matrix()
        X = np.array([rec.points3D[p.point3D_id].xyz for p in im.points2D if p.has_point3D()])
        if len(X):
            depths.append(X @ P[:, :3].T[:, 2] + P[2, 3])
    return float(np.percentile(np.concatenate(depths), 5)) if depths else None


def _background_flow(db_path: Path, image_ids: dict[str, int], names: list[str]
                     ) -> tuple[np.ndarray, int]:
    """Median image motion (downscaled px) of the background matches of every matched frame
    pair, and the number of geometrically verified pairs. Raw matches, not verified ones:
    COLMAP's verification rejects pairs that do not move at all (no epipolar geometry, or
    a "watermark"), which are exactly a still camera's; the median is robust to the
    outliers among them."""
    import pycolmap

    db = pycolmap.Database.open(db_path)
    try:
        kps = {i: db.read_keypoints(i)[:, :2] for i in image_ids.values()}
        pair_ids, matches = db.read_all_matches()
        verified = sum(len(g.inlier_matches) >= 15 for g in db.read_two_view_geometries()[1])
    finally:
        db.close()
    flow = []
    for pid, m in zip(pair_ids, matches):
        m = np.asarray(m)
        if len(m) < 15:
            continue
        a, b = pycolmap.pair_id_to_image_pair(pid)
        d = np.linalg.norm(kps[a][m[:, 0]] - kps[b][m[:, 1]], axis=1)
        flow.append(float(np.median(d)))
    return np.asarray(flow), int(verified)
