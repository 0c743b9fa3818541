"""A picture of depth: the skeleton seen from the side (the camera's line of sight across the page), truth against
the motions of two `eventcap benchmark` runs (before and after a change), at a few moments of one capture.

    python benchmarks/figures/fig_side_view.py --before runs/benchmark/before10 --after runs/benchmark/after10
                                       [--motion karate_kick] [--seed 2] [--method default] [--moments 6]

Each run's `motion.npz` comes from the benchmark's run folder; the ground truth and the camera from the recording
(brought back from the cache, nothing else runs: benchmarks/diagnostics/diag_depth.py). Joints are root-relative (the pelvis at
the origin of each panel), drawn in the plane of the camera's depth axis (horizontal, away from the camera to the
right) and the world's up; the moments are spread around the fastest moment of the fastest end effector. The title
of each panel gives both runs' mean depth error there. Writes ``<after>/fig_side_view_<motion>-s<seed>.png``.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "diagnostics"))

import numpy as np  # noqa: E402

from diag_depth import from_run  # noqa: E402
from eventcap.body.skeleton import JOINT_INDEX, PARENTS  # noqa: E402
from eventcap.analysis.metrics import END_EFFECTORS, central_derivative, root_relative, truth_at  # noqa: E402


def side(joints: np.ndarray, R: np.ndarray) -> np.ndarray:
    """(..., J, 2): root-relative joints in (camera depth, world up), metres."""
    rel = root_relative(joints)
    depth_axis = R[2].copy()
    depth_axis[1] = 0.0  # the line of sight levelled, so that up stays up
    depth_axis /= np.linalg.norm(depth_axis)
    return np.stack([rel @ depth_axis, rel[..., 1]], axis=-1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--before", required=True)
    ap.add_argument("--after", required=True)
    ap.add_argument("--motion", default="karate_kick")
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--method", default="default")
    ap.add_argument("--moments", type=int, default=6)
    args = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = {label: Path(b) / "runs" / f"{args.motion}-s{args.seed}" / args.method
            for label, b in (("before", args.before), ("after", args.after))}
    rec = from_run(runs["before"])
    R = rec.camera.R
    motions = {}
    for label, rd in runs.items():
        with np.load(rd / "motion.npz") as z:
            motions[label] = (np.asarray(z["t_us"], np.int64), np.asarray(z["joints"], np.float64))
    t, _ = motions["before"]
    truth, inside = truth_at(rec.ground_truth.t_us, rec.ground_truth.joints, t)
    t = t[inside]
    ee = [JOINT_INDEX[n] for n in END_EFFECTORS]
    v, ok = central_derivative(root_relative(truth)[:, ee], t, 10_000)
    speed = np.where(ok[:, None], np.linalg.norm(v, axis=-1), 0.0).max(axis=1)
    peak = int(np.argmax(speed))
    idx = np.clip(peak + np.linspace(-150, 150, args.moments).astype(int), 0, t.size - 1)
    fig, axes = plt.subplots(1, args.moments, figsize=(2.6 * args.moments, 4.2), sharey=True)
    styles = {"truth": ("k", 2.6), "before": ("tab:red", 1.3), "after": ("tab:blue", 1.3)}
    for ax, i in zip(np.atleast_1d(axes), idx):
        curves = {"truth": truth[i]}
        for label, (tm, J) in motions.items():
            k = np.searchsorted(tm, t[i])
            curves[label] = J[k] if k < tm.size and tm[k] == t[i] else None
        errs = []
        for label, J in curves.items():
            if J is None:
                continue
            P = side(J, R)
            color, lw = styles[label]
            for j in range(1, P.shape[0]):
                ax.plot(P[[PARENTS[j], j], 0], P[[PARENTS[j], j], 1], color=color, lw=lw,
                        label=label if j == 1 else None)
            if label != "truth":
                errs.append(f"{label} {1000 * np.abs(P[:, 0] - side(truth[i], R)[:, 0]).mean():.0f}")
        ax.set_title(f"t = {(t[i] - t[0]) / 1000:.0f} ms\ndepth err " + ", ".join(errs) + " mm", fontsize=8)
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
        ax.set_xlabel("depth rel. pelvis (m, away →)", fontsize=7)
    np.atleast_1d(axes)[0].set_ylabel("up rel. pelvis (m)", fontsize=8)
    np.atleast_1d(axes)[0].legend(fontsize=7, loc="lower left")
    fig.suptitle(f"{args.motion} seed {args.seed}, {args.method}: side view (the camera looks along +x), truth "
                 f"(black) against {Path(args.before).name} (red) and {Path(args.after).name} (blue), around the "
                 f"fastest moment", fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    out = Path(args.after) / f"fig_side_view_{args.motion}-s{args.seed}.png"
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
