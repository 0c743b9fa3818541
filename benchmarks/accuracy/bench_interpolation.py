"""How much can events add between intensity frames? Linear interpolation of the *exact* poses at the frames.

    python benchmarks/accuracy/bench_interpolation.py [--duration 2] [--speeds 1,2,3] [--fps 25,12.5,8]

For every motion, the ground-truth poses at the intensity-frame times are interpolated linearly in pose space at
1 kHz (what the ``linear`` baseline does with perfect detections). The printed AE (mean per-joint error after
per-frame Procrustes, mm, over every tracking frame) is the most the in-between frames can gain from event data
in that setting. Nothing is simulated but the motion; this takes seconds.
"""

from __future__ import annotations

import argparse

import numpy as np

from eventcap.body.kinematics import joint_positions
from eventcap.body.motions import sequence_poses
from eventcap.body.procedural import DEFAULT_REST_JOINTS
from eventcap.analysis.metrics import mean_joint_error

MOTIONS = "karate_kick,boxing_combo,javelin_throw,dance_spin,fast_wave,jumping_jack"


def interpolation_error_mm(motion: str, duration_s: float, speed: float, fps: float, seed: int = 0) -> float:
    """Mean AE (mm) of linearly interpolating the exact poses sampled at ``fps`` back to 1 kHz."""
    t = np.arange(int(round(duration_s * 1000)) + 1) / 1000.0
    S = sequence_poses([(motion, duration_s)], t, seed=seed, speed=speed, amplitude=1.0)
    step = int(round(1000.0 / fps))
    keep = np.arange(0, t.size, step)
    n = keep[-1] + 1
    frames = np.arange(n)
    S_lin = np.stack([np.interp(frames, keep, S[keep, k]) for k in range(S.shape[1])], axis=1)
    err = mean_joint_error(joint_positions(S_lin, DEFAULT_REST_JOINTS), joint_positions(S[:n], DEFAULT_REST_JOINTS))
    return float(err.mean() * 1000.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--motions", default=MOTIONS)
    ap.add_argument("--duration", type=float, default=2.0)
    ap.add_argument("--speeds", default="1,2,3")
    ap.add_argument("--fps", default="25,12.5,8")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    motions = args.motions.split(",")
    print(f"{'speed':>5} {'fps':>5} " + " ".join(f"{m[:12]:>12}" for m in motions) + f" {'mean':>6}")
    for speed in (float(s) for s in args.speeds.split(",")):
        for fps in (float(f) for f in args.fps.split(",")):
            e = [interpolation_error_mm(m, args.duration, speed, fps, args.seed) for m in motions]
            print(f"{speed:5g} {fps:5g} " + " ".join(f"{x:12.1f}" for x in e) + f" {np.mean(e):6.1f}", flush=True)


if __name__ == "__main__":
    main()
