"""The built-in synthetic portrait scene (`flamenerf synth`): a head with an ARKit-named
expression rig, a swaying body and a textured room, rendered with ground truth; or, with
`handheld`, a phone's shaky capture of a moving head against a far skyline and leaves that
sway by themselves.

Public API (heavy modules are imported lazily):
    make_scene(out, seed=0, size=256, frames=300, sway=None, ..., handheld=False)  -> dataset
    SyntheticScene(seed, size, sway, handheld).render(c2w, expression, body_pose=None,
                                                      intr=None, head_pose=None, time=None)
    scene_from_dataset(ds)  -> the SyntheticScene that made a loaded dataset
    handheld_capture(seed, size, frames)  -> the handheld capture's frames with ground truth
    CONTROLS  (the expression control names, in dataset order)
See docs/synthetic_scene.md.
"""

from __future__ import annotations

__all__ = ["CONTROLS", "SyntheticScene", "View", "handheld_capture", "make_scene",
           "scene_from_dataset"]


def __getattr__(name: str):
    if name == "CONTROLS":
        from flamenerf.synthetic.head import CONTROLS

        return CONTROLS
    if name in ("SyntheticScene", "View"):
        from flamenerf.synthetic import render

        return getattr(render, name)
    if name in ("make_scene", "scene_from_dataset", "handheld_capture"):
        from flamenerf.synthetic import scene

        return getattr(scene, name)
    raise AttributeError(f"module 'flamenerf.synthetic' has no attribute {name!r}")
