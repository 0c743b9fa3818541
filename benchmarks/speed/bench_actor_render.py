"""Time per rendered frame of the synthetic capture's actors: skinning plus rasterising, procedural vs ANNY.

    python benchmarks/speed/bench_actor_render.py [--frames 60] [--supersample 3]

The frames are poses of the karate_kick motion seen by the default DAVIS240C camera, as the synthetic source
renders them (``eventcap/sim/capture.py``). Prints, per actor: vertices, faces, template build time, and the
median time per frame of skinning, of rendering and of both.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from eventcap.body.anny import anny_template  # noqa: E402
from eventcap.body.kinematics import skin  # noqa: E402
from eventcap.body.motions import motion_poses  # noqa: E402
from eventcap.body.procedural import procedural_template  # noqa: E402
from eventcap.camera import davis240c_default  # noqa: E402
from eventcap.imaging.render import render, textured_background  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--supersample", type=int, default=3)
    args = ap.parse_args()
    cam = davis240c_default(eye=(0.0, 1.0, 3.0), target=(0.0, 1.0, 0.0))
    bg = textured_background(cam.height, cam.width, seed=0)
    t = np.linspace(0.0, 1.0, args.frames)
    print(f"{'actor':12s} {'V':>6s} {'F':>6s} {'build s':>8s} {'skin ms':>8s} {'render ms':>10s} {'frame ms':>9s}")
    for name, make in (("procedural", lambda: procedural_template(seed=0)), ("anny", lambda: anny_template())):
        t0 = time.perf_counter()
        tpl = make()
        build = time.perf_counter() - t0
        S = motion_poses("karate_kick", t, template=tpl)
        render(cam, skin(S[0], tpl), tpl.faces, tpl.vertex_albedo, bg, supersample=args.supersample)  # jit warm-up
        ts, tr = [], []
        for s in S:
            a = time.perf_counter()
            v = skin(s, tpl)
            b = time.perf_counter()
            render(cam, v, tpl.faces, tpl.vertex_albedo, bg, supersample=args.supersample)
            c = time.perf_counter()
            ts.append(b - a)
            tr.append(c - b)
        ts, tr = np.array(ts) * 1e3, np.array(tr) * 1e3
        print(f"{name:12s} {tpl.num_vertices:6d} {tpl.num_faces:6d} {build:8.2f} {np.median(ts):8.2f} "
              f"{np.median(tr):10.2f} {np.median(ts + tr):9.2f}")


if __name__ == "__main__":
    main()
