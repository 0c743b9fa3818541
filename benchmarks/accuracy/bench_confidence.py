"""How trustworthy the confidence is on partial views: synthetic captures whose truth says what was in view.

    python benchmarks/accuracy/bench_confidence.py [--detector blazepose] [--duration 1.0] [--scenes upper,hands,dvs128,full]

Each scene is a synthetic capture run through `eventcap run` (the default command: an event-only camera picks the
event-only pipeline by itself), then measured against its ground truth, which the run never saw:

- ``marked observed``: the share of (frame, joint) pairs with confidence >= 0.5;
- ``observed but out of view``: of those, the share whose TRUE joint projects outside the image (target 0);
- the 3D error (mm, world frame, no alignment) of the joints marked observed and of the others;
- or the run's refusal line, when it refused (e.g. detect found no person in enough images).

Scenes (camera keys of the synthetic source; see README "Cameras, scenes and sensor realism"):
``full`` the default capture; ``upper`` an upper-body close-up (1.2 m, chest height); ``hands`` arms and hands at
0.6 m; ``dvs128`` a DVS128 (128 x 128, no frames) with the actor far (6 m).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
SCENES = {
    "full": [],
    "upper": ["source.camera_distance_m=1.2", "source.camera_height_m=1.35"],
    "hands": ["source.camera_distance_m=0.6", "source.camera_height_m=1.2", "source.motion=fast_wave"],
    "dvs128": ["source.camera=dvs128", "source.camera_distance_m=6.0"],
}


def run_scene(name: str, args, out: Path) -> dict:
    run_dir = out / name
    cmd = [sys.executable, "-m", "eventcap.apps.cli", "run", f"source.duration_s={args.duration}", f"source.seed={args.seed}",
           "outputs.video=false", "outputs.bvh=false", "export=[source.recording]", f"hydra.run.dir={run_dir}",
           f"stages/detect={args.detector}", f"cache_dir={args.cache}", *SCENES[name]]
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    log = p.stdout + p.stderr
    if not (run_dir / "motion.npz").exists():
        refusal = next((ln for ln in log.splitlines() if "FAILED" in ln or "run incomplete" in ln), log[-300:])
        return {"scene": name, "refused": refusal.strip()}
    return measure(name, run_dir)


def measure(name: str, run_dir: Path) -> dict:
    import zarr

    from eventcap.artifacts.recording import Recording
    from eventcap.analysis.confidence import OBSERVED, in_image
    from eventcap.analysis.metrics import truth_at

    m = np.load(run_dir / "motion.npz")
    rec = Recording.from_zarr(zarr.open_group(str(run_dir / "source.recording.zarr"), mode="r"))
    est = m["estimated"]
    t, J, c = m["t_us"][est], m["joints"][est], m["confidence"][est]
    truth, inside = truth_at(rec.ground_truth.t_us, rec.ground_truth.joints, t)
    J, c = J[inside], c[inside]
    seen = c >= OBSERVED
    true_in = in_image(rec.camera, truth)
    err = np.linalg.norm(J - truth, axis=-1) * 1000.0
    return {"scene": name, "frames": int(est.size), "gap_frames": int((~est).sum()),
            "truly_in_view": float(true_in.mean()), "marked_observed": float(seen.mean()),
            "observed_but_out_of_view": float((seen & ~true_in).sum() / max(seen.sum(), 1)),
            "out_of_view_marked_observed": float((seen & ~true_in).sum() / max((~true_in).sum(), 1)),
            "error_observed_mm": float(err[seen].mean()) if seen.any() else None,
            "error_unobserved_mm": float(err[~seen].mean()) if (~seen).any() else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--detector", default="blazepose", help="stages/detect variant (blazepose | simulated)")
    ap.add_argument("--duration", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--cache", default=str(ROOT / "runs" / "cache"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_confidence"))
    args = ap.parse_args()
    out = Path(args.out)
    rows = []
    for name in args.scenes.split(","):
        r = run_scene(name, args, out)
        rows.append(r)
        print(json.dumps(r), flush=True)
    print(f"\n{'scene':<8} {'in view':>8} {'marked':>7} {'obs. out':>9} {'err obs':>8} {'err not':>8}  (shares; mm)")
    for r in rows:
        if "refused" in r:
            print(f"{r['scene']:<8} refused: {r['refused'][:150]}")
            continue
        e1, e2 = r["error_observed_mm"], r["error_unobserved_mm"]
        print(f"{r['scene']:<8} {r['truly_in_view']:8.2f} {r['marked_observed']:7.2f} "
              f"{r['observed_but_out_of_view']:9.3f} {e1 if e1 is None else round(e1):>8} "
              f"{e2 if e2 is None else round(e2):>8}")


if __name__ == "__main__":
    main()
