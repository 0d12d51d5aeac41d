"""A filmed clip's frames as the model replays them: each frame's own codes, head pose and
tracked face mesh, with the expression free to change. What `render --split capture` renders
and what the viewer plays when a dataset track is shown as filmed; one home for how a frame's
mesh follows a changed expression, so that the prior's silhouette matches in both."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from flamenerf.data.dataset import Dataset, Frame
from flamenerf.data.head_pose import canonical_from_world, canonical_vertices, posed_vertices


def own_codes_settings(settings):
    """Render settings for frames with their own codes: the exact warp, no bake. A bake of
    each frame's ω costs what the exact warp costs (~0.06 s at 128³ on the 2-core CPU; a
    playing viewer track was no faster with it) and would stay in memory per frame.
    model/inference.RenderSettings -> the same with `warp_grid` 0."""
    import dataclasses

    return dataclasses.replace(settings, warp_grid=0)


def changed_meshes(canonical: np.ndarray, mesh_of: Callable[[np.ndarray], np.ndarray],
                   values: np.ndarray, source: np.ndarray) -> np.ndarray:
    """The tracked meshes moved as the expression model moves a face from the tracked
    expression to another: canonical (n, V, 3) + mesh_of(values[i]) - mesh_of(source[i]);
    values, source (n, E). Where they are equal, the tracked mesh itself (not the model's
    fit of it, which misses the tracker's detail)."""
    out = np.array(canonical, np.float32, copy=True)
    for i, (a, b) in enumerate(zip(values, source)):
        if not np.array_equal(a, b):
            out[i] += mesh_of(a) - mesh_of(b)
    return out


@dataclass(frozen=True)
class FilmedFrame:
    """One frame of a filmed clip: what the model needs to show it, at any expression."""

    index: int  # its place in the clip
    omega: torch.Tensor  # (code_dim,)
    phi: torch.Tensor  # (appearance_dim,)
    head: np.ndarray | None  # canonical-from-world (4, 4); None: the dataset has no head poses
    canonical: np.ndarray  # (V, 3) the tracked mesh in the canonical frame
    expression: np.ndarray  # (E,) the expression the mesh was tracked with
    own_codes: bool = True  # False: ω, φ are frame 0's (`render --codes first`)

    def same(self, other: FilmedFrame | None) -> bool:
        """Whether `other` shows what this does (a player asks for the same frame anew)."""
        return (other is not None and other.index == self.index
                and other.own_codes == self.own_codes
                and torch.equal(other.omega, self.omega) and torch.equal(other.phi, self.phi)
                and np.array_equal(other.expression, self.expression)
                and np.array_equal(other.canonical, self.canonical)
                and (other.head is None) == (self.head is None)
                and (self.head is None or np.array_equal(other.head, self.head)))

    def mesh(self, mesh_of: Callable[[np.ndarray], np.ndarray], expression: np.ndarray,
             head: np.ndarray | None = None) -> np.ndarray:
        """(V, 3) world: the frame's mesh at `expression`, posed by `head` (canonical-from-
        world (4, 4); None: the frame's own pose)."""
        v = changed_meshes(self.canonical[None], mesh_of, np.asarray(expression, np.float32)[None],
                           self.expression[None])[0]
        return posed_vertices(v, self.head if head is None else head)


class FilmedClip:
    """A dataset's frames in order: their codes, head poses and tracked meshes, made once.

    codes: one (ω, φ) for every frame (frame 0's: `render --codes first`, and what `render
    --split` gives a split whose frames have no codes, a re-animation's); None: each
    frame's own (`Run.clip_codes`: held-out frames between their neighbours';
    `Run.codes_error` must be None for the frames)."""

    def __init__(self, run, ds: Dataset, frames: list[Frame],
                 codes: tuple[torch.Tensor, torch.Tensor] | None = None):
        self.own_codes = codes is None
        if codes is None:
            self.omega, self.phi = run.clip_codes(ds, frames)  # on the run's device
        else:
            self.omega, self.phi = (c.expand(len(frames), -1) for c in codes)
        self.heads = canonical_from_world(ds, frames)
        self.canonical = canonical_vertices(ds, frames)
        self.expressions = ds.expression_matrix(frames)

    def __len__(self) -> int:
        return len(self.canonical)

    def frame(self, k: int) -> FilmedFrame:
        return FilmedFrame(k, self.omega[k], self.phi[k],
                           None if self.heads is None else self.heads[k],
                           self.canonical[k], self.expressions[k], self.own_codes)


def filmed_codes_error(run, ds: Dataset, frames: list[Frame], dataset_arg=None) -> str | None:
    """Why `frames` cannot be shown with their own codes, or None: `Run.codes_error`, or
    a dataset given in place of the run's own (`dataset_arg`; its frame indices are another
    capture's) while the run's is still where it trained."""
    from pathlib import Path

    why = run.codes_error(ds, frames)
    if why is not None or dataset_arg is None:
        return why
    trained_on = Path(run.meta["dataset"])
    if trained_on.exists() and Path(dataset_arg).resolve() != trained_on.resolve():
        return (f"{dataset_arg} is not the dataset the run trained on ({trained_on}), so its "
                "frames are not the codes' frames")
    return None
