"""Time and memory of the synthetic event-camera capture (issue 3 target: <= 60 s per second of capture).

    python benchmarks/speed/bench_synthetic.py [--motions karate_kick,jumping_jack] [--duration 1.0] [--supersample 3]

Prints, per motion: wall time per second of capture, renders, events/s, frames, and the process's peak RSS.
"""

from __future__ import annotations

import argparse
import os
import resource
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from eventcap.body.procedural import procedural_template  # noqa: E402
from eventcap.camera import davis240c_default  # noqa: E402
from eventcap.imaging.render import textured_background  # noqa: E402
from eventcap.sim.capture import CaptureConfig, simulate_synthetic  # noqa: E402
from eventcap.sim.events import SensorConfig  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--motions", default="karate_kick,boxing_combo,javelin_throw,dance_spin,fast_wave,jumping_jack")
    ap.add_argument("--duration", type=float, default=1.0)
    ap.add_argument("--supersample", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    t = time.perf_counter()
    tpl = procedural_template(seed=0)
    print(f"template: {tpl.num_vertices} vertices, {tpl.num_faces} faces in {time.perf_counter() - t:.2f} s")
    cam = davis240c_default(eye=(0.0, 1.0, 3.0), target=(0.0, 1.0, 0.0))
    bg = textured_background(cam.height, cam.width, seed=0)
    print(f"{'motion':<14} {'s per s':>8} {'renders':>8} {'ms/render':>9} {'events/s':>10} {'frames':>6} {'peak RSS':>9}")
    for name in args.motions.split(","):
        cfg = CaptureConfig(motions=((name, args.duration),), seed=args.seed, supersample=args.supersample,
                            sensor=SensorConfig(seed=args.seed))
        t = time.perf_counter()
        cap = simulate_synthetic(tpl, cam, bg, cfg)
        wall = time.perf_counter() - t
        rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        print(f"{name:<14} {wall / args.duration:8.1f} {cap.stats['renders']:8d} "
              f"{1000 * cap.stats['simulate_s'] / max(cap.stats['renders'], 1):9.2f} "
              f"{cap.stats['events_per_s']:10.0f} {cap.frame_images.shape[0]:6d} {rss_mb:8.0f}M", flush=True)


if __name__ == "__main__":
    main()
