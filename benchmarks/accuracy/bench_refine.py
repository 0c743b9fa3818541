"""Event-based pose refinement (paper Sec. 3.3): time per 40-frame batch and error before/after on synthetic batches.

    python benchmarks/accuracy/bench_refine.py [--motions jumping_jack,karate_kick,boxing_combo] [--offset 0.2]
                                      [--batches 2] [--faces 12000] [--configs default,stab0.5,huber,nodenoise]

Every motion is simulated by the synthetic source (default template and sensor: 12k faces, supersample 3,
DAVIS240C at 3 m, sensor noise 0.2 Hz/pixel), from 0 to ``--offset`` + the batches; the batches after ``--offset``
are refined (the first ~0.1 s of most motions is a slow wind-up). The refinement is the stage itself
(``eventcap_refine.spec:SILHOUETTE``, run function and config as in a pipeline), started per batch from two kinds
of estimates with exact ground truth to compare against:

- ``linear``: the ground-truth poses at the batch's two intensity frames, interpolated linearly in time (the
  paper's *_linear with exact detections): a good start, its error is the motion's non-linearity in the batch.
- ``perturbed``: ground truth plus a known error: one offset per batch drawn from N(0, 0.05 rad) on the 30 angles
  and N(0, 1 cm) on the root translation, plus N(0, 0.01 rad) per frame.

Configurations (``--configs``): ``default`` (the stage's defaults: the paper's λ_sil 1, λ_stab 5, λ_dist 4, l2, plus
the 5 ms event support filter), ``paper`` (denoise_us 0: every event searched, as in the paper), ``stab0.5``
(λ_stab 0.5), ``huber`` (sil_loss huber, 1 px).

Printed per motion, start and configuration (mean over batches): the stage's refinement time per batch (its
``refine_s``: event index, boundary rendering, search, IPOPT; the NLP build and numba's first-call compilation are
excluded and printed once), IPOPT iterations, events per batch, the matched fraction of boundary pixels, the AE
(mean per-joint error after per-frame Procrustes alignment, mm), the unaligned error (mm) and the silhouette IoU
against the ground-truth silhouettes, before -> after. At the end: the time per batch over all runs and the phases
of the default configuration.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "plugins"))

import numpy as np  # noqa: E402

from eventcap.artifacts import BatchPlan  # noqa: E402
from eventcap.artifacts.pose import PoseSequence  # noqa: E402
from eventcap.body.kinematics import joint_positions  # noqa: E402
from eventcap.body.procedural import procedural_template  # noqa: E402
from eventcap.body.skeleton import pose_bounds  # noqa: E402
from eventcap.core.config import build_config  # noqa: E402
from eventcap.analysis.metrics import mean_joint_error  # noqa: E402
from eventcap.core.registry import load_registry  # noqa: E402
from eventcap.core.stage import StageContext  # noqa: E402
from eventcap.energy.boundary import silhouette_iou, silhouettes  # noqa: E402
from eventcap_refine.spec import SILHOUETTE  # noqa: E402

N = 40  # tracking frames per batch - 1 (25 fps, 1 ms)
CONFIGS = {"default": {}, "paper": {"terms": {"sil": {"denoise_us": 0}}}, "stab0.5": {"terms": {"stab": {"weight": 0.5}}},
           "huber": {"terms": {"sil": {"loss": "huber", "huber_px": 1.0}}}}


def capture(template, motion: str, duration_s: float, seed: int):
    spec = load_registry().get("synthetic")
    cfg = build_config(spec, {"motion": motion, "duration_s": duration_s, "seed": seed, "n_track_points": 10},
                       "source")
    return spec.load_run()({"template": template}, cfg, StageContext(node="source", stage="synthetic"))["recording"]


def starts(rec, b, rng) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    t_us = b.t0_us + 1000 * np.arange(N + 1, dtype=np.int64)
    gt = rec.ground_truth
    S = gt.poses[np.searchsorted(gt.t_us, t_us)]
    a = ((t_us - t_us[0]) / (t_us[-1] - t_us[0]))[:, None]
    linear = (1 - a) * S[0] + a * S[-1]
    pert = S.copy()
    pert[:, :30] += rng.normal(0, 0.05, 30) + rng.normal(0, 0.01, (N + 1, 30))
    pert[:, 30:] += rng.normal(0, 0.01, 3)
    lo, hi = pose_bounds()
    return t_us, S, {"linear": np.clip(linear, lo, hi), "perturbed": np.clip(pert, lo, hi)}


def errors(rec, poses, truth, masks_true) -> tuple[float, float, float]:
    rest = rec.template.rest_joints
    J, Jt = joint_positions(poses, rest), joint_positions(truth, rest)
    iou = silhouette_iou(silhouettes(rec.template, rec.camera, poses), masks_true)
    return (1000 * mean_joint_error(J, Jt).mean(), 1000 * mean_joint_error(J, Jt, align=False).mean(), iou.mean())


def refine(rec, plan, b, t_us, poses, overrides: dict) -> tuple[np.ndarray, dict]:
    est = PoseSequence(t_us=t_us, poses=poses, status="Solve_Succeeded")
    ctx = StageContext(node="refine", stage="silhouette", batch=b)
    cfg = build_config(SILHOUETTE, overrides, "stages.refine")
    out = SILHOUETTE.load_run()({"recording": rec, "poses": est, "batches": plan}, cfg, ctx)
    return out["poses"].poses, ctx.stats


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--motions", default="jumping_jack,karate_kick,boxing_combo")
    ap.add_argument("--offset", type=float, default=0.2, help="seconds of each motion before the refined batches")
    ap.add_argument("--batches", type=int, default=2, help="batches refined per motion")
    ap.add_argument("--faces", type=int, default=12000, help="template triangles")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--configs", default="default,paper,stab0.5,huber")
    args = ap.parse_args()
    configs = args.configs.split(",")
    template = procedural_template(target_faces=args.faces)
    rng = np.random.default_rng(args.seed)
    print(f"template: {template.faces.shape[0]} faces; batches of {N + 1} tracking frames; configs: "
          + "; ".join(f"{c} {CONFIGS[c] or '(stage defaults)'}" for c in configs))
    print(f"{'motion':<13} {'start':<9} {'config':<8} {'s/batch':>7} {'iters':>5} {'events':>6} {'matched':>7}  "
          f"{'AE mm':>13}  {'unaligned mm':>13}  {'IoU':>12}")
    times, phases, warmed = [], [], False
    for motion in args.motions.split(","):
        t0 = time.perf_counter()
        rec = capture(template, motion, args.offset + 0.04 * (args.batches + 1) + 0.002, args.seed)
        sim_s = time.perf_counter() - t0
        plan = BatchPlan.between_frames(rec.frames.t_us)
        batches = [b for b in plan.batches() if b.t0_us >= args.offset * 1e6 - 1][: args.batches]
        data = []
        for b in batches:
            t_us, S, st = starts(rec, b, rng)
            data.append((b, t_us, S, st, silhouettes(template, rec.camera, S)))
        if not warmed:
            t0 = time.perf_counter()
            _, stats = refine(rec, plan, data[0][0], data[0][1], data[0][3]["linear"], {"icp_iterations": 1})
            print(f"(simulation {sim_s:.1f} s; NLP build {stats.get('build_s', 0):.2f} s, first call incl. build and "
                  f"compilation {time.perf_counter() - t0:.2f} s)")
            warmed = True
        for start in ("linear", "perturbed"):
            for name in configs:
                rows = []
                for b, t_us, S, st, masks in data:
                    poses, stats = refine(rec, plan, b, t_us, st[start], CONFIGS[name])
                    times.append(stats["refine_s"])
                    if name == "default":
                        phases.append(stats["phases_s"])
                    rows.append((stats["refine_s"], stats["iterations"], stats["events"] - stats["events_dropped"],
                                 stats["matched_fraction"][-1], *errors(rec, st[start], S, masks),
                                 *errors(rec, poses, S, masks)))
                m = np.array(rows).mean(axis=0)
                print(f"{motion:<13} {start:<9} {name:<8} {m[0]:>7.2f} {m[1]:>5.0f} {m[2]:>6.0f} {100 * m[3]:>6.0f}%  "
                      f"{m[4]:>5.1f} -> {m[7]:>4.1f}  {m[5]:>5.1f} -> {m[8]:>4.1f}  {m[6]:.3f}->{m[9]:.3f}")
    print(f"refinement time per 41-frame batch, all runs: median {np.median(times):.2f} s, "
          f"mean {np.mean(times):.2f} s, max {np.max(times):.2f} s (target <= 1 s on the 2-core machine)")
    if phases:
        print("default config, median phases per batch: "
              + ", ".join(f"{k} {np.median([p[k] for p in phases]):.3f} s" for k in phases[0]))


if __name__ == "__main__":
    main()
