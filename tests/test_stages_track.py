"""The Sec. 3.1 stages (edi, eklt, klt_latent, bspline) pass the conformance suite on a tiny synthetic capture, and
the default pipeline runs end to end through slicing."""

from __future__ import annotations

import functools
import json
import subprocess
import sys

import numpy as np

from eventcap.core.registry import load_registry
from eventcap.core.stage import StageContext
from eventcap.core.testing import StageConformance


@functools.lru_cache(maxsize=1)
def tiny_recording():
    """A 90 ms synthetic capture (3 frames, 2 batches) from the synthetic stage itself."""
    spec = load_registry().get("synthetic")
    from eventcap.body.procedural import procedural_template
    from eventcap.core.config import build_config

    cfg = build_config(spec, {"duration_s": 0.09, "supersample": 1, "n_track_points": 10, "motion": "jumping_jack",
                              "speed": 2.0}, "source")
    out = spec.load_run()({"template": procedural_template(target_faces=3000)}, cfg,
                          StageContext(node="source", stage="synthetic"))
    return out["recording"], out["batches"]


@functools.lru_cache(maxsize=1)
def tiny_latent():
    spec = load_registry().get("edi")
    from eventcap.core.config import build_config

    return spec.load_run()({"recording": tiny_recording()[0]}, build_config(spec, {"contrast": 0.2}, "sharpen"),
                           StageContext(node="sharpen", stage="edi"))["latent"]


class TestEdi(StageConformance):
    stage_name = "edi"
    sensitive = ("contrast", 0.25)

    def make_inputs(self):
        return {"recording": tiny_recording()[0]}

    def test_estimated_contrast_near_simulator(self):
        latent = self.run_once()["latent"]
        assert latent.contrast_estimated and 0.16 <= latent.contrast <= 0.24
        assert latent.log_images.shape == (3, 180, 240) and np.isfinite(latent.log_images).all()


class TestOracle(StageConformance):
    stage_name = "oracle"
    sensitive = ("noise_px", 0.5)

    def make_inputs(self):
        rec, plan = tiny_recording()
        return {"recording": rec, "batches": plan}

    def test_tracks_are_the_ground_truth_points(self):
        rec, plan = tiny_recording()
        tr = self.run_once()["tracks"]
        gt = rec.ground_truth
        b = plan.batch(0)
        assert tr.n_tracks >= 5 and np.all(tr.kind == 3)
        assert tr.t_us.min() >= b.t0_us and tr.t_us.max() <= b.t1_us
        for h in range(tr.n_tracks):
            m = tr.track_id == h
            rows = np.searchsorted(gt.t_us, tr.t_us[m])
            # some ground-truth point has exactly these positions at these times, visible throughout
            match = [k for k in range(gt.track_px.shape[1])
                     if gt.track_visible[rows, k].all() and np.allclose(gt.track_px[rows, k], tr.xy[m], atol=1e-4)]
            assert match, f"track {h} is not a ground-truth point"
            assert np.all(np.diff(tr.t_us[m]) == 1000)

    def test_needs_ground_truth_tracks(self):
        import dataclasses

        import pytest

        rec, plan = tiny_recording()
        bare = dataclasses.replace(rec, ground_truth=None)
        spec = load_registry().get("oracle")
        from eventcap.core.config import build_config

        with pytest.raises(ValueError, match="needs ground-truth surface tracks"):
            spec.load_run()({"recording": bare, "batches": plan}, build_config(spec, {}, "stages.track"),
                            StageContext(node="track", stage="oracle", batch=plan.batch(0)))


class TestEklt(StageConformance):
    stage_name = "eklt"
    sensitive = ("stitch_px", 2.0)

    def make_inputs(self):
        rec, plan = tiny_recording()
        return {"recording": rec, "latent": tiny_latent(), "batches": plan}

    def test_tracks_inside_batch_and_image(self):
        tr = self.run_once()["tracks"]
        assert tr.n_tracks >= 20
        assert tr.t_us.min() >= 5_000 and tr.t_us.max() <= 45_000
        assert (tr.xy[:, 0] >= 0).all() and (tr.xy[:, 0] < 240).all() and (tr.kind == 3).sum() >= 10

    def test_features_start_around_the_actor_given_detections(self):
        from helpers.poses import detect

        from eventcap.core.config import build_config

        rec, plan = tiny_recording()
        det = detect("simulated", rec)
        spec = load_registry().get("eklt")
        inputs = dict(self.make_inputs(), detections=det)
        ctx = StageContext(node="track", stage="eklt", batch=plan.batch(0))
        box = {}
        for roi in ("actor", "image"):
            tr = spec.load_run()(inputs, build_config(spec, {"roi": roi, "direction": "forward"}, "stages.track"),
                                 ctx)["tracks"]
            first = np.flatnonzero(np.r_[True, np.diff(tr.track_id) != 0])
            box[roi] = tr.xy[first]
        kp = det.keypoints_2d[0][det.confidence_2d[0] > 0.1]
        lo, hi = kp.min(axis=0) - 12.0, kp.max(axis=0) + 12.0
        assert box["actor"].shape[0] >= 5
        assert np.all((box["actor"] >= lo - 1) & (box["actor"] <= hi + 1))  # started inside the actor's box
        assert np.any((box["image"] < lo - 1) | (box["image"] > hi + 1))  # without it, background corners too


class TestKltLatent(StageConformance):
    stage_name = "klt_latent"
    sensitive = ("window_px", 15)

    def make_inputs(self):
        rec, plan = tiny_recording()
        return {"recording": rec, "latent": tiny_latent(), "batches": plan}


class TestBspline(StageConformance):
    stage_name = "bspline"
    sensitive = ("rate_hz", 500.0)

    def make_inputs(self):
        rec, plan = tiny_recording()
        from eventcap.artifacts.tracking import Tracks

        t = np.arange(5_000, 45_001, 250, dtype=np.int64)
        xy = np.stack([100 + 300e-6 * (t - 5_000), 80 + 20 * np.sin((t - 5_000) / 1e4)], 1).astype(np.float32)
        return {"tracks": Tracks(track_id=np.zeros(t.size, np.int32), t_us=t, xy=xy, cost=np.zeros(t.size, np.float32),
                                 kind=np.array([1], np.int8), survived=np.array([True])),
                "batches": plan}

    def test_slices_follow_the_track(self):
        s = self.run_once()["sliced"]
        assert s.t_us.shape == (41,) and np.all(np.diff(s.t_us) == 1000) and s.valid.all()
        truth = 100 + 300e-6 * (s.t_us - 5_000)
        assert np.abs(s.xy[:, 0, 0] - truth).max() < 0.05


def test_default_pipeline_runs_through_solving(tmp_path):
    p = subprocess.run([sys.executable, "-m", "eventcap.apps.cli", "run", "experiment=quick", "source.duration_s=0.09",
                        "template=procedural", "template.target_faces=3000", "hydra.run.dir=runs/x"], cwd=tmp_path, capture_output=True,
                       text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    run = json.loads((tmp_path / "runs" / "x" / "run.json").read_text())
    # per batch: track, slice; the solve runs per chunk of ~1 s, here one chunk holding both batches
    assert [run["nodes"][n]["computed"] for n in ("template", "source", "chunk", "sharpen", "track", "slice",
                                                  "solve")] == [1, 1, 1, 1, 2, 2, 1]
