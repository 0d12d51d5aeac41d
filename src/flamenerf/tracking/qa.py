"""Quality-assurance pictures of a preprocessing run: overlay frames (landmarks, silhouette,
head axes), a contact sheet, the camera trajectory, and expression traces."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from flamenerf.data.dataset import Intrinsics
from flamenerf.geometry import project_points
from flamenerf.tracking.world import mean_pose

AXIS_LENGTH = 0.06  # metres


def overlay_frame(rgb: np.ndarray, mask: np.ndarray, landmarks_px: np.ndarray | None,
                  intr: Intrinsics, c2w: np.ndarray, label: str = "",
                  upscale: int = 2) -> np.ndarray:
    """Picture of one frame: silhouette tinted red, tracked landmarks as green dots, the head
    frame's axes (x red, y green, z blue, from the head origin), and a label.
    rgb (H, W, 3) uint8, mask (H, W) bool, landmarks_px (L, 2) in the same pixels."""
    h, w = rgb.shape[:2]
    base = rgb.astype(np.float32)
    tint = np.array([255, 40, 40], np.float32)
    base[mask] = 0.72 * base[mask] + 0.28 * tint
    # silhouette outline
    edge = mask & ~_erode(mask)
    base[edge] = tint
    img = Image.fromarray(base.clip(0, 255).astype(np.uint8))
    if upscale > 1:
        img = img.resize((w * upscale, h * upscale), Image.Resampling.NEAREST)
    draw = ImageDraw.Draw(img)
    s = upscale
    if landmarks_px is not None:
        for x, y in landmarks_px[:, :2] * s:
            draw.rectangle([x - 0.5, y - 0.5, x + 0.5, y + 0.5], fill=(40, 255, 40))
    pts = np.array([[0, 0, 0], [AXIS_LENGTH, 0, 0], [0, AXIS_LENGTH, 0], [0, 0, AXIS_LENGTH]])
    uv, z = project_points(pts, intr, c2w)
    if np.all(z > 0):
        o = tuple(uv[0] * s)
        for k, col in ((1, (255, 0, 0)), (2, (0, 255, 0)), (3, (60, 120, 255))):
            draw.line([o, tuple(uv[k] * s)], fill=col, width=max(1, s))
    if label:
        draw.rectangle([0, 0, 7 * len(label) + 6, 14], fill=(0, 0, 0))
        draw.text((3, 1), label, fill=(255, 255, 255))
    return np.asarray(img)


def tint(rgb: np.ndarray, where: np.ndarray, colour: tuple[int, int, int],
         amount: float = 0.45) -> np.ndarray:
    """rgb (H, W, 3) uint8 with the pixels `where` (H, W) bool blended towards colour."""
    out = rgb.copy()
    out[where] = ((1 - amount) * rgb[where] + amount * np.asarray(colour)).astype(np.uint8)
    return out


def _erode(mask: np.ndarray) -> np.ndarray:
    m = mask.copy()
    m[1:] &= mask[:-1]
    m[:-1] &= mask[1:]
    m[:, 1:] &= mask[:, :-1]
    m[:, :-1] &= mask[:, 1:]
    return m


def contact_sheet(frames: list[np.ndarray], cols: int = 4, pad: int = 4) -> np.ndarray:
    """Tile equally-sized RGB frames in a grid with a dark gap."""
    if not frames:
        raise ValueError("no frames")
    h, w = frames[0].shape[:2]
    rows = (len(frames) + cols - 1) // cols
    sheet = np.full((rows * (h + pad) + pad, cols * (w + pad) + pad, 3), 24, np.uint8)
    for k, fr in enumerate(frames):
        r, c = divmod(k, cols)
        sheet[pad + r * (h + pad): pad + r * (h + pad) + h,
              pad + c * (w + pad): pad + c * (w + pad) + w] = fr[..., :3]
    return sheet


def plot_cameras(path: Path, c2w: np.ndarray, template: np.ndarray, times: np.ndarray,
                 splits: list[str], title: str = "") -> None:
    """Camera trajectory around the head: top view (x-z), side view (z-y) and a 3D view."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    C = c2w[:, :3, 3]
    fwd = -c2w[:, :3, 2]  # OpenGL: the camera looks down its -z axis
    d = float(np.linalg.norm(C, axis=1).mean())
    L = 0.15 * d
    fig = plt.figure(figsize=(14, 4.6), layout="constrained")
    views = [("top view (x right, z towards the face's front)", 0, 2),
             ("side view (z, y up)", 2, 1)]
    val = np.array([s == "val" for s in splits])
    for k, (name, a, b) in enumerate(views):
        ax = fig.add_subplot(1, 3, k + 1)
        ax.scatter(template[:, a], template[:, b], s=1, c="0.6", label="face template")
        sc = ax.scatter(C[:, a], C[:, b], c=times, cmap="viridis", s=10, label="cameras")
        ax.scatter(C[val, a], C[val, b], facecolors="none", edgecolors="r", s=22,
                   linewidths=0.6, label="val frames")
        step = max(1, len(C) // 25)
        for i in range(0, len(C), step):
            ax.plot([C[i, a], C[i, a] + L * fwd[i, a]], [C[i, b], C[i, b] + L * fwd[i, b]],
                    c="0.3", lw=0.6)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("xyz"[a] + " (m)")
        ax.set_ylabel("xyz"[b] + " (m)")
        if k == 0:
            ax.legend(fontsize=7, loc="best")
    fig.colorbar(sc, ax=fig.axes[:2], label="time (s)", location="bottom", shrink=0.5,
                 aspect=40)
    ax = fig.add_subplot(1, 3, 3)
    az = np.degrees(np.arctan2(C[:, 0], C[:, 2]))
    el = np.degrees(np.arctan2(C[:, 1], np.hypot(C[:, 0], C[:, 2])))
    ax.plot(times, az, ".-", ms=3, lw=0.8, label="azimuth (deg)")
    ax.plot(times, el, ".-", ms=3, lw=0.8, label="elevation (deg)")
    ax2 = ax.twinx()
    ax2.plot(times, np.linalg.norm(C, axis=1) * 100, c="0.5", lw=0.8, label="distance (cm)")
    ax2.set_ylabel("camera-head distance (cm)")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("degrees")
    ax.set_title("camera around the head over time", fontsize=9)
    ax.legend(fontsize=7, loc="upper left")
    ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_expression_traces(path: Path, times: np.ndarray, expressions: np.ndarray,
                           names: list[str], groups: dict[str, list[str]],
                           title: str = "") -> None:
    """One line per group: the mean of the named expression channels over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 3.2))
    for label, members in groups.items():
        idx = [names.index(m) for m in members if m in names]
        if idx:
            ax.plot(times, expressions[:, idx].mean(1), label=label, lw=1.2)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("score")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper right")
    if title:
        ax.set_title(title, fontsize=10)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def plot_motion(path: Path, times: np.ndarray, c2w: np.ndarray, head_pose: np.ndarray | None,
                title: str = "") -> None:
    """Camera motion and head motion, separately, in the scene's world: translation from
    the mean (cm) and rotation from the mean as yaw / pitch / roll (deg) over time.
    c2w, head_pose (N, 4, 4); head_pose None: the head is the world (nothing to plot)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(11, 5.6), sharex=True, layout="constrained")
    rows = (("camera", c2w), ("head", head_pose))
    for r, (name, T) in enumerate(rows):
        ax_t, ax_r = axes[r]
        if T is None:
            for ax in (ax_t, ax_r):
                ax.text(0.5, 0.5, "head taken as the world (fallback):\nits motion is in "
                        "the camera's", ha="center", va="center", transform=ax.transAxes)
            ax_t.set_title(f"{name} position", fontsize=9)
            continue
        t, ypr = _relative_motion(T, mean_pose(T))
        for k, axis in enumerate("xyz"):
            ax_t.plot(times, 100 * t[:, k], lw=1.0, label=axis)
        for k, axis in enumerate(("yaw", "pitch", "roll")):
            ax_r.plot(times, ypr[:, k], lw=1.0, label=axis)
        ax_t.set_title(f"{name} position from its mean (world axes)", fontsize=9)
        ax_r.set_title(f"{name} rotation from its mean", fontsize=9)
        ax_t.set_ylabel("cm")
        ax_r.set_ylabel("degrees")
        for ax in (ax_t, ax_r):
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7, loc="upper right")
    for ax in axes[1]:
        ax.set_xlabel("time (s)")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _relative_motion(T: np.ndarray, M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation (N, 3) and yaw/pitch/roll (N, 3) degrees of poses T relative to M."""
    from scipy.spatial.transform import Rotation

    rel = Rotation.from_matrix(np.einsum("nab,cb->nac", T[:, :3, :3], M[:3, :3]))
    return T[:, :3, 3] - M[:3, 3], rel.as_euler("YXZ", degrees=True)
