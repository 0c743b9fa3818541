"""Simulated event camera: DVS events and blurred intensity frames from any render function of time."""

from eventcap.sim.events import (
    EventChunk,
    EventSimulator,
    RenderSample,
    SensorConfig,
    hot_pixels,
    pixel_thresholds,
    render_samples,
    simulate,
    simulate_all,
)
from eventcap.sim.frames import (
    CaptureChunk,
    FrameConfig,
    IntensityFrame,
    frame_times_us,
    sensor_readout,
    simulate_capture,
)

__all__ = [
    "CaptureChunk",
    "EventChunk",
    "EventSimulator",
    "FrameConfig",
    "IntensityFrame",
    "RenderSample",
    "SensorConfig",
    "frame_times_us",
    "hot_pixels",
    "pixel_thresholds",
    "render_samples",
    "sensor_readout",
    "simulate",
    "simulate_all",
    "simulate_capture",
]
