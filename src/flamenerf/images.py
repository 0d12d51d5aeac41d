"""Image arrays: conversion, resizing, colour maps and the panels of figures and videos.

Images are (H, W, 3) float32 in [0, 1] unless a function says otherwise; writing them to
files is `flamenerf.io.save_png`'s job.
"""

from __future__ import annotations

import numpy as np


def to_uint8(img: np.ndarray) -> np.ndarray:
    if img.dtype == np.uint8:
        return img
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def resize_image(img: np.ndarray, w: int, h: int) -> np.ndarray:
    """Area-average resize of an (H, W, C) float image (what a lower-resolution camera sees)."""
    import torch

    if img.shape[1] == w and img.shape[0] == h:
        return img
    t = torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1)[None].float()
    t = torch.nn.functional.interpolate(t, size=(h, w), mode="area")
    return t[0].permute(1, 2, 0).numpy()


def colorize_depth(depth: np.ndarray, lo: float | None = None, hi: float | None = None,
                   cmap: str = "turbo") -> np.ndarray:
    """(H, W) depth -> (H, W, 3) float colour image (near = warm)."""
    import matplotlib

    d = np.asarray(depth, np.float64)
    lo = np.percentile(d, 1) if lo is None else lo
    hi = np.percentile(d, 99) if hi is None else hi
    x = 1.0 - np.clip((d - lo) / max(hi - lo, 1e-9), 0, 1)
    return matplotlib.colormaps[cmap](x)[..., :3].astype(np.float32)


# --------------------------------------------------------------------------- panels


def abs_diff(a: np.ndarray, b: np.ndarray, gain: float = 1.0) -> np.ndarray:
    """|a - b| per pixel, averaged over channels, times `gain`, as a grey (H, W, 3) image."""
    d = np.abs(np.asarray(a, np.float32) - np.asarray(b, np.float32))
    if d.ndim == 3:
        d = d.mean(-1)
    return np.repeat(np.clip(d * gain, 0, 1)[..., None], 3, -1)


def hstack(panels: list[np.ndarray], gap: int = 0) -> np.ndarray:
    """Panels of one height side by side (float [0, 1] or uint8; returns float)."""
    panels = [_as_float_rgb(p) for p in panels]
    h = panels[0].shape[0]
    out = []
    for i, p in enumerate(panels):
        if p.shape[0] != h:
            raise ValueError("hstack: panels must have one height")
        if i and gap:
            out.append(np.ones((h, gap, 3), np.float32))
        out.append(p)
    return np.concatenate(out, 1)


def vstack(rows: list[np.ndarray], gap: int = 0) -> np.ndarray:
    rows = [_as_float_rgb(r) for r in rows]
    w = max(r.shape[1] for r in rows)
    out = []
    for i, r in enumerate(rows):
        if r.shape[1] < w:
            r = np.concatenate([r, np.ones((r.shape[0], w - r.shape[1], 3), np.float32)], 1)
        if i and gap:
            out.append(np.ones((gap, w, 3), np.float32))
        out.append(r)
    return np.concatenate(out, 0)


def _as_float_rgb(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    if img.dtype == np.uint8:
        img = img.astype(np.float32) / 255
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, -1)
    return img[..., :3].astype(np.float32)


def resize_to_height(img: np.ndarray, h: int) -> np.ndarray:
    """Nearest/area resize of an image to height `h`, keeping its aspect ratio."""
    img = _as_float_rgb(img)
    if img.shape[0] == h:
        return img
    w = max(1, round(img.shape[1] * h / img.shape[0]))
    if h > img.shape[0]:  # enlarge with nearest neighbour so pixels stay crisp
        ys = np.minimum((np.arange(h) * img.shape[0]) // h, img.shape[0] - 1)
        xs = np.minimum((np.arange(w) * img.shape[1]) // w, img.shape[1] - 1)
        return img[ys][:, xs]
    return resize_image(img, w, h)


def text_strip(text: str, width: int, height: int = 14, align: str = "center") -> np.ndarray:
    """A white strip with black text (PIL's default bitmap font), (height, width, 3)."""
    from PIL import Image, ImageDraw

    im = Image.new("RGB", (max(1, width), height), (255, 255, 255))
    dr = ImageDraw.Draw(im)
    x = max(1, (width - text_width(text)) / 2) if align == "center" else 2
    dr.text((x, max(0, (height - 11) // 2)), text, fill=(0, 0, 0))
    return np.asarray(im, np.float32) / 255


def titled_row(panels: list[np.ndarray], titles: list[str], gap: int = 0) -> np.ndarray:
    """Panels of one height side by side (`hstack`), each under its title; without titles
    where one would not fit above its panel (a cut title reads as another word)."""
    panels = [_as_float_rgb(p) for p in panels]
    if any(text_width(t) + 2 > p.shape[1] for t, p in zip(titles, panels)):
        return hstack(panels, gap)
    heads = hstack([text_strip(t, p.shape[1]) for t, p in zip(titles, panels)], gap)
    return vstack([heads, hstack(panels, gap)])


def text_width(text: str) -> float:
    """Pixels `text` takes in `text_strip`'s font."""
    from PIL import Image, ImageDraw

    return ImageDraw.Draw(Image.new("RGB", (1, 1))).textlength(text)


def panel_rows(expr: np.ndarray, max_rows: int, ref: np.ndarray | None = None
               ) -> tuple[list[int], np.ndarray]:
    """The controls an expression panel shows, in the model's order: those that differ
    from `ref` (E,) by more than 0.01 first, most changed first (with 52 controls a small
    moving one would otherwise hide behind the still ones), then the largest |values|.
    -> (indices, moved (E,) bool)."""
    expr = np.asarray(expr, np.float64)
    change = np.zeros_like(expr) if ref is None else np.abs(expr - np.asarray(ref))
    moved = change > 0.01
    order = np.lexsort((-np.abs(expr), -change * moved, ~moved))[:max_rows]
    return sorted(int(j) for j in order), moved


def expression_panel(expr: np.ndarray, names: list[str], h: int, w: int,
                     max_rows: int = 8, ref: np.ndarray | None = None) -> np.ndarray:
    """Horizontal bars of an expression vector (values in [0, 1] fill the bar; negative
    ones are drawn in red), as an (h, w, 3) float image: `panel_rows`' controls, those
    that moved from `ref` darker."""
    from PIL import Image, ImageDraw

    expr = np.asarray(expr, np.float64)
    order, moved = panel_rows(expr, max_rows, ref)
    rows = max(len(order), 1)
    # draw on a canvas tall enough for the text, then shrink to (h, w)
    H = max(h, 16 * rows)
    W = max(w, round(w * H / h))
    im = Image.new("RGB", (W, H), (255, 255, 255))
    dr = ImageDraw.Draw(im)
    rh = H / rows
    for r, j in enumerate(order):
        y0 = r * rh
        v = float(expr[j])
        bw = int(np.clip(abs(v), 0, 1) * (W - 4))
        # light enough that the black name reads on top of its bar at a small size
        col = (((120, 165, 240) if moved[j] else (180, 205, 240)) if v >= 0
               else ((240, 130, 115) if moved[j] else (245, 185, 175)))
        dr.rectangle([2, y0 + rh * 0.15, 2 + bw, y0 + rh * 0.85], fill=col)
        dr.text((4, y0 + max(0, rh / 2 - 6)), f"{names[j]} {v:.2f}", fill=(0, 0, 0))
    im = im.resize((w, h), Image.LANCZOS)
    return np.asarray(im, np.float32) / 255
