"""What a warm start from the neighbouring window would give the spline solve: an in-process experiment.

    python benchmarks/speed/bench_warm_start.py [--motions karate_kick,fast_wave] [--seeds 0,1] [--duration 2]
                                          [--variants cold,warm] [--out runs/bench_warm_start]

Why an experiment and not an option of the stage: each batch's window is its own task, cached under a key made of
its inputs, and run in any order or in parallel. A window that starts from its neighbour's solution depends on
that solution, so its key would have to name it; a node cannot take its own output as an input (the pipeline
refuses the cycle), and a per-batch input is either the same batch of an upstream node or all of its batches. So
the DAG has no way to say "the previous batch of this node", and saying it would make the solve serial and every
batch's key depend on every earlier batch.

What this measures instead: the default pipeline on a synthetic capture (simulated detector, as the suite's
tuning runs), run serially in this process, with ``eventcap_spline.solve.solve_window`` wrapped:
- ``cold``: today's start (the smoothing spline through the per-frame fits); the same figures as a normal run;
- ``warm``: each window starts from the previous window's solution where their spans overlap (the control points
  shifted by the knots between the windows' starts, the root angles moved to the new window's 2π branch; E_3D's t'
  of the shared detection frames), and from the fits' spline beyond. E_still is still measured around the fits'
  spline, so only the start differs. IPOPT's barrier starts at ``mu_init`` 1e-7 (monotone) in both: the window
  solves already use IPOPT's warm-start barrier settings (eventcap.energy.ipopt.IpoptSettings).
- ``warm_mu9``: ``warm`` with mu_init 1e-9.

The solve runs under a private stage version (the cache neither serves today's windows nor keeps these under the
real version); everything upstream comes from the cache (``runs/cache``, shared with ``eventcap benchmark``).
Printed per capture and variant: IPOPT iterations per window (each ICP round and all), CPU seconds of
``solve_window`` per window (``time.process_time``; the machine may be shared), and the evaluate stage's AE, MPJVE
and peak-speed error. Results: <out>/results.json.
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
from hydra import compose, initialize_config_dir  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from eventcap.apps.cli import run_job  # noqa: E402

VARIANTS = {"cold": (False, None), "warm": (True, None), "warm_mu9": (True, 1e-9)}


def shifted_start(prev, spline, n_det: int, t_det_us: np.ndarray):
    """(control points (n_ctrl, 33), t' (D, 3)) of a window over ``spline`` from the previous window's solution
    prev = (spline, control, t_prime, t_det_us): its control points shifted by the knots between the two starts
    (NaN where the previous window has none, or when the knots do not line up), its t' at shared detection frames
    (NaN elsewhere)."""
    p_spline, p_C, p_T, p_tdet = prev
    C = np.full((spline.n_ctrl, p_C.shape[1]), np.nan)
    T = np.full((n_det, 3), np.nan)
    d_us = spline.t0_us - p_spline.t0_us
    if spline.h_us == p_spline.h_us and d_us >= 0 and d_us % spline.h_us == 0:
        k = d_us // spline.h_us
        n = max(0, min(spline.n_ctrl, p_C.shape[0] - k))
        C[:n] = p_C[k:k + n]
    idx = np.searchsorted(p_tdet, t_det_us)
    ok = (idx < p_tdet.size) & (p_tdet[np.minimum(idx, p_tdet.size - 1)] == t_det_us)
    T[ok] = p_T[idx[ok]]
    return C, T


def install(variant: str, log: list):
    """Wrap solve_window (and IPOPT's mu_init) for a variant; returns a function that undoes it."""
    import eventcap_spline.solve as sv
    from eventcap.energy.ipopt import IpoptSettings

    warm, mu = VARIANTS[variant]
    orig, options = sv.solve_window, IpoptSettings.options
    state = {"prev": None}

    def wrapped(solver, spline, inputs, *args, **kw):
        start = None
        det, t_det_us = inputs.detections, inputs.t_det_us
        prev = state["prev"]
        if warm and prev is not None and prev[0].t0_us <= spline.t0_us < prev[0].t1_us:
            C, T = shifted_start(prev, spline, det.n, np.asarray(t_det_us, dtype=np.int64))
            if np.isfinite(C).any():
                # the previous window's root angles onto this window's branch (its fits' spline decides)
                fits, _, _, _ = sv.fit_window(solver, det)
                seen = np.isfinite(fits).all(axis=1)
                ref = spline.evaluate(np.nan_to_num(C), np.asarray(t_det_us)[seen])[:, 27:30]
                turn = 2 * np.pi * np.round(np.median(fits[seen, 27:30] - ref, axis=0) / (2 * np.pi))
                C[:, 27:30] += turn
            start = (C, {"joints_3d": T})  # E_3D's t' per detection frame
        c0 = time.process_time()
        res = orig(solver, spline, inputs, *args, start=start, **kw)
        log.append({"t0_us": int(spline.t0_us), "cpu_s": time.process_time() - c0, "warm": start is not None,
                    "iterations": [s.iterations for s in res.solves],
                    "association_change_px": list(res.association_change_px)})
        t_prime = res.aux.get("joints_3d", np.zeros((det.n, 3)))
        state["prev"] = (spline, res.control, t_prime, np.asarray(t_det_us, dtype=np.int64))
        return res

    def options_mu(self, warm_solve):
        opts = options(self, warm_solve)
        if warm_solve and mu is not None:
            opts["ipopt.mu_init"] = mu
        return opts

    sv.solve_window = wrapped
    IpoptSettings.options = options_mu

    def undo():
        sv.solve_window = orig
        IpoptSettings.options = options

    return undo


def private_version(variant: str) -> None:
    """Run the spline stage under a version of its own for this variant (a cache miss, kept apart)."""
    import eventcap_spline.spec as sp

    object.__setattr__(sp.SPLINE, "version", 900_000 + sorted(VARIANTS).index(variant))  # the registry copies it


def run_capture(motion: str, seed: int, duration: float, variant: str, out: Path, extra: list[str]) -> dict:
    overrides = ["source=synthetic", f"source.motion={motion}", f"source.seed={seed}", f"source.duration_s={duration}",
                 "stages/detect=simulated", f"stages.detect.seed={seed}", "outputs.video=false", "log_level=WARNING",
                 *extra]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    data = OmegaConf.to_container(cfg, resolve=True)
    run_dir = out / f"{motion}-s{seed}" / variant
    run_dir.mkdir(parents=True, exist_ok=True)
    log: list = []
    private_version(variant)
    undo = install(variant, log)
    try:
        failures: list[str] = []
        res = run_job(data, run_dir, OmegaConf.to_yaml(cfg, resolve=True), failures)
    finally:
        undo()
    if res is None or failures:
        raise RuntimeError(f"{motion} seed {seed} {variant}: run failed: {failures}")
    m = res[1].metrics["evaluate.metrics"]
    it = [sum(w["iterations"]) for w in log]
    return {"motion": motion, "seed": seed, "variant": variant, "windows": len(log),
            "iterations_per_window": float(np.mean(it)) if it else None,
            "round_iterations": [float(np.mean([w["iterations"][r] for w in log if len(w["iterations"]) > r]))
                                 for r in range(max((len(w["iterations"]) for w in log), default=0))],
            "solve_cpu_s_per_window": float(np.mean([w["cpu_s"] for w in log])) if log else None,
            "AE_mm": m["AE_mm"], "MPJVE_mm_s": m["MPJVE_mm_s"], "peak_speed_err": m["peak_speed_err"], "log": log}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--motions", default="karate_kick,fast_wave")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--duration", type=float, default=2.0)
    ap.add_argument("--variants", default="cold,warm")
    ap.add_argument("--out", default="runs/bench_warm_start")
    ap.add_argument("extra", nargs="*", help="further run overrides")
    args = ap.parse_args()
    out = Path(args.out)
    results = []
    for motion in args.motions.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            for variant in args.variants.split(","):
                r = run_capture(motion, seed, args.duration, variant, out, args.extra)
                results.append(r)
                print(f"{motion} s{seed} {variant:9s} iterations/window {r['iterations_per_window']:.1f} (rounds "
                      f"{', '.join(f'{v:.1f}' for v in r['round_iterations'])}), solve CPU {r['solve_cpu_s_per_window']:.3f}"
                      f" s/window, AE {r['AE_mm']:.2f} mm, MPJVE {r['MPJVE_mm_s']:.1f} mm/s, peak "
                      f"{100 * r['peak_speed_err']:.1f}%", flush=True)
                (out / "results.json").write_text(json.dumps(results, indent=1))
    print("\nmeans over the captures:")
    for variant in args.variants.split(","):
        rs = [r for r in results if r["variant"] == variant]
        print(f"{variant:9s} iterations/window {np.mean([r['iterations_per_window'] for r in rs]):.1f}, solve CPU "
              f"{np.mean([r['solve_cpu_s_per_window'] for r in rs]):.3f} s/window, AE "
              f"{np.mean([r['AE_mm'] for r in rs]):.2f} mm, MPJVE {np.mean([r['MPJVE_mm_s'] for r in rs]):.1f} mm/s, "
              f"peak {100 * np.median([r['peak_speed_err'] for r in rs]):.1f}% (median of the runs)")


if __name__ == "__main__":
    main()
