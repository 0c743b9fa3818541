"""The `blazepose` detect stage: Google's BlazePose GHUM networks run offline on a real photograph of a person
(hand-checked key points), the landmark mappings, the crop geometry, finding the person from events, and the
stage's contract (conformance, errors, lost/re-found logging)."""

from __future__ import annotations

import functools
import logging
import math

import cv2
import numpy as np
import pytest

from eventcap.artifacts.recording import EventStream, FrameStack, Recording
from eventcap.body.skeleton import JOINT_INDEX, JOINT_NAMES, LANDMARK_INDEX, LANDMARK_NAMES
from eventcap.camera import Camera
from eventcap.core.config import build_config
from eventcap.events import EVENT_DTYPE, make_events
from eventcap.core.registry import load_registry
from eventcap.core.stage import StageContext
from eventcap.core.testing import StageConformance

from eventcap_detect import blazepose as bp  # noqa: E402

# Grace Hopper's portrait (US Navy photograph, public domain), shipped with matplotlib's sample data: 512 x 600,
# head and shoulders, facing the camera. Key points checked by hand on a zoomed, gridded copy (image pixels,
# x right, y down): pupils, nose tip, and the shoulder joints inside the jacket's outline. "left" is hers (image
# right).
HAND_CHECKED = {"nose": (266, 240), "r_eye": (220, 190), "l_eye": (305, 186),
                "r_shoulder": (100, 400), "l_shoulder": (430, 400)}
# The networks put her eyes 15-25 px below the pupils (on the lower rims of her glasses; seen on the drawn
# detections), the nose within 5 px; 30 px is a third of the distance between the eyes, so a swap still fails.
TOLERANCE_PX = {"nose": 20, "r_eye": 30, "l_eye": 30, "r_shoulder": 35, "l_shoulder": 35}


@functools.lru_cache(maxsize=1)
def photo_rgb() -> np.ndarray:
    import matplotlib.cbook

    path = matplotlib.cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)
    bgr = cv2.imread(str(path))
    assert bgr is not None and bgr.shape == (600, 512, 3)
    return np.ascontiguousarray(bgr[:, :, ::-1])


@functools.lru_cache(maxsize=1)
def photo_linear() -> np.ndarray:
    """The photo as a camera's linear grey intensity in [0, 1] (the JPEG's sRGB-like gamma undone)."""
    grey = cv2.cvtColor(photo_rgb(), cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    return grey ** 2.2


@functools.lru_cache(maxsize=2)
def net(model: str = "full") -> bp.BlazePose:
    return bp.BlazePose(model)


@functools.lru_cache(maxsize=1)
def photo_recording() -> Recording:
    """Three frames of the photo, 40 ms apart, no events: a recording a real camera could have made."""
    h, w = photo_linear().shape
    cam = Camera(w, h, 500.0, 500.0, w / 2, h / 2, np.zeros(5), np.eye(3), np.zeros(3))
    frames = FrameStack(images=np.repeat(photo_linear()[None], 3, axis=0), t_us=np.array([0, 40_000, 80_000]),
                        exposure_us=np.full(3, 10_000), height=h, width=w)
    return Recording(events=EventStream(events=np.zeros(0, EVENT_DTYPE), width=w, height=h), camera=cam,
                     frames=frames, name="grace_hopper")


def detect(rec: Recording, **config):
    spec = load_registry().get("blazepose")
    cfg = build_config(spec, {"at": "frames", "gamma": 2.2, **config}, "stages.detect")
    return spec.load_run()({"recording": rec}, cfg, StageContext(node="detect", stage="blazepose"))["detections"]


# -- the networks on a real photograph ------------------------------------------------------------------------------
@pytest.mark.parametrize("model", ["full", "lite"])
def test_real_photo_hand_checked_keypoints(model):
    rgb = photo_rgb()
    found = net(model).detect_person(rgb)
    assert found is not None, "the person detector missed a frontal portrait"
    roi, score = found
    assert score > 0.7
    pose = net(model).landmarks(rgb, roi)
    assert pose.flag > 0.9
    w = bp.mapping_matrix(bp.LANDMARK_FROM_BLAZEPOSE, LANDMARK_NAMES)
    xy, conf = bp.mapped(w, pose.xy, pose.visibility * pose.presence)
    for name, (x, y) in HAND_CHECKED.items():
        i = LANDMARK_INDEX[name]
        err = math.hypot(xy[i, 0] - x, xy[i, 1] - y)
        assert err < TOLERANCE_PX[name], f"{model}: {name} at {xy[i].round(1)}, hand-checked ({x}, {y}): {err:.1f} px"
        assert conf[i] > 0.5, f"{model}: {name} confidence {conf[i]:.2f}"
    # her left eye and shoulder are on the image's right: the mapping keeps the person's sides
    assert xy[LANDMARK_INDEX["l_eye"], 0] > xy[LANDMARK_INDEX["r_eye"], 0] + 50
    # hips and knees are below the picture: they must not be reported as seen there
    for name in ("r_knee", "l_knee", "r_ankle", "l_ankle"):
        assert conf[LANDMARK_INDEX[name]] < 0.3 or xy[LANDMARK_INDEX[name], 1] > rgb.shape[0]


def test_real_photo_world_landmarks_are_metric_camera_axes():
    pose = net().landmarks(photo_rgb(), net().detect_person(photo_rgb())[0])
    wl = {n: pose.world[i] for i, n in enumerate(bp.BLAZEPOSE_NAMES)}
    shoulders = np.linalg.norm(wl["left_shoulder"] - wl["right_shoulder"])
    assert 0.25 < shoulders < 0.45, f"shoulder width {shoulders:.3f} m"
    assert wl["left_shoulder"][0] > wl["right_shoulder"][0]  # her left is +x (image right) in camera axes
    assert wl["nose"][1] < wl["left_shoulder"][1] < 0.0  # y down, origin between the hips: head above (negative)
    assert np.allclose(pose.world[[23, 24]].mean(axis=0)[:2], 0.0, atol=0.03)  # hips centred at the origin


def test_a_rotated_camera_rotates_the_points_not_the_body():
    """Turning the image by 90 degrees (a camera rolled about its axis): 2D points follow the image, the world
    landmarks turn by the same angle about the camera's z axis, and the body found is the same."""
    rgb = photo_rgb()
    rot = np.ascontiguousarray(np.rot90(rgb, k=-1))  # clockwise: (x, y) -> (h - 1 - y, x)
    a = net().landmarks(rgb, net().detect_person(rgb)[0])
    b = net().landmarks(rot, net().detect_person(rot)[0])
    h = rgb.shape[0]
    expect = np.stack([h - 1 - a.xy[:, 1], a.xy[:, 0]], axis=1)
    face_and_shoulders = [0, 2, 5, 11, 12]
    assert np.median(np.linalg.norm(b.xy[face_and_shoulders] - expect[face_and_shoulders], axis=1)) < 15
    turned = a.world[:, [1, 0, 2]] * np.array([-1.0, 1.0, 1.0])  # (x, y) -> (-y, x): 90 degrees about z
    err = np.linalg.norm(b.world[face_and_shoulders] - turned[face_and_shoulders], axis=1)
    assert np.median(err) < 0.05, f"world landmarks of the rolled image differ by {err.round(3)} m"


def test_deterministic():
    a = net().landmarks(photo_rgb(), bp.Roi(265, 420, 700, 0.1))
    b = bp.BlazePose("full").landmarks(photo_rgb(), bp.Roi(265, 420, 700, 0.1))
    assert np.array_equal(a.xy, b.xy) and np.array_equal(a.world, b.world) and a.flag == b.flag


def test_unknown_model_named():
    with pytest.raises(ValueError, match=r"expected one of \['full', 'lite'\], got 'huge'"):
        bp.BlazePose("huge")


# -- mappings ---------------------------------------------------------------------------------------------------------
def test_landmark_mapping_rows_and_what_is_left_out():
    w = bp.mapping_matrix(bp.LANDMARK_FROM_BLAZEPOSE, LANDMARK_NAMES)
    assert w.shape == (25, 33)
    mapped = w.any(axis=1)
    assert np.allclose(w[mapped].sum(axis=1), 1.0)
    assert {LANDMARK_NAMES[i] for i in np.flatnonzero(~mapped)} == {"l_small_toe", "r_small_toe"}
    names = {n: i for i, n in enumerate(bp.BLAZEPOSE_NAMES)}
    assert w[LANDMARK_INDEX["neck"], names["left_shoulder"]] == 0.5
    assert w[LANDMARK_INDEX["l_wrist"], names["left_wrist"]] == 1.0
    # every left landmark comes from a BlazePose "left_" point and vice versa
    for i, n in enumerate(LANDMARK_NAMES):
        src = [bp.BLAZEPOSE_NAMES[j] for j in np.flatnonzero(w[i])]
        if n.startswith("l_"):
            assert all(s.startswith("left_") for s in src), (n, src)
        if n.startswith("r_"):
            assert all(s.startswith("right_") for s in src), (n, src)


def test_joint_mapping_leaves_out_what_has_no_counterpart():
    w = bp.mapping_matrix(bp.JOINT_FROM_BLAZEPOSE, JOINT_NAMES)
    missing = {JOINT_NAMES[i] for i in np.flatnonzero(~w.any(axis=1))}
    assert missing == {"spine1", "spine2", "spine3", "neck", "l_collar", "r_collar", "head"}
    pts = np.arange(33 * 3, dtype=float).reshape(33, 3)
    conf = np.linspace(0.1, 0.9, 33)
    pos, c = bp.mapped(w, pts, conf)
    names = {n: i for i, n in enumerate(bp.BLAZEPOSE_NAMES)}
    hips = [names["left_hip"], names["right_hip"]]
    assert np.allclose(pos[JOINT_INDEX["pelvis"]], pts[hips].mean(axis=0))
    assert c[JOINT_INDEX["pelvis"]] == conf[hips].min()  # a mean is as sure as its least sure source
    assert c[JOINT_INDEX["head"]] == 0.0 and np.all(pos[JOINT_INDEX["head"]] == 0.0)


def test_mapping_rejects_unknown_targets():
    with pytest.raises(KeyError, match="mapping target 'chin'"):
        bp.mapping_matrix({"chin": ("nose",)}, LANDMARK_NAMES)


# -- geometry -------------------------------------------------------------------------------------------------------
def test_anchor_layout():
    a = bp.ssd_anchors()
    assert a.shape == (2254, 2)  # 28x28x2 + 14x14x2 + 7x7x6
    assert np.allclose(a[0], [0.5 / 28, 0.5 / 28]) and np.allclose(a[1], a[0])
    assert np.allclose(a[1568], [0.5 / 14, 0.5 / 14]) and np.allclose(a[-1], [6.5 / 7, 6.5 / 7])


def test_roi_rotation_and_crop_mapping():
    up = bp.roi_from_points(np.array([100.0, 200.0]), np.array([100.0, 150.0]))
    assert up.rotation == pytest.approx(0.0) and up.size == pytest.approx(2 * 50 * 1.25)
    assert np.allclose(up.to_image(np.array([128.0, 128.0]), 256), [100, 200])
    right = bp.roi_from_points(np.array([100.0, 200.0]), np.array([150.0, 200.0]))  # body lying, head right
    assert right.rotation == pytest.approx(math.pi / 2)
    top_of_crop = right.to_image(np.array([128.0, 0.0]), 256)  # the crop's top is the head's side
    assert top_of_crop[0] > 100 + 60 and abs(top_of_crop[1] - 200) < 1e-9


def test_events_roi_finds_the_moving_region_and_ignores_noise():
    rng = np.random.default_rng(0)
    n = 4000  # a moving 30 x 60 px body at (100..130, 50..110), each pixel firing several times
    ev = make_events(np.sort(rng.integers(0, 10_000, n)), rng.integers(100, 130, n), rng.integers(50, 110, n),
                     rng.choice([-1, 1], n))
    roi = bp.events_roi(ev, 5_000, 10_000, 240, 180)
    assert abs(roi.cx - 114.5) < 2 and abs(roi.cy - 79.5) < 2
    assert 60 * 1.25 * 0.9 < roi.size < 60 * 1.25 * 1.1 and roi.rotation == 0.0
    px = rng.permutation(240 * 180)[:300]  # isolated noise: one event per pixel
    noise = make_events(np.sort(rng.integers(0, 10_000, 300)), px % 240, px // 240, np.ones(300))
    assert bp.events_roi(noise, 5_000, 10_000, 240, 180) is None
    assert bp.events_roi(ev, 50_000, 10_000, 240, 180) is None  # nothing moves then


# -- the stage ------------------------------------------------------------------------------------------------------
def test_stage_on_the_photo_maps_2d_and_3d():
    rec = photo_recording()
    det = detect(rec)
    assert det.keypoints_2d.shape == (3, 25, 2) and det.joints_3d.shape == (3, 24, 3)
    assert np.array_equal(det.t_us, rec.frames.t_us)
    assert "blazepose" in det.detector and "frames" in det.detector
    # on the grey image (what a DAVIS gives) the networks put the face points lower than on the colour photo:
    # nose ~17 px, eyes ~35 px below the hand-checked points (measured); 40 px still tells the eyes apart
    grey_tolerance = {**TOLERANCE_PX, "r_eye": 40, "l_eye": 40, "nose": 30}
    for name, (x, y) in HAND_CHECKED.items():
        i = LANDMARK_INDEX[name]
        assert np.all(np.hypot(*(det.keypoints_2d[:, i] - [x, y]).T) < grey_tolerance[name])
        assert np.all(det.confidence_2d[:, i] > 0.5)
    assert np.all(det.keypoints_2d[:, LANDMARK_INDEX["l_eye"], 0] > det.keypoints_2d[:, LANDMARK_INDEX["r_eye"], 0])
    assert np.all(det.confidence_2d[:, [LANDMARK_INDEX["l_small_toe"], LANDMARK_INDEX["r_small_toe"]]] == 0)
    # below the picture: not reported (confidence 0, position 0)
    knees = [LANDMARK_INDEX["l_knee"], LANDMARK_INDEX["r_knee"]]
    assert np.all(det.confidence_2d[:, knees] == 0) and np.all(det.keypoints_2d[:, knees] == 0)
    # 3D: root-relative, world axes (identity camera here), spine/head left out
    assert np.allclose(det.joints_3d[:, 0], 0.0)
    assert np.all(det.confidence_3d[:, [JOINT_INDEX[n] for n in ("spine1", "neck", "head")]] == 0)
    sh = det.joints_3d[:, JOINT_INDEX["l_shoulder"]] - det.joints_3d[:, JOINT_INDEX["r_shoulder"]]
    assert np.all(sh[:, 0] > 0.2)
    # the same photo three times: found, then tracked (a crop the model frames itself); the crops differ, and
    # so do the points, by up to ~8 px (measured) on this 512 x 600 image
    idx = [LANDMARK_INDEX[n] for n in HAND_CHECKED]
    assert np.abs(det.keypoints_2d[1:, idx] - det.keypoints_2d[:1, idx]).max() < 15.0


def test_stage_world_axes_follow_the_camera_rotation():
    """A camera turned 90 degrees about the world's vertical: the camera's x axis is the world's -z."""
    rec = photo_recording()
    yaw = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])  # world -> camera
    cam = Camera(rec.width, rec.height, 500.0, 500.0, rec.width / 2, rec.height / 2, np.zeros(5), yaw, np.zeros(3))
    turned = Recording(events=rec.events, camera=cam, frames=rec.frames, name="turned")
    a, b = detect(rec), detect(turned)
    assert np.allclose(b.joints_3d, a.joints_3d @ yaw, atol=1e-9)


def test_stage_errors_name_the_key():
    with pytest.raises(ValueError, match="stages.detect.at: expected frames | latent | tracking, got 'raw'"):
        detect(photo_recording(), at="raw")
    with pytest.raises(ValueError, match=r"at=latent: .* 'latent' input .*sharpen.latent"):
        detect(photo_recording(), at="latent")


def test_losing_and_finding_the_person_is_logged(caplog):
    """Frames 0-1 the photo, frame 2 a blank image (the person is gone), frame 3 the photo again."""
    img = photo_linear()
    images = [img, img, np.zeros_like(img), img]
    times = np.arange(4) * 40_000
    messages = []
    seq = bp.detect_sequence(net(), images, times, gamma=2.2, log=messages.append)
    assert [p is not None for p in seq.poses] == [True, True, False, True]
    assert seq.found_by == ["detector", "tracked", "", "detector"]
    assert messages == ["lost the person at image 2 (t = 80000 us)",
                        "found the person again at image 3 (t = 120000 us) by the detector"]


def test_finding_by_events_when_asked():
    """find=events: the first ROI comes from the events (here a box of events over the person), not the detector."""
    img = photo_linear()
    rng = np.random.default_rng(1)
    n = 100_000  # on every third pixel, so that each fires several times
    ev = make_events(np.sort(rng.integers(0, 10_000, n)), 3 * rng.integers(20, 153, n), 3 * rng.integers(34, 199, n),
                     rng.choice([-1, 1], n))
    seq = bp.detect_sequence(net(), [img], np.array([5_000]), find="events", events=ev, gamma=2.2,
                             events_window_us=10_000)
    assert seq.found_by == ["events"]
    nose = seq.poses[0].xy[0]
    assert math.hypot(nose[0] - 266, nose[1] - 240) < 25
    with pytest.raises(ValueError, match="find='events' needs the recording's events"):
        bp.detect_sequence(net(), [img], np.array([0]), find="events")


class TestBlazePoseConformance(StageConformance):
    stage_name = "blazepose"
    config_overrides = {"at": "frames", "gamma": 2.2}
    sensitive = ("model", "lite")

    def make_inputs(self):
        return {"recording": photo_recording()}


def test_log_says_how_many_images_and_how_fast(caplog):
    with caplog.at_level(logging.INFO):
        detect(photo_recording())
    assert any("person found in 3 of 3 images" in r.getMessage() and "ms per image" in r.getMessage()
               for r in caplog.records)


def test_stage_at_latent_and_tracking_uses_the_edi_images():
    """at=latent looks at the latent images (here the photo itself, as EDI gives for a still scene without
    events); at=tracking at latent images every tracking_step_us from the nearest frame and the events: with no
    events they are that frame."""
    from eventcap.artifacts.tracking import LatentFrames

    rec = photo_recording()
    eps = 1e-3
    logs = np.log(rec.frames.images ** (1 / 2.2) + eps).astype(np.float32)  # gamma applied here, not in the stage
    latent = LatentFrames(log_images=logs, t_us=rec.frames.t_us.copy(), contrast=0.2, eps=eps,
                          height=rec.height, width=rec.width)
    spec = load_registry().get("blazepose")

    def run(**cfg):
        c = build_config(spec, {"gamma": 1.0, **cfg}, "stages.detect")
        return spec.load_run()({"recording": rec, "latent": latent}, c,
                               StageContext(node="detect", stage="blazepose"))["detections"]

    lat = run(at="latent")
    assert np.array_equal(lat.t_us, rec.frames.t_us) and "latent" in lat.detector
    trk = run(at="tracking", tracking_step_us=20_000)
    assert np.array_equal(trk.t_us, np.arange(0, 80_001, 20_000))
    # every image holds the same still photo; the crops, each framed by the previous pose, wander (hips below
    # the picture make the framing points unsteady: up to ~25 px over 5 images), the nose stays on the nose
    nose = LANDMARK_INDEX["nose"]
    assert np.all(np.hypot(*(trk.keypoints_2d[:, nose] - HAND_CHECKED["nose"]).T) < 30)
    assert np.all(trk.confidence_2d[:, nose] > 0.5)
    with pytest.raises(ValueError, match=r"tracking_step_us: expected an integer > 0, got 0"):
        run(at="tracking", tracking_step_us=0)


def test_no_person_anywhere_fails_the_stage_with_the_reason():
    from eventcap.core.stage import StageFailed

    rec = photo_recording()
    blank = FrameStack(images=np.zeros_like(rec.frames.images), t_us=rec.frames.t_us,
                       exposure_us=rec.frames.exposure_us, height=rec.height, width=rec.width)
    empty = Recording(events=rec.events, camera=rec.camera, frames=blank, name="blank")
    with pytest.raises(StageFailed, match=r"^blazepose \(full, at frames\): no person in 3 of 3 images; the network "
                                          r"saw no person in its images: look at the recording in `eventcap "
                                          r"preview FILE`") as info:
        detect(empty)
    assert info.value.status == "no_person"


def test_events_roi_on_a_sparse_sensor_takes_clustered_pixels_that_fired_once():
    """A DVS128 walking recording: 200 events of a 20 x 40 px body, no pixel twice; noise of 100 isolated events."""
    rng = np.random.default_rng(1)
    px = rng.permutation(20 * 40)[:200]
    body = make_events(np.sort(rng.integers(0, 10_000, 200)), 50 + px % 20, 40 + px // 20, np.ones(200))
    roi = bp.events_roi(body, 5_000, 10_000, 128, 128)
    assert roi is not None and abs(roi.cx - 59.5) < 2 and abs(roi.cy - 59.5) < 3
    noise_px = rng.permutation(128 * 128)[:100]
    noise = make_events(np.sort(rng.integers(0, 10_000, 100)), noise_px % 128, noise_px // 128, np.ones(100))
    assert bp.events_roi(noise, 5_000, 10_000, 128, 128) is None


def test_detect_sequence_keeps_the_alternative_the_network_scores_best():
    """Of the images of one moment, the pose with the highest flag is kept and found_by names its image."""
    from types import SimpleNamespace

    class Net:  # scores an image by its mean: the landmark model's flag, no person detector
        presence_threshold = 0.5

        def detect_person(self, rgb):
            return None

        def landmarks(self, rgb, roi):
            flag = float(rgb.mean()) / 255.0
            xy = np.tile([[roi.cx, roi.cy]], (35, 1))
            return SimpleNamespace(flag=flag, roi=roi, next_roi=lambda: roi, xy=xy)

    images = [np.full((20, 20), 0.3), np.full((20, 20), 0.3)]
    alts = lambda i, im: [("dim", im), ("bright", np.full((20, 20), 0.9)), ("mid", np.full((20, 20), 0.7))]
    seq = bp.detect_sequence(Net(), images, np.array([0, 40_000]), alternatives=alts)
    assert [round(p.flag, 2) for p in seq.poses] == [0.9, 0.9]
    assert seq.found_by == ["image@bright", "tracked@bright"]
    plain = bp.detect_sequence(Net(), images, np.array([0, 40_000]))
    assert plain.poses == [None, None] and plain.found_by == ["", ""]


def test_poses_agree_when_their_landmarks_lie_within_a_share_of_the_body():
    """agreeing_poses: the median distance over the body landmarks against ratio x the kept pose's box diagonal."""
    from types import SimpleNamespace

    rng = np.random.default_rng(3)
    xy = np.column_stack([rng.uniform(0, 60, 35), rng.uniform(0, 80, 35)])
    best = SimpleNamespace(xy=xy)
    ref = xy[list(bp.AGREE_POINTS)]
    diag = float(np.hypot(*(ref.max(0) - ref.min(0))))
    near = SimpleNamespace(xy=xy + [0.09 * diag, 0.0])
    far = SimpleNamespace(xy=xy + [0.0, 0.11 * diag])
    assert bp.agreeing_poses(best, [best, near, None, far], 0.1) == 1
    assert bp.agreeing_poses(best, [near, far], 0.12) == 2
    assert bp.agreeing_poses(best, [None, None], 0.1) == 0


def test_detect_sequence_counts_the_images_that_show_the_kept_pose():
    """Per moment: how many of the images tried put the body where the kept pose does, and how many were tried."""
    from types import SimpleNamespace

    class Net:  # the pose lies where the image is bright; its flag is the image's brightness
        presence_threshold = 0.5

        def detect_person(self, rgb):
            return None

        def landmarks(self, rgb, roi):
            ys, xs = np.nonzero(rgb[..., 0] > 100)
            if xs.size == 0:
                return SimpleNamespace(flag=0.0, roi=roi, next_roi=lambda: roi, xy=np.zeros((35, 2)))
            xy = np.column_stack([np.linspace(xs.min(), xs.max(), 35), np.linspace(ys.min(), ys.max(), 35)])
            return SimpleNamespace(flag=float(rgb.max()) / 255, roi=roi, next_roi=lambda: roi, xy=xy)

    def image(x0, value=0.9):
        im = np.zeros((40, 40))
        im[5:35, x0:x0 + 10] = value
        return im

    alts = lambda i, im: [("a", image(5)), ("b", image(6, 0.8)), ("c", image(25, 0.7))] if i == 0 else \
        [("a", image(5)), ("b", image(25, 0.8)), ("c", np.zeros((40, 40)))]
    seq = bp.detect_sequence(Net(), [np.zeros((40, 40))] * 2, np.array([0, 40_000]), track=False, alternatives=alts)
    assert seq.agreeing == [2, 1] and seq.tried == [3, 3]
    plain = bp.detect_sequence(Net(), [image(5)], np.array([0]), track=False)
    assert plain.agreeing == [1] and plain.tried == [1]
