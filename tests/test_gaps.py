"""What was seen and what was not (issue: a real recording gives a motion you can trust, or says why not).

- A missed detection is a missing observation: the window's solve goes on without it.
- A window whose frames hold no observation at all is a gap: no motion there (NaN), nothing extrapolated beyond a
  window's observed frames, and stitch leaves the gap as it is.
- Outputs mark the gaps: motion.npz (``estimated``, NaN, ``gaps_us``), BVH cut into one file per stretch, C3D
  residual -1; and carry a confidence per joint.
- The confidence: in view, detections agreeing at the frames, events between them; an out-of-view joint is never
  marked observed.
- A recording without intensity frames picks the event-only pipeline by itself.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from eventcap.artifacts.pose import Detections
from eventcap.body.kinematics import joint_positions
from eventcap.analysis.confidence import in_image, interval_support, motion_confidence
from helpers.spline_scene import run_stage, stage_inputs, stitch


def _without(det: Detections, frames: list[int]) -> Detections:
    """The detections with nothing observed at the given frame indices (as a rejected or missed image)."""
    c2, c3 = det.confidence_2d.copy(), det.confidence_3d.copy()
    c2[frames], c3[frames] = 0.0, 0.0
    in_view = None if det.in_view is None else det.in_view.copy()
    if in_view is not None:
        in_view[frames] = False
    return dataclasses.replace(det, confidence_2d=c2, confidence_3d=c3, in_view=in_view)


def test_a_missed_detection_is_a_missing_observation_not_a_failed_window():
    """Frame 2 of the 4 holds no observation: batch 1's window (frames 0..3) still solves, and the poses around the
    missing frame stay near the truth (the other frames, the events and the prior carry them)."""
    inputs = stage_inputs()
    rec, plan = inputs["recording"], inputs["batches"]
    full, _ = run_stage(inputs, plan.batch(1))
    missed, ctx = run_stage(dict(inputs, detections=_without(inputs["detections"], [2])), plan.batch(1))
    p = missed["poses"]
    assert p.status == "Solve_Succeeded" and np.isfinite(p.poses).all()
    assert ctx.stats["fits_computed"] <= 3  # no fit of the frame without an observation
    gt = rec.ground_truth
    t = p.t_us
    truth = joint_positions(gt.poses[np.searchsorted(gt.t_us, t)], rec.template)
    err = {k: float(np.linalg.norm(joint_positions(v["poses"].poses, rec.template) - truth, axis=-1).mean()) * 1000
           for k, v in (("full", full), ("missed", missed))}
    assert err["missed"] < 2.0 * err["full"] + 10.0, err


def test_a_window_without_observations_is_a_gap_and_nothing_is_extrapolated():
    """7 frames, 6 batches, windows of 3 batches (half_window 1). Frames 2-5 hold nothing: batch 3's window sees
    nothing (status gap, NaN); windows 1..5 keep only their observed span; the stitched motion has estimates up to
    frame 1 and is NaN after it (a gap: frame 6 alone, a single observation at the end, spans no motion), never
    filled in."""
    inputs = stage_inputs(n_frames=7)
    plan = inputs["batches"]
    t_det = np.asarray(inputs["detections"].t_us)
    inputs = dict(inputs, detections=_without(inputs["detections"], [2, 3, 4, 5]))
    windows = [run_stage(inputs, plan.batch(k))[0]["poses"] for k in range(len(plan))]
    assert windows[3].status == "gap" and np.isnan(windows[3].poses).all()
    for w in windows:  # nothing beyond a window's observed frames
        t, ok = w.t_us, np.isfinite(w.poses).all(axis=1)
        assert not ok[(t > t_det[1]) & (t < t_det[6])].any()
    motion, cut, _ = stitch(windows, plan)
    t, ok = motion.t_us, np.isfinite(motion.poses).all(axis=1)
    assert ok[t <= t_det[1]].all() and not ok[t > t_det[1]].any()
    assert [c.status for c in cut][2:5] == ["gap", "gap", "gap"]


def test_the_outputs_mark_gaps_and_cut_the_bvh(tmp_path):
    """A motion with a gap: motion.npz keeps every frame (NaN and estimated false in the gap, its span in gaps_us);
    the BVH is cut into one file per stretch; every estimated frame is finite."""
    from eventcap.apps.outputs import OutputsConfig, _write_bvh, _write_npz, motion_segments

    rec = stage_inputs()["recording"]
    t = np.arange(0, 50_000, 1000, dtype=np.int64)
    poses = np.zeros((t.size, 33))
    poses[20:30] = np.nan
    est = np.isfinite(poses).all(axis=1)
    joints = np.full((t.size, 24, 3), np.nan)
    joints[est] = joint_positions(poses[est], rec.template)
    cfg = OutputsConfig(poses="cut.poses")
    _write_npz(tmp_path / "motion.npz", t, poses, joints, est, np.full((t.size, 24), 0.9) * est[:, None], cfg)
    m = np.load(tmp_path / "motion.npz")
    assert m["estimated"].sum() == 40 and np.isnan(m["poses"][20:30]).all() and np.isfinite(m["poses"][est]).all()
    assert m["gaps_us"].tolist() == [[20_000, 29_000]] and m["confidence"].shape == (50, 24)
    assert [(s.start, s.stop) for s in motion_segments(t[est], 1000)] == [(0, 20), (20, 40)]
    written = _write_bvh(tmp_path / "motion.bvh", t[est], poses[est], rec.template, 1000, cfg)
    assert not (tmp_path / "motion.bvh").exists()
    assert (tmp_path / "motion_part01.bvh").exists() and (tmp_path / "motion_part02.bvh").exists()
    assert "motion_part02.bvh" in str(written)


def test_confidence_is_zero_out_of_view_and_where_nothing_supports_the_estimate():
    """At the truth with exact detections every joint in view is observed at the frames; a joint pushed out of the
    image is 0; a landmark not observed gives its joint no support; between two frames a joint that moved and has
    no event support decays to 0 half way, a still one keeps its support."""
    from helpers.poses import detect
    from helpers.spline_scene import EXACT

    inputs = stage_inputs()
    rec = inputs["recording"]
    det = detect("simulated", rec, **EXACT)  # exact landmarks; those hidden by the body are not observations
    gt = rec.ground_truth
    t_det = np.asarray(det.t_us, dtype=np.int64)
    t = np.arange(t_det[0], t_det[-1] + 1, 1000, dtype=np.int64)
    P = gt.poses[np.searchsorted(gt.t_us, t)]
    cam = rec.camera
    ones = np.ones((t.size, 24))
    c = motion_confidence(rec.template, cam, t, P, t_det, np.asarray(det.keypoints_2d, np.float64),
                          det.observed(), np.asarray(det.confidence_2d, np.float64), ones, 0.05, 0.05)
    at = np.searchsorted(t, t_det)
    seen = in_image(cam, joint_positions(P, rec.template))
    assert c.shape == (t.size, 24) and c.min() >= 0 and c.max() <= 1
    lj = np.asarray(rec.template.landmark_joint)
    obs = det.observed()
    for d, k in enumerate(at):  # every joint whose own landmark is observed: as sure as the detector (exact data)
        joints = np.unique(lj[obs[d]])
        assert (c[k, joints] > 0.89).all(), (d, c[k, joints])  # the detector says 0.9 for a sharp landmark
    assert not (c[~seen] > 0).any()  # out of view: never marked seen
    # no observation of the right wrist's landmark at frame 1: its support there is gone
    bad = det.observed().copy()
    from eventcap.body.skeleton import JOINT_INDEX, LANDMARK_INDEX

    bad[1, LANDMARK_INDEX["r_wrist"]] = False
    c2 = motion_confidence(rec.template, cam, t, P, t_det, np.asarray(det.keypoints_2d, np.float64), bad,
                           np.asarray(det.confidence_2d, np.float64), ones, 0.05, 0.05)
    assert c2[at[1], JOINT_INDEX["r_wrist"]] == 0.0 < c[at[1], JOINT_INDEX["r_wrist"]]
    # between two frames: a moving joint without events decays to 0 half way, a still one keeps its support
    s = interval_support(np.array([0, 500, 1000]), np.array([0, 1000]), np.ones((2, 24)),
                         np.tile(np.arange(24) % 2 == 0, (1, 1)), np.zeros((3, 24)))
    assert np.allclose(s[[0, 2]], 1.0) and np.allclose(s[1, 0::2], 0.0) and np.allclose(s[1, 1::2], 1.0)


def test_a_recording_without_frames_picks_the_event_only_pipeline():
    from eventcap.apps.compose import frameless_source

    assert frameless_source({"source": {"stage": "synthetic", "camera": "davis240c", "frames": None}}) is None
    assert "dvxplorer" in frameless_source({"source": {"stage": "synthetic", "camera": "dvxplorer", "frames": None}})
    assert "frames=false" in frameless_source({"source": {"stage": "synthetic", "camera": "davis240c",
                                                          "frames": False}})
    assert frameless_source({"source": {"stage": "recording", "path": "/nonexistent.aedat4"}}) is None


@pytest.mark.parametrize("has_frames", [True, False])
def test_recording_has_frames_reads_the_file(tmp_path, has_frames):
    from eventcap.events import make_events
    from eventcap.io.hdf5 import write_hdf5
    from eventcap.io.readers import recording_has_frames

    ev = make_events(np.arange(50) * 100, np.arange(50) % 30, np.arange(50) % 20, np.ones(50, int))
    frames = (np.zeros((3, 24, 32), np.float32), np.array([0, 2000, 4000]), np.full(3, 1000)) if has_frames else None
    write_hdf5(tmp_path / "rec.h5", iter([ev]), 32, 24, frames=frames)
    assert recording_has_frames(tmp_path / "rec.h5") is has_frames


def test_a_joint_whose_body_the_image_edge_cuts_is_not_in_view():
    """joint_radii: each joint's depth inside the template's body (its distance to the surface); in_image with a
    radius needs the ball around the point inside the image: f r / z px from every edge."""
    from eventcap.body.procedural import procedural_template
    from eventcap.body.skeleton import JOINT_INDEX
    from eventcap.camera import Camera
    from eventcap.analysis.confidence import joint_radii

    tpl = procedural_template(target_faces=3000)
    r = joint_radii(tpl)
    nearest_vertex = np.linalg.norm(tpl.vertices[None] - tpl.rest_joints[:, None], axis=-1).min(axis=1)
    assert r.shape == (24,) and (r > 0.01).all() and (r <= nearest_vertex + 1e-12).all()
    assert r[JOINT_INDEX["pelvis"]] > 0.07 > r[JOINT_INDEX["l_wrist"]]  # a torso is thicker than a wrist
    cam = Camera(240, 180, 200.0, 200.0, 119.5, 89.5, np.zeros(5), np.eye(3), np.zeros(3))
    z, rad = 2.0, 0.1  # the margin: 200 * 0.1 / 2 = 10 px
    u = np.array([-0.5 + 9.0, -0.5 + 11.0, 239.5 - 9.0, 239.5 - 11.0])  # 9 and 11 px inside the left / right edge
    pts = np.stack([(u - 119.5) * z / 200.0, np.zeros(4), np.full(4, z)], axis=1)
    assert in_image(cam, pts).all()
    assert in_image(cam, pts, rad).tolist() == [False, True, False, True]
    assert in_image(cam, pts, np.array([0.0, rad, 0.0, rad])).tolist() == [True, True, True, True]
