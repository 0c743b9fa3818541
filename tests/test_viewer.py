"""The Rerun recording of a run (eventcap/apps/viewer.py, outputs.rerun=true, `eventcap view`): written from a small
default-like run, read back with Rerun's own reader (entities, time range, row counts, values)."""

from __future__ import annotations

import collections
import json
import logging
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from eventcap.export.bvh import read_motion_npz

pytest.importorskip("rerun")
from helpers.runs import small_capture_config
from rerun.chunk import RrdReader  # noqa: E402

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent

#: The default pipeline (conf/pipeline/default.yaml) with the solve replaced by known poses and no refine: every
#: layer of the recording (frames, EDI latent images, events, detections, EKLT tracks sliced at 1 ms, the 1 kHz motion,
#: ground truth, the evaluation's errors, per-batch nodes) in a few seconds.
DEFAULT_LIKE = {"nodes": {
    "template": {"config": "template"},
    "source": {"config": "source", "inputs": {"template": "template.template"}},
    "sharpen": {"inputs": {"recording": "source.recording"}},
    "track": {"inputs": {"recording": "source.recording", "latent": "sharpen.latent", "batches": "source.batches",
                         "detections": "detect.detections"}},
    "slice": {"inputs": {"tracks": "track.tracks", "batches": "source.batches"}},
    "detect": {"inputs": {"recording": "source.recording"}},
    "solve": {"inputs": {"recording": "source.recording", "batches": "source.batches"}},
    "evaluate": {"inputs": {"recording": "source.recording", "poses": "solve.poses"}},
}}

pytestmark = pytest.mark.usefixtures("known_poses")  # conftest: tests/output_stages.py registered


@pytest.fixture(autouse=True)
def _view_cache(tmp_path, monkeypatch):
    """What `eventcap view` builds goes to the test's own folder, not ~/.cache."""
    monkeypatch.setenv("EVENTCAP_VIEW_DIR", str(tmp_path / "views"))


def config(cache: Path, **outputs) -> dict:
    data = json.loads(json.dumps(small_capture_config()))
    data["pipeline"] = json.loads(json.dumps(DEFAULT_LIKE))
    data["cache_dir"] = str(cache)
    data["stages"]["solve"] = {"stage": "known_poses"}
    data["outputs"].update({"poses": "solve.poses", "bvh": False, "video": False, **outputs})
    return data


def run_job(cfg: dict, run_dir: Path):
    """Through the CLI's own job function: the pipeline, config.yaml, run.json and the outputs."""
    import yaml

    from eventcap.apps.cli import run_job as cli_run_job

    failures: list[str] = []
    got = cli_run_job(cfg, run_dir, yaml.safe_dump(cfg), failures)
    assert got is not None and failures == [], failures
    return got


def read_rrd(path: Path) -> tuple[dict[str, int], dict[str, np.ndarray], list]:
    """Rows per entity (static rows included), the t_us times (µs) of each temporal entity, and the chunks."""
    reader = RrdReader(str(path))
    chunks = reader.stream().to_chunks()
    rows: dict[str, int] = collections.Counter()
    times: dict[str, list] = collections.defaultdict(list)
    for c in chunks:
        rows[c.entity_path] += c.num_rows
        if not c.is_static:
            assert "t_us" in c.timeline_names, (c.entity_path, c.timeline_names)
            t = c.to_record_batch().column("t_us").to_numpy()
            times[c.entity_path].append(t.astype("timedelta64[us]").astype(np.int64))
    return dict(rows), {k: np.sort(np.concatenate(v)) for k, v in times.items()}, chunks


def column(chunks, entity: str, component: str) -> list:
    """Values of one component column of an entity, row by row in time order."""
    out = []
    for c in chunks:
        if c.entity_path != entity or c.is_static:
            continue
        rb = c.to_record_batch()
        name = next(n for n in rb.schema.names if n.endswith(component))
        t = rb.column("t_us").to_numpy().astype("timedelta64[us]").astype(np.int64)
        out += list(zip(t.tolist(), rb.column(name).to_pylist()))
    return [v for _, v in sorted(out, key=lambda tv: tv[0])]


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """One small default-like run with outputs.rerun=true (and the motion npz to compare with)."""
    mp = pytest.MonkeyPatch()
    from eventcap.core.runner import reset_process_caches

    mp.setenv("EVENTCAP_STAGES", "output_stages:SPECS")
    mp.syspath_prepend(str(TESTS))
    reset_process_caches()
    tmp = tmp_path_factory.mktemp("viewer")
    run_dir = tmp / "run"
    runner, result = run_job(config(tmp / "cache", rerun=True), run_dir)
    yield tmp, run_dir, runner, result
    mp.undo()
    reset_process_caches()


def test_the_recording_of_a_default_like_run_read_back_with_rerun(finished_run):
    _, run_dir, runner, result = finished_run
    rrd = run_dir / "capture.rrd"
    summary = json.loads((run_dir / "run.json").read_text())["outputs"]
    assert summary["written"]["rerun"] == str(rrd) and summary["problems"] == []
    stats = summary["rerun"]
    assert stats["bytes"] == rrd.stat().st_size and stats["decimated"] == {}
    m = read_motion_npz(run_dir / "motion.npz")
    T = m["t_us"].size
    assert T == 81  # 2 batches of 40 ms at 1 kHz, the shared frame once
    rows, times, chunks = read_rrd(rrd)

    # every layer is there, on the run's own time axis
    layers = {"/world/camera/image/frame", "/world/camera/image/latent", "/world/camera/image/events",
              "/world/camera/image/detections", "/world/camera/image/tracks", "/world/camera/image/silhouette",
              "/world/camera/image/skeleton", "/world/camera/image/truth", "/world/skeleton/estimate",
              "/world/skeleton/truth", "/error/mean_joint_error_mm", "/batches/plan", "/batches/track",
              "/batches/slice", "/batches/solve"}
    layers |= {f"/speed/{w}/{j}" for w in ("estimate", "truth") for j in ("l_wrist", "r_wrist", "l_ankle",
                                                                          "r_ankle", "head")}
    assert layers <= set(times)
    assert {"/", "/world", "/world/camera", "/world/camera/image"} <= set(rows) - set(times)  # static
    rec = runner.load_output(result, "source.recording")[None]
    t0, t1 = int(m["t_us"][0]), int(m["t_us"][-1])
    assert (t0, t1) == (int(rec.frames.t_us[0]), int(rec.frames.t_us[-1]))
    assert min(t.min() for t in times.values()) == t0 and max(t.max() for t in times.values()) == t1

    # counts: one row per motion frame for the 1 kHz layers, per frame for images, per sliced frame for tracks
    for e in ("events", "skeleton", "truth"):
        assert np.array_equal(times[f"/world/camera/image/{e}"], m["t_us"]), e
    assert np.array_equal(times["/world/camera/image/silhouette"], m["t_us"][::5])  # every 5 ms
    assert np.array_equal(times["/world/skeleton/estimate"], m["t_us"])
    assert np.array_equal(times["/world/camera/image/frame"], rec.frames.t_us)
    latent = runner.load_output(result, "sharpen.latent")[None]
    assert np.array_equal(times["/world/camera/image/latent"], latent.t_us)
    assert rows["/world/camera/image/detections"] == rec.frames.t_us.size == 3
    sliced = runner.load_output(result, "slice.sliced")
    assert rows["/world/camera/image/tracks"] == sum(s.t_us.size for s in sliced.values()) == 82
    n_pts = sum(int((s.valid & np.isfinite(s.xy).all(-1)).sum()) for s in sliced.values())
    assert sum(len(v) for v in column(chunks, "/world/camera/image/tracks", "positions")) == n_pts > 0
    # speeds: central differences over +-5 ms, so the first and last 5 frames drop out (+1 static style row)
    assert times["/speed/estimate/l_wrist"].size == T - 10 and rows["/speed/estimate/l_wrist"] == T - 10 + 1
    errors = runner.load_output(result, "evaluate.errors")[None]
    assert times["/error/mean_joint_error_mm"].size == errors.t_us.size
    # batches: a step at each boundary, one log line per batch of each per-batch node
    assert np.array_equal(times["/batches/plan"], [t0, int(rec.frames.t_us[1]), t1])
    for node in ("track", "slice", "solve"):
        assert rows[f"/batches/{node}"] == 2
    lines = column(chunks, "/batches/solve", "text")
    assert lines[0][0].startswith("batch 0: solve committed; status known")

    # values: the 3D skeleton is motion.npz's joints (float32), the projected one the camera's projection
    est = column(chunks, "/world/skeleton/estimate", "positions")
    assert len(est) == T and np.abs(np.array(est) - m["joints"]).max() < 1e-5
    kp = column(chunks, "/world/skeleton/estimate", "keypoint_ids")
    assert kp[0] == list(range(24))
    px = np.array(column(chunks, "/world/camera/image/skeleton", "positions"))
    want = rec.camera.project(m["joints"].reshape(-1, 3)).reshape(T, 24, 2)
    assert np.abs(px - want).max() < 1e-3
    truth = np.array(column(chunks, "/world/skeleton/truth", "positions"))
    gt = rec.ground_truth
    k = np.searchsorted(gt.t_us, m["t_us"])
    assert np.abs(truth - gt.joints[k]).max() < 1e-5
    # a blueprint (the layout of the views) comes with the file
    assert len(RrdReader(str(rrd)).blueprints()) == 1


def test_speeds_are_central_differences_and_skip_gaps():
    from eventcap.apps.viewer import speeds

    t = np.r_[np.arange(0, 30_000, 1000), np.arange(40_000, 60_000, 1000)].astype(np.int64)
    J = np.zeros((t.size, 24, 3))
    J[:, 20, 0] = 2.0 * t * 1e-6  # the left wrist moves at 2 m/s along x
    J[:, 0, 1] = (t * 1e-6) ** 2  # the pelvis accelerates: v = 2t
    idx, v = speeds(t, J)
    # inside each stretch: frames at least 5 ms from its ends
    assert np.array_equal(t[idx], np.r_[np.arange(5000, 25_000, 1000), np.arange(45_000, 55_000, 1000)])
    assert np.allclose(v[:, 20], 2.0) and np.allclose(v[:, 0], 2 * t[idx] * 1e-6) and np.all(v[:, 1] == 0)


def test_decimation_is_logged_and_respected(finished_run, caplog):
    tmp, run_dir, runner, result = finished_run
    from eventcap.apps.viewer import collect_run_content, write_recording

    m = read_motion_npz(run_dir / "motion.npz")
    rec = runner.load_output(result, "source.recording")[None]
    content = collect_run_content(runner, result, m["t_us"], m["poses"], m["joints"], rec, rec.template)
    with caplog.at_level(logging.INFO, logger="eventcap.apps.viewer"):
        stats = write_recording(tmp / "small.rrd", content, events_ms=2, every_ms=1, max_frames=20,
                                outline_every_ms=1)
    n = stats["counts"]["event images"]
    assert 15 <= n <= 20  # the overlay video's rule: the step widens evenly to a whole number of ms
    assert stats["decimated"] == {"event images": f"{n} of 81", "silhouettes": f"{n} of 81"}
    assert f"event images decimated: {n} of 81" in caplog.text and f"silhouettes decimated: {n} of 81" in caplog.text
    _, times, _ = read_rrd(tmp / "small.rrd")
    ev = times["/world/camera/image/events"]
    assert ev.size == n and ev[0] == m["t_us"][0] and ev[-1] >= m["t_us"][-1] - 5000
    assert set(np.diff(ev).tolist()) <= {4000, 5000}  # evenly spread: one per 80 ms / 19 = 4.2 ms
    assert times["/world/skeleton/estimate"].size == 81  # the motion itself is never decimated
    assert not list(tmp.glob("*.partial*"))


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): (p.read_bytes() if p.is_file() else b"<dir>") for p in folder.rglob("*")}


def test_eventcap_view_builds_the_recording_of_a_finished_run(finished_run, tmp_path, capsys, monkeypatch):
    """Built into the view cache, not into the run folder: reading a run writes nothing into it."""
    from eventcap.apps.cli import main

    _, run_dir, _, _ = finished_run
    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    (copy / "capture.rrd").unlink()
    before = _snapshot(copy)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert main(["view", str(copy)]) == 0
    out = capsys.readouterr()
    built = next((tmp_path / "views").rglob("capture.rrd"))
    assert built.parent.name == "run"  # the run folder's name: the recording's id carries it
    assert "building" in out.err and "no display here" in out.out
    assert f"rerun {built}" in out.out and f"eventcap view {copy} --web\n" in out.out  # which ends the viewer
    # the address that loads the served recording, not the bare viewer (a welcome page)
    assert "open http://127.0.0.1:9090?url=rerun%2Bhttp%3A%2F%2Flocalhost%3A9876%2Fproxy" in out.out
    rows_a, times_a, _ = read_rrd(run_dir / "capture.rrd")
    rows_b, times_b, _ = read_rrd(built)
    assert rows_a == rows_b and all(np.array_equal(times_a[k], times_b[k]) for k in times_a)
    assert _snapshot(copy) == before  # no capture.rrd, no plausibility.json, run.json untouched
    assert sorted(p.name for p in built.parent.iterdir()) == ["capture.rrd"]
    # a second look reuses what was built; --rebuild builds it again, still outside the run folder
    assert main(["view", str(copy), "--no-open"]) == 0
    assert "building" not in capsys.readouterr().err
    assert main(["view", str(copy), "--no-open", "--rebuild"]) == 0
    assert "building" in capsys.readouterr().err and _snapshot(copy) == before
    # a run folder with its own capture.rrd (outputs.rerun=true) is shown as it is, and left as it is
    before = _snapshot(run_dir)
    assert main(["view", str(run_dir), "--no-open"]) == 0
    assert f"rerun {run_dir / 'capture.rrd'}" in capsys.readouterr().out and _snapshot(run_dir) == before
    # an .rrd given directly, and --no-open
    assert main(["view", str(built), "--no-open"]) == 0
    assert "open it with the Rerun viewer" in capsys.readouterr().out


def test_eventcap_view_errors_say_what_is_wrong(finished_run, tmp_path, capsys):
    from eventcap.apps.cli import main

    _, run_dir, _, _ = finished_run
    assert main(["view", str(tmp_path / "nowhere")]) == 2
    assert "expected a run folder (runs/<name>/<timestamp>/) or an .rrd file" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["view", str(tmp_path / "empty")]) == 2
    assert "not a finished run folder (no config.yaml" in capsys.readouterr().err
    # a run whose cache entries are gone: says which and how to restore them
    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    (copy / "capture.rrd").unlink()
    import yaml

    cfg = yaml.safe_load((copy / "config.yaml").read_text())
    cfg["cache_dir"] = str(tmp_path / "other_cache")
    (copy / "config.yaml").write_text(yaml.safe_dump(cfg))
    summary = json.loads((copy / "run.json").read_text())
    summary["cache_dir"] = cfg["cache_dir"]
    (copy / "run.json").write_text(json.dumps(summary))
    assert main(["view", str(copy), "--no-open"]) == 2
    err = capsys.readouterr().err
    assert "of the run's cache entries are gone from" in err and "--recompute" in err


def test_without_rerun_installed_the_message_says_what_to_install(tmp_path, capsys, monkeypatch):
    from eventcap.apps.cli import main
    from eventcap.apps.outputs import check_outputs_config
    from eventcap.core.runner import Runner

    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun -> ImportError
    assert main(["view", str(tmp_path)]) == 2
    assert 'the Rerun viewer is not installed: pip install rerun-sdk (or: pip install -e ".[viewer]")' in \
        capsys.readouterr().err
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "rerun" else real(name, *a))
    with pytest.raises(ValueError, match=r"outputs\.rerun=true needs the rerun-sdk package: pip install rerun-sdk"):
        check_outputs_config(Runner(config(tmp_path, rerun=True)))


@pytest.mark.slow
def test_the_quick_preset_through_the_real_pipeline(tmp_path):
    """`eventcap run experiment=quick outputs.rerun=true` (the real solve and refine; ~1-2 min)."""
    import subprocess

    p = subprocess.run([sys.executable, "-m", "eventcap.apps.cli", "run", "experiment=quick", "outputs.rerun=true",
                        "outputs.video=false", f"cache_dir={tmp_path / 'cache'}", f"hydra.run.dir={tmp_path / 'run'}"],
                       cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr[-2000:]
    rows, times, _ = read_rrd(tmp_path / "run" / "capture.rrd")
    m = read_motion_npz(tmp_path / "run" / "motion.npz")
    assert np.array_equal(times["/world/skeleton/estimate"], m["t_us"])
    for node in ("track", "slice", "solve", "refine"):
        assert rows[f"/batches/{node}"] == 6


# -- the viewer's processes end with `eventcap view` ------------------------------------------------------------------
#: A stand-in for the `rerun` binary (on PATH): it starts a child of its own (as the wheel's launcher script starts the
#: binary), writes both pids, and serves nothing until it is killed.
FAKE_RERUN = """#!{python}
import os, subprocess, sys, time
child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
with open(os.environ["FAKE_RERUN_PIDS"] + ".tmp", "w") as fh:
    fh.write(f"{{os.getpid()}} {{child.pid}}")
os.replace(os.environ["FAKE_RERUN_PIDS"] + ".tmp", os.environ["FAKE_RERUN_PIDS"])
time.sleep(600)
"""


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split(")")[-1].split()[0] != "Z"  # a zombie has ended
    except FileNotFoundError:
        return False


def _start_view(tmp_path, *args):
    import os
    import subprocess
    import time

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    fake = bin_dir / "rerun"
    fake.write_text(FAKE_RERUN.format(python=sys.executable))
    fake.chmod(0o755)
    rrd = tmp_path / "x.rrd"
    rrd.write_bytes(b"not read by the fake viewer")
    pids = tmp_path / "pids"
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}", "FAKE_RERUN_PIDS": str(pids),
           "DISPLAY": ":99"}
    env.pop("RERUN_CLI_PATH", None)
    proc = subprocess.Popen([sys.executable, "-m", "eventcap.apps.cli", "view", str(rrd), *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not pids.exists():
        assert proc.poll() is None, proc.communicate()
        if time.monotonic() > deadline:
            raise TimeoutError("the fake viewer did not start within 60 s")
        time.sleep(0.05)
    return proc, [int(p) for p in pids.read_text().split()]


def _gone(pids, timeout_s=10.0) -> bool:
    import time

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if not any(_alive(p) for p in pids):
            return True
        time.sleep(0.05)
    return False


@pytest.mark.parametrize("how, args", [("SIGTERM", ["--web"]), ("SIGINT", ["--web"]), ("SIGHUP", ["--web"]),
                                       ("SIGTERM", [])])
def test_every_viewer_process_ends_with_eventcap_view(tmp_path, how, args):
    """`kill PID` (or Ctrl-C, or a closed terminal) of `eventcap view --web` ends the viewer and what it started."""
    import os
    import signal

    proc, pids = _start_view(tmp_path, *args)
    try:
        assert all(_alive(p) for p in pids)
        os.kill(proc.pid, getattr(signal, how))
        proc.wait(timeout=20)
        assert _gone(pids), f"left running after {how}: {[p for p in pids if _alive(p)]}"
        assert proc.returncode == (0 if how == "SIGINT" else 128 + getattr(signal, how))
        assert "Traceback" not in proc.stderr.read()
    finally:
        for p in [proc.pid, *pids]:
            if _alive(p):
                os.kill(p, signal.SIGKILL)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the parent-death signal is Linux's")
def test_the_viewer_dies_with_a_killed_eventcap_view(tmp_path):
    """`kill -9` gives `eventcap view` no chance to clean up: the kernel ends the viewer (PR_SET_PDEATHSIG)."""
    import os
    import signal

    proc, (viewer, _grandchild) = _start_view(tmp_path, "--web")
    try:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=20)
        assert _gone([viewer])
    finally:
        for p in (viewer, _grandchild):
            if _alive(p):
                os.kill(p, signal.SIGKILL)


def test_the_viewer_is_the_wheels_binary_not_its_launcher(tmp_path, monkeypatch):
    """The rerun-sdk wheel's `rerun` script only starts its binary as a second process: the binary is run instead."""
    from eventcap.apps.viewer import rerun_command

    launcher = tmp_path / "rerun"
    launcher.write_text(f"#!{sys.executable}\nfrom rerun_cli.__main__ import main\nmain()\n")
    launcher.chmod(0o755)
    binary = tmp_path / "rerun_binary"
    binary.write_text("")
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.setenv("RERUN_CLI_PATH", str(binary))
    assert rerun_command() == [str(binary)]
    launcher.write_text("#!/bin/sh\nexec true\n")  # any other `rerun` on PATH is the user's choice
    assert rerun_command() == [str(launcher)]


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _listening(port: int) -> bool:
    import socket

    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


@pytest.mark.parametrize("how", ["SIGTERM", "SIGKILL"])
def test_the_real_web_viewer_frees_its_ports_when_eventcap_view_is_killed(tmp_path, how):
    """The rerun-sdk wheel's viewer itself (a few seconds): serving, then killed with `eventcap view`."""
    import os
    import signal
    import subprocess
    import time

    from eventcap.apps.viewer import _wheel_binary

    if _wheel_binary() is None:
        pytest.skip("rerun-sdk's viewer binary is not installed")
    import rerun as rr

    rr.init("fake_capture")
    rr.save(str(tmp_path / "x.rrd"))
    rr.log("p", rr.Points3D(np.zeros((3, 3))))
    rr.disconnect()
    port, grpc = _free_port(), _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "eventcap.apps.cli", "view", str(tmp_path / "x.rrd"), "--web",
                             "--port", str(port), "--grpc-port", str(grpc)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while not (_listening(port) and _listening(grpc)):
            assert proc.poll() is None, "the web viewer exited before serving"
            if time.monotonic() > deadline:
                raise TimeoutError("the web viewer did not start within 60 s")
            time.sleep(0.1)
        os.kill(proc.pid, getattr(signal, how))
        proc.wait(timeout=20)
        deadline = time.monotonic() + 15
        while (_listening(port) or _listening(grpc)) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _listening(port) and not _listening(grpc), f"a viewer still serves after {how}"
    finally:
        if proc.poll() is None:
            proc.kill()
