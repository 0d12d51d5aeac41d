"""Markdown (and LaTeX) tables of evaluation results: one run, and runs side by side in
the layout of the paper's Table 1 (Method, MSE, PSNR) plus our extra columns."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from flamenerf.data.captured_views import MAX_ANGLE_DEG
from flamenerf.errors import UserError
from flamenerf.evaluation.metrics import BEYOND_HEAD, GEOMETRY_FOLLOWS, RESPONDS
from flamenerf.io import read_json

FORMAT = "flamenerf-eval"  # metrics.json, written by evaluation/protocol.py
VERSION = 1


def fmt_mse(x: float | None) -> str:
    """The paper's style: 2.045e-3."""
    if x is None or not math.isfinite(x):
        return "–"
    if x == 0:
        return "0"
    m, e = f"{x:.3e}".split("e")
    return f"{m}e{int(e)}"


def fmt_mm(x: float | None) -> str:
    """A length in scene units (metres) as millimetres."""
    return "–" if x is None or not math.isfinite(x) else f"{1000 * x:.1f}"


def fmt(x: float | None, digits: int = 2) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def _get(res: dict, *path: str) -> float | None:
    cur: Any = res
    for p in path:
        if not isinstance(cur, dict) or cur.get(p) is None:
            return None
        cur = cur[p]
    return float(cur) if isinstance(cur, (int, float)) else None


@dataclass
class Column:
    title: str
    path: tuple[str, ...]
    format: Callable[[float | None], str]
    higher_is_better: bool | None
    """None: a reference (the ground truth's own reading), never the best."""
    shown: Callable[[dict], bool] = lambda res: True
    """Whether a run's value means something (else the cell is empty)."""

    def get(self, res: dict) -> float | None:
        return _get(res, *self.path) if self.shown(res) else None


def _frames_respond(res: dict) -> bool:
    # the tracker reads none of the built-in head's val expressions even from the frames
    # themselves, so there every run reads 0 and the count says nothing about the model
    return bool(_get(res, "driven", "retracked", "truth", "responding"))


COLUMNS = [
    Column("MSE ↓", ("heldout", "mse"), fmt_mse, False),
    Column("PSNR ↑", ("heldout", "psnr"), fmt, True),
    Column("SSIM ↑", ("heldout", "ssim"), lambda x: fmt(x, 3), True),
    Column("PSNR face ↑", ("heldout", "psnr_face"), fmt, True),
    Column("PSNR bg ↑", ("heldout", "psnr_background"), fmt, True),
    Column("Re-anim. PSNR ↑", ("reanimate", "psnr"), fmt, True),
    Column("Re-anim. SSIM ↑", ("reanimate", "ssim"), lambda x: fmt(x, 3), True),
    Column("Re-anim. PSNR face ↑", ("reanimate", "psnr_face"), fmt, True),
    Column("Re-anim. PSNR face int. ↑", ("reanimate", "psnr_face_interior"), fmt, True),
    Column("Novel-pose PSNR face ↑", ("novel_pose", "psnr_face"), fmt, True),
    Column("Driven PSNR face ↑", ("driven", "psnr_face"), fmt, True),
    Column("Driven PSNR scene ↑", ("driven", "psnr_scene"), fmt, True),
    Column("Driven PSNR expr. ↑", ("driven", "psnr_expressive"), fmt, True),
    Column("Control gain ↑", ("control", "mean_gain"), fmt, True),
    # the truth's own frames re-tracked the same way: at a small size the tracker reads
    # them weakly too, and a model's gain means something only beside it
    Column("Control gain, truth", ("control", "mean_gt_gain"), fmt, None),
    Column("Controls following ↑", ("driven", "retracked", "responding"), lambda x: fmt(x, 0),
           True, _frames_respond),
    Column("Leakage ↓", ("leakage", "mean"), fmt, False),
    Column("Controls alone ↑", ("separation", "mean_change"), fmt, True),
]
"""Table columns: the paper's two first (held-out MSE and PSNR), then ours. Leakage is
the mean absolute background change on the 0-255 scale. Controls alone: the mean share of a
control's true change from neutral that a render of it alone reproduces (`change`,
evaluation/separation.py; `reproduced` also counts the render's error at neutral, which
differs between methods more than their controls do).
Controls following: of the controls
the driven held-out renders are re-tracked for, how many meet the bar of `metrics.RESPONDS` (`driven` →
`retracked`), where the frames themselves show any."""


def _geometry_cells(g: dict | None) -> str:
    if g is None:
        return " | | |"
    return f" {g['measure']} | {fmt(g['change'], 3)} | {fmt(g['correlation'])} |"


def _best(values: list[float | None], higher: bool | None) -> float | None:
    vals = [v for v in values if v is not None and math.isfinite(v)]
    if len(vals) < 2 or higher is None:
        return None
    return max(vals) if higher else min(vals)


def compare_markdown(results: list[dict[str, Any]], labels: list[str] | None = None) -> str:
    """A Markdown table of several runs' eval results, best value per column in bold.
    Columns no run has are left out."""
    labels = labels or [str(r.get("method", "?")) for r in results]
    cols = [c for c in COLUMNS if any(c.get(r) is not None for r in results)]
    head = ["Method", "Preset", "Steps", *[c.title for c in cols]]
    rule = "|" + "|".join(["---"] * 3 + ["--:"] * len(cols)) + "|"
    lines = ["| " + " | ".join(head) + " |", rule]
    bests = [_best([c.get(r) for r in results], c.higher_is_better) for c in cols]
    for lab, r in zip(labels, results):
        cells = [lab, str(r.get("preset", "")), str(r.get("step", ""))]
        for c, b in zip(cols, bests):
            v = c.get(r)
            s = c.format(v)
            if b is not None and v is not None and c.format(v) == c.format(b):
                s = f"**{s}**"
            cells.append(s)
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def compare_latex(results: list[dict[str, Any]], labels: list[str] | None = None) -> str:
    """The same table as LaTeX (booktabs), best values in bold."""
    labels = labels or [str(r.get("method", "?")) for r in results]
    cols = [c for c in COLUMNS if any(c.get(r) is not None for r in results)]
    bests = [_best([c.get(r) for r in results], c.higher_is_better) for c in cols]

    def tex(s: str) -> str:
        return s.replace("↓", r"(\(\downarrow\))").replace("↑", r"(\(\uparrow\))")

    out = [r"\begin{tabular}{@{}l" + "l" * len(cols) + "@{}}", r"\toprule",
           " & ".join(["Method"] + [tex(c.title) for c in cols]) + r" \\ \midrule"]
    for lab, r in zip(labels, results):
        cells = [lab]
        for c, b in zip(cols, bests):
            v = c.get(r)
            s = c.format(v).replace("–", "--")
            if b is not None and v is not None and c.format(v) == c.format(b):
                s = rf"\textbf{{{s}}}"
            cells.append(s)
        out.append(" & ".join(cells) + r" \\")
    out += [r"\bottomrule", r"\end{tabular}"]
    return "\n".join(out) + "\n"


def load_eval(path: str | Path) -> dict[str, Any]:
    """A run's eval results: RUN/eval/metrics.json, or a metrics.json path."""
    p = Path(path)
    if not p.exists():
        raise UserError(f"{p}: no such run directory or metrics.json")
    if p.is_dir():
        cand = p / "eval" / "metrics.json"
        p = cand if cand.exists() or not (p / "metrics.json").exists() else p / "metrics.json"
    if not p.exists():
        hint = f" (run `flamenerf eval {path}` first)" if Path(path).is_dir() else ""
        raise UserError(f"{p}: file is missing{hint}")
    d = read_json(p)
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise UserError(f"{p}: not a flamenerf eval result (no \"format\": \"{FORMAT}\")")
    version = d.get("version", VERSION)
    if not isinstance(version, int) or isinstance(version, bool):
        raise UserError(f"{p}: version {version!r} is not a version number")
    if version > VERSION:
        raise UserError(f"{p}: version {version} is newer than this flamenerf reads "
                        f"({VERSION}); update flamenerf")
    return d


def eval_markdown(res: dict[str, Any]) -> str:
    """metrics.md of one run."""
    p = res.get("protocol", {})
    L = [f"# Evaluation: {res.get('method')} ({res.get('preset')}, step {res.get('step')})", "",
         f"- run: `{res.get('run')}`",
         f"- dataset: `{res.get('dataset')}`, evaluated at {res['resolution'][0]}x"
         f"{res['resolution'][1]} (the training resolution), device {res.get('device')}",
         f"- held-out protocol: only ω fitted per `{p.get('split')}` frame, from ω_0 with φ_0, "
         f"{p.get('fit_steps')} steps x {p.get('fit_batch_rays')} rays, lr {p.get('fit_lr')}",
         f"- view directions: {res.get('view_directions', 'as asked')} (captured: a ray more "
         f"than {MAX_ANGLE_DEG:g}° from every captured view takes its colour "
         f"{MAX_ANGLE_DEG:g}° from the nearest)",
         "",
         "| split | frames | MSE ↓ | PSNR ↑ | SSIM ↑ | PSNR face ↑ | PSNR face interior ↑ "
         "| PSNR background ↑ | PSNR scene ↑ |",
         "|---|--:|--:|--:|--:|--:|--:|--:|--:|"]
    for key, title in (("heldout", f"{p.get('split', 'val')} (held-out, ω fitted)"),
                       ("reanimate", "reanimate (ω_0, φ_0; novel expressions and cameras)"),
                       ("novel_pose", "novel_pose (ω_0, φ_0; novel head poses, expressions "
                                      "and cameras)")):
        s = res.get(key)
        if s:
            L.append(f"| {title} | {s['num_frames']} | {fmt_mse(s.get('mse'))} | "
                     f"{fmt(s.get('psnr'))} | {fmt(s.get('ssim'), 3)} | "
                     f"{fmt(s.get('psnr_face'))} | {fmt(s.get('psnr_face_interior'))} | "
                     f"{fmt(s.get('psnr_background'))} | "
                     f"{fmt(s.get('psnr_scene'))} |")
    ra = res.get("reanimate") or {}
    if "psnr_face_on_head" in ra:
        L += ["", f"Re-animation face at the head's silhouette (ground-truth depth): "
              f"{fmt(ra['psnr_face_on_head'])} dB on the head, "
              f"{fmt(ra['psnr_face_beyond_head'])} dB beyond it (the face mask's pixels more "
              f"than {100 * BEYOND_HEAD:g} cm behind the face: the room past the silhouette), "
              f"which hold "
              f"{100 * ra['face_error_beyond_head']:.0f} % of the face's squared error."]
    dr = res.get("driven")
    if dr:
        L += ["", f"**Driven** ({dr['num_frames']} `{dr.get('split')}` frames, their own camera "
              "and β, frame 0's codes, nothing fitted: what a re-animation gets)", "",
              "| PSNR ↑ | SSIM ↑ | PSNR face ↑ | PSNR face interior ↑ | PSNR background ↑ "
              "| PSNR scene ↑ | PSNR expressive region ↑ | face depth error (mm) ↓ |",
              "|--:|--:|--:|--:|--:|--:|--:|--:|",
              f"| {fmt(dr.get('psnr'))} | {fmt(dr.get('ssim'), 3)} | {fmt(dr.get('psnr_face'))} "
              f"| {fmt(dr.get('psnr_face_interior'))} "
              f"| {fmt(dr.get('psnr_background'))} | {fmt(dr.get('psnr_scene'))} "
              f"| {fmt(dr.get('psnr_expressive'))} | {fmt_mm(dr.get('face_depth_error'))} |",
              "", "*Face interior*: the face mask without its outline (H/64 pixels eroded), "
              "whose pixels mix the face with what lies behind it; "
              "*background*: outside the face mask (hair, neck and shoulders included); "
              "*scene*: outside a generous region around the person, the static world; "
              "*face depth error*: median distance along the ray between the rendered depth "
              "and the frame's face mesh (scene units taken as metres)."]
        rt = dr.get("retracked")
        if rt and rt.get("controls"):
            tr = rt["truth"]["controls"]
            L += ["", f"**Driven, re-tracked**: the driven renders and the frames themselves "
                  "re-tracked with MediaPipe's landmarker; gain and correlation against the "
                  "frames' β over these frames, for the controls the training frames vary; "
                  "*frames*: the same for the captured frames at this resolution (the most "
                  f"a render can show). Responding (gain ≥ {RESPONDS[0]}, correlation ≥ "
                  f"{RESPONDS[1]}): **{rt['responding']}** of {len(rt['controls'])} "
                  f"(frames: {rt['truth']['responding']}).", "",
                  "| control | gain | correlation | frames' gain | frames' correlation |",
                  "|---|--:|--:|--:|--:|"]
            for n, c in rt["controls"].items():
                t = tr.get(n, {})
                L.append(f"| {n} | {fmt(c['gain'])} | {fmt(c['correlation'])} | "
                         f"{fmt(t.get('gain'))} | {fmt(t.get('correlation'))} |")
            L.append(f"| **mean** | **{fmt(rt.get('mean_gain'))}** | "
                     f"{fmt(rt.get('mean_correlation'))} | "
                     f"{fmt(rt['truth'].get('mean_gain'))} | "
                     f"{fmt(rt['truth'].get('mean_correlation'))} |")
    ct = res.get("control")
    if ct and ct.get("controls"):
        gt = any("gt_gain" in c for c in ct["controls"].values())
        comp = "mean_gain_with_companions" in ct
        geo = "mean_landmark_gain" in ct
        own = "mean_mesh_gain" in ct
        shape = "geometry_measured" in ct
        L += ["", f"**Control response** ({ct.get('source')}): renders re-tracked with "
              "MediaPipe's landmarker; gain = slope of re-tracked on commanded"
              + (", gt = the same for the ground-truth images" if gt else "")
              + ("; *with companions*: swept with the controls the tracker reads with it "
                 "(same part of the face and side), as `render --expressions` keyframes do"
                 if comp else "")
              + ("; *landmark gain*: how far the re-tracked face mesh moves along the motion "
                 "the clip's own β → mesh model gives the command (1: as the clip's meshes "
                 "say; the largest such motion in pixels beside it), with companions where "
                 "the control has some" if geo else "")
              + ("; *mesh gain*: the landmarker's scores of the swept meshes themselves (its "
                 "blendshape stage on the projected β → mesh model): what a render that "
                 "followed the mesh exactly would score" if own else "")
              + ("; *geometry*: the plain measure the control moves in the re-tracked "
                 "landmarks (mouth opening or width, eye opening, brow height over the eye "
                 "distance; '-': it should fall), its change over the sweep and its "
                 "correlation with the command, with companions where the control has some"
                 if shape else ""), "",
              "| control | gain | correlation |" + (" gt gain | gt correlation |" if gt else "")
              + (" gain with companions | correlation with companions |" if comp else "")
              + (" landmark gain | motion px |" if geo else "")
              + (" mesh gain |" if own else "")
              + (" geometry | change | r |" if shape else ""),
              "|---|--:|--:|" + ("--:|--:|" if gt else "") + ("--:|--:|" if comp else "")
              + ("--:|--:|" if geo else "") + ("--:|" if own else "")
              + ("---|--:|--:|" if shape else "")]
        for n, c in ct["controls"].items():
            lg = c.get("landmark_gain_with_companions", c.get("landmark_gain"))
            lm = c.get("landmark_motion_px_with_companions", c.get("landmark_motion_px"))
            mg = c.get("mesh_gain_with_companions", c.get("mesh_gain"))
            L.append(f"| {n}{' (generic shape)' if c.get('generic') else ''} | "
                     f"{fmt(c['gain'])} | {fmt(c['correlation'])} |"
                     + (f" {fmt(c.get('gt_gain'))} | {fmt(c.get('gt_correlation'))} |"
                        if gt else "")
                     + (f" {fmt(c.get('gain_with_companions'))} | "
                        f"{fmt(c.get('correlation_with_companions'))} |" if comp else "")
                     + (f" {fmt(lg)} | {fmt(lm)} |" if geo else "")
                     + (f" {fmt(mg)} |" if own else "")
                     + (_geometry_cells(c.get("geometry_with_companions", c.get("geometry")))
                        if shape else ""))
        L.append(f"| **mean** | **{fmt(ct.get('mean_gain'))}** | "
                 f"{fmt(ct.get('mean_correlation'))} |"
                 + (f" {fmt(ct.get('mean_gt_gain'))} | |" if gt else "")
                 + (f" **{fmt(ct.get('mean_gain_with_companions'))}** | |" if comp else "")
                 + (f" **{fmt(ct.get('mean_landmark_gain'))}** | |" if geo else "")
                 + (f" **{fmt(ct.get('mean_mesh_gain'))}** |" if own else "")
                 + (" | | |" if shape else ""))
        if shape:
            L.append(f"\nMoving the face as commanded by geometry (correlation ≥ "
                     f"{GEOMETRY_FOLLOWS[0]}, change ≥ {GEOMETRY_FOLLOWS[1]} of the eye "
                     f"distance): **{ct['geometry_following']}** of {ct['geometry_measured']} "
                     f"alone, **{ct['geometry_following_with_companions']}** with companions.")
        if ct.get("responding") is not None:
            L.append(f"\nResponding (gain ≥ {RESPONDS[0]}, correlation ≥ {RESPONDS[1]}): "
                     f"**{ct['responding']}** of {len(ct['controls'])}"
                     + (f", with companions **{ct['responding_with_companions']}**"
                        if "responding_with_companions" in ct else "") + ".")
        if ct.get("figure_rows"):
            L.append(f"\n`images/control.png`: the sweep's renders, one row per control "
                     f"(low to high): {', '.join(ct['figure_rows'])}.")
        if ct.get("responsive_controls") is not None:
            L.append(f"\nMeans over the controls the landmarker sees in the ground truth "
                     f"(gt gain > 0.1): {', '.join(ct['responsive_controls']) or 'none'}.")
    dv = res.get("drive")
    if dv:
        L += ["", f"**Drive** (`{dv.get('video')}`, {dv.get('frames')} frames at the reference "
              "frame's camera with frame 0's codes): correlation over time of the driving "
              "video's tracked controls and the renders' re-tracked ones; `drive.png`: driving "
              "over result", ""]
        # on the built-in scene: the same commands through the scene's own renderer
        gt = dv.get("ground_truth")
        if gt is not None:
            L += ["Ground truth: the built-in scene's own renders of the same commands, "
                  "re-tracked the same way.", ""]
        extra = " ground truth's correlation | gain |" if gt is not None else ""
        L += ["| control | correlation | gain |" + extra,
              "|---|--:|--:|" + ("--:|--:|" if gt is not None else "")]

        def truth(c: dict) -> str:
            return f" {fmt(c.get('correlation'))} | {fmt(c.get('gain'))} |"

        for n, c in dv["controls"].items():
            L.append(f"| {n} | {fmt(c['correlation'])} | {fmt(c['gain'])} |"
                     + (truth(gt["controls"].get(n, {})) if gt is not None else ""))
        L.append(f"| **mean** | **{fmt(dv.get('mean_correlation'))}** | "
                 f"{fmt(dv.get('mean_gain'))} |"
                 + (f" {fmt(gt.get('mean_correlation'))} | {fmt(gt.get('mean_gain'))} |"
                    if gt is not None else ""))
        if not dv["controls"]:
            L.append("\nThe driving video moves no control the landmarker reports enough to "
                     "measure.")
        elif dv.get("responding") is not None:
            L.append(f"\nControls with gain ≥ {RESPONDS[0]} and correlation ≥ {RESPONDS[1]}: "
                     f"**{dv['responding']}** of {len(dv['controls'])}"
                     + (f" (ground truth {gt['responding']})"
                        if gt is not None and gt.get("responding") is not None else "")
                     + ".")
        geo = (dv.get("geometry") or {}).get("measures")
        if geo:
            L += ["", "Openings from the landmarks (lip and lid gaps over the eye distance; "
                  "comparable across faces, whatever the tracker's split into controls):", "",
                  "| measure | correlation | gain |", "|---|--:|--:|"]
            L += [f"| {n} | {fmt(m['correlation'])} | {fmt(m['gain'])} |"
                  for n, m in geo.items()]
    lk = res.get("leakage")
    if lk:
        L += ["", f"**Background leakage** ({lk['num_frames']} frames, fixed camera, expression "
              f"sweep): mean |Δ| outside the face masks dilated by {lk['dilate_px']} px "
              f"({100 * lk['background_fraction']:.0f} % of the image) = "
              f"**{fmt(lk.get('mean'))}** / 255 (max {fmt(lk.get('max'))}); inside the masks "
              f"{fmt(lk.get('face_change'))}; ground truth {fmt(lk.get('gt_mean'))}.", ""]
        if lk.get("per_control"):
            L += ["| control | " + " | ".join(lk["per_control"]) + " |",
                  "|---|" + "--:|" * len(lk["per_control"]),
                  "| leakage | " + " | ".join(fmt(v) for v in lk["per_control"].values())
                  + " |"]
    sp = res.get("separation")
    if sp:
        L += ["", "**Controls alone** (the leakage sweep against the scene's own renders of "
              "each control alone from neutral): *reproduced* = 1 − MSE(render, truth) / "
              "MSE(neutral truth, truth) inside the face masks (1 exact, 0 no better than not "
              "moving); *change* the same on the changes from neutral; *outside* the share "
              "of the render's change beyond the control's own part of the face (the "
              "truth's beside it).", "",
              "| control | reproduced | change | outside | truth outside |",
              "|---|--:|--:|--:|--:|"]
        rows = list(sp["controls"].items()) + list(sp.get("pairs", {}).items())
        L += [f"| {n} | {fmt(r['reproduced'])} | {fmt(r['change'])} | {fmt(r['outside'])} "
              f"| {fmt(r['truth_outside'])} |" for n, r in rows]
        L += [f"| **mean** | **{fmt(sp['mean_reproduced'])}** | {fmt(sp['mean_change'])} | "
              f"{fmt(sp['mean_outside'])} | |", "",
              f"Reproduced ≥ {sp['target']}: **{sp['reaching_target']}** of "
              f"{len(sp['controls'])} controls, change ≥ {sp['target']}: "
              f"**{sp.get('change_reaching_target')}**"
              + (f"; pairs (two controls the capture never combined) "
                 f"{fmt(sp['mean_pair_reproduced'])} reproduced, "
                 f"{fmt(sp.get('mean_pair_change'))} change on average"
                 if sp.get("mean_pair_reproduced") is not None else "") + "."]
        if sp.get("never_trained"):
            L.append(f"\nNever moved in the training frames: {', '.join(sp['never_trained'])}.")
    if res.get("images"):
        L += ["", "Images (`images/`): GT | render | |diff| x4 per frame; `leakage.png`: the "
              "sweep's renders and |render - neutral| x4 (blue: the face region, not counted)."]
    L += ["", f"Total time {fmt(res.get('seconds'), 0)} s."]
    return "\n".join(L) + "\n"
