"""What is in view and the detect checks (issue 35, item 2), through the `detections_file` stage with detections
made from the ground truth: landmarks out of the image are not observations, a partial view stays partial, a
body that does not fit the events is rejected with the reason per image and counted, and too few detections stop
the stage naming the counts. The numbers on BlazePose and real captures: benchmarks/accuracy/bench_view_checks.py."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from eventcap.body.skeleton import LANDMARK_INDEX, LANDMARK_NAMES
from eventcap.events import make_events
from eventcap.core.stage import StageFailed


from eventcap_detect import checks  # noqa: E402
from helpers.poses import detect, posed_recording, truth_2d, truth_3d

N = 10  # images
HEAD = [LANDMARK_INDEX[n] for n in ("nose", "r_eye", "l_eye", "r_ear", "l_ear")]
SHOULDERS = [LANDMARK_INDEX["r_shoulder"], LANDMARK_INDEX["l_shoulder"]]
LEGS = [LANDMARK_INDEX[n] for n in ("r_knee", "r_ankle", "l_knee", "l_ankle", "l_big_toe", "l_small_toe", "l_heel",
                                    "r_big_toe", "r_small_toe", "r_heel")]


@pytest.fixture(autouse=True)
def detect_stages(monkeypatch):
    from eventcap.core.runner import reset_process_caches

    monkeypatch.setenv("EVENTCAP_STAGES", "eventcap_detect.spec:SIMULATED,eventcap_detect.spec:FILE")
    reset_process_caches()
    yield
    reset_process_caches()


def box_events(rec, boxes, per_image: int = 3000, seed: int = 0) -> np.ndarray:
    """Events spread uniformly over a box (x0, y0, x1, y1) within 10 ms of each frame: a moving silhouette."""
    rng = np.random.default_rng(seed)
    parts = []
    for t, (x0, y0, x1, y1) in zip(rec.frames.t_us, boxes):
        parts.append(np.stack([rng.integers(t - 10_000, t + 10_000, per_image), rng.integers(x0, x1, per_image),
                               rng.integers(y0, y1, per_image)], axis=1))
    a = np.concatenate(parts)
    a = a[np.argsort(a[:, 0], kind="stable")]
    return make_events(a[:, 0], a[:, 1], a[:, 2], np.where(a[:, 1] % 2, 1, -1))


def with_events(rec, events):
    import dataclasses

    from eventcap.artifacts.recording import EventStream

    return dataclasses.replace(rec, events=EventStream(events=events, width=rec.width, height=rec.height))


def body_boxes(kp: np.ndarray, grow: float = 0.1) -> list[tuple[int, int, int, int]]:
    out = []
    for p in kp:
        lo, hi = p.min(axis=0), p.max(axis=0)
        g = grow * (hi - lo).max()
        out.append((int(lo[0] - g), int(lo[1] - g), int(hi[0] + g), int(hi[1] + g)))
    return out


def run_file(tmp_path, rec, kp, conf=None, **config):
    conf = np.full(kp.shape[:2], 0.9) if conf is None else conf
    path = tmp_path / "det.npz"
    np.savez(path, t_us=rec.frames.t_us, keypoints_2d=kp, confidence_2d=conf, joints_3d=truth_3d(rec),
             confidence_3d=np.full((kp.shape[0], 24), 0.8))
    return detect("detections_file", rec, path=str(path), **config)


def test_whole_bodies_that_fit_the_events_pass_and_the_person_is_upright(tmp_path, caplog):
    rec = posed_recording("jumping_jack", N)
    kp = truth_2d(rec)
    rec = with_events(rec, box_events(rec, body_boxes(kp)))
    caplog.set_level(logging.INFO)
    d = run_file(tmp_path, rec, kp)
    assert d.image_status == ("ok",) * N and d.in_view.all() and (d.confidence_2d > 0).all()
    # the person's vertical in camera axes: the synthetic camera looks 4.3 deg down (from 1.3 m at 4 m to 1.0 m);
    # the skeleton's shoulders are 2.5 deg behind its pelvis, so the person's vertical says 1.7 deg down
    from eventcap.camera import tilt_from_up

    pitch, roll = tilt_from_up(d.person_up)
    assert pitch == pytest.approx(-np.degrees(np.arctan2(0.3, 4.0)), abs=3.0) and abs(roll) < 1.0
    assert "detections_file det.npz: a person in 10 of 10 images; the longest run without one: 0 images" in caplog.text
    assert "world up: the person's mean vertical (pelvis to shoulders, 10 images) is" in caplog.text


def test_a_partial_view_gives_a_partial_detection(tmp_path):
    """A close-up: the legs below the image are not observations; the head and arms are; nothing is rejected."""
    rec = posed_recording("jumping_jack", N)
    kp = truth_2d(rec)
    kp = (kp - kp[:, :1]) * 2.5 + kp[:, :1] + np.array([0.0, 40.0])  # 2.5x nearer, the legs below the image
    rec = with_events(rec, box_events(rec, [(40, 10, 200, 179)] * N))
    d = run_file(tmp_path, rec, kp)
    inside = checks.inside_image(kp, rec.width, rec.height)
    assert d.image_status == ("ok",) * N
    assert np.array_equal(d.in_view, inside) and not inside[:, LEGS].any() and inside[:, HEAD].all()
    assert (d.confidence_2d[~inside] == 0).all() and (d.keypoints_2d[~inside] == 0).all()


def test_a_small_body_under_a_big_head_is_a_close_up(tmp_path, caplog):
    """Issue 53: a head and shoulders with a small body drawn under them is a person partly out of view, not a
    rejection: the head, shoulders and arms are kept, the lower body drawn under them is marked unobserved."""
    rec = posed_recording("jumping_jack", N)
    kp = truth_2d(rec).copy()
    neck = kp[:, LANDMARK_INDEX["neck"]][:, None]
    kp[:, HEAD] = (kp[:, HEAD] - neck) * 3.0 + neck  # the face of a close-up
    kp[:, SHOULDERS] = (kp[:, SHOULDERS] - neck) * 2.0 + neck
    rec = with_events(rec, box_events(rec, body_boxes(kp)))
    caplog.set_level(logging.INFO)
    d = run_file(tmp_path, rec, kp)
    inside = checks.inside_image(kp, rec.width, rec.height)
    assert d.image_status == (checks.CLOSE_UP,) * N
    upper = np.zeros(len(LANDMARK_NAMES), bool)
    upper[list(checks.UPPER_BODY)] = True
    assert np.array_equal(d.in_view, inside & upper[None]) and d.in_view[:, HEAD].all()
    assert not d.in_view[:, LEGS].any() and not d.in_view[:, LANDMARK_INDEX["mid_hip"]].any()
    assert (d.confidence_2d[:, ~upper] == 0).all() and (d.confidence_2d[d.in_view] > 0).all()
    assert (d.confidence_3d[:, list(checks.LOWER_JOINTS)] == 0).all()
    assert "image 0 (t = 0.005 s) a close-up: the head 0.78 x the torso wide" in caplog.text
    assert "a person in 10 of 10 images (10 of them close-ups: the head and shoulders kept, the lower body " \
           "unobserved)" in caplog.text
    # only the region check: the events fit the body, a whole body kept
    assert run_file(tmp_path, rec, kp, checks=["region"]).image_status == ("ok",) * N


def test_a_refusal_names_the_check_that_rejected_and_its_setting(tmp_path):
    """The hint of a refusal points where the cause is: a person found and rejected by a check names the check and
    the setting that changes it, not 'is there a person in view'."""
    rec = posed_recording("jumping_jack", N)
    kp = truth_2d(rec).copy()
    # a body drawn inside a face: the events fire over a region three times its size (check region)
    box = body_boxes(kp)
    big = [(max(0, x0 - 2 * (x1 - x0)), y0, min(rec.width - 1, x1 + 2 * (x1 - x0)), y1) for x0, y0, x1, y1 in box]
    rec = with_events(rec, box_events(rec, big))
    with pytest.raises(StageFailed) as info:
        run_file(tmp_path, rec, kp)
    msg = str(info.value)
    assert "rejected (region" in msg and "check region rejected (first: a whole body" in msg
    assert "stages.detect.region_ratio" in msg and "is there a person in view" not in msg
    assert info.value.status == "no_person"
    # nobody found at all: the hint points at the images and at preview
    hint = checks.refusal_hint(["no_person"] * 5 + ["ok"], [""] * 6, event_images=True)
    assert "stages.detect.event_images" in hint and "eventcap preview FILE" in hint
    assert "agree" not in hint
    # more images without a person than poses the images made from the events disagreed on: both said
    hint = checks.refusal_hint(["no_person"] * 5 + ["agree"] * 2 + ["ok"], [""] * 8, event_images=True)
    assert hint.startswith("the images made from the events (stages.detect.event_images) showed the network no "
                           "person (and in 2 more, too few of them agreed on one: check agree, stages.detect.min_agree"
                           " / stages.detect.agree_ratio): look at the recording in `eventcap preview FILE`")


def test_a_whole_body_inside_a_much_larger_moving_region_is_rejected(tmp_path):
    """A body drawn inside a face: the events fire over a region three times its size."""
    rec = posed_recording("jumping_jack", N)
    kp = truth_2d(rec)
    x0, y0, x1, y1 = body_boxes(kp, 0.0)[0]
    cx, cy, s = (x0 + x1) / 2, (y0 + y1) / 2, 1.5 * max(x1 - x0, y1 - y0)
    big = (int(max(cx - s, 0)), int(max(cy - s, 0)), int(min(cx + s, rec.width)), int(min(cy + s, rec.height)))
    rec_big = with_events(rec, box_events(rec, [big] * N, per_image=20000))
    d = run_file(tmp_path, rec_big, kp, min_found=0)
    assert d.image_status == ("region",) * N
    assert run_file(tmp_path, rec_big, kp, checks=["scale", "outside"]).image_status == ("ok",) * N
    # no events near the body: the region check does not judge (a person standing still)
    d = run_file(tmp_path, rec, kp)
    assert d.image_status == ("ok",) * N


def test_landmarks_outside_the_image_and_too_few_detections(tmp_path):
    rec = posed_recording("jumping_jack", N)
    kp = truth_2d(rec).copy()
    kp[:3] += np.array([0.0, 400.0])  # three images: the body below the image
    kp[:3, LANDMARK_INDEX["nose"]] = (120, 170)  # one landmark left inside
    kp[3:6] = kp[3:6] * 0 + np.array([np.nan, np.nan])
    conf = np.full(kp.shape[:2], 0.9)
    conf[3:6] = 0.0  # three images the detector found nobody in
    d = run_file(tmp_path, rec, np.nan_to_num(kp), conf, min_found=0.3)
    assert d.image_status[:6] == ("outside",) * 3 + ("no_person",) * 3 and d.image_status[6:] == ("ok",) * 4
    with pytest.raises(StageFailed) as info:
        run_file(tmp_path, rec, np.nan_to_num(kp), conf)
    assert str(info.value) == ("detections_file det.npz: no person in 3 of 10 images, 3 rejected (outside 3): a "
                               "person in 4: 40% of the images, fewer than 50% (stages.detect.min_found=0.5): too "
                               "few to solve anything; the detector found a person in 3 images that check outside "
                               "rejected (first: 1 landmarks in the image (at least 3)): look at them in `eventcap "
                               "preview FILE --t SECONDS`; if a person shows there, the check is wrong for this "
                               "recording: stages.detect.min_in_view (or stages.detect.checks without outside) "
                               "changes it")
    assert info.value.status == "too_few_detections"


def test_head_and_ankles_in_view_without_the_hips_do_not_hang_together(tmp_path):
    """A face close-up with feet drawn on it: the hips, between the head and the ankles, would be in the image."""
    rec = posed_recording("jumping_jack", N)
    kp = truth_2d(rec).copy()
    hips = [LANDMARK_INDEX[n] for n in ("mid_hip", "r_hip", "l_hip")]
    kp[:, hips] = (-50.0, 90.0)  # outside the image
    d = run_file(tmp_path, rec, kp, min_found=0)
    assert d.image_status == ("parts",) * N
    assert run_file(tmp_path, rec, kp, checks=["outside", "region", "scale"], min_found=0).image_status == \
        ("ok",) * N


def test_too_few_detections_name_the_stretch_worth_solving(tmp_path):
    rec = posed_recording("jumping_jack", 30)
    kp = truth_2d(rec)
    conf = np.zeros(kp.shape[:2])
    conf[5:17] = 0.9  # a person in images 5-16 only (0.205-0.645 s)
    with pytest.raises(StageFailed, match=r"no person in 18 of 30 images: a person in 12: 40% of the images, fewer "
                                          r"than 50% .*; the longest stretch with a person is images 5-16: "
                                          r"source.t_start_s=0.20 source.t_end_s=0.65 keeps it"):
        run_file(tmp_path, rec, kp, conf)


def test_found_message_and_gaps():
    status = ["no_person"] * 199 + ["ok"] * 3
    assert checks.found_message(status, "blazepose", enough=False) == \
        "blazepose: no person in 199 of 202 images: a person in 3"
    assert checks.found_message(["ok", "region", "ok", "no_person"], "x") == \
        "x: a person in 2 of 4 images (rejected: region 1; no person in 1)"
    assert checks.longest_gap(["ok", "region", "no_person", "ok", "no_person"]) == 2
    status = ["no_person"] * 3 + ["ok"] * 4 + ["region"] + ["ok"] * 5 + ["no_person"] * 2 + ["ok"] * 6
    assert checks.longest_stretch(status) == (3, 12)  # one rejected image inside the stretch, two end it
    assert checks.longest_stretch(["no_person"] * 3) == (0, -1)
    with pytest.raises(ValueError, match="checks: unknown check 'silhouette'"):
        checks.ViewSettings(checks=("silhouette",), border_px=0.0, min_in_view=3, region_ratio=0.5, edge_ratio=0.15,
                            head_ratio=0.35, shoulder_ratio=0.9, window_us=40_000, min_found=0.5)


def test_the_simulated_detector_states_what_is_in_view(tmp_path):
    rec = posed_recording("jumping_jack", N)
    d = detect("simulated", rec)
    assert d.image_status == ("ok",) * N and np.array_equal(d.in_view, d.confidence_2d > 0)


def test_the_davis346_lab_scene_stops_at_detect_naming_the_count(tmp_path, monkeypatch):
    """The real DAVIS346 recording (a lab with a robot arm, no person): detect stops with the count, every later
    node is skipped because of it, and the run's last line says so once."""
    from eventcap.apps.cli import main
    from eventcap.core.runner import reset_process_caches

    real = [Path(__file__).resolve().parent / "data" / "davis346_lab_aps.aedat4",
            Path("/work/shared/data/real/davis346_lab_aps.aedat4")]
    path = next((p for p in real if p.is_file()), None)
    if path is None:
        pytest.skip(f"the DAVIS346 sample is not here ({' nor '.join(map(str, real))})")
    monkeypatch.delenv("EVENTCAP_STAGES", raising=False)
    reset_process_caches()
    run_dir = tmp_path / "run"
    code = main(["run", "source=recording", f"source.path={path}", "stages/detect=blazepose", "template=procedural",
                 "template.target_faces=2000", f"cache_dir={tmp_path / 'cache'}", f"hydra.run.dir={run_dir}"])
    log = (run_dir / "eventcap.log").read_text()
    assert code == 1
    assert ("detect (blazepose v12): FAILED (no_person): StageFailed: blazepose (full, at latent): no person in 3 of 3 "
            "images; the network saw no person in its images: look at the recording in `eventcap preview FILE`") in log
    assert ("run incomplete: detect failed (no_person); skipped because of it: 8 nodes (body, track, slice, solve, "
            "stitch, cut, confidence, evaluate); the first error is above (detect)") in log
    assert "world frame: y up, the camera at the origin looking along -z, assumed level until the detect stage measures" in log


def test_detections_of_schema_1_are_refused_and_new_fields_round_trip(tmp_path):
    import zarr

    from eventcap.artifacts import ArtifactError
    from eventcap.artifacts.pose import Detections

    d = detect("simulated", posed_recording("jumping_jack", N))
    g = zarr.open_group(str(tmp_path / "d.zarr"), mode="w")
    d.to_zarr(g)
    back = Detections.from_zarr(zarr.open_group(str(tmp_path / "d.zarr"), mode="r"))
    assert back.equals(d) and back.image_status == ("ok",) * N and len(back.person_up) == 3
    import dataclasses

    from eventcap.camera import level_rotation

    turned = dataclasses.replace(d, world_R=level_rotation(-20.0, 3.0))  # schema 3: the upright world's rotation
    turned.to_zarr(zarr.open_group(str(tmp_path / "t.zarr"), mode="w"))
    back = Detections.from_zarr(zarr.open_group(str(tmp_path / "t.zarr"), mode="r"))
    assert back.equals(turned) and np.allclose(back.world_R, level_rotation(-20.0, 3.0))
    with pytest.raises(ArtifactError, match=r"Detections.world_R: expected a rotation matrix \(R R\^T = I\)"):
        dataclasses.replace(d, world_R=2 * np.eye(3))
    g.attrs["schema_version"] = 1  # a cache entry written before what is in view was stated
    with pytest.raises(ArtifactError, match="Detections schema version 1 on disk, this code reads version 4"):
        Detections.from_zarr(zarr.open_group(str(tmp_path / "d.zarr"), mode="r"))
    # a landmark out of view cannot carry a confidence
    with pytest.raises(ArtifactError, match="landmark 0 of image 0 is not in view but has confidence"):
        Detections(t_us=d.t_us, keypoints_2d=d.keypoints_2d, confidence_2d=d.confidence_2d, joints_3d=d.joints_3d,
                   confidence_3d=d.confidence_3d, in_view=np.zeros_like(d.in_view))


def test_sensor_noise_is_not_a_moving_region():
    """A large sensor's noise (Poisson, ~3 events per 16 px cell in 40 ms, as a DVXplorer's at 1000 lux) around a
    person 260 px tall: only the person's cells are active, so the moving region is the person's size, not the whole
    image (which rejected every detection of such a capture as 'a whole body inside a moving region of 640 px').
    A close-up whose every cell fires stays active all over."""
    rng = np.random.default_rng(0)
    W, H, cell = 640, 480, checks.cell_size(640, 480)
    assert cell == 16
    n = rng.poisson(3.0 * W * H / cell**2)
    x, y = rng.integers(0, W, n), rng.integers(0, H, n)
    px, py = rng.integers(300, 380, 20000), rng.integers(100, 360, 20000)  # the person: 80 x 260 px
    ev = make_events(np.sort(rng.integers(0, 40_000, n + px.size)), np.r_[x, px], np.r_[y, py],
                     np.ones(n + px.size, dtype=np.int8))
    active = checks.activity_cells(ev, 20_000, W, H, 40_000)
    assert 0.02 < active.mean() < 0.1, active.mean()
    region = checks.moving_region(active, (300.0, 100.0, 380.0, 360.0), cell)
    assert region is not None and region[3] - region[1] <= 300 and region[2] - region[0] <= 160, region
    # a close-up: every cell fires (about 40 events each), the person's cells twice as much
    m = rng.poisson(40.0 * W * H / cell**2)
    cx, cy = rng.integers(0, W, m), rng.integers(0, H, m)
    ev = make_events(np.sort(rng.integers(0, 40_000, m + px.size)), np.r_[cx, px], np.r_[cy, py],
                     np.ones(m + px.size, dtype=np.int8))
    assert checks.activity_cells(ev, 20_000, W, H, 40_000).mean() > 0.9


def test_images_made_from_the_events_must_agree_on_the_person():
    """Check agree: a pose that only one of the images of its moment shows, and that no corroborated pose of the
    moment before or after vouches for, is rejected naming the counts; a pose next to a corroborated one is
    followed through time; one image per moment, min_agree 1 and checks without agree are not judged."""
    n, lm = 5, len(LANDMARK_NAMES)
    body = np.column_stack([np.linspace(10, 40, lm), np.linspace(20, 100, lm)])  # diagonal ~85 px
    shift = np.array([0.0, 0.0, 60.0, 10.0, 10.0])  # image 2 drawn 60 px away from the others
    kp = body[None] + shift[:, None, None] * [1.0, 0.0]
    in_view = np.ones((n, lm), bool)
    found = np.array([True, True, True, True, False])
    t = np.arange(n) * 40_000
    agreeing = (np.array([2, 1, 1, 1, 0]), np.array([5, 5, 5, 1, 5]))

    def settings(names=checks.CHECKS, min_agree=2):
        return checks.ViewSettings(checks=tuple(names), border_px=0.0, min_in_view=3, region_ratio=0.5,
                                   edge_ratio=0.15, head_ratio=0.35, shoulder_ratio=0.9, window_us=40_000,
                                   min_found=0.5, min_agree=min_agree)

    status, why = checks.check_images(kp, in_view, found, t, None, 128, 128, settings(), agreeing)
    # 0: two images agree; 1: one image, next to 0 (followed); 2: one image, 60 px off both neighbours (0.7 of the
    # body); 3: one image tried, not judged
    assert status == ["ok", "ok", "agree", "ok", "no_person"]
    assert why[2] == ("the person shows in 1 of the 5 images made from the events of that moment (at least 2 must "
                      "agree on where they are) and at no neighbouring moment's agreed place")
    assert checks.corroborated(kp, in_view, found, agreeing[0] >= 2, 0.8).tolist() == [True, True, True, True, False]
    for s in (settings(min_agree=1), settings(names=("outside", "parts", "region", "scale"))):
        assert checks.check_images(kp, in_view, found, t, None, 128, 128, s, agreeing)[0][:4] == ["ok"] * 4
    assert checks.check_images(kp, in_view, found, t, None, 128, 128, settings(), None)[0][:4] == ["ok"] * 4
    assert checks.CHECK_SETTINGS["agree"] == "stages.detect.min_agree / stages.detect.agree_ratio"
    with pytest.raises(ValueError, match="min_agree: expected at least 1 image, got 0"):
        settings(min_agree=0)
