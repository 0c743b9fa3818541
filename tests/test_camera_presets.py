"""Camera presets and scene keys of the synthetic source: resolution, intrinsics, frames, overrides, clear refusals,
and the default capture left exactly as main's code made it."""

from __future__ import annotations

import functools
import hashlib
import math

import numpy as np
import pytest

from eventcap.body.procedural import procedural_template
from eventcap.camera_presets import load_preset, preset_names
from eventcap.core.config import ConfigError, build_config
from eventcap.imaging.render import BACKGROUNDS, background, textured_background
from eventcap.sim.frames import FrameConfig, sensor_readout
from eventcap.core.stage import StageContext
from eventcap_synthetic._impl import camera_for, resolve_camera, run_synthetic, sensor_settings
from eventcap_synthetic.spec import SYNTHETIC, SyntheticConfig

# (width, height, fx, frames) each preset states: the davis240c keeps the rpg calibration (fx 199.092).
EXPECTED = {
    "davis240c": (240, 180, 199.092, True),
    "davis346": (346, 260, 6.0 / 18.5e-3, True),
    "dvxplorer": (640, 480, 6.0 / 9e-3, False),
    "dvs128": (128, 128, 6.0 / 40e-3, False),
    "evk4": (1280, 720, 6.0 / 4.86e-3, False),
}


@functools.lru_cache(maxsize=1)
def template():
    return procedural_template(seed=0, target_faces=3000)


def tiny(**kw):
    cfg = SyntheticConfig(duration_s=kw.pop("duration_s", 0.09), supersample=1, n_track_points=10, **kw)
    return run_synthetic({"template": template()}, cfg, StageContext(node="source", stage="synthetic"))["recording"]


def sha(a) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()[:16]


def test_every_shipped_preset_is_listed_and_expected():
    assert preset_names() == tuple(sorted(EXPECTED))


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_preset_resolves_to_its_resolution_intrinsics_and_frames(name):
    w, h, fx, frames = EXPECTED[name]
    preset, eff, given = resolve_camera(SyntheticConfig(camera=name))
    cam = camera_for(SyntheticConfig(camera=name))
    assert given == [] and (cam.width, cam.height) == (w, h) and eff["frames"] is frames
    assert cam.fx == pytest.approx(fx, rel=1e-9)
    if name != "davis240c":
        assert cam.fy == cam.fx and (cam.cx, cam.cy) == ((w - 1) / 2, (h - 1) / 2) and not cam.has_distortion
        assert preset.focal_px == pytest.approx(fx)
    # The preset's distance frames the standing actor alike: the 1.75 m actor spans ~64 % of the image height.
    span = 1.75 * cam.fy / eff["camera_distance_m"] / h
    assert 0.58 < span < 0.68, (name, span)


def test_default_capture_is_main_s_capture_bit_for_bit():
    # Values computed by main's code (before presets) for this exact config: 793 events, their sha256, the frames'.
    rec = tiny(motion="fast_wave")
    ev = rec.events.events
    assert ev.size == 793 and sha(ev[:1000]) == "381954c0a06e29bf"
    assert rec.frames.images.shape == (3, 180, 240) and sha(rec.frames.images) == "16d8efbaadbd8aca"
    assert sha(rec.ground_truth.joints) == "9ca5d4e49972d16b" and rec.camera.fx == 199.092
    assert rec.camera.dist.tolist() == [-0.3684, 0.1509, -0.0003, -0.0008, 0.0]


def test_event_only_preset_gives_an_event_only_recording():
    rec = tiny(camera="dvs128", motion="fast_wave", duration_s=0.05)
    assert rec.frames is None and (rec.width, rec.height) == (128, 128) and rec.camera.fx == pytest.approx(150.0)
    assert rec.events.events.size > 0 and rec.ground_truth.frame_t_us is not None
    assert int(rec.events.events["x"].max()) < 128 and "camera=dvs128" in rec.source


def test_explicit_keys_win_over_the_preset():
    cfg = SyntheticConfig(camera="davis346", width=200, height=100, lens_mm=8.0, contrast_threshold=0.3,
                          threshold_sigma=0.0, refractory_us=0, leak_rate_hz=0.0, bandwidth=False, frames=False,
                          camera_distance_m=2.0)
    _, eff, given = resolve_camera(cfg)
    cam = camera_for(cfg)
    assert (cam.width, cam.height) == (200, 100) and cam.fx == pytest.approx(8000 / 18.5)
    assert eff["contrast_threshold"] == 0.3 and eff["frames"] is False and eff["bandwidth"] is False
    assert np.allclose(cam.center, [0.0, 1.0, 2.0])
    assert set(given) == {"width", "height", "lens_mm", "contrast_threshold", "threshold_sigma", "refractory_us",
                          "leak_rate_hz", "bandwidth", "frames", "camera_distance_m"}
    sensor, _ = sensor_settings(cfg, eff)
    assert sensor.threshold_pos == 0.3 and sensor.photoreceptor_cutoff_hz is None and sensor.leak_rate_hz == 0.0


def test_realism_presets_scale_the_bandwidth_with_the_light():
    for lux, white_hz in ((500.0, 1500.0), (10.0, 30.0)):
        cfg = SyntheticConfig(camera="davis346", illuminance_lux=lux)
        sensor, frames = sensor_settings(cfg, resolve_camera(cfg)[1])
        assert sensor.photoreceptor_cutoff_hz == pytest.approx(white_hz) and sensor.leak_rate_hz == 0.1
        assert frames.illuminance_lux == lux
    default = sensor_settings(SyntheticConfig(), resolve_camera(SyntheticConfig())[1])[0]
    assert default.photoreceptor_cutoff_hz is None and default.leak_rate_hz == 0.0  # the suite's ideal pixel


def test_tilt_pitches_the_camera_down_and_level_is_today_s_look_at():
    level = camera_for(SyntheticConfig())
    assert np.allclose(level.R[2], [0.0, 0.0, -1.0])  # looks along -z, level
    tilted = camera_for(SyntheticConfig(camera_tilt_deg=20.0, camera_height_m=2.5))
    assert math.degrees(math.asin(-tilted.R[2][1])) == pytest.approx(20.0)
    assert np.allclose(tilted.center, [0.0, 2.5, 3.0])


def test_roi_is_the_region_of_the_full_sensor():
    full = camera_for(SyntheticConfig(camera="evk4"))
    roi = camera_for(SyntheticConfig(camera="evk4", roi=[400, 100, 480, 520]))
    pts = np.array([[0.0, 1.0, 0.0], [0.3, 1.5, 0.2], [-0.2, 0.4, 0.0]])
    assert (roi.width, roi.height) == (480, 520)
    np.testing.assert_allclose(roi.project(pts), full.project(pts) - [400, 100], atol=1e-9)


def test_backgrounds():
    assert BACKGROUNDS == SYNTHETIC.config.__dataclass_fields__["background"].metadata["choices"]
    tex = background("textured", 90, 120, seed=3)
    np.testing.assert_array_equal(tex, textured_background(90, 120, seed=3))
    low = background("low_texture", 90, 120, seed=3)
    assert low.std() == pytest.approx(0.25 * tex.std(), rel=1e-4) and low.mean() == pytest.approx(tex.mean(), abs=1e-6)
    plain = background("plain", 90, 120)
    assert plain.dtype == np.float32 and plain.shape == (90, 120) and np.ptp(plain) == 0
    with pytest.raises(ValueError, match="textured | low_texture | plain"):
        background("carpet", 90, 120)


def test_dim_light_makes_noisier_frames_and_bright_light_changes_nothing():
    img = np.full((64, 64), 0.5)
    ref = sensor_readout(img, FrameConfig())
    np.testing.assert_array_equal(ref, sensor_readout(img, FrameConfig(illuminance_lux=5000.0)))
    dim = sensor_readout(img, FrameConfig(illuminance_lux=50.0)).astype(float)
    # shot noise x sqrt(10) and read noise x 10: std 2.7 -> 12.9 DN, same mean
    assert 4.0 < dim.std() / ref.astype(float).std() < 5.5 and abs(dim.mean() - ref.mean()) < 1.0


@pytest.mark.parametrize("key, value, message", [
    ("contrast_threshold", float("nan"), "source.contrast_threshold: expected a finite number > 0"),
    ("contrast_threshold", 0.0, "source.contrast_threshold: expected a finite number > 0"),
    ("lens_mm", -4.0, "source.lens_mm: expected a finite number > 0"),
    ("camera_distance_m", float("inf"), "source.camera_distance_m: expected a finite number > 0"),
    ("illuminance_lux", 0.0, "source.illuminance_lux: expected a finite number > 0"),
    ("cutoff_hz_at_1klux", float("nan"), "source.cutoff_hz_at_1klux: expected a finite number > 0"),
    ("leak_rate_hz", -0.1, "source.leak_rate_hz: expected a finite number >= 0"),
    ("noise_rate_hz", float("inf"), "source.noise_rate_hz: expected a finite number >= 0"),
    ("threshold_sigma", -0.01, "source.threshold_sigma: expected a finite number >= 0"),
    ("camera_tilt_deg", 90.0, r"source.camera_tilt_deg: expected a finite number in \[-89, 89\]"),
    ("camera_height_m", 0.0, "source.camera_height_m: expected a finite number > 0"),
    ("width", 0, r"source.width: expected an integer in \[1, 65535\]"),
    ("refractory_us", -5, "source.refractory_us: expected an integer >= 0"),
    ("supersample", 2, "source.supersample: expected an odd integer"),
    ("roi", [1200, 0, 200, 100], r"source.roi: expected \[x, y, width, height\] inside the 1280x720 sensor"),
])
def test_bad_values_are_refused_naming_the_key(key, value, message):
    with pytest.raises(ValueError, match=message):
        camera_for(SyntheticConfig(camera="evk4", **{key: value}))


def test_calibrated_preset_refuses_another_size_without_a_lens():
    with pytest.raises(ValueError, match=r"source.width, source.height: the davis240c preset's calibration"):
        camera_for(SyntheticConfig(width=320, height=240))
    cam = camera_for(SyntheticConfig(width=320, height=240, lens_mm=3.68))
    assert (cam.width, cam.height) == (320, 240) and cam.fx == pytest.approx(3680 / 18.5)


def test_unknown_preset_is_refused_when_the_config_is_built():
    with pytest.raises(ConfigError, match=r"source.camera: expected one of davis240c \| davis346 .*did you mean "
                                          r"'davis346'"):
        build_config(SYNTHETIC, {"camera": "davis364"}, "source")


def test_a_broken_preset_file_names_the_file_and_key(tmp_path, monkeypatch):
    import eventcap.camera_presets as cp

    text = (cp.PRESET_DIR / "dvs128.yaml").read_text().replace("pixel_pitch_um: 40.0", "pixel_pitch_um: -40.0")
    (tmp_path / "broken.yaml").write_text(text)
    monkeypatch.setattr(cp, "PRESET_DIR", tmp_path)
    with pytest.raises(ValueError, match=r"broken.yaml: pixel_pitch_um: expected a finite number > 0, got -40.0"):
        load_preset("broken")
    (tmp_path / "short.yaml").write_text("width: 10\n")
    with pytest.raises(ValueError, match=r"short.yaml: expected the keys .* missing \['sensor', 'height'"):
        load_preset("short")
