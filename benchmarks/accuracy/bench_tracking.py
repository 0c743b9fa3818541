"""Benchmark of the event feature trackers (EKLT forward / backward / stitched, and the KLT-on-latents baseline).

Scenes are *simulated*: analytic textures at 240x180 moving with known fast motions (translation, rotation, affine,
a textured disc over a textured background), turned into events by ``eventcap.sim.events``. The true position of
every texture point is known at every time, so each track is scored against ground truth: its position is read
every 1 ms over the part of the 40 ms batch it covers (linear interpolation between its samples) and compared with
where the texture point it started on really is.

Printed per scene and method: number of tracks, survival (fraction alive at the end of their direction), median and
90th-percentile error (px) over all (track, ms) pairs, mean coverage of the batch, time per 40 ms batch, events/s.

    python3 benchmarks/accuracy/bench_tracking.py [--scenes translate_1500,disc_2000] [--repeat 1]

The scenes and their scoring (``make_scene``, ``SCENES``, ``evaluate``) are tests/helpers/tracking_scenes.py, shared with
``tests/test_eklt.py``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "plugins"))  # eventcap_track without an install
sys.path.insert(0, str(ROOT))  # the scenes: tests/helpers

from eventcap.sim.events import SensorConfig
from tests.helpers.tracking_scenes import (
    LOG_EPS,
    SCENES,
    T0_US,
    T1_US,
    evaluate,
    event_latents,
    log_image,
    make_scene,
    simulate_events,
    true_latents,
)


# ---------------------------------------------------------------------------------------------------- main
def run_scene(name: str, repeat: int, sensor: SensorConfig, with_true_klt: bool = True) -> None:
    from eventcap_track import eklt, klt

    scene = make_scene(name)
    t = time.perf_counter()
    events = simulate_events(scene, config=sensor)
    sim_s = time.perf_counter() - t
    L0, L1 = log_image(scene, T0_US), log_image(scene, T1_US)
    m0, m1 = scene.mask(T0_US), scene.mask(T1_US)
    cfg = eklt.EkltConfig()

    def timed(fn):
        best, out = float("inf"), None
        for _ in range(repeat):
            t = time.perf_counter()
            out = fn()
            best = min(best, time.perf_counter() - t)
        return out, best

    stats: dict = {}
    fwd, t_fwd = timed(lambda: eklt.track(L0, events, T0_US, T1_US, +1, cfg, mask=m0, stats=stats))
    n_fwd_updates = stats["n_updates"]
    bwd, t_bwd = timed(lambda: eklt.track(L1, events, T0_US, T1_US, -1, cfg, mask=m1))
    both, t_both = timed(lambda: eklt.track_bidirectional(L0, L1, events, T0_US, T1_US, mask_0=m0, mask_1=m1))
    paper = eklt.track_bidirectional(L0, L1, events, T0_US, T1_US, mask_0=m0, mask_1=m1, backward_start="detect")
    feats = np.c_[fwd.x[fwd.offsets[:-1]], fwd.y[fwd.offsets[:-1]]]
    latents = event_latents(L0, events, T0_US, T1_US)
    k_ev, t_klt = timed(lambda: klt.klt_latent(latents, T0_US, T1_US, features=feats))
    print(f"\n== {name}: {events.size} events in 40 ms ({events.size / 0.04 / 1e6:.2f} Mev/s), simulated in "
          f"{sim_s:.1f} s; {fwd.n_tracks} forward features, {n_fwd_updates} forward updates")
    rows = [
        ("eklt forward", fwd, t_fwd),
        ("eklt backward", bwd, t_bwd),
        ("eklt stitched (paper: detect on L1)", paper, float("nan")),
        ("eklt stitched (default: relocate)", both, t_both),
        ("  ...stitched tracks only", _subset(both, both.kind == eklt.KIND_STITCHED), float("nan")),
        ("  ...the same points, forward only", _subset(fwd, _same_points(fwd, both)), float("nan")),
        ("klt_latent on event-integrated latents", k_ev, t_klt),
    ]
    if with_true_klt:
        rows.append(("klt_latent on true 1 ms images (bound)", klt.klt_latent(true_latents(scene), T0_US, T1_US,
                                                                               features=feats), float("nan")))
    for label, tracks, secs in rows:
        timing = "" if not np.isfinite(secs) else f"  {secs:6.3f} s  {events.size / secs / 1e6:5.2f} Mev/s"
        print(f"  {label:42s} {evaluate(tracks, scene)}{timing}")


def _same_points(fwd, stitched) -> np.ndarray:
    """(K_fwd,) bool: forward tracks whose detection starts one of the stitched tracks."""
    from eventcap_track.eklt import KIND_STITCHED

    o, so = fwd.offsets, stitched.offsets
    starts = np.c_[fwd.x[o[:-1]], fwd.y[o[:-1]]]
    keep = np.zeros(fwd.n_tracks, bool)
    for k in np.flatnonzero(stitched.kind == KIND_STITCHED):
        d = np.hypot(starts[:, 0] - stitched.x[so[k]], starts[:, 1] - stitched.y[so[k]])
        keep[np.argmin(d)] = True
    return keep


def _subset(tracks, keep: np.ndarray):
    """The tracks selected by the (K,) bool ``keep``, renumbered."""
    from eventcap_track.eklt import FeatureTracks

    sel = keep[tracks.track_id]
    new_id = np.cumsum(keep) - 1
    return FeatureTracks(tracks.t_us[sel], tracks.x[sel], tracks.y[sel], new_id[tracks.track_id[sel]].astype(np.int32),
                         tracks.cost[sel], tracks.kind[keep], tracks.survived[keep], tracks.height, tracks.width)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default=",".join(SCENES), help=f"comma-separated subset of {SCENES}")
    parser.add_argument("--repeat", type=int, default=2, help="timing repeats (the best is reported)")
    parser.add_argument("--sensor", choices=("default", "harsh"), default="default",
                        help="default: C=0.2, sigma_C=0.03, 100 us refractory, 0.2 Hz noise; harsh: sigma_C=0.06, "
                             "300 us refractory, 5 Hz noise, 1%% hot pixels")
    args = parser.parse_args()
    sensor = SensorConfig(log_eps=LOG_EPS)
    if args.sensor == "harsh":
        sensor = SensorConfig(log_eps=LOG_EPS, threshold_sigma=0.06, refractory_us=300, noise_rate_hz=5.0,
                              hot_pixel_fraction=0.01)
    from eventcap_track import eklt

    # Compile the numba kernels once, outside the timings.
    warm = make_scene("translate_500")
    ev = simulate_events(warm, 0, 2000, SensorConfig(log_eps=LOG_EPS))
    eklt.track(log_image(warm, 0), ev, 0, 2000)
    print(f"sensor: {args.sensor}; times are the best of {args.repeat} on this machine (one core, numba)")
    print("errors: median / p90 over all (track, 1 ms) pairs a track covers; survival: not dropped before its end")
    for name in args.scenes.split(","):
        run_scene(name.strip(), args.repeat, sensor)


if __name__ == "__main__":
    main()
