"""Implementations of the template and synthetic-source stages (imported only when they run)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.recording import EventStream, FrameStack, GroundTruth, Recording
from eventcap.camera import davis240c_default, look_at, read_rpg_calibration
from eventcap.render import textured_background
from eventcap.sim.capture import CaptureConfig, simulate_synthetic
from eventcap.sim.events import SensorConfig
from eventcap.sim.frames import FrameConfig
from eventcap.stage import StageFailed


def run_procedural(inputs, config, ctx):
    from eventcap.body.procedural import procedural_template

    ctx.log.info("template: the generic procedural actor (%.2f m); for a real person give their height "
                 "(template.height_m=...) or use template=anny with height_m, build and sex", config.height_m)
    return {"template": procedural_template(seed=config.seed, height_m=config.height_m,
                                            target_faces=config.target_faces)}


def run_anny(inputs, config, ctx):
    from eventcap.body.anny import anny_template

    return {"template": anny_template(height_m=config.height_m, build=config.build, muscle=config.muscle,
                                      sex=config.sex, seed=config.seed)}


def run_smpl(inputs, config, ctx):
    from eventcap.body.smpl import load_smpl

    if not config.path:
        raise StageFailed("template=smpl needs template.path=<SMPL model file>", status="missing_file")
    return {"template": load_smpl(config.path, betas=np.asarray(config.betas) if config.betas else None)}


def run_mesh(inputs, config, ctx):
    from eventcap.body.mesh import load_mesh_template

    if not config.mesh_path or not config.rig_path:
        raise StageFailed("template=mesh needs template.mesh_path and template.rig_path", status="missing_file")
    return {"template": load_mesh_template(config.mesh_path, config.rig_path)}


def camera_for(config):
    """The simulated camera: DAVIS240C-like default or a calibration file, looking at the actor from +z."""
    eye = (0.0, config.camera_height_m, config.camera_distance_m)
    target = (0.0, config.camera_height_m, 0.0)
    R, t = look_at(eye, target)
    if config.calibration:
        cam = read_rpg_calibration(config.calibration, config.width, config.height, R=R, t=t)
        return cam if config.distortion else cam.without_distortion()
    return davis240c_default(distortion=config.distortion, eye=eye, target=target)


def run_synthetic(inputs, config, ctx):
    template = inputs["template"]
    names = [m.strip() for m in config.motion.split(",") if m.strip()]
    if not names:
        raise ValueError("source.motion: give at least one motion name")
    if not config.duration_s * 1e6 >= 1:  # also NaN
        raise ValueError(f"source.duration_s: expected the capture's length in seconds, > 0, got {config.duration_s}")
    cam = camera_for(config)
    sensor = SensorConfig(threshold_pos=config.contrast_threshold, threshold_neg=config.contrast_threshold,
                          threshold_sigma=config.threshold_sigma, refractory_us=config.refractory_us,
                          noise_rate_hz=config.noise_rate_hz, hot_pixel_fraction=config.hot_pixel_fraction,
                          min_step_us=config.min_step_us, seed=config.seed)
    frames = FrameConfig(fps=config.fps, exposure_us=config.exposure_us, seed=config.seed)
    capture = CaptureConfig(
        motions=tuple((n, config.duration_s / len(names)) for n in names), motion_start_s=config.motion_start_s,
        motion_map=config.motion_map, seed=config.seed, speed=config.speed,
        amplitude=config.amplitude, sensor=sensor, frames=frames, gt_rate_hz=config.gt_rate_hz,
        n_track_points=config.n_track_points, supersample=config.supersample,
    )
    background = textured_background(cam.height, cam.width, seed=config.background_seed)
    cap = simulate_synthetic(template, cam, background, capture, progress=ctx.report)
    ctx.log.info("synthetic capture: %d events (%.2f M/s), %d frames, %d renders in %.1f s", cap.stats["events"],
                 cap.stats["events_per_s"] / 1e6, len(cap.frame_t_us), cap.stats["renders"], cap.stats["total_s"])
    h, w = cam.height, cam.width
    gt = GroundTruth(
        t_us=cap.gt_t_us, poses=cap.gt_poses, joints=cap.gt_joints, landmarks=cap.gt_landmarks,
        frame_poses=cap.frame_poses, frame_joints=cap.frame_joints, sharp_images=cap.sharp_images.astype(np.float32),
        track_tri=cap.track_tri, track_bary=cap.track_bary, track_px=cap.track_px, track_visible=cap.track_visible,
        height=h, width=w,
        # Without frames the sharp images and frame poses no longer sit at the recording's frame times: say when.
        frame_t_us=None if config.frames else cap.frame_t_us.copy(),
    )
    frame_stack = FrameStack(images=cap.frame_images.astype(np.float32) / np.float32(255.0), t_us=cap.frame_t_us,
                        exposure_us=cap.frame_exposure_us, height=h, width=w) if config.frames else None
    if not config.frames:
        ctx.log.info("source.frames=false: an event-only recording (the %d simulated frames are left out; batches "
                     "keep their clock)", len(cap.frame_t_us))
    rec = Recording(
        events=EventStream(events=cap.events, width=w, height=h), camera=cam,
        frames=frame_stack, template=template, ground_truth=gt,
        name=f"synthetic-{'+'.join(Path(n).stem if n.endswith('.bvh') else n.replace('/', '_') for n in names)}"
             f"-seed{config.seed}",
        source=f"synthetic: motion={config.motion} duration_s={config.duration_s} seed={config.seed} "
               f"speed={config.speed} amplitude={config.amplitude}" + ("" if config.frames else " frames=false")
               + (f" motion_start_s={config.motion_start_s}" if config.motion_start_s else ""),
    )
    return {"recording": rec, "batches": BatchPlan.between_frames(cap.frame_t_us)}
