"""Cameras from the background and head poses from the face, against ground truth: a tiny
textured room (tests/room.py) seen from known cameras while a head moves in it."""

from __future__ import annotations

import re

import numpy as np
import pytest
from PIL import Image
from room import render_room
from scipy.spatial.transform import Rotation

from flamenerf.geometry import rotation_angle_deg
from flamenerf.tracking.background import (BackgroundOptions, person_mask,
                                           register_background)
from flamenerf.tracking.cameras import SolveConfig, solve_cameras
from flamenerf.tracking.world import CASES, compose_world, metric_scale

N, SIZE = 20, (320, 240)


def _fov(f: float) -> float:
    return float(np.degrees(2 * np.arctan(0.5 * SIZE[0] / f)))


def _face_solve(room, mesh, fov=None):
    """The face solve as preprocessing runs it: 20 frames over 4 s of a 30 fps clip."""
    return solve_cameras(room.landmarks, np.arange(N) * 4.0 / N, mesh.vertices, mesh.faces,
                         mesh.weights, *SIZE, None, SolveConfig(fov_deg=fov), frame_step=1 / 30)


def _solve(room, mesh):
    """solve_scene's steps on in-memory frames: face solve -> background -> face solve at
    the background's focal length -> world."""
    sol = _face_solve(room, mesh)
    frames = ((k, f, person_mask(lm[:, :2], *SIZE))
              for k, (f, lm) in enumerate(zip(room.frames, room.landmarks)))
    reg = register_background(frames, BackgroundOptions(), focal=sol.focal,
                              still_head_c2w=sol.c2w)
    if reg.status == "registered":
        sol = _face_solve(room, mesh, _fov(reg.focal))
    return sol, reg, compose_world(sol.w2c, reg, mesh.vertices.mean(0))




def _align(est: np.ndarray, gt: np.ndarray):
    """Similarity (s, R, t) taking the estimated camera poses (N, 4, 4) onto the true ones:
    R from the rotations (the camera centres lie near a line), then s, t by least squares."""
    R = Rotation.from_matrix(np.einsum("nab,ncb->nac", gt[:, :3, :3], est[:, :3, :3])
                             ).mean().as_matrix()
    a, b = est[:, :3, 3] @ R.T, gt[:, :3, 3]
    da, db = a - a.mean(0), b - b.mean(0)
    s = float((da * db).sum() / (da * da).sum())
    return s, R, b.mean(0) - s * a.mean(0)


@pytest.mark.slow
def test_cameras_and_head_poses_of_a_moving_head(canonical_mesh):
    room = render_room(canonical_mesh.vertices, n=N, size=SIZE)
    sol, reg, world = _solve(room, canonical_mesh)
    assert reg.status == "registered", reg.reason
    assert reg.registered.all()
    assert reg.reprojection_error_px < 0.5
    assert reg.focal == pytest.approx(room.intr.fx, rel=0.03)
    assert world.case == "both moving"
    s, R, t = _align(world.c2w, room.c2w)
    # tolerances: the camera arc is 30 deg, 31 cm long, at 0.6 m from the head
    assert s == pytest.approx(1.0, abs=0.05)  # metric scale from the face
    centres = s * world.c2w[:, :3, 3] @ R.T + t
    assert np.linalg.norm(centres - room.c2w[:, :3, 3], axis=1).max() < 0.015
    assert rotation_angle_deg(R @ world.c2w[:, :3, :3], room.c2w[:, :3, :3]).max() < 0.5
    heads = s * world.head_pose[:, :3, 3] @ R.T + t
    assert np.linalg.norm(heads - room.head_pose[:, :3, 3], axis=1).max() < 0.025
    assert rotation_angle_deg(R @ world.head_pose[:, :3, :3],
                              room.head_pose[:, :3, :3]).max() < 1.0
    assert world.head_motion["rotation_max_deg"] > 15  # the head turned ±20 deg
    assert reg.details["still_head_hypothesis"]["chosen"] == "sfm"
    assert world.warnings == []


@pytest.mark.slow
def test_still_head_gets_one_pose_and_metric_cameras(canonical_mesh):
    room = render_room(canonical_mesh.vertices, n=N, size=SIZE, head_yaw_deg=0.0,
                       head_shift=0.0)
    _, reg, world = _solve(room, canonical_mesh)
    assert reg.status == "registered", reg.reason
    assert world.case == "moving camera, still head"
    assert reg.details["still_head_hypothesis"]["chosen"] == "still head"
    np.testing.assert_allclose(world.head_pose, np.tile(np.eye(4), (N, 1, 1)), atol=1e-9)
    # the world is the head's frame, in metres: the cameras are the true ones seen from it
    gt = np.linalg.inv(room.head_pose) @ room.c2w
    assert np.linalg.norm(world.c2w[:, :3, 3] - gt[:, :3, 3], axis=1).max() < 0.02
    assert rotation_angle_deg(world.c2w[:, :3, :3], gt[:, :3, :3]).max() < 1.0


@pytest.mark.slow
def test_still_camera_is_detected_and_held_fixed(canonical_mesh):
    room = render_room(canonical_mesh.vertices, n=N, size=SIZE, camera_deg=0.0)
    sol, reg, world = _solve(room, canonical_mesh)
    assert reg.status == "still", reg.reason
    assert world.case == "still camera, moving head"
    assert np.ptp(world.c2w, axis=0).max() == 0  # one camera for every frame
    # the head moves as the face says, relative to that camera
    np.testing.assert_allclose(np.linalg.inv(world.c2w) @ world.head_pose, sol.w2c,
                               atol=1e-9)
    assert any("does not move" in w for w in world.warnings)


@pytest.mark.slow
def test_textureless_background_falls_back_to_the_head(canonical_mesh):
    room = render_room(canonical_mesh.vertices, n=N, size=SIZE, textured=False)
    sol, reg, world = _solve(room, canonical_mesh)
    assert reg.status == "failed" and "texture" in reg.reason
    assert world.case == CASES[4]
    assert world.head_pose is None
    np.testing.assert_allclose(world.c2w, sol.c2w, atol=1e-9)  # today's cameras
    assert any("could not be solved from the background" in w for w in world.warnings)
    # --cameras head asks for this: the same world, and no warning that it failed
    asked = compose_world(sol.w2c, None, canonical_mesh.vertices.mean(0), head_asked=True)
    assert asked.case == CASES[4] and np.allclose(asked.c2w, world.c2w)
    assert not any("could not be solved" in w for w in asked.warnings)


@pytest.mark.slow
def test_textureless_background_of_a_still_camera_is_a_still_camera(canonical_mesh):
    # a plain wall behind a tripod clip: nothing to register, but its pixels stay put
    room = render_room(canonical_mesh.vertices, n=N, size=SIZE, textured=False,
                       camera_deg=0.0)
    sol, reg, world = _solve(room, canonical_mesh)
    assert reg.status == "still" and "texture" in reg.reason, reg.reason
    assert reg.details["background_change"] < 4.0
    assert world.case == "still camera, moving head"
    np.testing.assert_allclose(np.linalg.inv(world.c2w) @ world.head_pose, sol.w2c,
                               atol=1e-9)


# ----------------------------------------------------------------------------- pure math


def _poses(n=12, cam_deg=30.0, head_deg=0.0, seed=0):
    rng = np.random.default_rng(seed)
    from flamenerf.geometry import look_at

    az = np.radians(np.linspace(-cam_deg / 2, cam_deg / 2, n))
    c2w = np.stack([look_at(0.6 * np.array([np.sin(a), 0.05, np.cos(a)]), np.zeros(3))
                    for a in az])
    head = np.tile(np.eye(4), (n, 1, 1))
    yaw = np.radians(rng.uniform(-head_deg, head_deg, n))
    head[:, :3, :3] = Rotation.from_rotvec(yaw[:, None] * [0.0, 1.0, 0.0]).as_matrix()
    return c2w, head


def test_metric_scale_is_exact_for_a_still_head():
    c2w, head = _poses()
    cam_from_head = np.linalg.inv(c2w) @ head
    # COLMAP's world: rotated, shifted and 3.7x smaller
    G = Rotation.from_euler("xyz", [10, -40, 5], degrees=True).as_matrix()
    colmap = c2w.copy()
    colmap[:, :3, :3] = G @ c2w[:, :3, :3]
    colmap[:, :3, 3] = (c2w[:, :3, 3] @ G.T + [1.0, -2.0, 0.5]) / 3.7
    assert metric_scale(colmap, cam_from_head) == pytest.approx(3.7, rel=1e-9)


def test_case_detection_from_motion():
    class Reg:  # a background registration of these cameras, in metres already
        status = "registered"

    for cam_deg, head_deg, case in ((30, 0, CASES[0]), (30, 15, CASES[2]),
                                    (0.5, 0, CASES[3]), (0.5, 15, CASES[1])):
        c2w, head = _poses(cam_deg=cam_deg, head_deg=head_deg)
        Reg.c2w = c2w
        w = compose_world(np.linalg.inv(c2w) @ head, Reg, np.zeros(3))
        assert w.case == case, (cam_deg, head_deg)
        assert w.scale == pytest.approx(1.0, rel=1e-6) or cam_deg < 1
        assert any("novel views will extrapolate" in m for m in w.warnings) == (cam_deg < 5)
        # a head that turns before a still camera is seen from other sides: the room is not
        assert any("the head's own turns" in m for m in w.warnings) == (case == CASES[1])


def test_preprocess_tells_the_case_the_still_head_check_and_every_warning():
    from flamenerf.tracking.report import scene_lines

    hyp = {"sfm_error_px": 0.7, "sfm_points": 400, "chosen": "sfm", "still_head_error_px": 1.05,
           "still_head_inliers": 0.94, "still_head_turn_deg": 2.3, "still_head_shift_m": 0.01}
    scene = {"case": CASES[2], "cameras_from": "the static background",
             "warnings": ["scale floor used", "the camera barely moves"],
             "background": {"reason": "94 of 94 frames registered", "still_head_hypothesis": hyp}}
    lines = scene_lines(scene)
    assert lines[0].startswith(f"scene: {CASES[2]}; cameras from the static background")
    assert "not kept" in lines[1] and "1.05 px" in lines[1] and "0.70 px" in lines[1]
    assert lines[2:] == ["  warning: scale floor used", "  warning: the camera barely moves"]
    lines = scene_lines({**scene, "background": {"still_head_hypothesis":
                                                 {**hyp, "chosen": "still head"}}})
    assert "still-head check: kept" in lines[1]
    assert not any("--fov" in line for line in lines)
    lines = scene_lines({**scene, "background": {"still_head_hypothesis": {
        **hyp, "chosen": "still head", "rule": "SfM contradicts the face",
        "still_head_turn_max_deg": 10.6}}})
    assert "against the face's account" in lines[1]
    assert "turn up to 11 deg" in lines[2] and "--fov" in lines[2]
    assert scene_lines({"case": CASES[4], "cameras_from": "the face (head as world)",
                        "warnings": [], "background": None}) == [
        f"scene: {CASES[4]}; cameras from the face (head as world)"]


def test_controls_that_follow_the_view_are_named():
    """In an orbit the eyes follow the camera: a control that tracks the view's azimuth is
    flagged, one that does not is not, and an elevation that does not vary is not judged."""
    from flamenerf.tracking.report import view_confounds

    az = np.radians(np.linspace(-15, 15, 40))
    c2w = np.tile(np.eye(4), (40, 1, 1))
    c2w[:, :3, 3] = np.stack([0.6 * np.sin(az), np.zeros(40), 0.6 * np.cos(az)], 1)
    rng = np.random.default_rng(0)
    names = ["eyeLookOutRight", "jawOpen", "eyeBlinkLeft"]
    expr = np.stack([0.3 + 0.01 * np.degrees(az) + 0.01 * rng.normal(size=40),
                     rng.uniform(0, 0.5, 40), np.zeros(40)], 1)
    got = view_confounds(expr, names, c2w, names)
    assert list(got) == ["eyeLookOutRight"]
    assert got["eyeLookOutRight"]["azimuth_r"] > 0.9
    assert got["eyeLookOutRight"]["elevation_r"] is None  # the camera stays level


def test_a_nodding_head_before_a_still_camera_is_a_changing_view():
    """A still camera and a head that nods: the world's cameras do not move, but the view
    of the head does, and a control that follows the nod is named (the expressions clip's
    brows rise with the head up; the report once judged the world's cameras and named
    nothing)."""
    from flamenerf.tracking.report import expression_coverage

    n = 40
    pitch = np.radians(np.linspace(-10, 10, n))
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, 2, 3] = 0.6  # the camera stays put, 0.6 m in front of the head
    head = np.tile(np.eye(4), (n, 1, 1))
    head[:, :3, :3] = Rotation.from_euler("x", pitch[:, None]).as_matrix()
    rng = np.random.default_rng(0)
    names = ["browOuterUpLeft", "jawOpen"]
    expr = np.stack([0.3 + 0.02 * np.degrees(pitch) + 0.01 * rng.normal(size=n),
                     rng.uniform(0, 0.5, n)], 1)
    splits = ["train"] * n
    assert expression_coverage(expr, names, splits, c2w)["follow_the_view"] == {}
    got = expression_coverage(expr, names, splits, c2w, head)["follow_the_view"]
    assert list(got) == ["browOuterUpLeft"]
    assert abs(got["browOuterUpLeft"]["elevation_r"]) > 0.9


def test_the_report_gives_the_azimuths_the_head_is_seen_from():
    """A still camera and a head that turns ±15°: the report's azimuth range is the head's
    view's (what the model sees it from), the room's is kept apart (it once gave the room's
    alone, 0° for such a clip)."""
    from flamenerf.tracking.report import azimuth_ranges

    n = 31
    yaw = np.radians(np.linspace(-15, 15, n))
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, 2, 3] = 0.6
    head = np.tile(np.eye(4), (n, 1, 1))
    head[:, :3, :3] = Rotation.from_euler("y", yaw[:, None]).as_matrix()
    got = azimuth_ranges(c2w, head)
    assert got["room_azimuth_range_deg"] == pytest.approx([0.0, 0.0], abs=1e-6)
    assert got["azimuth_range_deg"] == pytest.approx([-15.0, 15.0], abs=1e-4)
    assert azimuth_ranges(c2w, None)["azimuth_range_deg"] == pytest.approx([0.0, 0.0], abs=1e-6)


@pytest.mark.slow
def test_handheld_shake_registers_as_rotations_and_the_sway_is_flagged(canonical_mesh,
                                                                      capfd):
    # a phone turned in the hand about its own centre (no parallax at all), the head moving
    # on its own, and a patch of the back wall swaying by itself
    room = render_room(canonical_mesh.vertices, n=N, size=SIZE, camera_deg=0.0,
                       shake_deg=4.0, sway=True)
    sol, reg, world = _solve(room, canonical_mesh)
    assert reg.status == "registered", reg.reason
    assert reg.camera_model == "rotation", reg.details.get("camera_model_choice")
    assert reg.registered.all()
    # rotations against the truth, up to the world's own orientation
    G = Rotation.from_matrix(np.einsum("nab,ncb->nac", room.c2w[:, :3, :3],
                                       world.c2w[:, :3, :3])).mean().as_matrix()
    cam_err = rotation_angle_deg(G @ world.c2w[:, :3, :3], room.c2w[:, :3, :3])
    assert np.median(cam_err) < 0.3, cam_err
    head_err = rotation_angle_deg(G @ world.head_pose[:, :3, :3],
                                  room.head_pose[:, :3, :3])
    assert np.median(head_err) < 1.0, head_err
    assert world.camera_motion["rotation_max_deg"] > 2.0  # the shake is a camera motion
    # what swayed is flagged, and little else (on the background: the person is masked)
    person = np.stack([person_mask(lm[:, :2], *SIZE) for lm in room.landmarks])
    truth = room.moving & ~person
    est = np.stack([np.asarray(Image.fromarray(m).resize(SIZE, Image.Resampling.NEAREST))
                    for m in reg.moving.astype(np.uint8) * 255]) > 0
    hit = (est & truth).sum()
    assert hit / truth.sum() > 0.5, (hit / truth.sum())
    assert hit / max(est.sum(), 1) > 0.7, (hit / max(est.sum(), 1))
    assert 0 < reg.details["moving_background_share"] < 0.5
    # COLMAP failed to start here; its own log lines ("Failed to create any sparse model")
    # stay off the terminal, the reason is ours
    assert "structure from motion" in reg.details["camera_model_choice"]["why"]
    assert not re.search(r"^[EWI]\d{8} |sfm\.cc", capfd.readouterr().err, re.M)
