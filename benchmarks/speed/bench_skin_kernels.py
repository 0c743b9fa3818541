"""CPU time of the skinning kernels per call: the compiled ones (eventcap/energy/_skin_kernels.py, numba) against the
CasADi graphs they replace (eventcap.energy.kernels.CasadiSkinning), over windows of several frame counts.

    python benchmarks/speed/bench_skin_kernels.py [--frames 50 500] [--calls 20]

Per frame count: the CasADi graph's build time, then for each implementation the CPU milliseconds of one
``transforms_jac`` (G and dG) and one ``contracted_hessian`` call, the median of ``--calls`` calls after one warm-up
call (numba's first call loads or compiles its machine code). Poses are random, the joints within their limits (seed 0);
the poses change by 1e-9 rad between Jacobian calls so the kernels' memo of the last poses is not what is timed.
Nothing is asserted; tests/test_skin_kernels.py holds the kernels to the graphs and to finite differences.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from eventcap.body.skeleton import pose_bounds
from eventcap.body.procedural import procedural_template
from eventcap.energy.kernels import CasadiSkinning, SkinningKernels


def _cpu_ms(call, n: int) -> float:
    call()
    times = []
    for _ in range(n):
        t = time.process_time()
        call()
        times.append((time.process_time() - t) * 1e3)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, nargs="+", default=[50, 500], help="frames per window")
    ap.add_argument("--calls", type=int, default=20, help="timed calls per figure")
    args = ap.parse_args()
    rest = procedural_template(target_faces=3000).rest_joints
    lo, hi = pose_bounds()
    rng = np.random.default_rng(0)
    print(f"{'frames':>6} {'kernels':>8} {'build s':>8} {'G+dG ms':>9} {'Hessian ms':>11}")
    for n in args.frames:
        S = rng.uniform(-np.pi, np.pi, (n, len(lo)))
        S[:, :27] = rng.uniform(lo[:27], hi[:27], (n, 27))  # the joints within their limits, the root anyhow
        S[:, 30:] = [0.0, 0.9, 3.5]
        lam = rng.normal(size=(n, 96, 3))
        t = time.process_time()
        graphs = CasadiSkinning(rest, n)
        build = time.process_time() - t
        for name, k, b in (("casadi", graphs, f"{build:.2f}"), ("numba", SkinningKernels(rest, n), "-")):
            jac = _cpu_ms(lambda k=k, S=S: k.transforms_jac(S + rng.normal(0.0, 1e-9, S.shape)), args.calls)
            hess = _cpu_ms(lambda k=k, S=S, lam=lam: k.contracted_hessian(S, lam), args.calls)
            print(f"{n:>6} {name:>8} {b:>8} {jac:>9.2f} {hess:>11.2f}")


if __name__ == "__main__":
    main()
