"""The spline solve (pipeline=spline) through `eventcap run`: a failed window is recorded, the nodes after it are
skipped with its cause, and once the cause is gone only that window is computed again; a run killed with SIGKILL
during the window solves resumes without recomputing a committed window and ends with the same motion."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from eventcap.apps.cli import main
from eventcap.core.stage import StageFailed
from helpers.paths import ROOT
from helpers.runs import TINY_SPLINE_RUN


def _run(tmp_path, name: str, cache: str) -> tuple[int, dict]:
    run_dir = tmp_path / name
    code = main(["run", *TINY_SPLINE_RUN, f"cache_dir={tmp_path / cache}", f"hydra.run.dir={run_dir}"])
    return code, json.loads((run_dir / "run.json").read_text())


def _motion(tmp_path, name: str) -> dict[str, np.ndarray]:
    with np.load(tmp_path / name / "motion.npz") as z:
        return {k: z[k] for k in z.files}


def test_a_failed_window_is_recorded_and_alone_recomputed_once_its_cause_is_gone(tmp_path, monkeypatch):
    import eventcap_spline.solve as spline_solve

    real = spline_solve.solve_window

    def failing(*args, what: str, **kw):  # stands in for a solver failure of batch 1's window
        if what.startswith("batch 1 "):
            raise StageFailed(f"{what}: IPOPT stopped (Maximum_Iterations_Exceeded)",
                              status="Maximum_Iterations_Exceeded")
        return real(*args, what=what, **kw)

    monkeypatch.setattr(spline_solve, "solve_window", failing)
    code, first = _run(tmp_path, "first", "cache")
    assert code == 1 and not first["ok"]
    solve = first["nodes"]["solve"]
    [fail] = solve["failed"]
    assert fail["batch"] == 1 and "window of batches 0..2" in fail["error"] and solve["computed"] == 2
    cause = first["nodes"]["stitch"]["skip_causes"][0]["cause"]
    assert cause.startswith("upstream failed: solve[batch 1]") and first["nodes"]["stitch"]["computed"] == 0
    assert not (tmp_path / "first" / "motion.npz").exists()

    monkeypatch.setattr(spline_solve, "solve_window", real)  # the cause is gone
    code, second = _run(tmp_path, "second", "cache")
    assert code == 0 and second["ok"]
    solve = second["nodes"]["solve"]
    assert (solve["computed"], solve["cached"]) == (1, 2)  # batch 1's window alone
    assert second["nodes"]["source"]["cached"] == 1 and second["nodes"]["track"]["computed"] == 0

    # the same motion as a run that never failed (its window entries and everything after them computed afresh)
    for stage in ("spline", "stitch", "cut", "evaluate"):
        shutil.rmtree(tmp_path / "cache" / "entries" / stage)
    code, clean = _run(tmp_path, "clean", "cache")
    assert code == 0 and clean["nodes"]["solve"]["computed"] == 3
    a, b = _motion(tmp_path, "second"), _motion(tmp_path, "clean")
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    assert a["poses"].shape == (121, 33)  # 5..125 ms at 1 kHz


def _entries(cache, stage: str) -> set[str]:
    d = cache / "entries" / stage
    return {p.name for p in d.iterdir() if (p / "manifest.json").exists()} if d.exists() else set()


@pytest.mark.slow
def test_killed_during_the_window_solves_resumes_without_recomputing_and_ends_equal(tmp_path):
    cache = tmp_path / "cache"
    cmd = [sys.executable, "-m", "eventcap.apps.cli", "run", *TINY_SPLINE_RUN, "source.duration_s=0.25", f"cache_dir={cache}"]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([*cmd, f"hydra.run.dir={tmp_path / 'killed'}"], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 600  # gives up waiting (a hung run), not a speed claim
    while len(_entries(cache, "spline")) < 2:  # two windows committed, the next ones under way
        assert proc.poll() is None, "the run ended before it could be killed"
        if time.monotonic() > deadline:
            proc.kill()
            raise TimeoutError("no two windows committed within 600 s: the run hangs")
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    committed = _entries(cache, "spline")
    assert 2 <= len(committed) < 6  # 6 batches at 25 fps in 0.25 s

    resumed = subprocess.run([*cmd, f"hydra.run.dir={tmp_path / 'resumed'}"], cwd=ROOT, env=env,
                             capture_output=True, text=True, timeout=900)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    summary = json.loads((tmp_path / "resumed" / "run.json").read_text())
    solve = summary["nodes"]["solve"]
    assert not set(solve["computed_keys"]) & committed and solve["cached"] >= len(committed)

    fresh = subprocess.run([*cmd, f"cache_dir={tmp_path / 'fresh'}", f"hydra.run.dir={tmp_path / 'fresh_run'}"],
                           cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert fresh.returncode == 0, fresh.stderr[-3000:]
    with np.load(tmp_path / "resumed" / "motion.npz") as a, np.load(tmp_path / "fresh_run" / "motion.npz") as b:
        assert all(np.array_equal(a[k], b[k]) for k in a.files)


def test_a_frame_clock_off_the_millisecond_grid_runs_through(tmp_path):
    """15 fps frames are 66 666.7 us apart, so the batches' ends are off the 1 ms tracking grid (so is any real
    camera's frame clock). The spline solve's windows, the stitch, the evaluation and every output handle it: the
    motion holds each frame and the whole grid between, the BVH and C3D have one frame per millisecond."""
    run_dir = tmp_path / "run"
    code = main(["run", *TINY_SPLINE_RUN, "source.duration_s=0.3", "source.fps=15", "source.exposure_us=20000",
                 "outputs.c3d=true", f"cache_dir={tmp_path / 'cache'}", f"hydra.run.dir={run_dir}"])
    assert code == 0
    t = _motion(tmp_path, "run")["t_us"]
    frames = 10_000 + np.round(np.arange(5) * 1e6 / 15).astype(np.int64)  # 10000, 76667, 143333, 210000, 276667
    assert set(t[t % 1000 != 0].tolist()) == {76_667, 143_333, 276_667}
    assert np.array_equal(t[t % 1000 == 0], np.arange(10_000, 276_001, 1000)) and set(frames) <= set(t.tolist())
    metrics = json.loads((run_dir / "metrics.json").read_text())["evaluate.metrics"]
    assert 5 < metrics["AE_mm"] < 60 and np.isfinite(metrics["MPJVE_mm_s"])
    assert metrics["n_velocity_frames"] == 267 - 10  # the grid frames 5 ms or more from the ends; no frame between
    bvh = (run_dir / "motion.bvh").read_text()
    assert "Frames: 267" in bvh and "Frame Time: 0.001" in bvh
    assert (run_dir / "motion.c3d").stat().st_size > 10_000
