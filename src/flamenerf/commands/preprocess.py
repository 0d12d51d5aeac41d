"""`flamenerf preprocess`."""

from __future__ import annotations

# what the command runs is imported inside its function: the CLI imports every command
# module to build its --help (cli.py), which stays quick that way

from pathlib import Path
from typing import Annotated

import tyro

from flamenerf.tracking.pipeline import PreprocessOptions


def preprocess(
    video: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="VIDEO")],
    out: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="OUT")],
    opts: Annotated[PreprocessOptions, tyro.conf.OmitArgPrefixes, tyro.conf.arg(name="")],
) -> None:
    """Turn a portrait video (the camera, the head or both moving) into a flamenerf dataset.

    Decodes VIDEO (rotation metadata honoured), tracks the face in every selected frame
    with MediaPipe's FaceLandmarker (478 landmarks, head pose, 52 ARKit blendshape scores
    = the expression vector), solves one focal length and each frame's camera-from-head
    pose with a per-subject face template (metres), then registers the cameras against the
    static background with the person masked out (COLMAP) and gives each frame its head
    pose in that world; `--cameras head` keeps the head as the world. It cuts one stable
    square crop around the face, resizes it, and rasterises the face mesh of each frame
    into the silhouette mask (the spatial prior). Frames without a face, or whose landmarks
    the solve cannot explain, are dropped and listed in OUT/qa/tracking_report.json, next
    to an overlay video and the camera and head motion plots. Every --val-every'th frame
    goes to the val split. The landmarker model comes with `scripts/setup.sh`
    (scripts/get_landmarker.py). See docs/preprocessing.md and docs/head_pose.md.

    Example: flamenerf preprocess selfie.mp4 data/me --fps 15 --max-frames 300

    Args:
        video: Input video (anything ffmpeg reads: mp4, mov, ...).
        out: Output dataset directory (written atomically).
    """
    import os

    from flamenerf.tracking.pipeline import preprocess_video
    from flamenerf.tracking.clip import crowded_note
    from flamenerf.tracking.report import scene_lines

    if opts.verbose:  # read by runtime.quiet_native_stderr, wherever native code logs
        os.environ["FLAMENERF_VERBOSE"] = "1"
    rep = preprocess_video(video, out, opts)
    err = rep["reprojection_error_px"]
    print(f"wrote {out}: {rep['kept_frames']} frames ({rep['splits']}), tracked "
          f"{rep['tracked_frames']}/{rep['selected_frames']} ({rep['tracked_percent']:.1f}%), "
          f"dropped {len(rep['dropped'])}; median reprojection error "
          f"{err['rigid_median_out']:.2f} px at {opts.size}px "
          f"({err['rigid_median_source']:.2f} px in the source); "
          f"fov {rep['camera']['fov_x_deg']:.1f} deg; "
          f"{rep['frames_per_second']:.1f} frames/s")
    if "val" not in rep["splits"] and opts.val_every > 1:
        print(f"note: no val split: {rep['kept_frames']} frames kept, and --val-every "
              f"{opts.val_every} holds out one frame in {opts.val_every}; `flamenerf eval` "
              f"needs held-out frames (keep more with --fps or --max-frames, or lower "
              f"--val-every)")
    for line in scene_lines(rep["scene"]):
        print(line)
    cov = rep.get("expressions")
    if cov:
        top = sorted(cov["varying"], key=lambda n: -(cov["controls"][n]["p95"]
                                                      - cov["controls"][n]["p5"]))
        print(f"expressions: {len(cov['varying'])} of {len(cov['controls'])} controls vary in "
              f"the training frames ({', '.join(top[:6])}{', ...' if len(top) > 6 else ''}); "
              f"renders and the viewer keep each within its range "
              f"(qa/tracking_report.json: expressions)")
    if cov and cov.get("follow_the_view"):
        confounds = ", ".join(
            f"{n} ({' '.join(f'{k[:-2]} r {r:+.2f}' for k, r in rs.items() if r is not None)})"
            for n, rs in cov["follow_the_view"].items())
        print(f"  these move with the view in the training frames, so a model cannot tell them "
              f"from it (moved alone, they may change the shading nearby): {confounds}")
    mm = rep.get("mesh_model")
    if mm:
        print(f"expression model: fitted so that each of the {mm['controls']} varying controls "
              f"commanded alone reads back through the tracker as itself "
              f"({mm['seconds']:.0f} s; {out}/expression_model.npz)")
    if rep["video"].get("hdr"):
        print(f"note: an HDR clip ({rep['video']['hdr']}): its frames were tone-mapped to SDR "
              f"(BT.709) for training")
    cuts = rep.get("cuts") or []
    if cuts:
        print(f"note: the clip has {len(cuts)} cut{'s' * (len(cuts) > 1)} (a new shot at frame"
              f"{'s' * (len(cuts) > 1)} {', '.join(map(str, cuts[:8]))}"
              f"{', ...' if len(cuts) > 8 else ''}): the camera solve does not smooth the "
              f"motion across them (qa/tracking_report.json: cuts)")
    note = crowded_note(rep.get("crowded_frames") or [], opts.face)
    if note:
        print(f"{note} and frames with only other faces were dropped "
              f"(qa/tracking_report.json: crowded_frames)")
    for d in rep["dropped"][:10]:
        print(f"  dropped frame {d['source_frame']} ({d['time']:.2f}s): {d['reason']}")
    if len(rep["dropped"]) > 10:
        print(f"  ... {len(rep['dropped']) - 10} more in {out}/qa/tracking_report.json")
