"""Simulated intensity (APS) frames of a DAVIS-like camera by the paper's Eq. 1, sharing renders with the events.

This is a *simulator*: the frames are synthetic. Frame k is centred at ``t_k`` and exposed over
``[t_k - T//2, t_k - T//2 + T]`` (T = ``exposure_us``; symmetric for even T). Its noise-free value is the
exposure average of the linear latent intensity, ``(1/T) ∫ I(t) dt`` (Eq. 1 with I = exp(L)), integrated with
the trapezoid rule over the render samples of the event simulator. The exposure boundaries are forced to be
samples, and inside an exposure the step is at most ``T / min_samples_per_exposure``. Why that is dense enough:
the adaptive sampling already bounds every pixel's log change between samples by a fraction of C (0.1 by default,
~10 % intensity change) or, for fast sharp edges, the step by ``min_step_us`` (200 µs: 0.2 px at 1000 px/s, 2 % of
a 10 ms exposure), so a moving edge blurs into a smooth ramp, not a row of ghost copies (docs/results/
implementation.md). The minimum count only matters for slowly changing scenes
whose adaptive step would otherwise span the whole exposure.

Sensor readout (documented model, not a calibrated one): the average intensity is taken as a fraction of the
full well, so a pixel collects ``I * full_well_electrons`` photo-electrons (auto-exposure: white saturates) in a
scene lit at ``full_well_lux`` or brighter, and proportionally fewer in dimmer light (``illuminance_lux``), with the
gain raised so that white stays at 255;
shot noise is Poisson in electrons; read noise is Gaussian with ``read_noise_dn`` digital numbers std; the result
is quantised linearly (no gamma: the DAVIS APS readout is linear) to 8 bits with clipping.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from eventcap.sim.events import EventChunk, RenderSample, SensorConfig, _require_int, simulate


@dataclass(frozen=True)
class FrameConfig:
    """Parameters of the simulated intensity frames (defaults: DAVIS240C APS at 25 fps in indoor light)."""

    # Frame rate, frames per second; DAVIS APS frames run at 7-25 fps in the paper's setting.
    fps: float = 25.0
    # Exposure time T in µs. Indoor DAVIS exposures are ~5-20 ms (our real DAVIS346 file: 4.8 ms in a bright lab);
    # 10 ms blurs a limb moving at 5 m/s at 3 m (~330 px/s with f = 200 px) over ~3 px, the paper's "severe motion
    # blur" for fast motions, while slow motions stay sharp. Must not exceed the frame period.
    exposure_us: int = 10_000
    # Minimum number of render samples inside one exposure (step <= T / this), so slow changes integrate smoothly.
    min_samples_per_exposure: int = 16
    # Photo-electrons of a white (I = 1) pixel over the exposure: shot-noise std is sqrt(I * this) electrons, i.e.
    # 2.5 DN at I = 0.5. None disables shot noise.
    full_well_electrons: float | None = 5000.0
    # Std of the Gaussian read noise in 8-bit digital numbers (DN); 0 disables it.
    read_noise_dn: float = 1.0
    # Scene illuminance (lux) and the illuminance at which a white pixel collects full_well_electrons (auto exposure
    # and gain hold white at full scale from there up: brighter scenes look the same). Below it a white pixel
    # collects proportionally fewer electrons and the gain rises to keep white at 255: shot noise grows as
    # 1/sqrt(light) relative to the signal and the read noise, fixed in electrons, grows as 1/light in DN. The
    # exposure time stays exposure_us (set it longer for a dim scene, as an auto-exposure would, with more blur).
    illuminance_lux: float = 500.0
    full_well_lux: float = 500.0
    # Seed of the readout noise (frame k uses a generator derived from (seed, k)).
    seed: int = 0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"FrameConfig.fps: expected a finite number > 0, got {self.fps!r}")
        for name in ("exposure_us", "min_samples_per_exposure", "seed"):
            _require_int(f"FrameConfig.{name}", getattr(self, name))
        if self.exposure_us < 1:
            raise ValueError(f"FrameConfig.exposure_us: expected >= 1 µs, got {self.exposure_us}")
        if self.exposure_us > self.period_us:
            raise ValueError(
                f"FrameConfig.exposure_us: expected at most the frame period {self.period_us:.0f} µs "
                f"(fps={self.fps}), got {self.exposure_us}"
            )
        if self.min_samples_per_exposure < 1:
            raise ValueError(
                f"FrameConfig.min_samples_per_exposure: expected >= 1, got {self.min_samples_per_exposure}"
            )
        if self.full_well_electrons is not None and not (
            math.isfinite(self.full_well_electrons) and self.full_well_electrons > 0
        ):
            raise ValueError(
                f"FrameConfig.full_well_electrons: expected None or a finite number > 0, got {self.full_well_electrons!r}"
            )
        for name in ("illuminance_lux", "full_well_lux"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"FrameConfig.{name}: expected a finite number > 0, got {value!r}")
        if not (math.isfinite(self.read_noise_dn) and self.read_noise_dn >= 0):
            raise ValueError(f"FrameConfig.read_noise_dn: expected a finite number >= 0, got {self.read_noise_dn!r}")

    @property
    def light_fraction(self) -> float:
        """Fraction of the full well a white pixel collects in this light (1 at full_well_lux and above)."""
        return min(1.0, self.illuminance_lux / self.full_well_lux)

    @property
    def period_us(self) -> float:
        """Frame period in µs (not rounded; frame times are rounded individually so they do not drift)."""
        return 1e6 / self.fps


@dataclass(frozen=True)
class IntensityFrame:
    """One simulated intensity frame."""

    image: np.ndarray  # (height, width) uint8, linear 8-bit readout with noise
    t_us: int  # centre of the exposure, µs
    exposure_us: int  # exposure time T, µs
    mean_intensity: np.ndarray  # (height, width) float32 noise-free Eq. 1 average in [0, 1] (ground truth)


@dataclass(frozen=True)
class CaptureChunk:
    """One stretch of a simulated capture: its events and the frames whose exposure ended in it."""

    events: EventChunk
    frames: tuple[IntensityFrame, ...]


def frame_times_us(t0_us: int, t1_us: int, config: FrameConfig) -> np.ndarray:
    """Centres (int64 µs) of the frames whose whole exposure lies in [t0_us, t1_us]: the first exposure starts
    at t0_us, then one frame per period (times rounded to µs individually)."""
    half = config.exposure_us // 2
    n = math.floor((t1_us - t0_us - config.exposure_us) / config.period_us) + 1
    if n <= 0:
        return np.empty(0, np.int64)
    centres = t0_us + half + np.round(np.arange(n) * config.period_us).astype(np.int64)
    return centres[centres - half + config.exposure_us <= t1_us]


def sensor_readout(
    mean_intensity: np.ndarray, config: FrameConfig, rng: np.random.Generator | None = None
) -> np.ndarray:
    """8-bit APS readout of an exposure-averaged linear intensity (H, W) in [0, 1]: shot + read noise, quantise.

    ``rng`` defaults to a generator seeded with ``config.seed``. Returns (H, W) uint8."""
    if rng is None:
        rng = np.random.default_rng(config.seed)
    signal = np.clip(np.asarray(mean_intensity, np.float64), 0.0, 1.0)
    light = config.light_fraction  # exactly 1.0 at and above full_well_lux: the arithmetic below is then unchanged
    if config.full_well_electrons is not None:
        electrons = config.full_well_electrons * light
        signal = rng.poisson(signal * electrons) / electrons
    dn = signal * 255.0
    if config.read_noise_dn > 0:
        dn = dn + rng.normal(0.0, config.read_noise_dn / light, size=dn.shape)
    return np.clip(np.rint(dn), 0, 255).astype(np.uint8)


class _ExposureIntegrator:
    """Trapezoid-rule exposure averages over the render samples, one frame at a time, in time order."""

    def __init__(self, centres_us: np.ndarray, config: FrameConfig) -> None:
        self.config = config
        self.centres = centres_us
        self.starts = centres_us - config.exposure_us // 2
        self.ends = self.starts + config.exposure_us
        self.k = 0  # next frame to finish
        self.acc: np.ndarray | None = None
        self.prev: RenderSample | None = None
        self.finished: list[IntensityFrame] = []

    def max_step_us_at(self, t_us: int) -> int:
        """Step bound from sample time t_us: dense inside an exposure, unbounded outside."""
        k = self.k
        if k < self.centres.size and self.starts[k] <= t_us < self.ends[k]:
            return max(1, self.config.exposure_us // self.config.min_samples_per_exposure)
        return np.iinfo(np.int64).max

    def add(self, sample: RenderSample) -> None:
        k, prev = self.k, self.prev
        self.prev = sample
        if k >= self.centres.size:
            return
        if sample.t_us == self.starts[k]:
            self.acc = np.zeros(sample.intensity.shape, np.float64)
        elif self.acc is not None and prev is not None:
            # exposure boundaries are samples, so an interval is either wholly inside an exposure or outside
            dt = sample.t_us - prev.t_us
            self.acc += 0.5 * dt * (prev.intensity.astype(np.float64) + sample.intensity)
        if sample.t_us == self.ends[k] and self.acc is not None:
            mean = (self.acc / self.config.exposure_us).astype(np.float32)
            rng = np.random.default_rng([self.config.seed, k])
            self.finished.append(
                IntensityFrame(
                    sensor_readout(mean, self.config, rng), int(self.centres[k]), self.config.exposure_us, mean
                )
            )
            self.acc = None
            self.k += 1
            if self.k < self.centres.size and self.starts[self.k] == sample.t_us:
                self.acc = np.zeros(sample.intensity.shape, np.float64)  # back-to-back exposures share a boundary

    def pop_finished(self) -> tuple[IntensityFrame, ...]:
        out, self.finished = tuple(self.finished), []
        return out


def simulate_capture(
    render: Callable[[int], np.ndarray],
    t0_us: int,
    t1_us: int,
    sensor_config: SensorConfig | None = None,
    frame_config: FrameConfig | None = None,
    *,
    chunk_us: int = 10_000,
) -> Iterator[CaptureChunk]:
    """Simulate events and intensity frames over [t0_us, t1_us] in one pass over time (one render per sample).

    Frames are placed by :func:`frame_times_us`. Yields :class:`CaptureChunk` s in time order; each frame
    appears in the chunk during which its exposure ended. ``None`` configs mean the defaults.
    """
    sensor_config = SensorConfig() if sensor_config is None else sensor_config
    frame_config = FrameConfig() if frame_config is None else frame_config
    centres = frame_times_us(int(t0_us), int(t1_us), frame_config)
    integrator = _ExposureIntegrator(centres, frame_config)
    boundaries = np.concatenate([integrator.starts, integrator.ends]).tolist()
    for chunk in simulate(
        render,
        t0_us,
        t1_us,
        sensor_config,
        chunk_us=chunk_us,
        required_t_us=boundaries,
        max_step_us_at=integrator.max_step_us_at,
        on_sample=integrator.add,
    ):
        yield CaptureChunk(chunk, integrator.pop_finished())
