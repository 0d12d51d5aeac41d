"""The built-in synthetic scene: geometry, masks, expressions, determinism, dataset I/O."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
import torch

from flamenerf.data.dataset import Intrinsics, load_dataset
from flamenerf.data.rays import camera_rays
from flamenerf.geometry import project_points
from flamenerf.synthetic.cameras import capture_path, intrinsics, novel_path, orbit
from flamenerf.synthetic.head import CONTROLS, R_OUTER
from flamenerf.synthetic.render import SyntheticScene
from flamenerf.synthetic.scene import make_scene

SIZE = 64


@pytest.fixture(scope="module")
def still():
    """A scene with no sway (everything static but the face)."""
    return SyntheticScene(seed=3, size=SIZE, sway=0.0)


@pytest.fixture(scope="module")
def swaying():
    return SyntheticScene(seed=3, size=SIZE, sway=1.0)


def expr(**controls: float) -> np.ndarray:
    e = np.zeros(len(CONTROLS), np.float32)
    for k, v in controls.items():
        e[CONTROLS.index(k)] = v
    return e


def _reproject(va, vb, c2w_a, c2w_b, intr: Intrinsics, keep=None):
    """Back-project frame a's depth, project into b; -> predicted z in b and b's depth
    (bilinear, only where its 4 neighbours agree), for pixels landing inside b."""
    o, d = camera_rays(intr, c2w_a)
    pts = (o + d * torch.from_numpy(va.depth)[..., None]).reshape(-1, 3).numpy().astype(np.float64)
    if keep is not None:
        pts = pts[keep(pts)]
    uv, z = project_points(pts, intr, c2w_b)
    x, y = uv[:, 0] - 0.5, uv[:, 1] - 0.5  # pixel-centre coordinates
    inside = (x >= 0) & (y >= 0) & (x < intr.w - 1) & (y < intr.h - 1)
    x, y, z = x[inside], y[inside], z[inside]
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    D = vb.depth
    q = np.stack([D[y0, x0], D[y0, x0 + 1], D[y0 + 1, x0], D[y0 + 1, x0 + 1]])
    smooth = (q.max(0) - q.min(0)) < 0.01
    db = (1 - fy) * ((1 - fx) * q[0] + fx * q[1]) + fy * ((1 - fx) * q[2] + fx * q[3])
    return z[smooth], db[smooth]


# ----------------------------------------------------------------------------- conventions


def test_controls_are_arkit_names_and_enough():
    arkit = {"jawOpen", "mouthSmileLeft", "mouthSmileRight", "mouthFrownLeft",
             "mouthFrownRight", "mouthPucker", "cheekPuff", "browInnerUp", "browDownLeft",
             "browDownRight", "eyeBlinkLeft", "eyeBlinkRight", "eyeWideLeft", "eyeWideRight"}
    assert len(CONTROLS) >= 10 and set(CONTROLS) <= arkit


def test_frontal_camera_has_identity_rotation():
    c2w = orbit(0.0, 0.0, 0.6, target=np.zeros(3))
    np.testing.assert_allclose(c2w[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(c2w[:3, 3], [0, 0, 0.6], atol=1e-12)


def test_novel_cameras_are_off_the_capture_path():
    caps, _ = capture_path(300, seed=0)
    novel = novel_path(30, seed=0)
    # viewing directions (camera +z axes) and positions
    ang = np.degrees(np.arccos(np.clip(novel[:, :3, 2] @ caps[:, :3, 2].T, -1, 1)))
    dist = np.linalg.norm(novel[:, None, :3, 3] - caps[None, :, :3, 3], axis=-1)
    assert (ang.min(1) > 2.0).mean() > 0.5
    assert ((ang.min(1) > 2.0) | (dist.min(1) > 0.03)).all()


# ----------------------------------------------------------------------------- geometry


@pytest.mark.slow
def test_depth_reprojects_between_views_static_scene(still):
    intr = still.intr
    a, b = orbit(-5.0, 2.0), orbit(5.0, -2.0)
    e = expr(jawOpen=0.5, mouthSmileLeft=0.7)
    va, vb = still.render(a, e), still.render(b, e)
    assert np.isfinite(va.depth).all() and np.isfinite(vb.depth).all()
    z, db = _reproject(va, vb, a, b, intr)
    s = db - z
    assert len(s) > 0.4 * intr.w * intr.h
    # where the point is visible in b, b's depth agrees (to the bilinear interpolation of
    # the depth map); elsewhere it is occluded in b (b sees something nearer), never the
    # other way round
    assert np.median(np.abs(s)) < 2e-4
    assert (np.abs(s) < 1e-3).mean() > 0.8
    assert (s > 5e-3).mean() < 0.01


@pytest.mark.slow
def test_depth_reprojects_on_the_head_while_body_sways(swaying):
    intr = swaying.intr
    a, b = orbit(-5.0, 2.0), orbit(5.0, -2.0)
    e = expr(browInnerUp=0.6)
    va = swaying.render(a, e, swaying.body_pose(0))
    vb = swaying.render(b, e, swaying.body_pose(37))
    head = lambda p: (np.linalg.norm(p, axis=-1) < R_OUTER) & (p[:, 1] > -0.06)  # noqa: E731
    z, db = _reproject(va, vb, a, b, intr, keep=head)
    err = np.abs(db - z)
    assert len(err) > 200
    assert np.median(err) < 3e-4 and (err < 1e-3).mean() > 0.85
    # the background does move with the sway: the whole image does not reproject
    zf, dbf = _reproject(va, vb, a, b, intr)
    assert (np.abs(dbf - zf) > 2e-3).mean() > 0.15


@pytest.mark.slow
def test_depth_is_z_depth_of_pixel_centres(still):
    """A wall pixel's depth equals the plane's z-depth along the pixel-centre ray."""
    v = still.render(orbit(0.0, 0.0), expr())
    c2w = orbit(0.0, 0.0)
    o, d = camera_rays(still.intr, c2w)
    t_wall = (-0.55 - o[..., 2]) / d[..., 2]  # the wall plane z = -0.55 (no sway)
    corner = v.depth[:4, -4:]  # top right: plain wall
    np.testing.assert_allclose(corner, t_wall[:4, -4:].numpy(), rtol=1e-5)
    # a ray-length depth would be longer off-axis
    assert not np.allclose(corner, (t_wall * d.norm(dim=-1))[:4, -4:].numpy(), rtol=1e-3)


@pytest.mark.slow
def test_mesh_vertices_lie_on_the_rendered_surface(still):
    from flamenerf.synthetic.head import mesh_layout

    c2w = orbit(5.0, 3.0)
    v = still.render(c2w, expr(jawOpen=1.0, cheekPuff=0.5))
    uv, z = project_points(v.face_vertices.astype(np.float64), still.intr, c2w)
    # vertices on the front of the face (brows to lower lip), which the camera sees
    cu, cv = mesh_layout()[0].T
    front = (np.abs(cu) < 35) & (cv > -40) & (cv < 25)
    px = np.round(uv[front] - 0.5).astype(int)
    dz = z[front] - v.depth[px[:, 1], px[:, 0]]
    assert front.sum() > 100
    # they sit on the rendered surface (to a pixel's depth variation)
    assert (np.abs(dz) < 3e-3).mean() > 0.9


@pytest.mark.slow
def test_jaw_open_drops_the_chin_vertices(still):
    closed = still.head_state(expr()).vertices
    opened = still.head_state(expr(jawOpen=1.0)).vertices
    drop = closed[:, 1] - opened[:, 1]
    assert drop.max() > 0.01  # the chin goes down by more than a centimetre
    assert np.abs(drop[closed[:, 1] > 0.0]).max() < 1e-6  # nothing above the nose moves


# ----------------------------------------------------------------------------- masks


@pytest.mark.slow
def test_mask_covers_the_face_and_not_the_wall(still):
    c2w = orbit(0.0, 0.0)
    v = still.render(c2w, expr())
    m = v.mask
    assert 0.05 < m.mean() < 0.4
    # no wall (depth > 1 m from the frontal camera) inside the mask, except in the
    # dilation ring where the face mesh reaches the head's silhouette (the jaw line)
    from scipy import ndimage

    core = ndimage.binary_erosion(m, iterations=still.mask_dilate + 1)  # +1: outline pixels
    assert not (core & (v.depth > 1.0)).any()
    assert (m & (v.depth > 1.0)).sum() < 0.05 * m.sum()
    # every pixel showing the central face (eyes to chin) is in the mask
    o, d = camera_rays(still.intr, c2w)
    p = (o + d * torch.from_numpy(v.depth)[..., None]).numpy()
    r = np.linalg.norm(p, axis=-1)
    u = np.degrees(np.arctan2(p[..., 0], p[..., 2]))
    el = np.degrees(np.arcsin(np.clip(p[..., 1] / np.maximum(r, 1e-9), -1, 1)))
    face = (r < R_OUTER) & (np.abs(u) < 40) & (el > -55) & (el < 20)
    assert face.sum() > 100
    assert m[face].all()


# ----------------------------------------------------------------------------- expressions


@pytest.mark.slow
@pytest.mark.parametrize("yaw,pitch", [(0.0, 0.0), (24.0, -8.0), (-25.0, 9.0)])
def test_expression_changes_only_pixels_inside_the_face_mask(swaying, yaw, pitch):
    c2w = orbit(yaw, pitch)
    pose = swaying.body_pose(11)
    base = swaying.render(c2w, expr(), pose)
    q = lambda v: (np.clip(v.rgb, 0, 1) * 255 + 0.5).astype(np.uint8)  # noqa: E731
    b8 = q(base)
    for e in (expr(jawOpen=1.0, mouthSmileLeft=1.0, browDownRight=1.0, cheekPuff=1.0),
              expr(mouthPucker=1.0, eyeBlinkLeft=1.0, eyeWideRight=1.0, browInnerUp=1.0),
              expr(mouthFrownRight=1.0, mouthSmileRight=0.6, jawOpen=0.3)):
        v = swaying.render(c2w, e, pose)
        changed = (q(v) != b8).any(-1)
        assert changed.sum() > 20
        outside = changed & ~(base.mask | v.mask)
        assert outside.sum() == 0, f"{outside.sum()} pixels changed outside the face mask"
        # the geometry behind those pixels is equally confined
        dchanged = np.abs(v.depth - base.depth) > 1e-6
        assert not (dchanged & ~(base.mask | v.mask)).any()


@pytest.mark.slow
def test_every_control_has_a_visible_effect(still):
    c2w = orbit(0.0, 0.0)
    intr = intrinsics(128)
    base = still.render(c2w, expr(), intr=intr)
    for name in CONTROLS:
        v = still.render(c2w, expr(**{name: 1.0}), intr=intr)
        diff = np.abs(v.rgb - base.rgb).max(-1)
        assert (diff > 0.05).sum() >= 15, f"{name} barely changes the image"


# ----------------------------------------------------------------------------- dataset files


def _digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.mark.slow
def test_same_seed_gives_identical_bytes_different_seed_does_not(tmp_path):
    kw = dict(size=32, frames=4, reanimate=2, leakage_steps=1)
    a = make_scene(tmp_path / "a", seed=5, workers=1, **kw)
    b = make_scene(tmp_path / "b", seed=5, workers=2, **kw)
    c = make_scene(tmp_path / "c", seed=6, workers=1, **kw)
    da, db, dc = _digest(a), _digest(b), _digest(c)
    assert len(da) > 10 and da == db
    differing = [k for k in da if da[k] != dc.get(k)]
    assert "transforms.json" in differing
    images = [k for k in da if k.startswith("images/")]
    assert all(k in differing for k in images)


def test_scene_from_dataset_rerenders_a_frame(dataset_dir):
    from flamenerf.synthetic.scene import scene_from_dataset

    ds = load_dataset(dataset_dir)
    scene = scene_from_dataset(ds)
    f = ds.split("reanimate")[1]
    v = scene.render(f.c2w, f.expression, np.array(f.extra["body_pose"]))
    rgb8 = (np.clip(v.rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
    np.testing.assert_array_equal(rgb8, (ds.load_image(f) * 255 + 0.5).astype(np.uint8))
    np.testing.assert_array_equal(v.depth, ds.load_depth(f))


def test_cli_synth(tmp_path):
    from flamenerf.cli import main

    out = tmp_path / "cli"
    assert main(["synth", str(out), "--size", "24", "--frames", "2", "--reanimate", "1",
                 "--leakage-steps", "0", "--workers", "1"]) == 0
    assert (out / "transforms.json").exists()
    assert main(["synth", str(out), "--size", "24", "--frames", "2"]) == 2  # exists
    assert main(["synth", str(tmp_path / "h"), "--head-motion", "--sway", "1"]) == 2
    for sway in ("-5", "90"):
        assert main(["synth", str(tmp_path / "s"), "--sway", sway]) == 2
    assert not (tmp_path / "s").exists()


def test_intrinsics_frame_the_head():
    intr = intrinsics(256)
    assert intr.w == intr.h == 256 and intr.cx == 128


def test_speech_trajectory_covers_the_controls_smoothly():
    from flamenerf.synthetic.expressions import leakage_sweep, speech_trajectory

    e = speech_trajectory(300, seed=0)
    assert e.shape == (300, len(CONTROLS)) and e.min() >= 0 and e.max() <= 1
    assert (e.max(0) >= 0.9).all()  # every control is exercised strongly
    assert np.median((e > 0.1).sum(1)) >= 2  # several controls at once, most of the time
    jaw = e[:, CONTROLS.index("jawOpen")]
    assert np.abs(np.diff(jaw)).max() < 0.5  # smooth (no jumps between frames)
    assert not np.allclose(speech_trajectory(300, seed=0, stream=1), e)
    sweep, labels = leakage_sweep(3)
    assert len(sweep) == 1 + 3 * len(CONTROLS) and labels[0] == ("neutral", 0.0)
    assert ((sweep > 0).sum(1) <= 1).all()


def test_no_sway_means_identity_body_pose():
    from flamenerf.synthetic.background import sway_pose

    np.testing.assert_array_equal(sway_pose(17.0, 0.0, seed=2), np.eye(4))
    T = sway_pose(17.0, 1.0, seed=2)
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3))
    ang = np.degrees(np.arccos((np.trace(T[:3, :3]) - 1) / 2))
    assert 0 < ang < 3 and np.linalg.norm(T[:3, 3]) < 0.02


def test_every_capture_has_a_val_split():
    from flamenerf.synthetic.scene import capture_split

    for n in (2, 3, 5, 6, 12, 300):
        splits = [capture_split(t, n) for t in range(n)]
        assert splits[0] == "train" and "val" in splits
    assert [t for t in range(300) if capture_split(t, 300) == "val"] == list(range(5, 300, 10))


@pytest.mark.slow
def test_expressions_act_only_well_inside_the_face_mesh(still):
    from flamenerf.synthetic.head import GEO_STEP, MESH_STEP, Grid, mesh_layout

    head = still.head
    u, v = Grid(GEO_STEP).uv()
    ua, va = u[head.active], v[head.active]  # every texel an expression may change
    assert len(ua) > 1000
    # canonical mesh cells (quads) present in the face mesh
    uv, faces = mesh_layout()
    u0, v0 = uv[:, 0].min(), uv[:, 1].max()
    cells = set()
    for a, _, _ in faces[::2]:  # each quad is two triangles starting at its top-left vertex
        cells.add((round((v0 - uv[a, 1]) / MESH_STEP), round((uv[a, 0] - u0) / MESH_STEP)))
    for du, dv in ((-2, -2), (-2, 2), (2, -2), (2, 2)):  # a 2 degree margin all round
        rows = torch.floor((v0 - (va + dv)) / MESH_STEP).long().tolist()
        cols = torch.floor(((ua + du) - u0) / MESH_STEP).long().tolist()
        assert all((r, c) in cells for r, c in zip(rows, cols))
    # and the fields really are zero outside that region
    outside = ~head.active[head.win_rows[0]:head.win_rows[1], head.win_cols[0]:head.win_cols[1]]
    assert head.warp_basis[..., outside].abs().max() == 0
    assert head.radial_basis[..., outside].abs().max() == 0


@pytest.fixture(scope="module")
def head_motion_scene(tmp_path_factory):
    """The built-in scene with head motion at 32x32: 12 capture frames."""
    out = tmp_path_factory.mktemp("head") / "scene"
    return make_scene(out, seed=2, size=32, frames=12, sway=0.0, reanimate=3, leakage_steps=1,
                      workers=1, head_motion=True)


@pytest.mark.slow
def test_head_motion_scene_has_consistent_posed_meshes_and_masks(head_motion_scene):
    from flamenerf.data.head_pose import canonical_vertices
    from flamenerf.synthetic.scene import scene_from_dataset

    ds = load_dataset(head_motion_scene)
    assert ds.has_head_poses and "novel_pose" in ds.splits and len(ds.split("novel_pose")) == 3
    assert ds.source["head_motion"] and "head_pose" not in ds.frames[0].extra
    cap = ds.split("train") + ds.split("val")
    angles = [np.degrees(np.arccos(np.clip((np.trace(f.head_pose[:3, :3]) - 1) / 2, -1, 1)))
              for f in cap]
    assert max(angles) > 10  # the head really turns
    # the posed mesh is the head pose applied to the un-posed one, and it projects inside
    # the stored face mask
    scene = scene_from_dataset(ds)
    for f in cap[:3] + ds.split("novel_pose")[:2]:
        v = scene.render(f.c2w, f.expression, head_pose=f.head_pose).face_vertices
        assert np.allclose(v, ds.face_vertices[f.position], atol=1e-6)
        un = scene.head_state(f.expression).vertices
        assert np.allclose(v, un @ f.head_pose[:3, :3].T + f.head_pose[:3, 3], atol=1e-5)
        uv, z = project_points(ds.face_vertices[f.position], ds.intrinsics, f.c2w)
        m = ds.load_mask(f)
        px = np.clip(uv.astype(int), 0, ds.intrinsics.w - 1)
        assert (z > 0).all() and m[px[:, 1], px[:, 0]].mean() > 0.99
    # canonical meshes (frame 0's pose) differ only by expression: well under the motion
    canon = canonical_vertices(ds, cap)
    world = ds.face_vertices[[f.position for f in cap]]
    spread = lambda v: np.abs(v - v.mean(0)).max()  # noqa: E731
    assert spread(canon) < 0.5 * spread(world)


@pytest.mark.slow
def test_head_pose_moves_the_head_not_the_background():
    from flamenerf.synthetic.motion import head_pose

    scene = SyntheticScene(seed=3, size=SIZE, sway=0.0)
    c2w, e = orbit(10, 5), np.zeros(len(CONTROLS))
    a = scene.render(c2w, e)
    b = scene.render(c2w, e, head_pose=head_pose(20, -8, 3, (0.01, 0, 0.01)))
    assert np.array_equal(scene.render(c2w, e, head_pose=np.eye(4)).rgb, a.rgb)
    changed = np.abs(a.rgb - b.rgb).max(-1) > 0
    near_head = np.maximum(a.mask, b.mask)
    from scipy import ndimage

    far = ~ndimage.binary_dilation(a.depth < 0.75, iterations=10) & ~ndimage.binary_dilation(
        b.depth < 0.75, iterations=10)
    assert changed[near_head].mean() > 0.5 and not changed[far].any() and far.mean() > 0.15
