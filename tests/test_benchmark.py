"""``eventcap benchmark`` (eventcap/apps/benchmark.py): aggregation into Table 1 by hand on a fake results set, the method
list from config, a tiny end-to-end benchmark run twice (the second from the cache), and the quick preset (slow)."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from eventcap.apps.benchmark import (
    Benchmark,
    aggregate,
    compose_benchmark,
    format_tables,
    parse_methods,
    per_capture,
    split_overrides,
    write_results,
)

TESTS = Path(__file__).resolve().parent
CONF = TESTS.parent / "conf"


def fake_run(method, motion, seed, err, raw_every=4, data=2.0, solve_s=1.0, mpjve=None, peaks=None, true=None,
             signed=None):
    """A run record with per-frame errors ``err`` (mm) on every-n-th frames; every ``raw_every``-th is also raw;
    optionally its MPJVE (mm/s), peak-speed errors per (batch, end effector), and their true peaks (m/s) and signed
    errors."""
    err = np.asarray(err, dtype=float)
    n = err.size
    raw = np.arange(n) % raw_every == 0
    return {"motion": motion, "seed": seed, "method": method, "ok": True, "computed": 0, "cached": 10,
            "AE_mm": float(err.mean()), "data_MBps": data, "MPJVE_mm_s": mpjve, "peak_speed_errors": peaks,
            "AE_rootrel_mm": None if mpjve is None else 2 * float(err.mean()),
            "depth_mm": None if mpjve is None else 1.5 * float(err.mean()),
            "image_plane_mm": None if mpjve is None else 0.5 * float(err.mean()),
            "frames": {"t_us": (10_000 * np.arange(n)).tolist(), "err_mm": err.tolist(),
                       "sampled": [True] * n, "raw": raw.tolist()},
            "s_per_batch": {"track": 0.5, "solve": solve_s}, "stats": {"solve": {"solve_s": solve_s, "iterations": 20}},
            "peak_speed_true_mps": true, "peak_speed_signed": signed}


def test_aggregation_of_a_fake_results_set_by_hand(tmp_path):
    runs = [fake_run("A", "kick", 0, [10, 20, 30, 40], mpjve=300.0, peaks=[[0.1, None], [0.5, 0.2]],
                     true=[[4.0, None], [1.0, 6.5]], signed=[[-0.2, None], [0.1, -0.5]]),
            fake_run("A", "kick", 1, [20, 20, 20, 20], data=4.0, mpjve=500.0, peaks=[[0.3, 0.9]],
                     true=[[3.5, 2.0]], signed=[[0.3, -0.9]]),
            fake_run("A", "wave", 0, [50, 50, 50, 50], solve_s=3.0, mpjve=1000.0, peaks=[[2.0, None]]),
            fake_run("B", "kick", 0, [100, 100, 100, 100], data=1.0),
            {"motion": "wave", "seed": 0, "method": "B", "ok": False, "error": "solve batch 0", "frames": None}]
    table = aggregate(runs, ["A", "B"], ["kick", "wave"])
    a, b = table
    pooled = np.array([10, 20, 30, 40, 20, 20, 20, 20, 50, 50, 50, 50], float)
    assert a["AE_mm"] == pytest.approx(pooled.mean()) and a["AE_STD_mm"] == pytest.approx(pooled.std())
    assert a["AE_raw_mm"] == pytest.approx(np.mean([10, 20, 50]))  # frame 0 of each run is raw
    non_raw = np.array([20, 30, 40, 20, 20, 20, 50, 50, 50], float)
    assert a["AE_nonRaw_mm"] == pytest.approx(non_raw.mean()) and a["AE_nonRaw_STD_mm"] == pytest.approx(non_raw.std())
    assert a["per_motion"]["kick"]["AE_mm"] == pytest.approx(22.5) and a["per_motion"]["wave"]["STD_mm"] == 0
    assert a["data_MBps"] == pytest.approx((2 + 4 + 2) / 3)
    assert a["s_per_batch"] == {"track": 0.5, "solve": pytest.approx(5 / 3)} and a["stats"]["solve.solve_s"] == 1.0
    # motion detail: MPJVE the mean of the runs, the peak-speed error the median of all pooled pairs
    assert a["MPJVE_mm_s"] == pytest.approx(600.0) and a["per_motion"]["kick"]["MPJVE_mm_s"] == pytest.approx(400.0)
    assert a["peak_speed_err"] == pytest.approx(0.4)  # median of 0.1, 0.5, 0.2, 0.3, 0.9, 2.0
    assert a["per_motion"]["kick"]["peak_speed_err"] == pytest.approx(0.3)  # of 0.1, 0.5, 0.2, 0.3, 0.9
    assert a["per_motion"]["wave"]["AE_rootrel_mm"] == pytest.approx(100.0)
    # the fast peaks: the pooled pairs whose true peak reaches 3 m/s (4.0, 6.5, 3.5: |-0.2|, |-0.5|, |0.3|)
    assert a["peak_speed_err_fast"] == pytest.approx(0.3) and a["n_fast_pairs"] == 3
    by_bin = a["peak_speed_signed_by_bin"]
    assert by_bin["0.5-1.5"] == {"median": pytest.approx(0.1), "n": 1}
    assert by_bin["1.5-3"] == {"median": pytest.approx(-0.9), "n": 1}
    assert by_bin["3-6"] == {"median": pytest.approx(0.05), "n": 2} and by_bin["6+"]["median"] == pytest.approx(-0.5)
    assert b["peak_speed_err_fast"] is None and b["n_fast_pairs"] == 0
    assert b["MPJVE_mm_s"] is None and b["peak_speed_err"] is None
    assert (b["runs"], b["evaluated"], b["incomplete"]) == (2, 1, 1)
    assert b["per_motion"]["wave"]["AE_mm"] is None and b["AE_mm"] == 100
    text = format_tables(table, ["kick", "wave"], "fake")
    lines = text.splitlines()
    assert lines[0] == "Table 1 (fake)"
    assert lines[1].split() == ["method", "AE.all", "(mm)", "AE.raw", "(mm)", "AE.nonRaw", "(mm)", "AE.rootrel",
                                "(mm)", "depth", "(mm)", "image", "plane", "(mm)", "MPJVE", "(mm/s)", "Acc.err", "(m/s²)", "peak", "speed", "err", "(runs)",
                                "fast", "peak", "(pairs)", "Size.sec", "(MB/s)", "runs"]
    # (runs): the median of the runs' own peak_speed_err (fake runs carry none: n/a)
    # depth and image plane: the means of the runs' (1.5 and 0.5 x their AE here)
    assert lines[3].split() == ["A", "31.7", "±", "14.6", "26.7", "±", "17.0", "33.3", "±", "13.3", "63.3", "47.5",
                                "15.8", "600",
                                "n/a", "40%", "n/a", "30%", "(3)", "2.67", "3/3"]
    assert lines[4].split() == ["B", "100.0", "±", "0.0", "100.0", "±", "0.0", "100.0", "±", "0.0", "n/a", "n/a",
                                "n/a", "n/a", "n/a", "n/a", "n/a", "n/a", "(0)", "1.00", "1/2"]
    detail = text.split("Per motion: AE of root-relative joints")[1].splitlines()
    assert detail[3].split() == ["A", "45.0", "/", "400", "/", "30%", "100.0", "/", "1000", "/", "200%"]
    per_motion = text.split("AE per motion")[1].splitlines()
    assert per_motion[1].split() == ["method", "kick", "wave"]
    assert per_motion[3].split() == ["A", "22.5", "±", "8.3", "50.0", "±", "0.0"]  # sqrt(550 / 8)
    assert per_motion[4].split() == ["B", "100.0", "±", "0.0", "n/a"]  # B has no evaluated wave run
    results = {"config": {}, "methods": ["A", "B"], "motions": ["kick", "wave"], "runs": runs, "table": table}
    files = write_results(tmp_path, results)
    rows = list(csv.DictReader(open(files["table"])))
    assert [r["method"] for r in rows] == ["A", "B"]
    assert float(rows[0]["AE_mm"]) == pytest.approx(380 / 12) and rows[1]["AE_wave_mm"] == ""
    assert float(rows[0]["s_per_batch.solve"]) == pytest.approx(5 / 3)
    assert float(rows[0]["MPJVE_mm_s"]) == 600 and float(rows[0]["peak_speed_err.kick"]) == pytest.approx(0.3)
    assert len(list(csv.DictReader(open(files["runs"])))) == 5
    assert json.loads(files["json"].read_text())["table"][0]["method"] == "A"
    assert files["plot"].stat().st_size > 1000


def test_the_first_method_against_the_others_capture_by_capture():
    """per_capture counts, per measure, the captures where the first method is lower, names those where it is not
    (ties included), leaves out captures one of the two did not measure, and the report prints both; the peak-speed
    error of the runs is also summarised as the median of their own medians."""
    def run(method, motion, seed, ae, rr, mpjve, peak, fast=None):
        frames = {"t_us": [0], "err_mm": [ae], "sampled": [True], "raw": [True]}
        return {"motion": motion, "seed": seed, "method": method, "ok": True, "frames": frames, "AE_mm": ae,
                "AE_rootrel_mm": rr, "depth_mm": 0.8 * rr, "MPJVE_mm_s": mpjve, "peak_speed_err": peak,
                "peak_speed_err_fast": fast}

    runs = [run("default", "kick", 0, 20.0, 30.0, 180.0, 0.10, 0.05),
            run("smooth", "kick", 0, 25.0, 35.0, 300.0, 0.40, 0.2),
            run("default", "kick", 1, 22.0, 31.0, 320.0, 0.15, 0.3), run("smooth", "kick", 1, 21.0, 36.0, 310.0, 0.15, 0.1),
            run("default", "wave", 0, 19.0, 28.0, 100.0, None), run("smooth", "wave", 0, 30.0, 40.0, 190.0, 0.80),
            {"motion": "wave", "seed": 1, "method": "smooth", "ok": False, "frames": None}]
    cmp_ = per_capture(runs, ["default", "smooth"])
    got = cmp_["against"]["smooth"]
    assert cmp_["reference"] == "default"
    assert [(got[k]["lower"], got[k]["of"]) for k in ("AE_mm", "AE_rootrel_mm", "depth_mm", "MPJVE_mm_s",
                                                      "peak_speed_err", "peak_speed_err_fast")] == [
        (2, 3), (3, 3), (3, 3), (2, 3), (1, 2), (1, 2)]
    assert got["AE_mm"]["not_lower"] == [{"motion": "kick", "seed": 1, "default": 22.0, "smooth": 21.0}]
    assert got["peak_speed_err"]["not_lower"] == [{"motion": "kick", "seed": 1, "default": 0.15, "smooth": 0.15}]
    text = format_tables(aggregate(runs, ["default", "smooth"], ["kick", "wave"]), ["kick", "wave"], "", cmp_)
    part = text.split("Per capture: where default is lower than each method")[1].splitlines()
    assert part[1].split() == ["method", "AE", "AE.rootrel", "depth", "MPJVE", "peak", "fast", "peak"]
    assert part[3].split() == ["smooth", "2/3", "3/3", "3/3", "2/3", "1/2", "1/2"]
    assert part[4:] == ["  default not lower than smooth: kick seed 1 AE 22.0 against 21.0",
                        "  default not lower than smooth: kick seed 1 MPJVE 320 against 310",
                        "  default not lower than smooth: kick seed 1 peak 15% against 15%",
                        "  default not lower than smooth: kick seed 1 fast peak 30% against 10%"]
    table = aggregate(runs, ["default", "smooth"], ["kick", "wave"])
    assert table[0]["peak_speed_err_runs"] == pytest.approx(0.125) and table[1]["peak_speed_err_runs"] == 0.4
    assert per_capture(runs, ["default"]) == {"reference": "default", "against": {}}


def test_method_list_comes_from_config_and_rows_needing_a_missing_node_are_left_out():
    cfg = compose_benchmark(CONF, "default", [])
    assert len(cfg["motions"]) >= 6 and len(cfg["seeds"]) >= 2
    names = [m.name for m in parse_methods(cfg["methods"])]
    assert names == ["default", "paper", "linear", "frames_smooth", "all", "w/o_batch", "w/o_refine", "fused"]
    # every row of the paper's pipeline names its pipeline, so none depends on the default's nodes: w/o_refine runs
    # although the default pipeline (the spline solve) has no refine node
    assert [m.name for m in Benchmark(cfg, CONF, []).active_methods()[0]] == names
    # a row that requires a node its own pipeline (common overrides, then its own) lacks is left out, with the reason
    plain = [f"hydra.searchpath=[file://{TESTS / 'conf'}]", "pipeline=known_poses"]
    rows = {**cfg, "methods": [{"name": "plain", "requires": ["refine"]},
                               {"name": "with_refine", "requires": ["refine"],
                                "overrides": ["+pipeline.nodes.refine.inputs={poses: solve.poses}"]}]}
    active, left_out = Benchmark(rows, CONF, plain).active_methods()
    assert [m.name for m in active] == ["with_refine"]
    assert left_out == {"plain": "the pipeline has no node 'refine'"}
    quick = compose_benchmark(CONF, "quick", [])
    assert (len(quick["motions"]), quick["seeds"], quick["duration_s"], quick["name"]) == (2, [0], 0.2, "quick")


def test_a_row_that_runs_what_an_earlier_row_runs_is_left_out_naming_it():
    """`pipeline=spline` is the default pipeline: such a row would print the default's figures twice (and ten lines of
    "default not lower than spline: 37.3 against 37.3"). A row that differs in one setting stays."""
    cfg = compose_benchmark(CONF, "quick", [])
    cfg["methods"] = [{"name": "default"}, {"name": "spline", "overrides": ["pipeline=spline"]},
                      {"name": "every5", "overrides": ["pipeline=spline", "stages.evaluate.every=5"]},
                      {"name": "paper", "overrides": ["pipeline=paper", "stages/solve=batch"]}]
    active, left_out = Benchmark(cfg, CONF, []).active_methods()
    assert [m.name for m in active] == ["default", "every5", "paper"]
    assert left_out == {"spline": "the same runs as 'default': its overrides compose the same config"}
    # an override of every run can make two rows one: then the later one goes
    active, left_out = Benchmark(cfg, CONF, ["pipeline=paper", "stages/solve=batch"]).active_methods()
    assert [m.name for m in active] == ["default", "spline", "every5"]
    assert left_out == {"paper": "the same runs as 'default': its overrides compose the same config"}
    # the shipped presets have no twin rows
    for preset in ("default", "quick"):
        bench = Benchmark(compose_benchmark(CONF, preset, []), CONF, [])
        assert bench.active_methods()[1] == {}, preset


def test_bad_benchmark_configs_are_refused():
    with pytest.raises(ValueError, match=r"methods\[0\] \(x\): unknown key 'overide'"):
        parse_methods([{"name": "x", "overide": []}])
    with pytest.raises(ValueError, match=r"methods\[0\] \(x\)\.data: expected one of total_MBps"):
        parse_methods([{"name": "x", "data": "MBps"}])
    with pytest.raises(ValueError, match=r"methods\[1\]: name 'wo_batch' repeats"):
        parse_methods([{"name": "w/o_batch"}, {"name": "wo_batch"}])  # the same folder name
    with pytest.raises(ValueError, match=r"benchmark=nope: no conf/benchmark/nope.yaml \(presets: default, ladder, "
                                         r"ladder25, ladder25_check, ladder_check, open, open_check, quick, real\)"):
        compose_benchmark(CONF, "nope", [])
    from eventcap.apps.benchmark import main

    with pytest.raises(ValueError, match=r"(?s)Could not override 'motion'.*not benchmark keys are overrides of every "
                                         r"run; the benchmark keys: cache_dir, detector, detectors, duration_s"):
        main(["benchmark=quick", "motion=[a]"], CONF)  # a typo of motions: refused before anything runs


def test_the_ladder_rows_bring_their_own_detector_and_the_frame_rate():
    """The oracle ladder's rows name their detector (a rung): a row's run drops the benchmark's detector overrides
    for its own, filled with the capture's values; the suite's sequence_values fill the frame rate; a row naming a
    detector the benchmark does not define is refused before anything runs."""
    bench = Benchmark(compose_benchmark(CONF, "ladder", ["motions=[karate_kick]", "seeds=[1]"]), CONF, [])
    cap = bench.captures[0]
    assert "source.fps=10" in cap.overrides and "source.exposure_us=30000" in cap.overrides
    assert cap.detector == ("stages/detect=simulated", "stages.detect.seed=1")
    rows = {m.name: bench.row_overrides(cap, m) for m in bench.methods}
    a = rows["a default"]
    assert "stages.detect.sigma_px=0" in a and "stages.detect.seed=1" not in a and a.count("stages/detect=simulated") == 1
    assert "stages.detect.seed=1" in rows["d default"]
    assert "stages/detect=blazepose" in rows["e linear"] and "stages/detect=simulated" not in rows["e linear"]
    assert rows["e linear"][-1] == "stages.detect.at=frames" and "stages.body.estimate=false" in rows["e linear"]
    # rows differing only by their detector are not twins
    active, left_out = Benchmark(compose_benchmark(CONF, "ladder", ['only=["a default","d default","e default"]']),
                                 CONF, []).active_methods()
    assert [m.name for m in active] == ["a default", "d default", "e default"] and left_out == {}
    check = Benchmark(compose_benchmark(CONF, "ladder25_check", []), CONF, [])
    assert check.seeds == [2, 3] and "source.fps=25" in check.captures[0].overrides
    with pytest.raises(ValueError, match=r"methods \(x\)\.detector: expected one of \['blazepose', 'oracle', "):
        Benchmark(compose_benchmark(CONF, "ladder", ["methods=[{name: x, detector: perfect}]"]), CONF, [])


def test_split_overrides():
    preset, bench, runs = split_overrides(["benchmark=quick", "motions=[a]", "seeds=[0,1]", "stages.track.stitch_px=2",
                                           "stages/solve=batch", "cache_dir=/c", "+outputs.x=1"],
                                          {"motions", "seeds", "cache_dir", "name"})
    assert preset == "quick" and bench == ["motions=[a]", "seeds=[0,1]", "cache_dir=/c"]
    assert runs == ["stages.track.stitch_px=2", "stages/solve=batch", "+outputs.x=1"]


def test_tiny_benchmark_end_to_end_twice_second_time_from_the_cache(tmp_path, known_poses, capsys):
    """Two methods on one 0.09 s synthetic sequence whose 'solve' returns known poses: the right one (the motion
    performed) and a wrong one; a second call recomputes nothing and writes the same table."""
    cfg = compose_benchmark(CONF, "quick", [f"out={tmp_path / 'out'}", f"cache_dir={tmp_path / 'cache'}",
                                            "motions=[jumping_jack]", "duration_s=0.09", "plot=false",
                                            "detector=simulated"])
    cfg["methods"] = [{"name": "right", "overrides": ["stages.solve.motion=jumping_jack"]},
                      {"name": "wrong/motion", "overrides": ["stages.solve.motion=karate_kick"], "data": "frames_MBps"}]
    run_ov = [f"hydra.searchpath=[file://{TESTS / 'conf'}]", "pipeline=known_poses", "stages/solve=known_poses",
              "template=procedural", "template.target_faces=2000", "source.n_track_points=20"]
    tables = []
    for call in range(2):
        bench = Benchmark(cfg, CONF, run_ov)
        results = bench.run(echo=print)
        write_results(bench.out, results, plot=False)
        tables.append((tmp_path / "out" / "table.csv").read_text())
        runs = list(csv.DictReader(open(tmp_path / "out" / "runs.csv")))
        assert [(r["method"], r["ok"]) for r in runs] == [("right", "True"), ("wrong/motion", "True")]
        if call == 1:
            assert [int(r["computed"]) for r in runs] == [0, 0] and all(int(r["cached"]) == 5 for r in runs)
    out = capsys.readouterr().out
    assert "[1/2] jumping_jack seed 0 right: 0 computed, 5 cached" in out
    assert tables[0] == tables[1]
    right, wrong = list(csv.DictReader(open(tmp_path / "out" / "table.csv")))
    assert 0 < float(right["AE_mm"]) < float(wrong["AE_mm"])
    assert float(wrong["data_MBps"]) < float(right["data_MBps"])  # frames only vs events + frames
    assert (tmp_path / "out" / "runs" / "jumping_jack-s0" / "wrongmotion" / "motion.bvh").is_file()
    # every run keeps its motion.npz; the speed series (first seed) come from it and the recording's truth
    assert (tmp_path / "out" / "runs" / "jumping_jack-s0" / "right" / "motion.npz").is_file()
    sp = {r["method"]: r["speed"] for r in results["runs"]}
    assert sp["right"]["joint"] == sp["wrong/motion"]["joint"] and len(sp["right"]["t_us"]) > 50
    assert np.allclose(sp["right"]["true_mps"], sp["wrong/motion"]["true_mps"])
    assert float(right["MPJVE_mm_s"]) < float(wrong["MPJVE_mm_s"])
    assert float(right["s_per_batch.solve"]) > 0 and float(right["s_per_batch.source"]) > 0


@pytest.mark.slow
def test_quick_preset_twice(tmp_path):
    """`eventcap benchmark benchmark=quick` (about a minute), then again: everything from the cache."""
    cmd = [sys.executable, "-m", "eventcap.apps.cli", "benchmark", "benchmark=quick", f"out={tmp_path / 'out'}",
           f"cache_dir={tmp_path / 'cache'}"]
    first = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=1200)
    assert first.returncode == 0, first.stderr[-3000:]
    second = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert second.returncode == 0, second.stderr[-3000:]
    methods = [m.name for m in Benchmark(compose_benchmark(CONF, "quick", []), CONF).active_methods()[0]]
    n = 2 * len(methods)
    assert f"{n} runs in" in second.stdout and "(0 cache entries computed" in second.stdout
    assert "w/o_refine" in methods and "left out" not in second.stdout  # the paper's ablations run whatever the default
    table = list(csv.DictReader(open(tmp_path / "out" / "table.csv")))
    assert [r["method"] for r in table] == methods and methods[:4] == ["default", "paper", "linear", "frames_smooth"]
    for r in table:
        assert r["evaluated"] == "2" and 0 < float(r["AE_mm"]) < 300 and float(r["s_per_batch.solve"]) > 0
        assert r["AE_jumping_jack_mm"] and r["AE_karate_kick_mm"]
    rate = {r["method"]: float(r["data_MBps"]) for r in table}
    assert rate["linear"] == rate["frames_smooth"] < rate["paper"] < rate["all"]
    assert "Table 1 (2 motion(s) x 1 seed(s) x 0.2 s" in second.stdout
    runs = list(csv.DictReader(open(tmp_path / "out" / "runs.csv")))
    assert len(runs) == n and all(r["computed"] == "0" for r in runs)
    assert (tmp_path / "out" / "fig7_per_frame_error.png").stat().st_size > 10_000


def test_apps_do_not_import_each_other():
    """cli -> benchmark -> cli was an import cycle: what both need (run_job, the file writers) lives in
    eventcap.apps.jobs, below cli, benchmark and report."""
    code = ("import sys, eventcap.apps.benchmark, eventcap.apps.report; "
            "print(sorted(m for m in sys.modules if m in ('eventcap.apps.cli', 'eventcap.apps.benchmark', 'eventcap.apps.report')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "['eventcap.apps.benchmark', 'eventcap.apps.report']"  # neither pulled in eventcap.apps.cli
    from eventcap.apps import cli

    from eventcap.apps import jobs
    assert cli.run_job is jobs.run_job


def test_speed_figure_from_run_records(tmp_path):
    from eventcap.apps.benchmark import plot_speeds

    t = (1000 * np.arange(200)).tolist()
    true = np.abs(np.sin(np.arange(200) / 30.0)) * 3.0
    runs = [{"motion": "kick", "seed": 0, "method": m, "MPJVE_mm_s": 100.0 * k,
             "speed": {"joint": "r_foot", "t_us": t, "true_mps": true.tolist(),
                       "pred_mps": (true + 0.3 * k * np.cos(np.arange(200))).tolist()}}
            for k, m in enumerate(["A", "B"])]
    runs.append({"motion": "wave", "seed": 0, "method": "A", "speed": None})  # no series: no panel
    path = plot_speeds(tmp_path / "speed.png", runs, ["A", "B"], ["kick", "wave"])
    assert path is not None and path.stat().st_size > 10_000
    assert plot_speeds(tmp_path / "none.png", runs[2:], ["A"], ["wave"]) is None and not (tmp_path / "none.png").exists()


def test_detector_choice_adds_its_overrides_to_every_sequence():
    cfg = compose_benchmark(CONF, "default", [])
    assert cfg["detector"] == "blazepose"  # a real CNN by default, as the paper's Table 1
    bench = Benchmark(cfg, CONF, [])
    assert bench.sequence_overrides("karate_kick", 1)[-1] == "stages/detect=blazepose"
    sim = Benchmark(compose_benchmark(CONF, "default", ["detector=simulated"]), CONF, [])
    assert sim.sequence_overrides("karate_kick", 1)[-2:] == ["stages/detect=simulated", "stages.detect.seed=1"]
    linear = next(m for m in parse_methods(cfg["methods"]) if m.name == "linear")
    assert "stages.detect.at=frames" in linear.overrides  # *_linear looks at the raw frames
    with pytest.raises(ValueError, match=r"detector: expected one of \['blazepose', 'simulated'\].*got 'openpose'"):
        Benchmark(compose_benchmark(CONF, "default", ["detector=openpose"]), CONF, []).sequence_overrides("a", 0)


def test_only_picks_rows_by_name_and_refuses_unknown_names():
    bench = Benchmark(compose_benchmark(CONF, "default", ["only=[fused,linear]"]), CONF, [])
    assert [m.name for m in bench.methods] == ["linear", "fused"]  # the config's order, not the option's
    assert [m.name for m in Benchmark(compose_benchmark(CONF, "default", ["only=paper"]), CONF, []).methods] == ["paper"]
    with pytest.raises(ValueError, match=r"only: expected names of methods \(default, paper, linear.*got \['splin'\]"):
        Benchmark(compose_benchmark(CONF, "default", ["only=[splin]"]), CONF, [])


def test_the_reliability_figures_and_plot_of_each_rows_uncertainty(tmp_path):
    """Each row's uncertainty against its error over its runs' (frame, joint) pairs: an uncertainty equal to the
    error ranks it perfectly (Spearman 1, sparsification area 0) and covers every error within 1 u; a constant one
    ranks nothing (area = random's); per group when the runs have several; the plot is written."""
    from eventcap.apps.benchmark import format_reliability, plot_reliability, reliability_figures

    rng = np.random.default_rng(0)
    records = []
    for k in range(4):
        e = rng.uniform(5.0, 100.0, size=(10, 24))
        for name, u in (("good", e), ("flat", np.full_like(e, 50.0))):
            records.append({"method": name, "group": "whole" if k < 2 else "partial",
                            "reliability": {"u_mm": u.tolist(), "err_mm": e.tolist()}})
    records.append({"method": "good", "group": "whole", "reliability": None})  # a run without an uncertainty
    figs = reliability_figures(records, ["good", "flat", "none"])
    assert set(figs) == {"good", "flat"} and set(figs["good"]) == {"all", "whole", "partial"}
    g = figs["good"]["all"]
    assert g["runs"] == 4 and g["pairs"] == 960 and g["spearman"] == pytest.approx(1.0)
    assert g["ause_ratio"] == pytest.approx(0.0, abs=1e-9) and g["cover1"] == 1.0
    assert g["u_median_mm"] == pytest.approx(g["error_median_mm"])
    assert figs["flat"]["all"]["ause_ratio"] == pytest.approx(1.0, abs=0.05)
    text = format_reliability(figs)
    assert "good" in text.splitlines()[2] and "1.00" in text.splitlines()[2]
    path = plot_reliability(tmp_path / "fig_reliability.png", records, ["good", "flat"])
    assert path is not None and path.stat().st_size > 10_000
