"""Where the time of a whole run goes: CPU seconds per stage and per part of the solve, per 40 ms of capture.

    python benchmarks/speed/profile_pipeline.py [--duration 1] [--motion karate_kick] [--seed 0] [--runs 1]
                                          [--source "source.fps=10 ..."] [--warm-start] [-- run overrides ...]

The default measures the README's default capture (1 s of karate_kick at 25 fps, 24 batches of 40 ms) through the
default pipeline with BlazePose (``stages/detect=blazepose``), serially, from a cache holding only the recording to
the outputs without video (``outputs.video=false``): what a user pays after recording. The recording is simulated
once into ``runs/profile/base-<capture>/`` (reused); every measured run starts from a fresh copy of that cache, in a
child process of its own (``eventcap run`` in-process there, with timers wrapped around the functions named below),
so the figures include Python's start-up, the imports, Hydra and the cache I/O.

Figures are CPU seconds (user + system: ``time.process_time`` inside, ``getrusage`` for the whole child), which a
shared machine disturbs less than wall time. Timers are inclusive and nested (a row's children are part of it):

- per stage: the stage's run function; ``cache I/O`` is the runner loading inputs and committing outputs;
- the tracker: its numba kernel (one call per direction per batch) and the rest of ``track_bidirectional``;
- the solve: the NLP build, the per-frame fits (the paper's initialisation; and the prior's gains chosen from the
  fits around the window), the events' stillness (E_still), E_sil's event index and closest-event search, the
  track-to-mesh correspondence search, the factors' ``prepare``, and IPOPT: the numpy callbacks (value, gradient,
  Hessian; inside them each factor's ``linearize`` and the problem's assembly), IPOPT's linear algebra (MUMPS: its
  own timing statistics, read from IPOPT's summary, which this script turns on for the window solves) and the rest
  of IPOPT, and CasADi's glue between IPOPT and the callbacks.

Nothing here is asserted; the figures are for comparing code, on the same machine, at the same load.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
EVENTCAP = [sys.executable, "-m", "eventcap.apps.cli"]


# --------------------------------------------------------------------------------------------- timers (child side)
class Timers:
    """Inclusive CPU and wall seconds and call counts per label."""

    def __init__(self):
        self.cpu = defaultdict(float)
        self.wall = defaultdict(float)
        self.calls = defaultdict(int)
        self.extra = defaultdict(float)

    def wrap(self, fn, label):
        timers = self

        def timed(*args, **kwargs):
            c0, w0 = time.process_time(), time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                lab = label(*args, **kwargs) if callable(label) else label
                timers.cpu[lab] += time.process_time() - c0
                timers.wall[lab] += time.perf_counter() - w0
                timers.calls[lab] += 1

        timed.__wrapped__ = fn
        return timed

    def patch(self, module: str, attr: str, label) -> bool:
        """Wrap ``module.attr`` (a function, or ``Class.method``); False when it does not exist (other code)."""
        import importlib

        try:
            obj = importlib.import_module(module)
        except ImportError:
            return False
        *owners, name = attr.split(".")
        for o in owners:
            obj = getattr(obj, o, None)
            if obj is None:
                return False
        fn = getattr(obj, name, None)
        if fn is None:
            return False
        setattr(obj, name, self.wrap(fn, label))
        return True


def _stage_label(spec):
    return lambda inputs, config, ctx: f"stage {ctx.node}"


def install(timers: Timers) -> None:
    """Wrap the functions whose time the report shows (whatever of them this code has)."""
    import eventcap.core.stage as stage

    load_run = stage.StageSpec.load_run

    def load_run_timed(self):
        return timers.wrap(load_run(self), _stage_label(self))

    stage.StageSpec.load_run = load_run_timed
    timers.patch("eventcap.core.cache", "Cache.load", "cache I/O")
    timers.patch("eventcap.core.cache", "Cache.commit", "cache I/O")
    timers.patch("eventcap.apps.outputs", "write_run_outputs", "outputs (motion files)")
    # the tracker
    try:
        from eventcap_track import eklt

        if hasattr(eklt, "_TRACK_KERNELS"):
            eklt._TRACK_KERNELS = tuple(timers.wrap(fn, "track: numba kernel") for fn in eklt._TRACK_KERNELS)
    except ImportError:
        pass
    timers.patch("eventcap_track.eklt", "detect_features", "track: feature detection")
    # the solve
    sv = "eventcap_spline.solve"
    timers.patch(sv, "SplineSolver.__init__", "solve: NLP build")
    timers.patch(sv, "fit_window", "solve: per-frame fits")
    timers.patch(sv, "window_context", "solve: smoothing evidence (fits around the window, GCV)")
    timers.patch(sv, "window_stillness", "solve: stillness evidence (events around the start)")
    timers.patch("eventcap.energy.sil", "EventIndex", "solve: E_sil (index + closest events)")
    timers.patch("eventcap.energy.sil", "find_silhouette_correspondences", "solve: E_sil (index + closest events)")
    timers.patch("eventcap.energy.window", "find_correspondences", "solve: correspondence search")
    timers.patch("eventcap.energy.problem", "FactorProblem.solve", "solve: IPOPT (window solves)")
    timers.patch("eventcap.energy.ipopt", "NumpyCallback.eval_buffer", lambda self, arg, res: "ipopt: callbacks " + (
        self.name().rsplit("_", 1)[-1] if self.name().endswith(("_grad", "_hess")) else "value"))
    timers.patch("eventcap.energy.problem", "FactorProblem.hessian_parts", "ipopt: Hessian (factors + assembly)")
    from eventcap.energy import terms  # noqa: F401  (registers every factor)
    from eventcap.energy.factor import FACTORS

    for cls in FACTORS.values():
        if "linearize" in cls.__dict__:
            cls.linearize = timers.wrap(cls.__dict__["linearize"], lambda self, S, aux, order: (
                f"factor {self.name} (order {min(order, 2)})"))
        for method in ("collect", "relinearize"):  # a factor's own data: once per window, at each ICP round
            if method in cls.__dict__:
                setattr(cls, method, timers.wrap(cls.__dict__[method], lambda self, *a, m=method: (
                    f"factor {self.name} ({m})")))
    # IPOPT's own timing statistics for the warm-started (window) solves; the fits stay silent
    from eventcap.energy.ipopt import IpoptSettings

    options = IpoptSettings.options

    def options_timed(self, warm):
        opts = options(self, warm)
        if warm:
            opts.update({"ipopt.print_level": 3, "ipopt.timing_statistics": "yes",
                         "ipopt.print_timing_statistics": "yes"})
        return opts

    IpoptSettings.options = options_timed


_IPOPT_ROWS = {"total": r"OverallAlgorithm$", "linsolve": r"LinearSystem(Scaling|SymbolicFactorization|Factorization|"
               r"BackSolve|StructureConverter)$", "feval": r"Function Evaluations$"}


def ipopt_seconds(text: str) -> dict:
    """CPU + system seconds of IPOPT's timing statistics summed over every solve printed in ``text``."""
    out = defaultdict(float)
    n = 0
    for line in text.splitlines():
        m = re.match(r"\s*([\w ]+?)\.+:\s+([\d.]+) \(sys:\s+([\d.]+) wall:\s+([\d.]+)\)", line)
        if not m:
            if line.startswith("Number of Iterations....:"):
                out["iterations"] += int(line.split(":")[1])
                n += 1
            continue
        for key, pat in _IPOPT_ROWS.items():
            if re.match(pat, m.group(1)):
                out[key] += float(m.group(2)) + float(m.group(3))
    out["solves"] = n
    return dict(out)


def child(args) -> None:
    """Run the pipeline in this process with timers; write the figures as JSON to args.child."""
    c0 = time.process_time()
    sys.path.insert(0, str(ROOT / "plugins"))
    timers = Timers()
    log = Path(args.child).with_suffix(".ipopt.txt")
    saved = os.dup(1)
    fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    os.dup2(fd, 1)  # IPOPT prints its summaries on the C stdout
    try:
        from eventcap.apps.cli import main

        install(timers)
        if args.warm_start:  # an experiment, not a stage option (benchmarks/speed/bench_warm_start.py says why)
            sys.path.insert(0, str(ROOT / "benchmarks" / "speed"))
            from bench_warm_start import install as warm_start

            warm_start("warm", [])
        setup = time.process_time() - c0
        code = main(["run", *args.overrides])
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
    ipopt = ipopt_seconds(log.read_text(errors="replace"))
    Path(args.child).write_text(json.dumps({"code": code, "setup_cpu": setup, "cpu": timers.cpu, "wall": timers.wall,
                                            "calls": timers.calls, "ipopt": ipopt,
                                            "process_cpu": time.process_time()}))


# --------------------------------------------------------------------------------------------- parent side
def base_cache(args) -> Path:
    """A cache holding only the template and the simulated recording (computed once, reused)."""
    tag = hashlib.sha256(f"{args.motion}|{args.duration}|{args.seed}|{args.source}".encode()).hexdigest()[:10]
    base = Path(args.base_dir) / f"base-{args.motion}-{args.duration:g}s-{tag}"
    if (base / "entries").is_dir():
        return base
    tmp = base.with_name(base.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    env = dict(os.environ, EVENTCAP_CACHE_DIR=str(tmp))
    with tempfile.TemporaryDirectory() as scratch:
        subprocess.run([*EVENTCAP, "run", "pipeline=simulate", "outputs.poses=null", "log_level=WARNING",
                        f"hydra.run.dir={scratch}/run", *source_overrides(args)], env=env, check=True, cwd=scratch)
    tmp.rename(base)
    return base


def source_overrides(args) -> list[str]:
    return [f"source.motion={args.motion}", f"source.duration_s={args.duration}", f"source.seed={args.seed}",
            *args.source.split()]


def measure(args, base: Path, i: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="profile_pipeline_") as tmp:
        cache = Path(tmp) / "cache"
        shutil.copytree(base, cache)
        out = Path(tmp) / "timers.json"
        overrides = ["stages/detect=blazepose", "outputs.video=false", "log_level=WARNING",
                     f"hydra.run.dir={tmp}/run", *source_overrides(args), *args.overrides]
        env = dict(os.environ, EVENTCAP_CACHE_DIR=str(cache), OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
                   MKL_NUM_THREADS="1")
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        w0 = time.perf_counter()
        subprocess.run([sys.executable, __file__, "--child", str(out), *(["--warm-start"] if args.warm_start else []),
                        "--", *overrides], env=env, check=True,
                       cwd=tmp, stdout=subprocess.DEVNULL)
        wall = time.perf_counter() - w0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        res = json.loads(out.read_text())
        if res["code"] != 0:
            raise SystemExit(f"run {i} failed (exit {res['code']}); run again without --runs to see its log")
        nodes = json.loads((Path(tmp) / "run" / "run.json").read_text())["nodes"]
        n_batches = max(len(n.get("computed_keys", [])) for n in nodes.values()) or 1  # the per-batch nodes'
        n_windows = len(nodes["solve"].get("computed_keys", []))
        m = json.loads((Path(tmp) / "run" / "metrics.json").read_text()).get("evaluate.metrics", {})
        res["accuracy"] = {k: m.get(k) for k in ("AE_mm", "AE_rootrel_mm", "MPJVE_mm_s", "peak_speed_err")}
        res.update(n_windows=n_windows, whole_cpu=(after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), wall=wall,
                   peak_mb=after.ru_maxrss / 1024, n_batches=n_batches)
        return res


ROWS = [  # (label, indent): the report's rows, in order; a row whose label has no time is left out
    ("startup (Python, imports, Hydra, config)", 0),
    ("stage template", 0), ("stage source", 0), ("stage sharpen", 0), ("stage detect", 0),
    ("stage track", 0), ("track: numba kernel", 1), ("track: feature detection", 1),
    ("stage slice", 0),
    ("stage solve", 0), ("solve: NLP build", 1), ("solve: per-frame fits", 1),
    ("solve: prior gains (fits around the window, GCV)", 1), ("solve: E_still (events' stillness)", 1),
    ("solve: E_sil (index + closest events)", 1), ("solve: correspondence search", 1), ("solve: factors' prepare", 1),
    ("solve: IPOPT (window solves)", 1), ("ipopt: callbacks value", 2), ("ipopt: callbacks grad", 2),
    ("ipopt: callbacks hess", 2), ("ipopt: Hessian (factors + assembly)", 3), ("ipopt: linear algebra (MUMPS)", 2),
    ("ipopt: IPOPT's own (the rest)", 2), ("ipopt: CasADi glue", 2),
    ("stage stitch", 0), ("stage cut", 0), ("stage evaluate", 0), ("cache I/O", 0), ("outputs (motion files)", 0),
]


def report(results: list[dict]) -> None:
    import numpy as np

    def med(f):
        return float(np.median([f(r) for r in results]))

    def med_of(field, key):
        return float(np.median([r[field].get(key, 0.0) for r in results]))

    n = results[0]["n_batches"]
    derived = []
    for r in results:
        cpu, ip = r["cpu"], r["ipopt"]
        cpu["startup (Python, imports, Hydra, config)"] = r["setup_cpu"] + max(
            0.0, r["process_cpu"] - r["setup_cpu"] - sum(v for k, v in cpu.items() if k.startswith("stage "))
            - cpu.get("cache I/O", 0.0) - cpu.get("outputs (motion files)", 0.0))
        cb = sum(cpu.get(f"ipopt: callbacks {k}", 0.0) for k in ("value", "grad", "hess"))
        solve = cpu.get("solve: IPOPT (window solves)", 0.0)
        cpu["ipopt: linear algebra (MUMPS)"] = ip.get("linsolve", 0.0)
        cpu["ipopt: IPOPT's own (the rest)"] = max(0.0, ip.get("total", 0.0) - ip.get("feval", 0.0)
                                                   - ip.get("linsolve", 0.0))
        cpu["ipopt: CasADi glue"] = max(0.0, solve - cb - ip.get("total", 0.0) + ip.get("feval", 0.0))
        derived.append(ip)
    whole = med(lambda r: r["whole_cpu"])
    print(f"{len(results)} run(s), {n} batches of 40 ms; CPU seconds (median of runs), per 40 ms of capture, share of "
          "the whole process")
    print(f"{'':<58} {'CPU s':>8} {'/40 ms':>8} {'share':>6} {'calls':>7}")
    for label, ind in ROWS:
        v = med_of("cpu", label)
        if v <= 0:
            continue
        calls = med_of("calls", label)
        name = label.split(": ", 1)[1] if ind and ": " in label else label
        print(f"{'  ' * ind + name:<58} {v:8.2f} {v / n:8.3f} {100 * v / whole:5.1f}% {int(calls) or '':>7}")
    factors = sorted({k for r in results for k in r["cpu"] if k.startswith("factor ")})
    if factors:
        print("factors' linearize (inside the callbacks, and the fits' curvature):")
        for k in factors:
            v = med_of("cpu", k)
            print(f"    {k:<54} {v:8.2f} {v / n:8.3f} {100 * v / whole:5.1f}% {int(med_of('calls', k)):>7}")
    its = med(lambda r: r["ipopt"].get("iterations", 0))
    sol = med(lambda r: r["ipopt"].get("solves", 0))
    print(f"window solves: {sol:.0f}, IPOPT iterations {its:.0f} ({its / max(sol, 1):.1f} per solve, "
          f"{its / n:.1f} per batch)")
    print("accuracy (first run): " + ", ".join(f"{k} {v:.4g}" for k, v in results[0]["accuracy"].items()
                                             if v is not None))
    print(f"{'whole process (getrusage: user + sys)':<58} {whole:8.2f} {whole / n:8.3f}   wall {med(lambda r: r['wall']):.1f} "
          f"s, peak {med(lambda r: r['peak_mb']):.0f} MB, load {os.getloadavg()[0]:.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=1.0, help="capture length, s")
    ap.add_argument("--motion", default="karate_kick")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--source", default="", help="more source overrides, e.g. 'source.fps=10 source.exposure_us=30000'")
    ap.add_argument("--base-dir", default=str(ROOT / "runs" / "profile"),
                    help="where the simulated recordings are kept (one per capture; share it between checkouts)")
    ap.add_argument("--runs", type=int, default=1, help="measured runs (the median is printed)")
    ap.add_argument("--json", help="also write every run's figures here")
    ap.add_argument("--warm-start", action="store_true",
                    help="each window starts from the previous window's solution (benchmarks/speed/bench_warm_start.py)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("overrides", nargs="*", help="more `eventcap run` overrides (after --)")
    args = ap.parse_args()
    if args.child:
        return child(args)
    base = base_cache(args)
    results = [measure(args, base, i) for i in range(args.runs)]
    if args.json:
        Path(args.json).write_text(json.dumps(results))
    report(results)


if __name__ == "__main__":
    main()
