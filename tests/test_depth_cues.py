"""What one camera knows about depth (eventcap/energy/floor.py, bones.py): the floor over a capture, foot contact,
and each bone's depth extent from its length and 2D points with the 3D detection's sign. Their derivatives are
checked with every other factor's in test_factors.py."""

from __future__ import annotations

import numpy as np
import pytest

from eventcap.body.kinematics import joint_positions
from eventcap.body.motions import motion_poses
from eventcap.body.skeleton import DEFAULT_REST_JOINTS
from eventcap.camera import Camera
from eventcap.energy.bones import _J, depth_extent_targets
from eventcap.energy.errors import EnergyError
from eventcap.energy.floor import contact_weights, floor_height, knot_stillness


def test_the_floor_is_the_median_lowest_sole_point_with_a_foot_in_the_air_a_third_of_the_time():
    rng = np.random.default_rng(0)
    K = 60
    y = 0.02 + rng.normal(0, 0.01, (K, 6))  # fits a centimetre off, soles 2 cm above y = 0
    y[: K // 3] += 0.3  # both feet in the air (a jump) in a third of the frames
    h = floor_height(y)
    assert h == pytest.approx(0.02 - 0.01, abs=0.006)  # the lowest of 6 noisy points sits ~1σ low
    assert floor_height(np.full((3, 6), np.nan)) is None
    with pytest.raises(EnergyError, match=r"expected sole heights of shape \(K, 6\), got \(4,\)"):
        floor_height(np.zeros(4))


def test_contact_needs_a_slow_foot_near_the_floor_that_the_events_call_still():
    p = np.zeros((4, 6, 3))
    p[1, :, 1] = 0.15  # lifted 15 cm
    speed = np.zeros((4, 6))
    speed[2] = 1.0  # moving at 1 m/s
    c = contact_weights(p, speed, 0.0, 0.3, 0.05)
    assert np.allclose(c[0], 1.0) and np.all(c[1] < 1e-3) and np.all(c[2] < 1e-4) and np.allclose(c[3], 1.0)
    still = np.ones((4, 24))
    still[3, 7] = 0.0  # the left ankle moves by its events: the left sole points (first three) are not in contact
    c = contact_weights(p, speed, 0.0, 0.3, 0.05, still)
    assert np.allclose(c[3], [0, 0, 0, 1, 1, 1])
    assert np.allclose(knot_stillness(np.array([[1.0], [0.2]]), 3)[:, 0], [1.0, 0.2, 0.2])
    with pytest.raises(EnergyError, match="expected a speed and a height > 0"):
        contact_weights(p, speed, 0.0, 0.0, 0.05)


def _camera():
    return Camera(width=240, height=180, fx=200.0, fy=200.0, cx=120.0, cy=90.0, R=np.diag([1.0, -1.0, -1.0]),
                  t=np.array([0.0, 1.0, 3.0]))  # looking along the world -z, y up


def test_depth_extents_of_exact_2d_points_are_the_true_ones_on_the_3d_detections_side():
    """From exact 2D points and the true depth of each bone's first end, the root on the side of the 3D
    detection's sign is the bone's true depth extent; the 3D detection's sign flipped picks the other root (the
    mirror image about the first end's ray), unless both roots lie on one side."""
    cam = _camera()
    S = motion_poses("karate_kick", np.linspace(0.2, 1.4, 7), seed=0)
    J = joint_positions(S, DEFAULT_REST_JOINTS)
    Jc = cam.to_camera(J)
    n = cam.undistort_points(cam.project(J))
    length = np.linalg.norm(DEFAULT_REST_JOINTS[_J[:, 1]] - DEFAULT_REST_JOINTS[_J[:, 0]], axis=1)
    dz = Jc[:, _J[:, 1], 2] - Jc[:, _J[:, 0], 2]
    args = (n[:, _J[:, 0]], n[:, _J[:, 1]], Jc[:, _J[:, 0], 2], np.broadcast_to(length, dz.shape))
    target, conf = depth_extent_targets(*args, dz, 0.05, 2.0 / 200)
    assert np.allclose(target, dz, atol=1e-9)
    flipped, _ = depth_extent_targets(*args, -dz, 0.05, 2.0 / 200)
    a = np.concatenate([args[0], np.ones(dz.shape + (1,))], -1)
    b = np.concatenate([args[1], np.ones(dz.shape + (1,))], -1)
    z_i = args[2]
    mirror = 2 * np.sum(a * b, -1) * z_i / np.sum(b * b, -1) - (z_i + dz) - z_i  # the other root's extent
    opposite = (np.sign(mirror) != np.sign(dz)) & (np.abs(dz) > 1e-3)
    assert opposite.sum() > 30 and np.allclose(flipped[opposite], mirror[opposite], atol=1e-9)
    steep = np.abs(dz) > 0.1
    # the confidence: low for a bone across the line of sight (2 px of noise spread its extent widely)
    across = np.abs(dz) < 0.02
    assert across.any() and conf[across].max() < 0.3 and np.median(conf[steep]) > 0.5
    with pytest.raises(EnergyError, match="bones_sign_m: expected a depth > 0"):
        depth_extent_targets(*args, dz, 0.0, 0.01)


def test_the_detectors_hip_and_shoulder_widths_are_measured_from_the_detections():
    """Detections whose hips sit 15% and shoulders 10% nearer together than the template's joints (as BlazePose's
    on the ANNY actor), on a kick seen from the side and the front: the widths are recovered from the 2D points,
    the 3D detections' directions and the fits' depths, and the template with those widths projects where the
    detections are."""
    from eventcap.body.kinematics import landmark_positions
    from eventcap.body.procedural import procedural_template
    from eventcap.energy.detections import FrameDetections
    from eventcap.energy.landmarks import LandmarkWidths, measure_widths, with_widths

    tpl = procedural_template(seed=0, target_faces=2000)
    cam = _camera()
    S = motion_poses("karate_kick", np.linspace(0.0, 1.9, 40), seed=0, template=tpl)
    truth = LandmarkWidths({"l_hip-r_hip": 0.85, "l_shoulder-r_shoulder": 0.9}, {})
    seen = with_widths(tpl, truth)
    J = joint_positions(S, tpl.rest_joints)
    det = FrameDetections(cam.project(landmark_positions(S, seen)), np.ones((40, 25)), J - J[:, :1],
                          np.ones((40, 24)))
    w = measure_widths(tpl, cam, S, det)
    assert w.scale["l_hip-r_hip"] == pytest.approx(0.85, abs=0.01)
    assert w.scale["l_shoulder-r_shoulder"] == pytest.approx(0.9, abs=0.01)
    assert min(w.frames.values()) >= 5
    moved = landmark_positions(S, with_widths(tpl, w))
    assert np.abs(cam.project(moved) - det.keypoints_2d).max() < 0.2  # px
    # too few frames across the line of sight: the template's widths
    few = measure_widths(tpl, cam, S[:3], det.rows([0, 1, 2]))
    assert few.scale == {"l_hip-r_hip": 1.0, "l_shoulder-r_shoulder": 1.0} and set(few.frames.values()) == {0}
