"""The built-in synthetic portrait scene (`flamenerf synth`): a head with an ARKit-named
expression rig, a swaying body and a textured room, rendered with ground truth.

Public API (heavy modules are imported lazily):
    make_scene(out, seed=0, size=256, frames=300, sway=1.0, ...)  -> dataset directory
    SyntheticScene(seed, size, sway).render(c2w, expression, body_pose=None, intr=None)
    scene_from_dataset(ds)  -> the SyntheticScene that made a loaded dataset
    CONTROLS  (the expression control names, in dataset order)
See docs/synthetic_scene.md.
"""

from __future__ import annotations

__all__ = ["CONTROLS", "SyntheticScene", "View", "make_scene", "scene_from_dataset"]


def __getattr__(name: str):
    if name == "CONTROLS":
        from flamenerf.synthetic.head import CONTROLS

        return CONTROLS
    if name in ("SyntheticScene", "View"):
        from flamenerf.synthetic import render

        return getattr(render, name)
    if name in ("make_scene", "scene_from_dataset"):
        from flamenerf.synthetic import scene

        return getattr(scene, name)
    raise AttributeError(f"module 'flamenerf.synthetic' has no attribute {name!r}")
