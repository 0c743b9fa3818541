"""Implementations of the template and synthetic-source stages (imported only when they run)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from eventcap import camera as camera_module
from eventcap.artifacts import BatchPlan
from eventcap.artifacts.recording import EventStream, FrameStack, GroundTruth, Recording
from eventcap.camera import Camera, check_rpg_calibration, look_at, read_rpg_calibration
from eventcap.camera_presets import CameraPreset, load_preset
from eventcap.imaging.render import background
from eventcap.sim.capture import CaptureConfig, simulate_synthetic
from eventcap.sim.events import SensorConfig
from eventcap.sim.frames import FrameConfig
from eventcap.core.stage import StageFailed, check_value, given_fields, given_or_unset


def run_procedural(inputs, config, ctx):
    from eventcap.body.procedural import procedural_template

    height = given_or_unset(config, "height_m")
    ctx.log.info("template: the generic procedural actor (%.2f m%s); for a real person give their height "
                 "(template.height_m=...) or use template=anny with height_m, build and sex", height,
                 "" if config.height_m is not None else ", not stated")
    t = procedural_template(seed=config.seed, height_m=height, target_faces=config.target_faces)
    return {"template": dataclasses.replace(t, stated=tuple(given_fields(config)))}


def run_anny(inputs, config, ctx):
    from eventcap.body.anny import anny_template

    body = {k: given_or_unset(config, k) for k in ("height_m", "build", "muscle", "sex")}
    t = anny_template(**body, seed=config.seed)
    stated = given_fields(config)
    ctx.log.info("template: %s; stated: %s", t.name, ", ".join(stated) if stated else
                 "nothing (ANNY's default body; the body stage estimates the person's)")
    return {"template": dataclasses.replace(t, stated=tuple(stated))}


def run_smpl(inputs, config, ctx):
    from eventcap.body.smpl import load_smpl

    if not config.path:
        raise StageFailed("template=smpl needs template.path=<SMPL model file>", status="missing_file")
    t = load_smpl(config.path, betas=np.asarray(config.betas) if config.betas else None)
    return {"template": dataclasses.replace(t, stated=("shape",))}


def run_mesh(inputs, config, ctx):
    from eventcap.body.mesh import load_mesh_template

    if not config.mesh_path or not config.rig_path:
        raise StageFailed("template=mesh needs template.mesh_path and template.rig_path", status="missing_file")
    return {"template": dataclasses.replace(load_mesh_template(config.mesh_path, config.rig_path), stated=("shape",))}


#: Keys of the synthetic source that default to the camera preset's value when null.
FROM_PRESET = ("width", "height", "lens_mm", "frames", "contrast_threshold", "threshold_sigma", "refractory_us",
               "noise_rate_hz", "leak_rate_hz", "bandwidth", "cutoff_hz_at_1klux")


def resolve_camera(config, where: str = "source") -> tuple[CameraPreset, dict, list[str]]:
    """The camera preset, the effective value of every preset key (explicit keys win over the preset; null means
    "the preset's"), and the keys given explicitly. Every numeric key is checked here, in one place."""
    preset = load_preset(config.camera)
    eff, given = {}, []
    for key in FROM_PRESET:
        value = getattr(config, key)
        eff[key] = getattr(preset, key) if value is None else value
        if value is not None:
            given.append(key)
    eff["camera_distance_m"] = preset.distance_m if config.camera_distance_m is None else config.camera_distance_m
    if config.camera_distance_m is not None:
        given.append("camera_distance_m")
    _check_values(config, eff, where)
    return preset, eff, given


def _check_values(config, eff: dict, where: str = "source") -> None:
    """Every value, those taken from the camera preset (keys left null) included, against the keys' declarations
    (plugins/eventcap_synthetic/spec.py: each bound is stated once, there; a config built in code is checked here
    too), and the ROI against the sensor size; a ValueError names the key (``where.<key>``)."""
    fields = {f.name: f for f in dataclasses.fields(type(config))}
    values = {**{f.name: getattr(config, f.name) for f in fields.values()}, **eff}  # a config built in code too
    for key, value in values.items():
        problem = check_value(fields[key], value) if key in fields else None
        if problem:
            given = getattr(config, key, None) is not None
            raise ValueError(f"{where}.{key}: {problem}" + ("" if given else f" (the camera preset "
                                                                             f"{config.camera!r}'s value)"))
    roi = list(config.roi)
    if roi and (len(roi) != 4 or roi[0] < 0 or roi[1] < 0 or roi[2] < 1 or roi[3] < 1
                or roi[0] + roi[2] > eff["width"] or roi[1] + roi[3] > eff["height"]):
        raise ValueError(f"{where}.roi: expected [x, y, width, height] inside the {eff['width']}x{eff['height']} "
                         f"sensor, got {roi!r}")


def check_config(config, where: str = "source") -> None:
    """The spec's ``check`` hook: run when the pipeline is built, before anything runs (the preset's values and the
    ROI, the motion names, the calibration file; every single key is bounded by its declaration)."""
    resolve_camera(config, where)
    check_motion(config.motion, f"{where}.motion")
    if config.calibration:
        check_rpg_calibration(config.calibration, f"{where}.calibration")


def check_motion(value: str, key: str) -> None:
    """Every name of a ``source.motion`` value is a built-in motion or a clip (a .bvh file, cmu/<trial>; whether its
    file exists is the file settings' check); ValueError naming ``key`` and what is available."""
    import difflib

    from eventcap.body.clips import is_clip, shipped_clips
    from eventcap.body.motions import MOTIONS, STATIC_MOTIONS

    names = [m.strip() for m in str(value).split(",") if m.strip()]
    known = sorted({*MOTIONS, *STATIC_MOTIONS})
    if not names:
        raise ValueError(f"{key}: give at least one motion name ({', '.join(known)}), a .bvh file or a shipped clip "
                         f"(cmu/<subject_trial>), got {value!r}")
    for name in names:
        if is_clip(name):
            if name.startswith("cmu/") and name not in shipped_clips():
                raise ValueError(f"{key}: {name!r} is no shipped clip; shipped: {', '.join(shipped_clips())}")
            continue
        if name not in known:
            close = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
            raise ValueError(f"{key}: unknown motion {name!r} (not a motion name, and not a .bvh file or cmu/<trial>)"
                             f"{f'; did you mean {close[0]!r}?' if close else ''}; motions: {', '.join(known)}")


def camera_for(config, resolved=None) -> Camera:
    """The simulated camera: the preset's (or a calibration file's) intrinsics, looking at the actor from +z.

    The camera stands camera_distance_m in front of the actor at camera_height_m and pitches down by
    camera_tilt_deg; with a ``roi`` it is that region of the sensor, principal point shifted to the region.
    """
    preset, eff, _ = resolve_camera(config) if resolved is None else resolved
    d, h = eff["camera_distance_m"], config.camera_height_m
    eye = (0.0, h, d)
    target = (0.0, h - d * math.tan(math.radians(config.camera_tilt_deg)), 0.0)  # (0, h, 0) when level
    R, t = look_at(eye, target)
    w, hh = int(eff["width"]), int(eff["height"])
    if config.calibration:
        cam = read_rpg_calibration(config.calibration, w, hh, R=R, t=t)
        cam = cam if config.distortion else cam.without_distortion()
    elif preset.calibration is not None and config.lens_mm is None:
        if (w, hh) != (preset.width, preset.height):
            raise ValueError(f"source.width, source.height: the {preset.name} preset's calibration "
                             f"({preset.calibration}) is for {preset.width}x{preset.height} pixels, got {w}x{hh}; "
                             "give source.lens_mm (a pinhole lens) or source.calibration for another size")
        fx, fy, cx, cy, *dist = getattr(camera_module, preset.calibration)
        cam = Camera(w, hh, fx, fy, cx, cy, np.array(dist) if config.distortion else np.zeros(5), R, t)
    else:
        f = eff["lens_mm"] * 1000.0 / preset.pixel_pitch_um
        cam = Camera(w, hh, f, f, (w - 1) / 2.0, (hh - 1) / 2.0, np.zeros(5), R, t)
    if config.roi:
        x0, y0, rw, rh = (int(v) for v in config.roi)
        cam = Camera(rw, rh, cam.fx, cam.fy, cam.cx - x0, cam.cy - y0, cam.dist, cam.R, cam.t)
    return cam


def _scene_background(config, cam: Camera, eff: dict) -> np.ndarray:
    """The backdrop of the whole sensor (cropped to the ROI, so a region sees what the full sensor would)."""
    full = background(config.background, int(eff["height"]), int(eff["width"]), seed=config.background_seed)
    if not config.roi:
        return full
    x0, y0, rw, rh = (int(v) for v in config.roi)
    return np.ascontiguousarray(full[y0:y0 + rh, x0:x0 + rw])


def _log_camera(ctx, config, preset: CameraPreset, eff: dict, given: list[str], cam: Camera, cutoff) -> None:
    roi = f", ROI {list(config.roi)} of {eff['width']}x{eff['height']}" if config.roi else ""
    ctx.log.info(
        "camera %s (%s): %dx%d px%s, fx %.1f fy %.1f px, %s; C %.3g (sigma %.3g), refractory %d us, noise %.3g Hz, "
        "leak %.3g Hz, photoreceptor bandwidth %s", preset.name, preset.sensor, cam.width, cam.height, roi, cam.fx,
        cam.fy, "frames" if eff["frames"] else "no frames (event-only)", eff["contrast_threshold"],
        eff["threshold_sigma"], eff["refractory_us"], eff["noise_rate_hz"], eff["leak_rate_hz"],
        f"on (white pixel {cutoff:.0f} Hz at {config.illuminance_lux:g} lux)" if cutoff else "ideal (off)")
    ctx.log.info("scene: camera %.2f m away, %.2f m high, tilted %.1f deg down; %g lux; %s background (seed %d). "
                 "Given explicitly: %s; the rest from the %s preset", eff["camera_distance_m"], config.camera_height_m,
                 config.camera_tilt_deg, config.illuminance_lux, config.background, config.background_seed,
                 ", ".join(given) or "nothing", preset.name)


def sensor_settings(config, eff: dict) -> tuple[SensorConfig, FrameConfig]:
    """The event sensor's and the frames' settings from the effective values (bandwidth scales with the light)."""
    cutoff = eff["cutoff_hz_at_1klux"] * config.illuminance_lux / 1000.0 if eff["bandwidth"] else None
    sensor = SensorConfig(threshold_pos=eff["contrast_threshold"], threshold_neg=eff["contrast_threshold"],
                          threshold_sigma=eff["threshold_sigma"], refractory_us=int(eff["refractory_us"]),
                          noise_rate_hz=eff["noise_rate_hz"], hot_pixel_fraction=config.hot_pixel_fraction,
                          min_step_us=config.min_step_us, seed=config.seed, leak_rate_hz=eff["leak_rate_hz"],
                          photoreceptor_cutoff_hz=cutoff)
    frames = FrameConfig(fps=config.fps, exposure_us=config.exposure_us, seed=config.seed,
                         illuminance_lux=config.illuminance_lux)
    return sensor, frames


def actor_template(config, ctx=None):
    """The filmed body of a synthetic capture with ``source.actor`` given (an ANNY body; unset keys take ANNY's
    defaults, :class:`~eventcap_synthetic.spec.AnnyConfig`), with its phenotypes as JSON; None when no actor key is
    given (the template is filmed)."""
    from eventcap.body.anny import anny_template

    from .spec import actor_given, anny_defaults

    if not actor_given(config.actor):
        return None, ""
    given = {k: getattr(config.actor, k) for k in ("height_m", "build", "muscle", "sex", "seed")}
    body = {k: (anny_defaults()[k] if v is None else v) for k, v in given.items()}
    try:
        actor = anny_template(**body)
    except ValueError as exc:
        raise ValueError(f"source.actor: {exc}") from None
    if ctx is not None:
        ctx.log.info("actor: the camera films a body of its own, not the template: %s (ANNY; given: %s); the "
                     "recording carries no template, its ground truth is the actor's joints", actor.name,
                     ", ".join(k for k, v in given.items() if v is not None))
    return actor, json.dumps({"model": "anny", **body}, sort_keys=True)


def run_synthetic(inputs, config, ctx):
    actor, actor_json = actor_template(config, ctx)
    template = inputs["template"] if actor is None else actor
    names = [m.strip() for m in config.motion.split(",") if m.strip()]
    if not names:
        raise ValueError("source.motion: give at least one motion name")
    if not config.duration_s * 1e6 >= 1:  # also NaN
        raise ValueError(f"source.duration_s: expected the capture's length in seconds, > 0, got {config.duration_s}")
    preset, eff, given = resolved = resolve_camera(config)
    cam = camera_for(config, resolved)
    sensor, frames = sensor_settings(config, eff)
    _log_camera(ctx, config, preset, eff, given, cam, sensor.photoreceptor_cutoff_hz)
    with_frames = bool(eff["frames"])
    capture = CaptureConfig(
        motions=tuple((n, config.duration_s / len(names)) for n in names), motion_start_s=config.motion_start_s,
        motion_map=config.motion_map, seed=config.seed, speed=config.speed,
        amplitude=config.amplitude, sensor=sensor, frames=frames, gt_rate_hz=config.gt_rate_hz,
        n_track_points=config.n_track_points, supersample=config.supersample,
    )
    cap = simulate_synthetic(template, cam, _scene_background(config, cam, eff), capture, progress=ctx.report)
    ctx.log.info("synthetic capture: %d events (%.2f M/s), %d frames, %d renders in %.1f s", cap.stats["events"],
                 cap.stats["events_per_s"] / 1e6, len(cap.frame_t_us), cap.stats["renders"], cap.stats["total_s"])
    h, w = cam.height, cam.width
    gt = GroundTruth(
        t_us=cap.gt_t_us, poses=cap.gt_poses, joints=cap.gt_joints, landmarks=cap.gt_landmarks,
        frame_poses=cap.frame_poses, frame_joints=cap.frame_joints, sharp_images=cap.sharp_images.astype(np.float32),
        track_tri=cap.track_tri, track_bary=cap.track_bary, track_px=cap.track_px, track_visible=cap.track_visible,
        height=h, width=w,
        # Without frames the sharp images and frame poses no longer sit at the recording's frame times: say when.
        frame_t_us=None if with_frames else cap.frame_t_us.copy(), actor=actor_json,
    )
    frame_stack = FrameStack(images=cap.frame_images.astype(np.float32) / np.float32(255.0), t_us=cap.frame_t_us,
                        exposure_us=cap.frame_exposure_us, height=h, width=w) if with_frames else None
    if not with_frames:
        ctx.log.info("frames=false (source.frames or the camera preset): an event-only recording (the %d simulated frames are left out; batches "
                     "keep their clock)", len(cap.frame_t_us))
    rec = Recording(
        events=EventStream(events=cap.events, width=w, height=h), camera=cam,
        frames=frame_stack, template=template if actor is None else None, ground_truth=gt,
        name=f"synthetic-{'+'.join(Path(n).stem if n.endswith('.bvh') else n.replace('/', '_') for n in names)}"
             f"-seed{config.seed}",
        source=f"synthetic: motion={config.motion} duration_s={config.duration_s} seed={config.seed} "
               f"speed={config.speed} amplitude={config.amplitude}" + ("" if with_frames else " frames=false")
               + (f" motion_start_s={config.motion_start_s}" if config.motion_start_s else "")
               + f" camera={config.camera}" + (f" actor={actor_json}" if actor is not None else ""),
    )
    return {"recording": rec, "batches": BatchPlan.between_frames(cap.frame_t_us)}
