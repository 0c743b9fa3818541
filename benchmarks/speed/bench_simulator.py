"""Benchmark of the simulated event camera: its own cost per render sample, renders and events per second of capture.

Scene: an analytic textured pattern (tests/helpers/edi_scenes.py) (smooth random texture plus sharp-edged blocks) at 240x180, rotating and
translating fast. The render time is measured separately and excluded from the simulator's cost.

    python3 benchmarks/speed/bench_simulator.py [--duration-ms 250] [--render-ms 10]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the scene: tests/helpers

from eventcap.sim.events import SensorConfig, simulate
from eventcap.sim.frames import FrameConfig, simulate_capture
from tests.helpers.edi_scenes import HEIGHT, WIDTH, textured_scene


def run(speed_px_s: float, duration_us: int, sensor: SensorConfig, frames: FrameConfig | None, render_ms: float):
    scene = textured_scene(speed_px_s)
    render_s = [0.0]

    def timed_render(t_us: int) -> np.ndarray:
        t = time.perf_counter()
        img = scene(t_us)
        render_s[0] += time.perf_counter() - t
        return img

    start = time.perf_counter()
    n_events = n_renders = n_forced = n_frames = 0
    if frames is None:
        chunks = simulate(timed_render, 0, duration_us, sensor)
    else:
        chunks = simulate_capture(timed_render, 0, duration_us, sensor, frames)
    for chunk in chunks:
        if frames is not None:
            n_frames += len(chunk.frames)
            chunk = chunk.events
        n_events += chunk.events.size
        n_renders += chunk.n_renders
        n_forced += chunk.n_forced_steps
    total_s = time.perf_counter() - start
    sim_ms = (total_s - render_s[0]) / n_renders * 1e3
    seconds = duration_us * 1e-6
    renders_per_s = n_renders / seconds
    label = "events+frames" if frames is not None else "events"
    print(
        f"{speed_px_s:6.0f} px/s  {label:13s}  sim {sim_ms:5.3f} ms/sample  "
        f"(analytic render {render_s[0] / n_renders * 1e3:5.3f} ms)  {renders_per_s:6.0f} renders/s  "
        f"forced {n_forced / n_renders:4.0%}  {n_events / seconds / 1e6:5.2f} M events/s  frames {n_frames}  "
        f"-> {renders_per_s * (render_ms + sim_ms) / 1e3:5.1f} s per s of capture at {render_ms:g} ms/render"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration-ms", type=int, default=250, help="simulated capture per scenario")
    parser.add_argument("--render-ms", type=float, default=10.0, help="assumed mesh render cost for the projection")
    args = parser.parse_args()
    duration_us = args.duration_ms * 1000
    sensor = SensorConfig()
    # warm-up: numba compilation (or cache load) is not part of the per-sample cost
    list(simulate(textured_scene(100.0), 0, 2_000, sensor))
    print(f"{WIDTH}x{HEIGHT}, {args.duration_ms} ms per scenario, default SensorConfig / FrameConfig")
    for speed in (200.0, 1000.0, 3000.0):
        run(speed, duration_us, sensor, None, args.render_ms)
    run(1000.0, duration_us, sensor, FrameConfig(), args.render_ms)


if __name__ == "__main__":
    main()
