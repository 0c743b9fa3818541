"""Camera presets of the synthetic capture: what a real event camera is, read from data files with citations.

Each preset is one YAML file in ``eventcap/assets/cameras/`` (the citations are comments there): the sensor's
resolution and pixel pitch, a typical lens (or a named public calibration), whether it has intensity frames, where
the synthetic camera stands, and its threshold, refractory, noise, leak and photoreceptor-bandwidth figures. This
module only reads and checks them; the synthetic source decides what a user's explicit keys override.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from pathlib import Path

PRESET_DIR = Path(__file__).resolve().parent / "assets" / "cameras"

#: Calibrations a preset may name instead of a lens (``calibration: NAME``): attributes of :mod:`eventcap.camera`.
NAMED_CALIBRATIONS = ("DAVIS240C_CALIBRATION",)


@dataclass(frozen=True)
class CameraPreset:
    """One camera preset (see the YAML files for the sources of every figure)."""

    name: str
    sensor: str  # maker and model, for the log
    width: int  # pixels
    height: int  # pixels
    pixel_pitch_um: float
    lens_mm: float  # focal length: fx = fy = lens_mm / pixel pitch (unless ``calibration`` names one)
    calibration: str | None  # a name in NAMED_CALIBRATIONS, or None for a pinhole from lens_mm
    frames: bool  # False: an event-only camera (no intensity frames)
    distance_m: float  # default camera distance of the synthetic capture
    contrast_threshold: float  # natural-log units
    threshold_sigma: float  # per-pixel spread, log units
    refractory_us: int
    noise_rate_hz: float  # background activity per pixel
    leak_rate_hz: float  # leak events per pixel (ON), 0 = none
    bandwidth: bool  # photoreceptor low-pass on/off
    cutoff_hz_at_1klux: float  # cutoff of a white pixel at 1000 lux scene illuminance

    @property
    def focal_px(self) -> float:
        """fx = fy of the preset's lens in pixels (lens_mm / pixel pitch)."""
        return self.lens_mm * 1000.0 / self.pixel_pitch_um


def preset_names() -> tuple[str, ...]:
    """Names of the shipped presets (file stems), sorted."""
    return tuple(sorted(p.stem for p in PRESET_DIR.glob("*.yaml")))


def load_preset(name: str) -> CameraPreset:
    """The preset ``name`` (e.g. ``davis346``), checked; a clear error names the file and the key."""
    import yaml

    path = PRESET_DIR / f"{name}.yaml"
    if not path.is_file():
        raise ValueError(f"camera preset {name!r}: unknown; expected one of {', '.join(preset_names())}")
    data = yaml.safe_load(path.read_text()) or {}
    names = [f.name for f in fields(CameraPreset) if f.name != "name"]
    data.setdefault("calibration", None)  # optional: most presets are a pinhole from lens_mm
    missing = [k for k in names if k not in data]
    extra = [k for k in data if k not in names]
    if missing or extra:
        raise ValueError(f"{path}: expected the keys {', '.join(names)}; missing {missing}, unknown {extra}")
    preset = CameraPreset(name=name, **data)
    _check(preset, path)
    return preset


def _check(p: CameraPreset, path: Path) -> None:
    def bad(key, expected):
        raise ValueError(f"{path}: {key}: expected {expected}, got {getattr(p, key)!r}")

    for key in ("width", "height", "refractory_us"):
        v = getattr(p, key)
        if isinstance(v, bool) or not isinstance(v, int) or v < (0 if key == "refractory_us" else 1):
            bad(key, "a non-negative integer" if key == "refractory_us" else "a positive integer")
    for key in ("pixel_pitch_um", "lens_mm", "distance_m", "contrast_threshold", "cutoff_hz_at_1klux"):
        v = getattr(p, key)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
            bad(key, "a finite number > 0")
    for key in ("threshold_sigma", "noise_rate_hz", "leak_rate_hz"):
        v = getattr(p, key)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v >= 0):
            bad(key, "a finite number >= 0")
    for key in ("frames", "bandwidth"):
        if not isinstance(getattr(p, key), bool):
            bad(key, "true or false")
    if p.calibration is not None and p.calibration not in NAMED_CALIBRATIONS:
        bad("calibration", f"null or one of {', '.join(NAMED_CALIBRATIONS)}")
