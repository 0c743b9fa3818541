"""Tests of eventcap.camera: projection (numpy, CasADi, OpenCV agree), undistortion, extrinsics, calibration I/O."""

import math

import casadi as ca
import cv2
import numpy as np
import pytest

from eventcap.camera import (DAVIS240C_CALIBRATION, Camera, davis240c_default, look_at,
                             read_rpg_calibration)


def _random_points_in_view(cam: Camera, n: int, seed: int = 0) -> np.ndarray:
    """World points whose projections fall inside the image (pixels drawn, then depths 1–6 m)."""
    rng = np.random.default_rng(seed)
    px = np.stack([rng.uniform(0, cam.width - 1, n), rng.uniform(0, cam.height - 1, n)], axis=1)
    return cam.backproject(px, rng.uniform(1.0, 6.0, n))


def _odd_camera() -> Camera:
    """Distortion with all five terms and a generic pose, so no term is tested by luck."""
    R, _ = cv2.Rodrigues(np.array([0.1, -0.3, 0.05]))
    return Camera(240, 180, 199.0, 198.5, 130.0, 95.0, np.array([-0.3, 0.12, 0.001, -0.002, 0.01]), R,
                  np.array([0.1, -0.2, 3.0]))


@pytest.mark.parametrize("cam", [davis240c_default(), _odd_camera()], ids=["davis240c", "odd"])
def test_project_matches_cv2(cam):
    pts = _random_points_in_view(cam, 500)
    rvec, _ = cv2.Rodrigues(cam.R)
    expected, _ = cv2.projectPoints(pts, rvec, cam.t, cam.K, cam.dist)
    np.testing.assert_allclose(cam.project(pts), expected[:, 0, :], atol=1e-9)


def test_project_shapes_and_behind_camera():
    cam = davis240c_default()
    pts = np.zeros((4, 5, 3))
    assert cam.project(pts).shape == (4, 5, 2)
    assert cam.depth(pts).shape == (4, 5)
    behind = cam.center + 2.0 * (cam.center - np.array([0.0, 1.0, 0.0]))  # on the far side of the lens
    assert cam.depth(behind) < 0
    assert np.all(np.isnan(cam.project(behind)))
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 3\)"):
        cam.project(np.zeros((4, 2)))


@pytest.mark.parametrize("cam", [davis240c_default(), davis240c_default(distortion=False), _odd_camera()],
                         ids=["davis240c", "pinhole", "odd"])
def test_project_sym_matches_numpy(cam):
    pts = _random_points_in_view(cam, 50, seed=1)
    P = ca.SX.sym("P", 3, 50)
    f = ca.Function("pi", [P], [cam.project_sym(P)])
    np.testing.assert_allclose(np.array(f(pts.T)).T, cam.project(pts), atol=1e-9)
    # MX and one point as a plain numpy (3,) vector give the same numbers.
    M = ca.MX.sym("M", 3, 1)
    g = ca.Function("pi1", [M], [cam.project_sym(M)])
    np.testing.assert_allclose(np.array(g(pts[0])).ravel(), cam.project(pts[0]), atol=1e-9)
    np.testing.assert_allclose(np.array(cam.project_sym(pts[3])).ravel(), cam.project(pts[3]), atol=1e-9)


def test_project_sym_rejects_wrong_layout():
    with pytest.raises(ValueError, match="3×n"):
        davis240c_default().project_sym(ca.SX.sym("P", 5, 3))


@pytest.mark.parametrize("cam", [davis240c_default(), _odd_camera()], ids=["davis240c", "odd"])
def test_undistort_inverts_projection(cam):
    xs, ys = np.meshgrid(np.arange(0, cam.width, 7.3), np.arange(0, cam.height, 5.1))
    px = np.stack([xs.ravel(), ys.ravel()], axis=1)
    rays = cam.undistort_points(px)
    back = cam.distort(rays) * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    np.testing.assert_allclose(back, px, atol=1e-9)
    # OpenCV's iterative undistortion agrees (it stops at its own tolerance, hence 1e-6).
    cv = cv2.undistortPoints(px[:, None, :], cam.K, cam.dist,
                             criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))
    np.testing.assert_allclose(rays, cv[:, 0, :], atol=1e-6)
    world = cam.backproject(px, np.full(len(px), 2.5))
    np.testing.assert_allclose(cam.project(world), px, atol=1e-9)
    np.testing.assert_allclose(cam.depth(world), 2.5, atol=1e-12)


def test_look_at_geometry():
    eye, target = np.array([0.5, 1.2, 3.0]), np.array([0.0, 1.0, 0.0])
    R, t = look_at(eye, target)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    cam = Camera(240, 180, 200.0, 200.0, 120.0, 90.0, np.zeros(5), R, t)
    np.testing.assert_allclose(cam.center, eye, atol=1e-12)
    np.testing.assert_allclose(cam.project(target), [120.0, 90.0], atol=1e-9)
    assert cam.depth(target) == pytest.approx(np.linalg.norm(target - eye))
    # World up is image up (smaller row).
    assert cam.project(target + [0, 0.3, 0])[1] < 90.0
    with pytest.raises(ValueError, match="parallel"):
        look_at([0, 5, 0], [0, 0, 0])
    with pytest.raises(ValueError, match="coincide"):
        look_at([1, 1, 1], [1, 1, 1])


def test_default_camera_sees_actor_workspace():
    """The synthetic placement keeps a jumping, kicking 1.75 m actor (facing +z) inside 240×180."""
    cam = davis240c_default()
    assert (cam.width, cam.height) == (240, 180)
    fx, fy, cx, cy, *dist = DAVIS240C_CALIBRATION
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (fx, fy, cx, cy)
    np.testing.assert_array_equal(cam.dist, dist)
    assert not davis240c_default(distortion=False).has_distortion
    assert 3.5 < np.linalg.norm(cam.center - [0, 1, 0]) < 4.5
    box = np.array([[x, y, z] for x in (-1.1, 1.1) for y in (-0.02, 2.6) for z in (-0.6, 0.9)])
    px = cam.project(box)
    assert np.all((px >= 0) & (px <= [cam.width - 1, cam.height - 1]))
    # Face to face: the actor's left hand (+x) appears on the image's right.
    assert cam.project([0.8, 1.4, 0.0])[0] > cam.project([-0.8, 1.4, 0.0])[0]


def test_max_valid_radius():
    assert math.isinf(davis240c_default().max_valid_radius)
    cam = Camera(240, 180, 200, 200, 120, 90, [-0.3, 0, 0, 0, 0])
    # d/dr r(1 + k1 r²) = 1 + 3 k1 r² vanishes at r = 1/sqrt(0.9).
    assert cam.max_valid_radius == pytest.approx(1 / math.sqrt(0.9))


def test_camera_validation_errors():
    with pytest.raises(ValueError, match=r"Camera.R: expected shape \(3, 3\)"):
        Camera(240, 180, 200, 200, 120, 90, R=np.eye(4))
    with pytest.raises(ValueError, match="rotation matrix"):
        Camera(240, 180, 200, 200, 120, 90, R=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match=r"Camera.dist: expected shape \(5,\)"):
        Camera(240, 180, 200, 200, 120, 90, dist=[0.1, 0.2])
    with pytest.raises(ValueError, match="focal lengths must be positive"):
        Camera(240, 180, 0.0, 200, 120, 90)
    with pytest.raises(ValueError, match="Camera.width: expected a positive integer"):
        Camera(240.5, 180, 200, 200, 120, 90)


def test_to_dict_round_trip():
    cam = _odd_camera()
    again = Camera.from_dict(cam.to_dict())
    pts = _random_points_in_view(cam, 10)
    np.testing.assert_array_equal(again.project(pts), cam.project(pts))
    assert again.to_dict() == cam.to_dict()


def test_read_rpg_calibration(tmp_path):
    path = tmp_path / "calib.txt"
    path.write_text("199.092 198.829 132.192 110.713 -0.3684 0.1509 -0.0003 -0.0008 0\n")
    cam = read_rpg_calibration(path, width=240, height=180)
    ref = davis240c_default()
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (ref.fx, ref.fy, ref.cx, ref.cy, 240, 180)
    np.testing.assert_array_equal(cam.dist, ref.dist)
    np.testing.assert_array_equal(cam.R, np.eye(3))

    path.write_text("# pinhole only\n\n200 201 120 90\n")
    cam = read_rpg_calibration(path, width=240, height=180)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (200, 201, 120, 90) and not cam.has_distortion


@pytest.mark.parametrize("text, message", [
    ("200 201 120 90 0.1\n", r"calib.txt:1: expected 4 numbers .* or 9 .*got 5"),
    ("\n200 201 abc 90\n", r"calib.txt:2: value 3 is not a number: 'abc'"),
    ("200 201 120 nan\n", r"calib.txt:1: value 4 is not finite"),
    ("", r"calib.txt: expected exactly one calibration line.*found 0"),
    ("200 201 120 90\n200 201 120 90\n", r"found 2 non-empty lines"),
])
def test_read_rpg_calibration_errors(tmp_path, text, message):
    path = tmp_path / "calib.txt"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        read_rpg_calibration(path, width=240, height=180)


def test_read_rpg_calibration_missing_file(tmp_path):
    with pytest.raises(ValueError, match="cannot read calibration file"):
        read_rpg_calibration(tmp_path / "nope.txt", width=240, height=180)
