"""The real suite (benchmark=real, eventcap/apps/real_suite.py) and how a motion is held against what a real camera
recorded (eventcap/analysis/event_fit.py)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from eventcap.analysis.event_fit import outline_event_share, outline_mask, reprojection_error
from eventcap.apps.real_suite import format_real, parse_recordings
from eventcap.events import make_events
from helpers.poses import posed_recording

ROOT = Path(__file__).resolve().parents[1]


def _outline_events(rec, poses, shift_px=0):
    """One event on every outline pixel of each pose, at its frame's time (shifted right by shift_px)."""
    parts = []
    tpl = rec.template
    for t, S in zip(rec.ground_truth.t_us[::20], poses[::20]):
        ys, xs = np.nonzero(outline_mask(rec.camera, tpl, S))
        xs = np.clip(xs + shift_px, 0, rec.width - 1)
        parts.append(make_events(np.full(xs.size, t), xs, ys, np.ones(xs.size)))
    ev = np.concatenate(parts)
    return ev[np.argsort(ev["t"], kind="stable")]


def test_outline_share_is_one_on_the_outline_and_falls_when_the_events_lie_beside_it():
    rec = posed_recording("jumping_jack", 5, with_template=True)
    t, S = rec.ground_truth.t_us, rec.ground_truth.poses
    on = outline_event_share(rec.camera, rec.template, t, S, _outline_events(rec, S), every_us=20_000)
    assert on.share == pytest.approx(1.0) and on.frames == len(t[::20]) and on.outline_px > 100
    off = outline_event_share(rec.camera, rec.template, t, S, _outline_events(rec, S, shift_px=6), every_us=20_000)
    assert 0.05 < off.share < 0.8  # only outline pixels within 2 px of the shifted outline
    gap = S.copy()
    gap[:] = np.nan  # nothing estimated: nothing to judge
    assert outline_event_share(rec.camera, rec.template, t, gap, _outline_events(rec, S)).frames == 0


def test_reprojection_error_is_zero_for_detections_on_the_motion_and_counts_only_what_is_in_view():
    rec = posed_recording("jumping_jack", 5, with_template=True)
    gt = rec.ground_truth
    at = np.searchsorted(gt.t_us, rec.frames.t_us)
    from eventcap.body.kinematics import landmark_positions

    kp = rec.camera.project(landmark_positions(gt.poses[at], rec.template))
    conf = np.ones(kp.shape[:2])
    det = SimpleNamespace(t_us=rec.frames.t_us, keypoints_2d=kp, confidence_2d=conf, in_view=None)
    r = reprojection_error(rec.camera, rec.template, gt.t_us, gt.poses, det)
    assert r["median_px"] == pytest.approx(0.0, abs=1e-6) and r["images"] == 5 and r["points"] == kp[..., 0].size
    kp2 = kp + np.array([3.0, 4.0])
    conf[:, :10] = 0  # not observed: not counted
    det2 = SimpleNamespace(t_us=rec.frames.t_us, keypoints_2d=kp2, confidence_2d=conf, in_view=None)
    r2 = reprojection_error(rec.camera, rec.template, gt.t_us, gt.poses, det2)
    assert r2["median_px"] == pytest.approx(5.0) and r2["points"] == 5 * (kp.shape[1] - 10)


def test_parse_recordings_finds_shipped_and_fetched_files_and_names_bad_entries(tmp_path):
    recs = parse_recordings([{"name": "lab", "file": "tests/data/real/davis346_lab_aps.aedat4", "person": "none"},
                             {"name": "walk", "file": "walk.aedat", "overrides": ["source.t_end_s=2"]}],
                            tmp_path, ROOT)
    assert recs[0].path == ROOT / "tests/data/real/davis346_lab_aps.aedat4" and recs[0].path.is_file()
    assert recs[1].path == tmp_path / "walk.aedat" and recs[1].overrides == ("source.t_end_s=2",)
    with pytest.raises(ValueError, match=r"recordings\[0\] \(x\): unknown key 'fiel'"):
        parse_recordings([{"name": "x", "file": "a", "fiel": 1}], tmp_path, ROOT)
    with pytest.raises(ValueError, match="repeats an earlier recording"):
        parse_recordings([{"name": "x", "file": "a"}, {"name": "x", "file": "b"}], tmp_path, ROOT)
    with pytest.raises(ValueError, match="expected a mapping with a name and a file"):
        parse_recordings([{"name": "x"}], tmp_path, ROOT)


def test_the_real_preset_lists_every_recording_with_its_licence_and_how_to_fetch_it():
    from eventcap.apps.benchmark import Benchmark, compose_benchmark

    cfg = compose_benchmark(ROOT / "conf", "real", [])
    bench = Benchmark(cfg, ROOT / "conf", [])
    assert len(bench.real) >= 9 and all(r.licence and r.source and r.fetch and r.person for r in bench.real.values())
    shipped = [r for r in bench.real.values() if r.fetch == "shipped"]
    assert shipped and all(r.path.is_file() and r.path.stat().st_size < 1_300_000 for r in shipped)
    assert all(("source=recording" in c.overrides) for c in bench.captures)


def test_format_real_says_motion_or_refusal_per_recording():
    runs = [{"motion_name": "walk", "person": "whole body", "has_motion": True, "ok": True, "observed_share": 0.61,
             "plausibility": [], "outline_share": 0.42, "outline_share_10ms": 0.7, "outline_frames": 12, "reproj_median_px": 3.2,
             "reproj_p90_px": 7.9},
            {"motion_name": "lab", "person": "none", "has_motion": False, "error": "detect: no person in 3 of 3"}]
    text = format_real(runs)
    assert "| walk " in text and "motion" in text and "61%" in text and "42%; 70% (12 moments)" in text
    assert "3.2 (p90 7.9)" in text and "refused: detect: no person in 3 of 3" in text
    assert text.splitlines()[-1] == "1 of 2 recordings gave a motion, 1 of them with no plausibility finding"


def test_format_real_names_the_chunk_seams_apart():
    runs = [{"motion_name": "walk", "person": "whole body", "has_motion": True, "ok": True, "observed_share": 0.55,
             "plausibility": [], "stats": {"stitch": {"seams": 3.0, "seams_apart": 3.0, "seam_pose_mm_max": 249.2,
                                                      "seam_shift_mm_max": 451.0}}},
            {"motion_name": "wave", "person": "whole body", "has_motion": True, "ok": True, "observed_share": 0.8,
             "plausibility": [], "stats": {"stitch": {"seams": 1.0, "seams_apart": 0.0, "seam_pose_mm_max": 12.0,
                                                      "seam_shift_mm_max": 3.0}}}]
    text = format_real(runs)
    assert "3 of 3 (249; 451 mm)" in text and "0 of 1 (12; 3 mm)" in text
    assert text.splitlines()[-1] == ("2 of 2 recordings gave a motion, 2 of them with no plausibility finding (1 of "
                                     "these with chunk seams apart: the motion hands over between two solutions "
                                     "there)")
