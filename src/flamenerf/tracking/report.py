"""The preprocessing report (qa/tracking_report.json) and the QA figures next to it."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np

from flamenerf.tracking.still_head import RULE_CONTRADICTED
from flamenerf.data.expression_range import ExpressionRange, span, varies
from flamenerf.tracking import qa

GROUPS_ARKIT = {  # channels plotted in qa/expressions.png (groups are averaged)
    "jawOpen": ["jawOpen"],
    "smile (mouthSmileLeft+Right)/2": ["mouthSmileLeft", "mouthSmileRight"],
    "eyeBlinkLeft": ["eyeBlinkLeft"],
    "eyeBlinkRight": ["eyeBlinkRight"],
}



def scene_report(scene) -> dict:
    """Which case the clip is, how the cameras were found, how much camera and head move,
    and what that allows (warnings)."""
    w, reg = scene.world, scene.registration
    return {
        "case": w.case,
        "cameras_from": ("the static background" if reg is not None and reg.status in
                         ("registered", "still") and w.head_pose is not None
                         else "the face (head as world)"),
        "warnings": w.warnings,
        "metric_scale_m_per_unit": w.scale,
        "camera_motion": w.camera_motion,
        "head_motion": w.head_motion,
        "background": reg.summary() if reg is not None else None,
    }


DISAGREE_DEG = 3.0
"""The cameras' largest turn from the face's (in the still-head check's adjusted world) above
which `preprocess` points to the field of view."""


MODEL_NAMES = {"sfm": "structure from motion (the camera travels; parallax)",
               "rotation": "rotations about one centre (a handheld camera that mostly "
                           "turns; little parallax)"}


def camera_model_lines(bg: dict) -> list[str]:
    """Which camera model the background registered with and why, its error, and how much
    of the background moved by itself (a `Registration.summary()`)."""
    lines = []
    model, choice = bg.get("camera_model"), bg.get("camera_model_choice") or {}
    if bg.get("status") == "registered" and model in MODEL_NAMES:
        err = bg.get("reprojection_error_px_source")
        at = f", {err:.2f} px registration error (source pixels)" if err is not None else ""
        lines.append(f"  camera model: {MODEL_NAMES[model]}{at}"
                     + (f"; {choice['why']}" if choice.get("why") else ""))
    share = bg.get("moving_background_share")
    if share:
        lines.append(
            f"  background moving by itself: {100 * share:.1f}% of the background's pixels "
            f"(in {bg.get('moving_background_frames', 0)} frames; leaves, water, passers-by): "
            + ("left out of the camera solve, " if bg.get("moving_left_out_of_solve") else "")
            + "weighed down in training (masks in moving/)")
    return lines


def scene_lines(scene: dict) -> list[str]:
    """What preprocess tells the user about the scene (a `scene_report`): the case, where
    the cameras came from, the still-head check, and every warning."""
    bg = scene.get("background") or {}
    lines = [f"scene: {scene['case']}; cameras from {scene['cameras_from']}"
             + (f" ({bg['reason']})" if bg.get("reason") else "")]
    lines += camera_model_lines(bg)
    hyp = bg.get("still_head_hypothesis")
    if hyp and "still_head_error_px" in hyp:
        verdict = "kept" if hyp["chosen"] == "still head" else "not kept"
        if hyp.get("rule") == RULE_CONTRADICTED:
            verdict += (", as structure from motion's world has the camera travel against "
                        "the face's account")
        lines.append(
            f"  still-head check: {verdict} (a still head explains the background at "
            f"{hyp['still_head_error_px']:.2f} px over {100 * hyp['still_head_inliers']:.0f}% "
            f"of its observations with the cameras {hyp['still_head_turn_deg']:.1f} deg from "
            f"the face's; structure from motion: {hyp['sfm_error_px']:.2f} px; source pixels)")
        top = hyp.get("still_head_turn_max_deg", 0.0)
        if hyp.get("rule") == RULE_CONTRADICTED and top > DISAGREE_DEG:
            lines.append(
                f"  note: the adjusted cameras turn up to {top:.0f} deg from the face's, so the "
                "head turns in this world; if it was in fact still, a wrong field of view is "
                "one cause (docs/head_pose.md): try `--fov`")
    lines += [f"  warning: {w}" for w in scene.get("warnings", [])]
    return lines


def tracking_report(video: Path, clip, sol, scene, intr, crop, crop_facts, n_tracked: int,
                    cam_dist: np.ndarray, near: float, far: float, kind: str,
                    names: list[str], splits: list[str], per_frame: list[dict],
                    timings: dict[str, float], expressions: np.ndarray | None = None) -> dict:
    """What preprocessing found and kept: video, frames, scene, cameras, crop, errors,
    bounds, and the expressions the training frames cover (expressions (N, E), one row per
    kept frame, in the order of `splits`)."""
    info, N = clip.info, len(clip.frames)
    return {
        "video": {"path": str(video), "width": info.width, "height": info.height,
                  "fps": info.fps, "frames": info.num_frames, "rotation": info.rotation,
                  "codec": info.codec, "hdr": info.hdr},
        "selected_frames": int(len(clip.selected)),
        "tracked_frames": n_tracked,
        "kept_frames": N,
        "tracked_percent": 100.0 * n_tracked / max(1, len(clip.selected)),
        "kept_percent": 100.0 * N / max(1, len(clip.selected)),
        "dropped": clip.dropped,
        # frames where faces other than the followed one were in view (tracking/clip.py)
        "crowded_frames": clip.crowded,
        # frames that begin a new shot (tracking/shots.py)
        "cuts": clip.cuts,
        "scene": scene_report(scene),
        "camera": {
            "focal_px_source": sol.focal, "fov_x_deg": _fov(sol.focal, info.width),
            "fov_y_deg": _fov(sol.focal, info.height),
            "focal_scan": sol.history.get("focal_scan"),
            "intrinsics_out": asdict(intr),
            "camera_distance_m": [float(cam_dist.min()), float(cam_dist.max())],
            **azimuth_ranges(sol.c2w, scene.world.head_pose),
        },
        "crop": {**crop.to_dict(), **crop_facts},
        "reprojection_error_px": {
            "what": "median over landmarks of |projection - landmark|, per frame; "
                    "rigid = shared template + camera, mesh = per-frame face mesh",
            "rigid_median_source": float(np.median(sol.rigid_error)),
            "rigid_median_out": float(np.median(sol.rigid_error) * crop.scale),
            "rigid_p95_out": float(np.percentile(sol.rigid_error, 95) * crop.scale),
            "mesh_median_out": float(np.median(sol.mesh_error) * crop.scale),
        },
        "near": near, "far": far,
        "expression_model": {"kind": kind, "dim": len(names)},
        "expressions": (None if expressions is None
                        else expression_coverage(expressions, names, splits, sol.c2w,
                                                 scene.world.head_pose)),
        "splits": {s: splits.count(s) for s in sorted(set(splits))},
        "timings_s": timings,
        "frames": per_frame,
    }


def cameras_in_head(c2w: np.ndarray, head_pose: np.ndarray | None) -> np.ndarray:
    """The cameras seen from the head: c2w (N, 4, 4) world cameras, head_pose (N, 4, 4)
    world-from-head or None (the head is the world) -> (N, 4, 4)."""
    return c2w if head_pose is None else np.linalg.inv(head_pose) @ c2w


def expression_coverage(expressions: np.ndarray, names: list[str], splits: list[str],
                        c2w: np.ndarray | None = None, head_pose: np.ndarray | None = None
                        ) -> dict:
    """What a model of this clip can learn about each control: over the training frames,
    its range (what `render` and the viewer clamp to, data/expression_range.py) and the
    span of most frames (5th-95th percentile; `eval` sweeps the controls whose span is at
    least 0.1); with the cameras (c2w (N, 4, 4), and the head's poses where it moves in the
    world), the controls that move with the view of the head (`view_confounds`): a head that
    nods before a still camera is seen from above and below as an orbit sees it. ->
    {"varying": [...], "barely_moving": [...], "controls": {name: {...}},
    "follow_the_view": {name: {...}}}"""
    x = np.asarray(expressions, np.float64)
    train = np.array([s == "train" for s in splits]) if "train" in splits else np.ones(len(x),
                                                                                         bool)
    rng = ExpressionRange.of(names, x[train])
    controls, moving, still = {}, [], []
    for k, n in enumerate(names):
        lo, hi = span(x[train, k])
        controls[n] = {"min": float(rng.lo[k]), "max": float(rng.hi[k]), "p5": lo, "p95": hi}
        (moving if varies(x[train, k]) else still).append(n)
    out = {"varying": moving, "barely_moving": still, "controls": controls}
    if c2w is not None:
        seen = cameras_in_head(np.asarray(c2w), head_pose)
        out["follow_the_view"] = view_confounds(x[train], names, seen[train], moving)
    return out


def view_confounds(expressions: np.ndarray, names: list[str], c2w: np.ndarray,
                   controls: list[str], min_r: float = 0.7, min_span_deg: float = 2.0
                   ) -> dict[str, dict[str, float]]:
    """Controls whose value follows where the camera sees the head from: expressions (N, E),
    c2w (N, 4, 4) cameras in the head's frame; of `controls`, those whose correlation with
    the view's azimuth or elevation (each only if it spans min_span_deg) reaches min_r. A
    model cannot tell such a control from the view (in an orbit the eyes follow the camera):
    it may learn the view's shading as the control's, and moving the control alone then
    changes the shading around it. -> {name: {"azimuth_r", "elevation_r"}} (None: the view
    does not span enough that way)"""
    angles = dict(zip(("azimuth_r", "elevation_r"), view_angles(c2w)))
    out = {}
    for n in controls:
        v = np.asarray(expressions, np.float64)[:, names.index(n)]
        if np.ptp(v) == 0:
            continue
        rs = {k: (float(np.corrcoef(v, a)[0, 1]) if np.ptp(a) >= min_span_deg else None)
              for k, a in angles.items()}
        if any(r is not None and abs(r) >= min_r for r in rs.values()):
            out[n] = {k: (None if r is None else round(r, 3)) for k, r in rs.items()}
    return out


def frame_entry(k: int, source_frame: int, clip, sol, crop, split: str, mask: np.ndarray,
                expression: np.ndarray, names: list[str]) -> dict:
    """One kept frame's line of the report."""
    return {
        "position": k, "source_frame": source_frame, "time": float(clip.times[k]),
        "split": split,
        "rigid_error_px_source": float(sol.rigid_error[k]),
        "rigid_error_px_out": float(sol.rigid_error[k] * crop.scale),
        "mesh_error_px_out": float(sol.mesh_error[k] * crop.scale),
        "camera_center": sol.c2w[k, :3, 3].round(5).tolist(),
        "mask_fraction": float(mask.mean()),
        "top_expressions": _top(expression, names),
    }


def write_qa(qa_dir: Path, report: dict, sheet_frames: list[np.ndarray], sol, scene, clip,
             splits, expressions, names, kind) -> None:
    import imageio.v3 as iio

    qa_dir.mkdir(exist_ok=True)
    iio.imwrite(qa_dir / "contact_sheet.png", qa.contact_sheet(sheet_frames, cols=4))
    rep = report["reprojection_error_px"]
    qa.plot_cameras(qa_dir / "cameras.png", sol.c2w, sol.template, clip.times, splits,
                    title=f"{len(sol.c2w)} cameras, focal {sol.focal:.0f} px (source), "
                          f"median reprojection error {rep['rigid_median_out']:.2f} px "
                          f"(output)")
    w = scene.world
    qa.plot_motion(qa_dir / "motion.png", clip.times, w.c2w, w.head_pose,
                   title=f"{w.case}" + (f" - {len(w.warnings)} warning(s), see "
                                        "tracking_report.json" if w.warnings else ""))
    if kind == "arkit":
        qa.plot_expression_traces(qa_dir / "expressions.png", clip.times, expressions, names,
                                  GROUPS_ARKIT, title="expression trace")


def _fov(f: float, extent: float) -> float:
    return float(np.degrees(2 * np.arctan(0.5 * extent / f)))


def view_angles(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each camera (N, 4, 4) in the head's frame sees the head from: azimuth and
    elevation of its centre, degrees. -> (N,), (N,)"""
    C = np.asarray(c2w, np.float64)[:, :3, 3]
    el = np.arcsin((C[:, 1] / np.linalg.norm(C, axis=1).clip(1e-12)).clip(-1, 1))
    return np.degrees(np.arctan2(C[:, 0], C[:, 2])), np.degrees(el)


def azimuth_ranges(c2w: np.ndarray, head_pose: np.ndarray | None) -> dict[str, list[float]]:
    """The (lowest, highest) azimuth, degrees, the cameras c2w (N, 4, 4) see the head from
    (`azimuth_range_deg`: a head that turns before a still camera is seen from as many
    sides as it turns) and the room from (`room_azimuth_range_deg`); head_pose (N, 4, 4)
    world-from-head or None (the head is the world)."""
    out = {}
    for key, cams in (("azimuth_range_deg", cameras_in_head(c2w, head_pose)),
                      ("room_azimuth_range_deg", c2w)):
        az = view_angles(cams)[0]
        out[key] = [float(az.min()), float(az.max())]
    return out


def _top(vec: np.ndarray, names: list[str], k: int = 3) -> dict[str, float]:
    idx = np.argsort(-np.abs(vec))[:k]
    return {names[i]: round(float(vec[i]), 3) for i in idx}
