"""CPU time of the BlazePose networks per image, on a synthetic capture's frames (240x180).

    python benchmarks/speed/bench_detector_speed.py [--model full|lite] [--images 200] [--find]

Loads the networks, then runs the landmark model ``--images`` times on the crops a tracked actor gives (the
normal case: one network per image), or with ``--find`` the person detector plus the landmark model on every
image (a person found anew each time). Prints the in-process time per image; run it as a whole process against
``--images 0`` to separate the start-up (imports, loading the networks) from the per-image cost.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "plugins"))

import numpy as np  # noqa: E402
from eventcap_detect import blazepose as bp  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default="full")
    ap.add_argument("--images", type=int, default=200)
    ap.add_argument("--find", action="store_true", help="person detector + landmark model on every image")
    args = ap.parse_args()
    net = bp.BlazePose(args.model)
    rng = np.random.default_rng(0)
    image = bp.to_rgb8(rng.uniform(0.2, 0.6, (180, 240)))  # the networks' cost does not depend on the content
    roi = bp.Roi(120, 100, 150, 0.0)
    t0 = time.perf_counter()
    for _ in range(args.images):
        if args.find:
            net.detect_person(image)
        net.landmarks(image, roi)
    dt = time.perf_counter() - t0
    if args.images:
        print(f"{args.model}{' + detector' if args.find else ''}: {1000 * dt / args.images:.1f} ms per image "
              f"({args.images} images)")


if __name__ == "__main__":
    main()
