"""Peak memory of the default pipeline against the capture's length (issue 55, item 3: memory flat as the capture
grows), optionally against another checkout's code on the same captures, with their motions compared exactly.

    python benchmarks/speed/bench_memory.py [--durations 2 8] [--against DIR] [--detector blazepose]
                                            [--base-dir runs/bench_duration] [--json out.json] [-- overrides ...]

For each duration, the synthetic recording is made once into a cache under ``--base-dir`` (as
``bench_duration.py`` does, and shared with it); then ``eventcap run`` runs the default pipeline from a fresh copy
of that cache (only the recording in it) to the outputs without video, serially, in a child process. Its peak
resident set size (``ru_maxrss`` from ``os.wait4``), CPU seconds (user + system) and wall seconds are printed per
capture, with the peak's ratio to the shortest capture's.

``--against DIR``: the same runs with the code of DIR (an export of another commit, e.g. ``git archive main | tar -x
-C DIR``; run with ``PYTHONPATH=DIR:DIR/plugins``, this checkout's virtualenv), and each capture's ``motion.npz`` of
both compared array by array, exactly (``np.array_equal``, NaNs equal). The machine may be shared: the load average
at the end of each run is printed; CPU seconds are disturbed less by other load than wall seconds, peak memory not
at all. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(HERE))
import bench_duration  # noqa: E402  (the simulated captures and the wait4 measurement)


def run_once(args, base: Path, duration: float, code: Path | None, keep: Path) -> dict:
    """The default pipeline from a copy of ``base`` with this checkout's code (``code`` None) or DIR's; the run
    folder's motion.npz is kept as ``keep``."""
    with tempfile.TemporaryDirectory(prefix="bench_memory_") as tmp:
        cache = Path(tmp) / "cache"
        shutil.copytree(base, cache)
        overrides = [f"stages/detect={args.detector}", "outputs.video=false", "log_level=WARNING",
                     f"hydra.run.dir={tmp}/run", *bench_duration.source_overrides(args, duration), *args.overrides]
        env = dict(os.environ, EVENTCAP_CACHE_DIR=str(cache), OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
                   MKL_NUM_THREADS="1")
        if code is not None:
            env["PYTHONPATH"] = os.pathsep.join([str(code), str(code / "plugins"), env.get("PYTHONPATH", "")])
        res = bench_duration.measured([*bench_duration.EVENTCAP, "run", *overrides], env=env, cwd=tmp,
                                      stdout=subprocess.DEVNULL)
        if res["code"] != 0:
            raise SystemExit(f"the {duration:g} s run ({code or 'this checkout'}) failed (exit {res['code']}); run "
                             f"`eventcap run` with {' '.join(overrides)} to see its log")
        keep.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(Path(tmp) / "run" / "motion.npz", keep)
    return res


def same_motion(a: Path, b: Path) -> str:
    """'equal' when every array of the two motion.npz files is equal (NaNs equal), else what differs."""
    with np.load(a) as x, np.load(b) as y:
        if set(x.files) != set(y.files):
            return f"different arrays: {sorted(set(x.files) ^ set(y.files))}"
        diff = [k for k in x.files if x[k].shape != y[k].shape or not np.array_equal(
            x[k], y[k], equal_nan=x[k].dtype.kind in "fc")]
    return "equal" if not diff else "differ: " + ", ".join(diff)


def report(rows: list[dict], against: str | None) -> None:
    print(f"\n{'code':<10} {'duration s':>10} {'peak RSS MB':>11} {'x shortest':>10} {'CPU s':>8} {'CPU s/40ms':>10} "
          f"{'wall s':>8} {'load':>5}")
    for who in ("this", "against") if against else ("this",):
        first = next(r[who]["peak_mb"] for r in rows)
        for r in rows:
            m, n40 = r[who], r["duration"] / 0.04
            print(f"{who:<10} {r['duration']:10g} {m['peak_mb']:11.0f} {m['peak_mb'] / first:10.2f} {m['cpu_s']:8.1f} "
                  f"{m['cpu_s'] / n40:10.3f} {m['wall_s']:8.1f} {m['load']:5.1f}")
    if against:
        print(f"\nmotion.npz, this checkout against {against}:")
        for r in rows:
            print(f"  {r['duration']:g} s: {r['motion']}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--durations", type=float, nargs="+", default=[2.0, 8.0], help="capture lengths, s")
    ap.add_argument("--against", type=Path, help="a checkout (export) of other code to run on the same captures")
    ap.add_argument("--motion", default="karate_kick")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--detector", default="blazepose", help="stages/detect option (blazepose | simulated)")
    ap.add_argument("--source", default="", help="more source overrides, e.g. 'source.fps=10'")
    ap.add_argument("--base-dir", default=str(ROOT / "runs" / "bench_duration"),
                    help="where the simulated recordings are kept (one cache per capture, reused)")
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_memory"), help="where the motions are kept")
    ap.add_argument("--json", help="also write the figures here")
    ap.add_argument("overrides", nargs="*", help="more `eventcap run` overrides (after --)")
    args = ap.parse_args()
    rows = []
    for d in args.durations:
        base, _ = bench_duration.base_cache(args, d)
        row = {"duration": d}
        for who, code in (("this", None), ("against", args.against)):
            if who == "against" and code is None:
                continue
            print(f"{d:g} s, {code or 'this checkout'}: running the pipeline", flush=True)
            row[who] = run_once(args, base, d, code, Path(args.out) / f"{d:g}s-{who}.npz")
        if args.against:
            row["motion"] = same_motion(Path(args.out) / f"{d:g}s-this.npz", Path(args.out) / f"{d:g}s-against.npz")
        rows.append(row)
        if args.json:
            Path(args.json).write_text(json.dumps(rows, indent=1))
    report(rows, str(args.against) if args.against else None)


if __name__ == "__main__":
    main()
