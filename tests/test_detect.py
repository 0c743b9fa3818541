"""The detect stages (paper Sec. 3.2): the simulated detector's error model is what its config says, and the file
reader round-trips OpenPose JSON (BODY_25, COCO-18), npz and csv detections with located errors."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
import pytest

from eventcap.artifacts.recording import GroundTruth, Recording
from eventcap.body.skeleton import LANDMARK_INDEX, LANDMARK_NAMES, MIRROR_LANDMARKS
from eventcap.core.config import build_config
from eventcap.core.registry import load_registry
from eventcap.core.stage import StageContext
from eventcap.core.testing import StageConformance

from eventcap_detect.files import BODY25_NAMES, COCO18_NAMES  # noqa: E402
from eventcap_detect.simulated import DetectorErrorModel  # noqa: E402
from helpers.poses import detect, posed_recording, truth_2d, truth_3d

STAGES = "eventcap_detect.spec:SIMULATED,eventcap_detect.spec:FILE"
RAYLEIGH_MEDIAN = np.sqrt(2 * np.log(2))  # median radius of a 2D isotropic Gaussian, in units of its per-axis std
ZERO_NOISE = {"sigma_px": 0.0, "outlier_prob": 0.0, "flip_prob": 0.0, "sigma_m": 0.0, "bias_m": 0.0}


@pytest.fixture(autouse=True)
def detect_stages(monkeypatch):
    from eventcap.core.runner import reset_process_caches

    monkeypatch.setenv("EVENTCAP_STAGES", STAGES)
    reset_process_caches()
    yield
    reset_process_caches()


# -- inputs -----------------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def tiny_recording() -> Recording:
    """A 90 ms synthetic capture (3 frames) from the synthetic stage, with template and ground truth."""
    from eventcap.body.procedural import procedural_template

    spec = load_registry().get("synthetic")
    cfg = build_config(spec, {"duration_s": 0.09, "supersample": 1, "n_track_points": 10, "motion": "jumping_jack",
                              "speed": 2.0}, "source")
    return spec.load_run()({"template": procedural_template(target_faces=3000)}, cfg,
                           StageContext(node="source", stage="synthetic"))["recording"]


def streaks(rec: Recording) -> np.ndarray:
    from eventcap_detect.simulated import frame_truth

    return frame_truth(rec, occlusion=False).streak_px


# -- the simulated detector ---------------------------------------------------------------------------------------
class TestSimulatedConformance(StageConformance):
    stage_name = "simulated"
    sensitive = ("sigma_px", 3.0)

    def make_inputs(self):
        return {"recording": tiny_recording()}


def test_zero_noise_is_the_ground_truth():
    rec = tiny_recording()
    d = detect("simulated", rec, **ZERO_NOISE)
    assert d.detector.startswith("simulated:") and "z-buffer" in d.detector
    assert np.array_equal(d.t_us, rec.frames.t_us) and d.keypoints_2d.shape == (3, 25, 2)
    seen = d.confidence_2d > 0
    assert seen.sum() >= 3 * 20  # a front view: at most a few points (heels) hidden
    err = np.linalg.norm(d.keypoints_2d - truth_2d(rec), axis=-1)
    assert err[seen].max() < 1e-4
    assert np.all(d.keypoints_2d[~seen] == 0)
    assert np.abs(d.joints_3d - truth_3d(rec)).max() < 1e-9
    assert np.all(d.joints_3d[:, 0] == 0) and (d.confidence_3d > 0).all()


def test_default_noise_matches_sigma_and_bias():
    rec = posed_recording("stand", 100)
    assert streaks(rec).max() < 0.05  # standing still: no blur
    d = detect("simulated", rec)  # defaults: sigma_px 2, 2 % outliers, 2 % flips, bias_m 0.04, sigma_m 0.025
    err = np.linalg.norm(d.keypoints_2d - truth_2d(rec), axis=-1)
    assert 0.7 * 2.0 <= np.median(err) <= 1.3 * 2.0
    assert 0.9 <= np.median(err) / (2.0 * RAYLEIGH_MEDIAN) <= 1.1
    d4 = detect("simulated", rec, sigma_px=4.0, outlier_prob=0.0, flip_prob=0.0)
    err4 = np.linalg.norm(d4.keypoints_2d - truth_2d(rec), axis=-1)
    assert 0.9 <= np.median(err4) / (4.0 * RAYLEIGH_MEDIAN) <= 1.1
    # 3D: a fixed offset per joint (std bias_m) plus per-frame noise (std sigma_m)
    e3 = d.joints_3d - truth_3d(rec)
    bias = e3.mean(axis=0)[1:]
    assert 0.7 * 0.04 <= bias.std() <= 1.3 * 0.04
    assert 0.9 * 0.025 <= (e3[:, 1:] - bias).std() <= 1.1 * 0.025
    assert np.all(e3[:, 0] == 0)


def test_motion_blur_increases_error_and_lowers_confidence():
    cfg = {"outlier_prob": 0.0, "flip_prob": 0.0, "sigma_px": 1.0, "blur_gain": 0.2}
    static, fast = posed_recording("stand", 100), posed_recording("jumping_jack", 100, speed=3.0)
    ds, df = detect("simulated", static, **cfg), detect("simulated", fast, **cfg)
    es = np.linalg.norm(ds.keypoints_2d - truth_2d(static), axis=-1)
    ef = np.linalg.norm(df.keypoints_2d - truth_2d(fast), axis=-1)
    sf = streaks(fast)
    blurred = sf > 3.0
    assert blurred.sum() > 150
    assert np.median(ef[blurred]) > 1.5 * np.median(es)
    # the error is the configured Gaussian scaled by 1 + blur_gain * streak, and confidence falls with it
    assert 0.9 <= np.median(ef / (1 + 0.2 * sf)) / RAYLEIGH_MEDIAN <= 1.1
    assert df.confidence_2d[blurred].max() < 0.9 / (1 + 0.2 * 3.0) + 1e-6
    assert np.allclose(ds.confidence_2d, 0.9, atol=1e-4)


def test_outlier_and_flip_rates_match_config():
    rec = posed_recording("stand", 200)
    d = detect("simulated", rec, sigma_px=0.5, outlier_prob=0.1, outlier_radius_px=30.0, flip_prob=0.1, seed=3)
    truth = truth_2d(rec)
    own = np.linalg.norm(d.keypoints_2d - truth, axis=-1)
    mirror = np.linalg.norm(d.keypoints_2d - truth[:, MIRROR_LANDMARKS], axis=-1)
    outlier = np.minimum(own, mirror) > 3.0  # 6 sigma: never Gaussian noise
    # ~1 % of outliers land within 3 px (disc of radius 30): rate measured ≈ 0.099
    assert abs(outlier.mean() - 0.1 * (1 - (3 / 30) ** 2)) < 0.015
    assert np.allclose(d.confidence_2d[outlier], 0.9 * 0.3, atol=1e-4)
    # flips, counted on pairs far enough apart to tell (shoulders, elbows, wrists, knees, ankles, ...)
    sep = np.linalg.norm(truth - truth[:, MIRROR_LANDMARKS], axis=-1).min(axis=0)
    left = [i for i in range(25) if MIRROR_LANDMARKS[i] > i and sep[i] > 6.0]
    assert len(left) >= 6
    a, b = np.array(left), MIRROR_LANDMARKS[left]
    clean = ~outlier[:, a] & ~outlier[:, b]
    flipped = (mirror[:, a] < own[:, a]) & (mirror[:, b] < own[:, b])
    rate = flipped[clean].mean()
    assert abs(rate - 0.1) < 0.02, rate
    assert clean.sum() > 1000


def test_seed_and_common_random_numbers():
    rec = posed_recording("stand", 100)
    a, b = detect("simulated", rec), detect("simulated", rec)
    assert a.equals(b)
    c = detect("simulated", rec, seed=1)
    assert not np.allclose(a.keypoints_2d, c.keypoints_2d)
    # more outliers leave every other keypoint's noise as it was
    d = detect("simulated", rec, outlier_prob=0.2)
    same = (a.confidence_2d == d.confidence_2d)
    assert same.mean() > 0.75 and np.array_equal(a.keypoints_2d[same], d.keypoints_2d[same])


def test_occluded_and_out_of_image_keypoints_have_zero_confidence():
    front = detect("simulated", posed_recording("stand", 2, with_template=True), **ZERO_NOISE)
    back = detect("simulated", posed_recording("stand", 2, yaw=np.pi, with_template=True), **ZERO_NOISE)
    face = [LANDMARK_INDEX[n] for n in ("nose", "l_eye", "r_eye")]
    assert (front.confidence_2d[:, face] > 0).all() and (back.confidence_2d[:, face] == 0).all()
    assert np.all(back.keypoints_2d[:, face] == 0)
    body = [LANDMARK_INDEX[n] for n in ("l_shoulder", "r_shoulder", "l_hip", "r_hip")]
    assert (back.confidence_2d[:, body] > 0).all()
    # an actor walked far to the right leaves the image: nothing detected, 3D confidence 0 too
    rec = posed_recording("stand", 2)
    gt = rec.ground_truth
    away = GroundTruth(t_us=gt.t_us, poses=gt.poses, joints=gt.joints + [5.0, 0, 0],
                       landmarks=gt.landmarks + [5.0, 0, 0], frame_poses=gt.frame_poses,
                       frame_joints=gt.frame_joints + [5.0, 0, 0], height=gt.height, width=gt.width)
    gone = detect("simulated", Recording(events=rec.events, camera=rec.camera, frames=rec.frames,
                                         ground_truth=away, name="away"))
    assert (gone.confidence_2d == 0).all() and (gone.confidence_3d == 0).all()


def test_simulated_errors():
    with pytest.raises(ValueError, match=r"recording 'posed-stand' has no ground truth.*detect=file"):
        detect("simulated", posed_recording("stand", 2, ground_truth=False))
    with pytest.raises(ValueError, match=r"outlier_prob: expected a finite number in \[0, 1\], got 1.5"):
        detect("simulated", posed_recording("stand", 2), outlier_prob=1.5)
    with pytest.raises(ValueError, match=r"sigma_px: expected a finite number >= 0"):
        DetectorErrorModel(sigma_px=-1.0)


# -- detections from files ----------------------------------------------------------------------------------------
def _openpose_doc(points: np.ndarray, conf: np.ndarray) -> dict:
    flat = np.concatenate([points, conf[:, None]], axis=1).ravel().tolist()
    return {"version": 1.3, "people": [{"person_id": [-1], "pose_keypoints_2d": flat, "face_keypoints_2d": [],
                                        "hand_left_keypoints_2d": [], "hand_right_keypoints_2d": [],
                                        "pose_keypoints_3d": []}]}


def write_openpose(folder: Path, rec: Recording, layout: str = "body25", frames=None, first: int = 0) -> np.ndarray:
    """OpenPose-style JSON files of the ground truth; returns the confidences written (n, 25) in landmark order."""
    folder.mkdir(parents=True, exist_ok=True)
    truth = truth_2d(rec)
    n = truth.shape[0]
    conf = np.round(np.linspace(0.3, 0.95, n * 25).reshape(n, 25), 3)
    names = BODY25_NAMES if layout == "body25" else COCO18_NAMES
    order = [BODY25_NAMES.index(nm) for nm in names]
    for f in range(n) if frames is None else frames:
        doc = _openpose_doc(truth[f, order], conf[f, order])
        (folder / f"clip_{f + first:012d}_keypoints.json").write_text(json.dumps(doc))
    return conf


def write_npz(path: Path) -> str:
    """Ground-truth detections of the tiny recording as npz (times, 2D, 3D)."""
    rec = tiny_recording()
    np.savez(path, t_us=rec.frames.t_us, keypoints_2d=truth_2d(rec), confidence_2d=np.full((3, 25), 0.8),
             joints_3d=truth_3d(rec), confidence_3d=np.full((3, 24), 0.7))
    return str(path)


class TestFileConformance(StageConformance):
    stage_name = "detections_file"
    sensitive = ("time_tolerance_us", 100)

    @pytest.fixture(autouse=True)
    def _detections_file(self, tmp_path):
        self.config_overrides = {"path": write_npz(tmp_path / "det.npz")}

    def make_inputs(self):
        return {"recording": tiny_recording()}


def test_openpose_body25_round_trip(tmp_path):
    rec = tiny_recording()
    conf = write_openpose(tmp_path / "op", rec)
    d = detect("detections_file", rec, path=str(tmp_path / "op"))
    assert np.abs(d.keypoints_2d - truth_2d(rec)).max() < 1e-4
    assert np.allclose(d.confidence_2d, conf, atol=1e-6)
    assert (d.joints_3d == 0).all() and (d.confidence_3d == 0).all()
    assert d.detector.startswith("file: op (openpose, layout body25)")
    # by frame number: file numbers start at 1, frame 1 has no file -> confidence 0 there
    write_openpose(tmp_path / "num", rec, frames=[0, 2], first=1)
    d = detect("detections_file", rec, path=str(tmp_path / "num"), match="number", first_frame=1)
    assert (d.confidence_2d[1] == 0).all() and (d.keypoints_2d[1] == 0).all()
    assert np.abs(d.keypoints_2d[[0, 2]] - truth_2d(rec)[[0, 2]]).max() < 1e-4


def test_openpose_coco18_round_trip_and_mapping(tmp_path):
    rec = tiny_recording()
    conf = write_openpose(tmp_path / "coco", rec, layout="coco18")
    d = detect("detections_file", rec, path=str(tmp_path / "coco"), layout="coco18")
    mapped = [LANDMARK_INDEX[n] for n in ("nose", "neck", "r_wrist", "l_ankle", "r_eye", "l_ear")]
    unmapped = [LANDMARK_INDEX[n] for n in ("mid_hip", "l_big_toe", "l_small_toe", "l_heel", "r_big_toe",
                                            "r_small_toe", "r_heel")]
    coco = [LANDMARK_INDEX[n] for n in LANDMARK_NAMES if n not in ("mid_hip",) and "toe" not in n and "heel" not in n]
    assert len(coco) == 18
    assert np.abs(d.keypoints_2d[:, coco] - truth_2d(rec)[:, coco]).max() < 1e-4
    assert np.allclose(d.confidence_2d[:, mapped], conf[:, mapped], atol=1e-6)
    assert (d.confidence_2d[:, unmapped] == 0).all() and (d.keypoints_2d[:, unmapped] == 0).all()
    # overrides: swap the wrists' sides, drop the nose
    d2 = detect("detections_file", rec, path=str(tmp_path / "coco"), layout="coco18",
                mapping={"RWrist": "l_wrist", "7": "r_wrist", "Nose": ""})
    lw, rw, nose = LANDMARK_INDEX["l_wrist"], LANDMARK_INDEX["r_wrist"], LANDMARK_INDEX["nose"]
    assert np.array_equal(d2.keypoints_2d[:, lw], d.keypoints_2d[:, rw]) and (d2.confidence_2d[:, nose] == 0).all()


def test_npz_round_trip_with_3d_in_camera_axes_and_mm(tmp_path):
    rec = tiny_recording()
    truth, rel = truth_2d(rec), truth_3d(rec)
    conf = np.full((3, 25), 0.75)
    conf[1, 4] = 0.0
    R = rec.camera.R
    np.savez(tmp_path / "d.npz", t_us=rec.frames.t_us + 300, keypoints_2d=truth, confidence_2d=conf,
             joints_3d=1000.0 * (rel + 0.5) @ R.T, confidence_3d=np.full((3, 24), 0.6))  # +0.5: not root-relative
    d = detect("detections_file", rec, path=str(tmp_path / "d.npz"), frame_3d="camera", unit_3d="mm")
    seen = conf > 0
    assert np.abs(d.keypoints_2d - truth)[seen].max() < 1e-4 and (d.keypoints_2d[1, 4] == 0).all()
    assert np.allclose(d.confidence_2d, conf) and np.allclose(d.confidence_3d, 0.6)
    assert np.abs(d.joints_3d - rel).max() < 1e-9
    # frame numbers instead of times; 3D joints from a second file
    np.savez(tmp_path / "f.npz", frame=np.array([2, 0, 1]), keypoints_2d=truth[[2, 0, 1]],
             confidence_2d=conf[[2, 0, 1]])
    np.savez(tmp_path / "j.npz", joints_3d=rel, confidence_3d=np.full((3, 24), 0.5))
    d = detect("detections_file", rec, path=str(tmp_path / "f.npz"), path_3d=str(tmp_path / "j.npz"))
    assert np.abs(d.keypoints_2d - truth)[seen].max() < 1e-4
    assert np.abs(d.joints_3d - rel).max() < 1e-12 and np.allclose(d.confidence_3d, 0.5)
    assert d.detector.endswith("3D: j.npz")


def write_csv(path: Path, rec: Recording, conf: np.ndarray, time_column: str = "t_us", joints: bool = True) -> None:
    truth, rel = truth_2d(rec), truth_3d(rec)
    header = [time_column] + [f"kp{k}_{a}" for k in range(25) for a in "xyc"]
    if joints:
        header += [f"j{j}_{a}" for j in range(24) for a in "xyzc"]
    lines = ["# detections of the tiny recording", ",".join(header)]
    for f in range(truth.shape[0]):
        row = [str(int(rec.frames.t_us[f])) if time_column == "t_us" else str(f)]
        for k in range(25):
            row += ["" if conf[f, k] == 0 else repr(float(v)) for v in truth[f, k]] + [repr(float(conf[f, k]))]
        if joints:
            for j in range(24):
                row += [repr(float(v)) for v in rel[f, j]] + ["0.9"]
        lines.append(",".join(row))
    path.write_text("\n".join(lines) + "\n")


def test_csv_round_trip(tmp_path):
    rec = tiny_recording()
    conf = np.full((3, 25), 0.8)
    conf[2, 10] = 0.0
    write_csv(tmp_path / "d.csv", rec, conf)
    d = detect("detections_file", rec, path=str(tmp_path / "d.csv"))
    seen = conf > 0
    assert np.abs(d.keypoints_2d - truth_2d(rec))[seen].max() < 1e-4 and (d.keypoints_2d[2, 10] == 0).all()
    assert np.allclose(d.confidence_2d, conf) and np.allclose(d.confidence_3d, 0.9)
    assert np.abs(d.joints_3d - truth_3d(rec)).max() < 1e-12
    write_csv(tmp_path / "f.csv", rec, conf, time_column="frame", joints=False)
    d = detect("detections_file", rec, path=str(tmp_path / "f.csv"))
    assert np.abs(d.keypoints_2d - truth_2d(rec))[seen].max() < 1e-4 and (d.confidence_3d == 0).all()


def test_file_errors(tmp_path):
    rec = tiny_recording()
    good = write_npz(tmp_path / "good.npz")

    def fails(message, **config):
        with pytest.raises(ValueError, match=message):
            detect("detections_file", rec, **config)

    fails(r"stages.detect.path: the detections file or folder is not set")
    fails(r"nope.npz: no such file or folder", path=str(tmp_path / "nope.npz"))
    # OpenPose: count mismatch, malformed JSON, wrong number of values, non-numbers, duplicate frame numbers
    write_openpose(tmp_path / "two", rec, frames=[0, 1])
    fails(r"two: has 2 files but the recording has 3 intensity frames", path=str(tmp_path / "two"))
    write_openpose(tmp_path / "bad", rec)
    (tmp_path / "bad" / "clip_000000000001_keypoints.json").write_text('{"people": [{"pose_keypoints_2d": [1, 2,')
    fails(r"clip_000000000001_keypoints.json \(frame 1 by order\): malformed JSON", path=str(tmp_path / "bad"))
    fails(r"clip_000000000001_keypoints.json \(frame number 1\): malformed JSON", path=str(tmp_path / "bad"),
          match="number")
    write_openpose(tmp_path / "coco", rec, layout="coco18")
    fails(r"clip_000000000000_keypoints.json \(frame 0 by order\): pose_keypoints_2d has 54 values, expected 75 "
          r".*set layout=coco18", path=str(tmp_path / "coco"))
    (tmp_path / "coco" / "clip_000000000002_keypoints.json").write_text(json.dumps({"people": [{"pose_keypoints_2d":
                                                                                    ["a"] * 54}]}))
    fails(r"clip_000000000002_keypoints.json \(frame 2 by order\): pose_keypoints_2d holds non-numeric values",
          path=str(tmp_path / "coco"), layout="coco18")
    (tmp_path / "notop").mkdir()
    (tmp_path / "notop" / "x_1.json").write_text("[1, 2]")
    (tmp_path / "notop" / "x_2.json").write_text("{}")
    (tmp_path / "notop" / "x_3.json").write_text("{}")
    fails(r"x_1.json \(frame 0 by order\): not an OpenPose keypoint file", path=str(tmp_path / "notop"))
    write_openpose(tmp_path / "far", rec, frames=[0, 1, 2], first=7)
    fails(r"far/clip_000000000007_keypoints.json: frame number 7 \(minus first_frame = 0\) is outside "
          r"the recording's 3 intensity frames", path=str(tmp_path / "far"), match="number")
    # npz: shapes, missing arrays, times, duplicates, confidences
    truth = truth_2d(rec)
    np.savez(tmp_path / "shape.npz", keypoints_2d=truth[:, :, :1], confidence_2d=np.ones((3, 25)))
    fails(r"shape.npz: array 'keypoints_2d' has shape \(3, 25, 1\), expected \(n, n, 2\)",
          path=str(tmp_path / "shape.npz"))
    np.savez(tmp_path / "noconf.npz", keypoints_2d=truth)
    fails(r"noconf.npz: has keypoints_2d but no confidence_2d", path=str(tmp_path / "noconf.npz"))
    np.savez(tmp_path / "late.npz", t_us=rec.frames.t_us + [0, 0, 2_000], keypoints_2d=truth,
             confidence_2d=np.ones((3, 25)))
    fails(r"late.npz \(frame row 2\): t_us = 87000 is 2000 us from the nearest intensity frame \(85000 us\), more "
          r"than time_tolerance_us = 500", path=str(tmp_path / "late.npz"))
    np.savez(tmp_path / "dup.npz", frame=np.array([0, 1, 1]), keypoints_2d=truth, confidence_2d=np.ones((3, 25)))
    fails(r"dup.npz \(frame row 2\): row 1 and row 2 both fall on intensity frame 1", path=str(tmp_path / "dup.npz"))
    c = np.ones((3, 25))
    c[1, 3] = 1.7
    np.savez(tmp_path / "conf.npz", keypoints_2d=truth, confidence_2d=c)
    fails(r"conf.npz \(frame row 1\): keypoint 3 has confidence 1.7, expected a value in \[0, 1\]",
          path=str(tmp_path / "conf.npz"))
    np.savez(tmp_path / "c18.npz", keypoints_2d=truth[:, :18], confidence_2d=c[:, :18])
    fails(r"c18.npz: has 18 keypoints per frame, layout body25 has 25 \(set layout=coco18\)",
          path=str(tmp_path / "c18.npz"))
    np.savez(tmp_path / "only2d.npz", keypoints_2d=truth, confidence_2d=np.ones((3, 25)))
    fails(r"only2d.npz: holds no 3D joints", path=str(tmp_path / "only2d.npz"), path_3d=str(tmp_path / "only2d.npz"))
    # csv: a bad number names its line and column; a missing column is named
    write_csv(tmp_path / "bad.csv", rec, np.full((3, 25), 0.8), joints=False)
    lines = (tmp_path / "bad.csv").read_text().splitlines()
    lines[3] = lines[3].replace(lines[3].split(",")[1], "twelve", 1)
    (tmp_path / "bad.csv").write_text("\n".join(lines))
    fails(r"bad.csv \(frame row 1\): line 4, column 'kp0_x': expected a number, got 'twelve'",
          path=str(tmp_path / "bad.csv"))
    (tmp_path / "cols.csv").write_text("t_us,kp0_x,kp0_y,kp0_c,kp1_x,kp1_c\n5000,1,2,0.5,3,0.5\n")
    fails(r"cols.csv: column kp1_y missing", path=str(tmp_path / "cols.csv"))
    (tmp_path / "short.csv").write_text("kp0_x,kp0_y,kp0_c\n1,2,0.5\n1,2\n")
    fails(r"short.csv \(frame row 1\): line 3 has 2 values, the header 3", path=str(tmp_path / "short.csv"))
    # config values
    fails(r"mapping: unknown keypoint 'RPinky' of layout body25", path=good, mapping={"RPinky": "nose"})
    fails(r"mapping\['Nose'\]: unknown landmark 'nose_tip'", path=good, mapping={"Nose": "nose_tip"})
    fails(r"mapping: landmark 'neck' is given by two keypoints of layout body25: Nose \(0\) and Neck \(1\)",
          path=good, mapping={"Nose": "neck"})
    fails(r"stages.detect.format: expected one of openpose \| npz \| csv \| auto, got 'xml'", path=good, format="xml")
