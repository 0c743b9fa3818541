"""Where a motion's depth error lies: the root-relative joint error along the camera's line of sight, split into what
a rotation of the whole body explains (its orientation) and what is left (the limbs), and per limb bone how often
its depth extent has the wrong sign (which end is nearer) and how far off it is.

    python benchmarks/diagnostics/diag_depth.py --bench runs/benchmark/before25 [--motions karate_kick,...] [--seeds 2,3,4]
                                    [--methods default,frames_smooth,linear]

Each method's `motion.npz` comes from the benchmark's run folder; the ground truth and the camera from the
recording, which the run's own config brings back from the cache (nothing is recomputed). Measures on every 10th
tracking frame, as the evaluate stage. A diagnosis with the ground truth: nothing here is used by a run.
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[2]

import numpy as np  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from eventcap.energy.bones import _J, BONES  # noqa: E402
from eventcap.analysis.metrics import depth_split, procrustes_align, root_relative, truth_at  # noqa: E402
from eventcap.core.runner import Runner  # noqa: E402


def from_run(run_dir: Path, port: str = "source.recording", keep: tuple[str, ...] = ("template", "source")):
    """An output of a run brought back from the cache: its config with only the nodes ``keep`` (so that nothing
    else runs, whatever changed in the code since), serially."""
    data = OmegaConf.to_container(OmegaConf.load(run_dir / "config.yaml"), resolve=True)
    data["log_level"] = "WARNING"
    data["executor"] = {"kind": "serial"}
    data["pipeline"]["nodes"] = {k: v for k, v in data["pipeline"]["nodes"].items() if k in keep}
    data["outputs"] = {}
    runner = Runner(data)
    with tempfile.TemporaryDirectory() as tmp:
        result = runner.run(Path(tmp))
        return runner.load_output(result, port)[None]


def recording_of(run_dir: Path):
    return from_run(run_dir)


def measure(run_dir: Path, rec) -> dict:
    with np.load(run_dir / "motion.npz") as z:
        t_us, joints = np.asarray(z["t_us"], np.int64), np.asarray(z["joints"], np.float64)
    true, inside = truth_at(rec.ground_truth.t_us, rec.ground_truth.joints, t_us)
    P, G = joints[inside][::10], true[::10]
    R = rec.camera.R
    depth, image = depth_split(P, G, R)
    # the same after the best rotation of the whole (root-relative) body: what its orientation does not explain
    aligned = procrustes_align(root_relative(P), root_relative(G))
    d_rot, i_rot = depth_split(aligned - aligned[:, :1], G, R)
    dz = lambda X: (X[:, _J[:, 1]] - X[:, _J[:, 0]]) @ R[2]  # noqa: E731
    dp, dt = dz(P), dz(G)
    steep = np.abs(dt) > 0.05
    flips = (np.sign(dp) != np.sign(dt)) & steep
    return {"depth": 1000 * depth.mean(), "image": 1000 * image.mean(), "depth_after_rotation": 1000 * d_rot.mean(),
            "image_after_rotation": 1000 * i_rot.mean(),
            "flip": flips.sum(0) / np.maximum(steep.sum(0), 1), "dz_err": 1000 * np.abs(dp - dt).mean(0)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bench", required=True)
    ap.add_argument("--motions", default="karate_kick,boxing_combo,javelin_throw,dance_spin,fast_wave,jumping_jack")
    ap.add_argument("--seeds", default="2,3,4")
    ap.add_argument("--methods", default="default,frames_smooth,linear")
    args = ap.parse_args()
    rows = {}
    for motion in args.motions.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            seq = Path(args.bench) / "runs" / f"{motion}-s{seed}"
            methods = [m for m in args.methods.split(",") if (seq / m / "motion.npz").is_file()]
            if not methods:
                continue
            rec = recording_of(seq / methods[0])
            for m in methods:
                r = measure(seq / m, rec)
                rows.setdefault(m, []).append(r)
                print(f"{motion:<14} s{seed} {m:<14} depth {r['depth']:5.1f} (after the body's rotation "
                      f"{r['depth_after_rotation']:5.1f}) image plane {r['image']:5.1f} ({r['image_after_rotation']:5.1f})"
                      f" mm; bones with the wrong nearer end {100 * r['flip'].mean():4.1f}%")
    for m, rs in rows.items():
        print(f"\n{m} over {len(rs)} captures: depth {np.mean([r['depth'] for r in rs]):.1f} mm, after the body's "
              f"rotation {np.mean([r['depth_after_rotation'] for r in rs]):.1f}; image plane "
              f"{np.mean([r['image'] for r in rs]):.1f} ({np.mean([r['image_after_rotation'] for r in rs]):.1f})")
        flip = np.mean([r["flip"] for r in rs], axis=0)
        err = np.mean([r["dz_err"] for r in rs], axis=0)
        for (a, b), f, e in zip(BONES, flip, err):
            print(f"  {a}-{b}: wrong nearer end {100 * f:4.1f}% of the frames where it is > 5 cm, depth extent off "
                  f"{e:5.1f} mm")


if __name__ == "__main__":
    main()
