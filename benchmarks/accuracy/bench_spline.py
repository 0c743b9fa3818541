"""The spline solve (pipeline=spline, not in the paper) against linear, the paper's pipeline and a frames-only
smoother: positions and velocities of the 1 kHz motion.

    python benchmarks/accuracy/bench_spline.py [--motions karate_kick,boxing_combo] [--duration 1] [--rates 25,10]
                                      [--tracks eklt,oracle] [--methods spline,linear,paper] [--extra "..."]

Methods (each a normal run through the runner and its cache; the recording is exported for the ground truth):
- ``spline``: ``pipeline=spline`` (plugins/eventcap_spline);
- ``spline_noev``: the same without event correspondences (``stages.solve.icp_rounds=0``);
- ``linear``: ``stages/solve=linear pipeline=no_refine`` (the paper's *_linear);
- ``paper``: the default pipeline (the paper's Sec. 3.2-3.3 method);
- ``frames_smooth`` (computed here, from linear's run): the per-frame detection fits (linear's poses at the
  intensity frames) smoothed over time per pose parameter by ``scipy.interpolate.make_smoothing_spline`` with
  ``lam=None`` (its smoothing chosen by generalised cross-validation, from the data alone), sampled at 1 kHz.
  No events.

Rates: ``25`` = the default source (25 fps, 10 ms exposure); ``10`` = ``source.fps=10 source.exposure_us=30000``.
Tracks: ``eklt`` (the default tracker) or ``oracle`` (exact tracks, ``stages/track=oracle``); linear and
frames_smooth use no tracks and are run once per rate.

Measures, over every tracking frame (1 kHz) of the run:
- ``AE``: the evaluate stage's AE (Procrustes per frame, every 10th frame; metrics.json), mm;
- ``rel``: root-relative joint error (joints minus the pelvis, no alignment), mm;
- ``MPJVE``: root-relative joint velocities by central differences over 10 ms (t ± 5 ms), mean |v_est - v_true|
  over joints and frames, mm/s;
- ``s/40ms``: the solve node's wall time per batch (40 ms at 25 fps; 100 ms at 10 fps: scaled to 40 ms).

Results go to --out (runs/bench_spline by default): results.json and one run folder per method.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "plugins"))

import numpy as np  # noqa: E402
import zarr  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from eventcap.artifacts.recording import Recording  # noqa: E402
from eventcap.apps.benchmark import stage_times  # noqa: E402
from eventcap.body.kinematics import joint_positions  # noqa: E402
from eventcap.apps.cli import run_job  # noqa: E402
from eventcap.analysis.metrics import pose_at  # noqa: E402

METHODS = {
    "spline": ["pipeline=spline"],
    "spline_noev": ["pipeline=spline", "stages.solve.icp_rounds=0"],  # detections and prior only: no events
    "linear": ["stages/solve=linear", "pipeline=no_refine"],
    "paper": [],
}
RATES = {"25": [], "10": ["source.fps=10", "source.exposure_us=30000"]}
VEL_HALF_US = 5_000  # central differences over 10 ms


def run_method(overrides: list[str], run_dir: Path) -> dict:
    """One run; returns its motion (t_us, poses, joints), AE, the recording and the solve's time per batch."""
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    data = OmegaConf.to_container(cfg, resolve=True)
    run_dir.mkdir(parents=True, exist_ok=True)
    failures: list[str] = []
    t0 = time.perf_counter()
    out = run_job(data, run_dir, OmegaConf.to_yaml(cfg, resolve=True), failures)
    wall = time.perf_counter() - t0
    if out is None or failures:
        raise RuntimeError(f"run failed ({' '.join(overrides)}): {failures}")
    runner, result = out
    m = np.load(run_dir / "motion.npz")
    rec = Recording.from_zarr(zarr.open_group(str(run_dir / "source.recording.zarr"), mode="r"))
    times = stage_times(runner, result)
    return {"t_us": m["t_us"], "poses": m["poses"], "joints": m["joints"], "rec": rec, "wall_s": wall,
            "AE": float(result.metrics["evaluate.metrics"]["AE_mm"]), "times": times}


def frames_smooth(rec: Recording, linear: dict) -> np.ndarray:
    """The frames-only baseline: per-frame fits (linear's poses at the intensity frames) smoothed by a GCV
    smoothing spline per parameter, sampled at linear's 1 kHz times."""
    from scipy.interpolate import make_smoothing_spline

    t, P = linear["t_us"], linear["poses"]
    ft = np.asarray(rec.frames.t_us, dtype=np.int64)
    ft = ft[(ft >= t[0]) & (ft <= t[-1])]
    idx = np.searchsorted(t, ft)
    fits = P[idx].copy()
    fits[:, 27:30] = np.unwrap(fits[:, 27:30], axis=0)
    x = ft * 1e-6
    out = np.empty((t.size, P.shape[1]))
    for k in range(P.shape[1]):
        out[:, k] = make_smoothing_spline(x, fits[:, k], lam=None)(t * 1e-6)
    return out


def measures(rec: Recording, t_us: np.ndarray, joints: np.ndarray) -> dict:
    """Root-relative joint error (mm) and MPJVE (mm/s, 10 ms central differences) against the ground truth."""
    rest = rec.template.rest_joints
    true = joint_positions(pose_at(rec.ground_truth, t_us), rest)
    rel_e, rel_t = joints - joints[:, :1], true - true[:, :1]
    rel = float(np.linalg.norm(rel_e - rel_t, axis=-1).mean() * 1000)
    step = int(np.median(np.diff(t_us)))
    k = VEL_HALF_US // step
    dt = (t_us[2 * k:] - t_us[:-2 * k])[:, None, None] * 1e-6
    v_e = (rel_e[2 * k:] - rel_e[:-2 * k]) / dt
    v_t = (rel_t[2 * k:] - rel_t[:-2 * k]) / dt
    ok = np.abs(dt[:, 0, 0] - 2 * VEL_HALF_US * 1e-6) < 1e-9  # no window across a gap
    mpjve = float(np.linalg.norm(v_e - v_t, axis=-1)[ok].mean() * 1000)
    return {"rel": rel, "MPJVE": mpjve}


def plot_wrist(path: Path, rec: Recording, t_us: np.ndarray, curves: dict, joint: str = "r_wrist") -> Path:
    """One end effector's root-relative position (3 axes) and speed over time: the truth against each method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from eventcap.body.skeleton import JOINT_INDEX

    j = JOINT_INDEX[joint]
    true = joint_positions(pose_at(rec.ground_truth, t_us), rec.template.rest_joints)
    series = {"truth": true, **curves}
    fig, axes = plt.subplots(4, 1, figsize=(11, 11), sharex=True)
    k = VEL_HALF_US // int(np.median(np.diff(t_us)))
    for name, J in series.items():
        rel = (J[:, j] - J[:, 0]) * 1000
        style = dict(color="k", lw=2.2) if name == "truth" else dict(lw=1.0)
        for a in range(3):
            axes[a].plot(t_us * 1e-3, rel[:, a], label=name, **style)
        v = np.linalg.norm(rel[2 * k:] - rel[:-2 * k], axis=1) / (2 * VEL_HALF_US * 1e-6) / 1000
        axes[3].plot(t_us[k:-k] * 1e-3, v, label=name, **style)
    for a, lab in enumerate(("x (mm)", "y (mm)", "z (mm)", "speed (m/s)")):
        axes[a].set_ylabel(lab)
    for ft in rec.frames.t_us:
        if t_us[0] <= ft <= t_us[-1]:
            for ax in axes:
                ax.axvline(ft * 1e-3, color="0.85", lw=0.5, zorder=0)
    axes[0].set_title(f"{joint} relative to the pelvis: truth vs methods (grey lines: intensity frames)")
    axes[0].legend(ncol=6, fontsize=8)
    axes[3].set_xlabel("time (ms)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def timing(args) -> None:
    """CPU seconds of one window solve against the window length (half_window 0..4), on batch --timing-batch of the
    first motion at the first rate: the spline stage's own code on the runner's cached inputs. CPU time (not wall
    time) so that a shared machine does not blur the comparison; the per-frame fits are excluded (cached per
    process in the stage: each frame is fitted once per run)."""
    from eventcap.artifacts.pose import Detections
    from eventcap.artifacts.tracking import SlicedTracks
    from eventcap.energy.detections import select_detections
    from eventcap.energy.factor import Layout
    from eventcap.energy.problem import SplinePoses, coupling_band
    from eventcap.energy.spline import UniformCubicBSpline
    from eventcap.energy.terms import sample_times
    from eventcap.energy.window import Tracks, WindowInputs
    from eventcap_spline._impl import window_of
    from eventcap_spline.plan import cor_frames
    from eventcap_spline.solve import SplineSolver, fit_window, solve_window
    from eventcap_spline.spec import SplineSolveConfig

    motion, rate = args.motions.split(",")[0], args.rates.split(",")[0]
    rd = Path(args.out) / f"timing-{motion}-{rate}fps"
    ov = [f"source.motion={motion}", f"source.duration_s={args.duration}", f"source.seed={args.seed}",
          f"cache_dir={args.cache}", "export=[source.recording,slice.sliced,detect.detections]",
          "outputs.video=false", "outputs.bvh=false", "log_level=WARNING", *RATES[rate], *METHODS["linear"],
          *args.extra.split()]
    r = run_method(ov, rd)
    rec = r["rec"]
    det = Detections.from_zarr(zarr.open_group(str(rd / "detect.detections.zarr"), mode="r"))
    sliced = [SlicedTracks.from_zarr(zarr.open_group(str(f), mode="r"))
              for f in sorted((rd / "slice.sliced").glob("batch*.zarr"))]
    k = min(args.timing_batch, len(sliced) - 1)
    frames = np.array([int(x.t_us[0]) for x in sliced] + [int(sliced[-1].t_us[-1])])
    cfg = SplineSolveConfig()  # the stage's defaults: every term of the default solve
    step = cfg.tracks.step
    print(f"window solve of batch {k} ({motion}, {rate} fps, stage defaults: correspondences every {step} "
          f"tracking frames, event silence, E_sil every {cfg.terms.sil.step_ms:g} ms, inertia-weighted prior), CPU "
          "seconds (fits excluded)")
    print(f"{'half_window':>11} {'batches':>7} {'ctrl':>5} {'build s':>8} {'solve s':>8} {'iters':>6} {'corr':>6}")
    for hw in range(0, 5):
        a, z = window_of(len(sliced), k, hw)
        t_det = frames[a:z + 2]
        d = select_detections(det, t_det)
        n_seg = int(np.ceil((t_det[-1] - t_det[0]) / 10_000))
        spl = UniformCubicBSpline(int(t_det[0]), 10_000, n_seg)
        s = sliced[k]
        idx = cor_frames(s.t_us.size, step)
        t_us = np.asarray(s.t_us, dtype=np.int64)
        inputs = WindowInputs(spl.t0_us, spl.t1_us, knots_us=spl.t0_us + spl.h_us * np.arange(n_seg + 1),
                              t_det_us=t_det, detections=d,
                              tracks=Tracks(t_us[idx], np.asarray(s.xy, dtype=np.float64)[idx],
                                            np.asarray(s.valid)[idx]), track_times_us=(t_us,),
                              events=rec.events.window(int(t_det[0]), int(t_det[-1]) + 1))
        times = sample_times(cfg.terms, inputs)
        c0 = time.process_time()
        layout = Layout(n_seg=n_seg, sizes=tuple((n, t.size) for n, t in times.items()),
                        band=coupling_band(SplinePoses(n_seg, spl), t_us[idx]))
        sol = SplineSolver(rec.template, rec.camera, layout, cfg)
        c1 = time.process_time()
        fit_window(sol, d)  # fills the per-process fit cache: not timed below
        c2 = time.process_time()
        res = solve_window(sol, spl, inputs)
        c3 = time.process_time()
        its = sum(x.iterations for x in res.solves)
        print(f"{hw:>11} {z - a + 1:>7} {spl.n_ctrl:>5} {c1 - c0:8.2f} {c3 - c2:8.2f} {its:>6} "
              f"{res.energies.get('n_correspondences', 0):>6}", flush=True)


def plot_runs(spec: str, png: Path) -> None:
    """The wrist figure from finished run folders: spec 'name=run_dir,...' (a run named linear also gives
    frames_smooth)."""
    curves, rec, t = {}, None, None
    for item in spec.split(","):
        name, d = item.split("=", 1)
        m = np.load(Path(d) / "motion.npz")
        if rec is None:
            rec = Recording.from_zarr(zarr.open_group(str(Path(d) / "source.recording.zarr"), mode="r"))
            t = m["t_us"]
        if m["t_us"].shape != t.shape:
            raise SystemExit(f"{d}: {m['t_us'].size} frames, the first run has {t.size}")
        curves[name] = m["joints"]
        print(f"{name:<14} " + " ".join(f"{k} {v:.1f}" for k, v in measures(rec, m["t_us"], m["joints"]).items()))
        if name == "linear":
            fs = joint_positions(frames_smooth(rec, {"t_us": m["t_us"], "poses": m["poses"]}), rec.template.rest_joints)
            curves["frames_smooth"] = fs
            print(f"{'frames_smooth':<14} " + " ".join(f"{k} {v:.1f}" for k, v in measures(rec, t, fs).items()))
    print(f"figure: {plot_wrist(png, rec, t, curves)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--motions", default="karate_kick")
    ap.add_argument("--duration", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rates", default="25,10")
    ap.add_argument("--tracks", default="eklt,oracle")
    ap.add_argument("--methods", default="spline,linear,paper")
    ap.add_argument("--cache", default=str(ROOT / "runs" / "bench-cache"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_spline"))
    ap.add_argument("--extra", default="", help="more hydra overrides for every run, space separated")
    ap.add_argument("--spline-extra", default="", help="more hydra overrides for the spline runs only")
    ap.add_argument("--timing", action="store_true", help="only time one window solve against the window length")
    ap.add_argument("--timing-batch", type=int, default=12)
    ap.add_argument("--plot-runs", default="", help="only draw the wrist figure from run folders: name=dir,...")
    args = ap.parse_args()
    if args.plot_runs:
        plot_runs(args.plot_runs, Path(args.out) / "wrist.png")
        return
    if args.timing:
        timing(args)
        return
    out = Path(args.out)
    results = []
    rpath = out / "results.json"
    if rpath.exists():
        results = json.loads(rpath.read_text())
    print(f"{'motion':<14} {'fps':>3} {'tracks':<7} {'method':<14} {'AE':>6} {'rel':>6} {'MPJVE':>7} {'s/40ms':>7}",
          flush=True)
    for motion in args.motions.split(","):
        for rate in args.rates.split(","):
            base = [f"source.motion={motion}", f"source.duration_s={args.duration}", f"source.seed={args.seed}",
                    f"cache_dir={args.cache}", "export=[source.recording]", "outputs.video=false",
                    "outputs.bvh=false", "log_level=WARNING", *RATES[rate], *args.extra.split()]
            curves: dict = {}
            for track in args.tracks.split(","):
                for method in args.methods.split(","):
                    if method == "linear" and track != args.tracks.split(",")[0]:
                        continue  # no tracks used
                    ov = base + METHODS[method] + [f"stages/track={track}"]
                    if method == "spline":
                        ov += args.spline_extra.split()
                    tag = f"{motion}-{rate}fps-{track}-{method}"
                    r = run_method(ov, out / tag)
                    rows = [(method, r["joints"], r["AE"])]
                    if method == "linear":
                        fs = frames_smooth(r["rec"], r)
                        rows.append(("frames_smooth", joint_positions(fs, r["rec"].template.rest_joints), None))
                    solve_s = r["times"]["s_per_batch"].get("solve", float("nan"))
                    batch_us = float(np.median(np.diff(r["rec"].frames.t_us)))
                    per40 = solve_s * 40_000 / batch_us
                    if track == args.tracks.split(",")[0]:
                        for name, J, _ in rows:
                            curves[name] = J
                        t_plot, rec_plot = r["t_us"], r["rec"]
                    for name, J, ae in rows:
                        m = measures(r["rec"], r["t_us"], J)
                        rec = {"motion": motion, "fps": rate, "tracks": track, "method": name, "AE": ae, **m,
                               "solve_s_per_40ms": per40 if name == method else None,
                               "s_per_batch": r["times"]["s_per_batch"] if name == method else None}
                        results = [x for x in results if not all(x[k] == rec[k] for k in
                                                                  ("motion", "fps", "tracks", "method"))]
                        results.append(rec)
                        ae_s = f"{ae:6.1f}" if ae is not None else "     -"
                        t_s = f"{per40:7.2f}" if name == method else "      -"
                        print(f"{motion:<14} {rate:>3} {track:<7} {name:<14} {ae_s} {m['rel']:6.1f} "
                              f"{m['MPJVE']:7.0f} {t_s}", flush=True)
                    out.mkdir(parents=True, exist_ok=True)
                    rpath.write_text(json.dumps(results, indent=1, default=float))
            if curves and all(c.shape == next(iter(curves.values())).shape for c in curves.values()):
                png = plot_wrist(out / f"wrist_{motion}_{rate}fps.png", rec_plot, t_plot, curves)
                print(f"figure: {png}", flush=True)


if __name__ == "__main__":
    main()
