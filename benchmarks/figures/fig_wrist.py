"""A picture of the 1 kHz motion itself: the faster wrist's position and speed (root-relative) over time, truth against
the methods of an `eventcap benchmark` run.

    python benchmarks/figures/fig_wrist.py [--bench runs/benchmark/default] [--motion karate_kick] [--seed 0]
                                   [--methods default,paper,linear,frames_smooth,spline] [--joint r_wrist]

Each method's `motion.npz` comes from the benchmark's run folder; the ground truth from the recording, which the
run's own config brings back from the cache (nothing is recomputed). Rows: the wrist's coordinate that moves most
in the truth (metres, relative to the pelvis), its speed (central differences over 10 ms, as the MPJVE), and both
again in a 300 ms window around the fastest moment, where the 1 kHz detail shows. Writes
``<bench>/fig_wrist_<motion>-s<seed>.png`` and prints each method's position and speed errors.
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[2]

import numpy as np  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from eventcap.body.skeleton import JOINT_INDEX  # noqa: E402
from eventcap.analysis.metrics import central_derivative, root_relative, truth_at  # noqa: E402
from eventcap.core.runner import Runner  # noqa: E402


def speed(t_us: np.ndarray, x: np.ndarray, window_us: float) -> np.ndarray:
    """|dx/dt| by the evaluate stage's central differences (NaN where the window leaves the motion), m/s."""
    return np.linalg.norm(central_derivative(x, t_us, window_us)[0], axis=-1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bench", default=str(ROOT / "runs" / "benchmark" / "default"))
    ap.add_argument("--motion", default="karate_kick")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--methods", default="default,paper,linear,frames_smooth,spline")
    ap.add_argument("--joint", default="auto", help="a joint name, or auto: the wrist that moves fastest in the truth")
    ap.add_argument("--window-ms", type=float, default=10.0, help="central-difference window of the speed")
    args = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seq = Path(args.bench) / "runs" / f"{args.motion}-s{args.seed}"
    methods = [m for m in args.methods.split(",") if (seq / m.replace("/", "_") / "motion.npz").is_file()]
    if not methods:
        raise SystemExit(f"no motion.npz of {args.methods} under {seq}")
    # the ground truth: the first run's config, run again from the cache (everything is committed)
    data = OmegaConf.to_container(OmegaConf.load(seq / methods[0].replace("/", "_") / "config.yaml"), resolve=True)
    data["log_level"] = "WARNING"
    runner = Runner(data)
    with tempfile.TemporaryDirectory() as tmp:
        result = runner.run(Path(tmp))
        gt = runner.load_output(result, "source.recording")[None].ground_truth
    window_us = args.window_ms * 1000.0
    if args.joint == "auto":
        rel = root_relative(gt.joints)
        fastest = {w: np.nanmax(speed(gt.t_us, rel[:, JOINT_INDEX[w]], window_us)) for w in ("l_wrist", "r_wrist")}
        args.joint = max(fastest, key=fastest.get)
    j = JOINT_INDEX[args.joint]
    curves = {}
    for m in methods:
        with np.load(seq / m.replace("/", "_") / "motion.npz") as z:
            t_us, joints = np.asarray(z["t_us"], np.int64), np.asarray(z["joints"], np.float64)
        true, inside = truth_at(gt.t_us, gt.joints, t_us)
        t, est, tru = t_us[inside], root_relative(joints[inside])[:, j], root_relative(true)[:, j]
        curves[m] = (t, est, tru, speed(t, est, window_us), speed(t, tru, window_us))
    t, _, tru, _, v_true = curves[methods[0]]
    axis = int(np.argmax(np.ptp(tru, axis=0)))
    peak = int(np.nanargmax(v_true))
    t0 = t[0]
    lo, hi = t[peak] - 150_000, t[peak] + 150_000
    fig, axes = plt.subplots(2, 2, figsize=(13, 6.5), gridspec_kw={"width_ratios": [2, 1]})
    colors = plt.get_cmap("tab10").colors
    for col, (a, b) in enumerate([(t[0], t[-1]), (lo, hi)]):
        sel = (t >= a) & (t <= b)
        axes[0, col].plot((t[sel] - t0) / 1000, tru[sel, axis], color="k", lw=2.4, label="truth")
        axes[1, col].plot((t[sel] - t0) / 1000, v_true[sel], color="k", lw=2.4, label="truth")
        for i, m in enumerate(methods):
            tm, est, tr, v, vt = curves[m]
            s = (tm >= a) & (tm <= b)
            if col == 0:
                pos_mm = 1000 * np.linalg.norm(est - tr, axis=1).mean()
                ok = np.isfinite(v) & np.isfinite(vt)
                vel = 1000 * np.abs(v[ok] - vt[ok]).mean()
                print(f"{m:<14} {args.joint} position error {pos_mm:6.1f} mm, speed error {vel:7.0f} mm/s")
                label = f"{m} ({pos_mm:.0f} mm, {vel:.0f} mm/s)"
            else:
                label = m
            axes[0, col].plot((tm[s] - t0) / 1000, est[s, axis], color=colors[i], lw=1.1, label=label)
            axes[1, col].plot((tm[s] - t0) / 1000, v[s], color=colors[i], lw=1.1)
        # a joint at rest in the truth: the methods' own speeds set the scale
        top = 3 * np.nanmax(v_true) if np.nanmax(v_true) > 0.05 else max(
            np.nanpercentile(curves[m][3], 99.5) for m in methods)
        axes[1, col].set_ylim(0, top)
    axes[0, 0].legend(fontsize=7, ncol=3, loc="best")
    axes[0, 0].set_ylabel(f"{args.joint} {'xyz'[axis]} rel. pelvis (m)")
    axes[1, 0].set_ylabel("speed rel. pelvis (m/s)")
    for ax in axes.ravel():
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
    axes[1, 0].set_xlabel("time (ms)")
    axes[1, 1].set_xlabel("time (ms), around the fastest moment")
    fig.suptitle(f"{args.motion} seed {args.seed} ({Path(args.bench).name}): {args.joint}, truth against each method "
                 f"(legend: mean position error, mean speed error over {args.window_ms:.0f} ms differences)", fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    out = Path(args.bench) / f"fig_wrist_{args.motion}-s{args.seed}.png"
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
