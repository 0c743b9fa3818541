"""``eventcap report RUNS_DIR`` (eventcap/apps/report.py): a fake sweep folder (override sets, a repeated set, a failed
job, jobs without Hydra's records) and one real tiny sweep through ``eventcap run -m``."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from eventcap.apps.report import ReportError, report

TESTS = Path(__file__).resolve().parent


def fake_job(folder: Path, overrides: list[str] | None, config: dict, ae: float | None, ok: bool = True,
             ran: bool = True) -> Path:
    folder.mkdir(parents=True)
    if overrides is not None:
        (folder / ".hydra").mkdir()
        (folder / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    (folder / "config.yaml").write_text(json.dumps(config))  # JSON is YAML
    if ran:
        (folder / "run.json").write_text(json.dumps({"ok": ok, "nodes": {}}))
        metrics = {} if ae is None else {"evaluate.metrics": {"AE_mm": ae, "STD_mm": ae / 10, "AE_raw_mm": ae + 1,
                                                              "AE_nonRaw_mm": ae - 1, "AE_rootrel_mm": ae + 5,
                                                              "MPJVE_mm_s": 10 * ae, "accel_err_m_s2": ae / 4,
                                                              "peak_speed_err": ae / 100,
                                                              "data_rate": {"total_MBps": 2.0},
                                                              "per_joint_mm": {"l_wrist": 2 * ae}}}
        (folder / "metrics.json").write_text(json.dumps(metrics))
    return folder


def test_fake_sweep_one_row_per_override_set(tmp_path, capsys):
    sweep = tmp_path / "multirun"
    base = ["stages/solve=batch", "hydra/launcher=joblib"]
    cfg = lambda px: {"name": "x", "stages": {"track": {"stitch_px": px}}}  # noqa: E731
    fake_job(sweep / "0", [*base, "stages.track.stitch_px=2"], cfg(2), 50.0)
    fake_job(sweep / "1", [*base, "stages.track.stitch_px=4"], cfg(4), 40.0)
    fake_job(sweep / "2", [*base, "stages.track.stitch_px=6"], cfg(6), None, ok=False)  # failed: no metrics
    fake_job(sweep / "10", [*base, "stages.track.stitch_px=4"], cfg(4), 44.0)  # the same set again: averaged
    fake_job(sweep / "3", [*base, "stages.track.stitch_px=8"], cfg(8), None, ran=False)  # refused before running
    res = report(sweep, extra_columns=["per_joint_mm.l_wrist"])
    assert res["keys"] == ["stages.track.stitch_px"] and res["source"] == "overrides"
    assert res["common"] == {"stages/solve": "batch"}  # hydra/launcher is left out
    rows = {r["stages.track.stitch_px"]: r for r in res["rows"]}
    assert list(rows) == ["2", "4", "6", "8"]  # job order: 0, 1, 2, 3, 10 (numeric folder names)
    assert rows["4"]["jobs"] == 2 and rows["4"]["AE (mm)"] == pytest.approx(42.0)
    assert rows["4"]["per_joint_mm.l_wrist"] == pytest.approx(84.0)
    assert rows["6"]["status"] == "incomplete" and rows["6"]["AE (mm)"] is None
    assert rows["8"]["status"] == "not run"
    out = capsys.readouterr().out
    assert "5 job(s), 4 override set(s); the jobs differ in stages.track.stitch_px (from .hydra/overrides.yaml)" in out
    lines = out.splitlines()
    head = next(i for i, line in enumerate(lines) if line.startswith("stages.track.stitch_px"))
    assert lines[head].split() == ["stages.track.stitch_px", "AE", "(mm)", "STD", "(mm)", "AE.raw", "(mm)",
                                   "AE.nonRaw", "(mm)", "AE.rootrel", "(mm)", "MPJVE", "(mm/s)", "Acc.err",
                                   "(m/s²)", "peak", "speed", "err", "MB/s", "per_joint_mm.l_wrist", "jobs", "status"]
    assert lines[head + 3].split() == ["4", "42.0", "4.20", "43.0", "41.0", "47.0", "420.0", "10.5", "0.42", "2.00",
                                       "84.0", "2", "ok"]
    assert lines[head + 4].split() == ["6", *["n/a"] * 10, "1", "incomplete"]
    table = list(csv.DictReader(open(sweep / "report.csv")))
    assert [r["stages.track.stitch_px"] for r in table] == ["2", "4", "6", "8"] and table[2]["AE (mm)"] == ""
    assert (sweep / "report.png").stat().st_size > 1000


def test_without_hydra_records_the_configs_are_compared(tmp_path, capsys):
    cfg = lambda seed, motion: {"name": "a", "source": {"seed": seed, "motion": motion}, "cache_dir": "c"}  # noqa: E731
    fake_job(tmp_path / "runs" / "a", None, cfg(0, "kick"), 30.0)
    fake_job(tmp_path / "runs" / "b", None, cfg(1, "kick"), 31.0)
    fake_job(tmp_path / "runs" / "c", None, cfg(0, "wave"), 20.0)
    res = report(tmp_path / "runs", out=tmp_path / "rep", plot=False)
    assert res["source"] == "config" and res["keys"] == ["source.seed", "source.motion"]
    assert [(r["source.seed"], r["source.motion"], r["AE (mm)"]) for r in res["rows"]] == [
        ("0", "kick", 30.0), ("1", "kick", 31.0), ("0", "wave", 20.0)]
    assert (tmp_path / "rep" / "report.csv").is_file() and not (tmp_path / "rep" / "report.png").exists()
    with pytest.raises(ReportError, match="no job folders"):
        report(tmp_path / "rep")
    with pytest.raises(ReportError, match=r"--metrics solve\.stats: no job has these metrics \(have: evaluate"):
        report(tmp_path / "runs", metrics="solve.stats")


def test_a_real_tiny_sweep(tmp_path):
    """`eventcap run -m` over two values of a stage parameter and two seeds, then `eventcap report` on the folder."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]),
               EVENTCAP_STAGES="output_stages:SPECS")
    run = subprocess.run([sys.executable, "-m", "eventcap.apps.cli", "run", "-m", f"hydra.searchpath=[file://{TESTS / 'conf'}]",
                          "pipeline=known_poses", "stages/solve=known_poses", "template=procedural", "template.target_faces=2000",
                          "source.duration_s=0.09", "source.supersample=1", "source.motion=jumping_jack",
                          "outputs.video=false", "stages.solve.motion=jumping_jack,karate_kick", "source.seed=0,1",
                          "hydra.sweep.dir=runs/sweep"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "sweep folder runs/sweep/: 4 job folder(s); one table of them: eventcap report runs/sweep" in run.stderr
    rep = subprocess.run([sys.executable, "-m", "eventcap.apps.cli", "report", "runs/sweep"], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=120)
    assert rep.returncode == 0, rep.stderr[-3000:]
    assert "4 job(s), 4 override set(s); the jobs differ in stages.solve.motion, source.seed" in rep.stdout
    rows = list(csv.DictReader(open(tmp_path / "runs" / "sweep" / "report.csv")))
    assert [(r["stages.solve.motion"], r["source.seed"], r["status"]) for r in rows] == [
        ("jumping_jack", "0", "ok"), ("jumping_jack", "1", "ok"), ("karate_kick", "0", "ok"), ("karate_kick", "1", "ok")]
    ae = {(r["stages.solve.motion"], r["source.seed"]): float(r["AE (mm)"]) for r in rows}
    assert ae[("jumping_jack", "0")] < ae[("karate_kick", "0")]  # the motion performed fits better
    assert (tmp_path / "runs" / "sweep" / "report.png").is_file()
    bad = subprocess.run([sys.executable, "-m", "eventcap.apps.cli", "report", "nowhere"], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "eventcap report: nowhere: not a folder" in bad.stderr
