"""The template and source stages pass the conformance suite, and recordings round-trip through the pipeline."""

from __future__ import annotations

import functools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import zarr

from eventcap.artifacts.recording import Recording
from eventcap.body.procedural import procedural_template
from eventcap.core.testing import StageConformance

REAL = Path(__file__).resolve().parent / "data" / "real" / "davis346_lab_aps.aedat4"  # shipped (tests/data/real/SOURCE.md)


@functools.lru_cache(maxsize=1)
def template():
    return procedural_template(seed=0, target_faces=4000)


class TestProcedural(StageConformance):
    stage_name = "procedural"
    config_overrides = {"target_faces": 3000}
    sensitive = ("seed", 1)

    def make_inputs(self):
        return {}


class TestSynthetic(StageConformance):
    stage_name = "synthetic"
    config_overrides = {"duration_s": 0.09, "supersample": 1, "n_track_points": 20, "motion": "jumping_jack"}
    sensitive = ("contrast_threshold", 0.3)

    def make_inputs(self):
        return {"template": template()}

    def test_batches_between_frames(self):
        out = self.run_once()
        rec, plan = out["recording"], out["batches"]
        assert rec.frames.images.shape == (3, 180, 240) and rec.frames.images.dtype == np.float32
        assert len(plan) == 2 and plan.t0_us[1] == rec.frames.t_us[1] and plan.t1_us[1] == rec.frames.t_us[2]
        assert rec.ground_truth.joints.shape == (91, 24, 3) and rec.template is not None


class TestRecordingReal(StageConformance):
    stage_name = "recording"
    config_overrides = {"path": str(REAL)}
    sensitive = ("t_end_s", 0.1)

    def make_inputs(self):
        return {}

    def test_real_davis346(self):
        out = self.run_once()
        rec, plan = out["recording"], out["batches"]
        assert (rec.width, rec.height) == (346, 260)
        assert rec.events.events.size == 117_667 and rec.frames.images.shape == (3, 260, 346)
        assert np.all(np.abs(rec.frames.exposure_us - 4_773) <= 1) and len(plan) == 2
        assert "UNCALIBRATED" in rec.source

    def test_time_window(self):
        out = self.run_once(t_start_s=0.02, t_end_s=0.09)
        ev = out["recording"].events.events
        assert ev["t"].min() >= 20_000 and ev["t"].max() < 90_000


def test_simulate_then_read_back_as_recording(tmp_path):
    env = {**__import__("os").environ}
    cmd = [sys.executable, "-m", "eventcap.apps.cli"]
    subprocess.run(cmd + ["simulate", "motion=jumping_jack", "duration_s=0.1", "seed=3", "supersample=1",
                          "n_track_points=10", "hydra.run.dir=runs/sim", "template=procedural", "template.target_faces=3000"],
                   cwd=tmp_path, env=env, check=True, capture_output=True, timeout=600)
    rec_path = tmp_path / "runs" / "sim" / "source.recording.zarr"
    original = Recording.from_zarr(zarr.open_group(str(rec_path), mode="r"))
    assert original.name == "synthetic-jumping_jack-seed3" and original.ground_truth is not None
    p = subprocess.run(cmd + ["run", "pipeline=simulate", "source=recording", f"source.path={rec_path}",
                              "export=[source.recording]", "hydra.run.dir=runs/read", "template=procedural", "template.target_faces=3000"],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    back = Recording.from_zarr(zarr.open_group(str(tmp_path / "runs" / "read" / "source.recording.zarr"), mode="r"))
    assert back.equals(original)
    png = subprocess.run(cmd + ["preview", str(rec_path), "--frame", "1", "--out", str(tmp_path / "p.png")],
                         capture_output=True, text=True, check=True)
    assert (tmp_path / "p.png").stat().st_size > 10_000 and "wrote" in png.stdout
    run = json.loads((tmp_path / "runs" / "read" / "run.json").read_text())
    assert run["nodes"]["template"]["cached"] == 1  # shared with the simulate run


def test_missing_path_is_a_clear_error(tmp_path):
    p = subprocess.run([sys.executable, "-m", "eventcap.apps.cli", "run", "pipeline=simulate", "source=recording",
                        f"source.path={tmp_path / 'nope.aedat4'}", "template=procedural", "template.target_faces=3000"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert p.returncode == 1
    assert f"source.path: {tmp_path / 'nope.aedat4'}: no such file or folder" in p.stdout + p.stderr
    assert not (tmp_path / "runs").exists()  # refused before the run folder (and the cache) exist


def test_recording_without_frames_runs_the_event_only_pipeline_unless_told_otherwise(tmp_path):
    """The default command on a recording without intensity frames takes pipeline=events_only and says why; a
    pipeline chosen explicitly (pipeline=default) is kept, and its sharpen stage refuses with a clear message."""
    from eventcap.events import make_events
    from eventcap.io import write_events

    rng = np.random.default_rng(0)
    n = 2000
    ev = make_events(np.sort(rng.integers(0, 100_000, n)), rng.integers(0, 64, n), rng.integers(0, 48, n),
                     rng.choice([-1, 1], n))
    path = write_events(tmp_path / "events_only.npz", ev, width=64, height=48)

    def run(*extra):
        p = subprocess.run([sys.executable, "-m", "eventcap.apps.cli", "run", "source=recording", f"source.path={path}",
                            "template=procedural", "template.target_faces=3000", "outputs.video=false", *extra],
                           cwd=tmp_path, capture_output=True, text=True, timeout=600)
        return p.returncode, p.stdout + p.stderr

    code, out = run("hydra.run.dir=runs/auto")
    assert f"{path} holds no intensity frames (an event-only recording): running pipeline=events_only" in out
    assert "sharpen" not in out.split("running pipeline=events_only")[1]  # no EDI node in that pipeline
    code, out = run("pipeline=default", "hydra.run.dir=runs/nf")
    assert code == 1
    assert "stage 'edi' needs intensity frames (at least 2), but recording 'events_only' has 0" in out
