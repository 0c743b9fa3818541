"""The synthetic event-camera capture: a simulated actor performing fast motions, filmed by a simulated DAVIS.

Everything here is simulated and says so: a rigged template (:mod:`eventcap.body`) is posed by a motion
(:mod:`eventcap.body.motions`), skinned, rendered over a static textured background (:mod:`eventcap.imaging.render`),
and turned into events and blurred intensity frames by the sensor model (:mod:`eventcap.sim.events`,
:mod:`eventcap.sim.frames`) — one render per sample time, shared by events and frames. Ground truth is exact:
poses, 3D joints and landmarks at the ground-truth rate (1000 fps by default) and at frame times, the true sharp
image at every frame centre, and 2D tracks of surface points with their visibility (to score trackers).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from eventcap.body.kinematics import joint_positions, landmark_positions, skin
from eventcap.body.template import Template
from eventcap.camera import Camera
from eventcap.events import EVENT_DTYPE
from eventcap.imaging.render import Light, pick_surface_points, rasterize, render, surface_points
from eventcap.sim.events import SensorConfig
from eventcap.sim.frames import FrameConfig, simulate_capture

log = logging.getLogger(__name__)

#: Spacing of the tabulated poses that renders interpolate (µs).
POSE_GRID_US = 50
#: Poses evaluated at once: a motion's poses cost a few kB each while they are made (the feet are placed by forward
#: kinematics), so the 1.2 M grid poses of a 60 s capture evaluated in one call peaked at about 4 GB.
POSE_CHUNK = 20_000


def poses_in_chunks(poses_at: Callable[[np.ndarray], np.ndarray], t_s: np.ndarray,
                    chunk: int = POSE_CHUNK) -> np.ndarray:
    """``poses_at(t_s)`` (T, 33), evaluated ``chunk`` times at a time: the same values (a motion's pose at t depends
    on t alone), memory bounded by the chunk instead of the capture's length."""
    t_s = np.asarray(t_s, dtype=np.float64)
    if t_s.size <= chunk:
        return poses_at(t_s)
    return np.concatenate([poses_at(t_s[a:a + chunk]) for a in range(0, t_s.size, chunk)])


@dataclass(frozen=True)
class CaptureConfig:
    """What to film and how (all simulated)."""

    # (motion name, duration in seconds) in order; see eventcap.body.motions.MOTIONS. Or a single recorded clip: a
    # BVH file or a shipped CMU clip "cmu/<subject_trial>" (eventcap.body.clips), retargeted onto the template.
    motions: tuple[tuple[str, float], ...] = (("karate_kick", 1.0),)
    motion_start_s: float = 0.0  # a clip, or a built-in motion's performance, plays from this time into it
    motion_map: str = ""  # a clip's joint-name mapping file (YAML/JSON: BVH joint name -> our joint name); "" = none
    seed: int = 0  # varies the performance (timing, amplitudes, side)
    speed: float = 1.0  # tempo multiplier of the motions
    amplitude: float = 1.0  # excursion multiplier of the motions
    sensor: SensorConfig = field(default_factory=SensorConfig)
    frames: FrameConfig = field(default_factory=FrameConfig)
    gt_rate_hz: float = 1000.0  # rate of the ground-truth poses/joints/tracks
    n_track_points: int = 300  # surface points whose 2D tracks are recorded as ground truth
    supersample: int = 3  # s×s samples per pixel (odd): anti-aliased edges, as a real pixel integrates its area
    light: Light = field(default_factory=Light)

    @property
    def duration_s(self) -> float:
        return float(sum(d for _, d in self.motions))


@dataclass(frozen=True)
class SyntheticCapture:
    """The simulated recording and its exact ground truth (plain arrays; the source stage wraps them)."""

    events: np.ndarray  # (N,) EVENT_DTYPE
    frame_images: np.ndarray  # (n, H, W) uint8, blurred (Eq. 1), noisy, quantised
    frame_t_us: np.ndarray  # (n,) int64 exposure centres
    frame_exposure_us: np.ndarray  # (n,) int64
    sharp_images: np.ndarray  # (n, H, W) float32 linear intensity of the true scene at each frame centre
    gt_t_us: np.ndarray  # (T,) int64
    gt_poses: np.ndarray  # (T, 33)
    gt_joints: np.ndarray  # (T, 24, 3) metres
    gt_landmarks: np.ndarray  # (T, L, 3) metres
    frame_poses: np.ndarray  # (n, 33)
    frame_joints: np.ndarray  # (n, 24, 3)
    track_tri: np.ndarray  # (P,) int32 triangle of each tracked surface point
    track_bary: np.ndarray  # (P, 3) float32 barycentrics
    track_px: np.ndarray  # (T, P, 2) float32 projection of each point (also when hidden)
    track_visible: np.ndarray  # (T, P) bool
    stats: dict


def motion_function(config: CaptureConfig, template: Template) -> Callable[[np.ndarray], np.ndarray]:
    """Pose S (T, 33) at times t (seconds) for the configured motion sequence (feet placed for this template).

    A recorded clip (BVH file or ``cmu/<subject_trial>``) plays alone: retargeted once onto the template on a grid
    at the ground-truth rate (:func:`eventcap.body.retarget.clip_motion`), its first played frame at the origin facing
    the camera. Clips are not mixed with built-in motions in a sequence: the cross-fade of simulated motions assumes
    performances that start where the actor stands, which a recorded clip does not."""
    from eventcap.body.clips import is_clip
    from eventcap.body.motions import sequence_poses

    motions = [(str(n), float(d)) for n, d in config.motions]
    clips = [n for n, _ in motions if is_clip(n)]
    if clips:
        if len(motions) != 1:
            raise ValueError(f"motion: a recorded clip ({clips[0]}) plays alone; it cannot be combined with other "
                             f"motions in a sequence (got {', '.join(n for n, _ in motions)}): film one at a time")
        from eventcap.body.retarget import clip_motion

        return clip_motion(motions[0][0], template, duration_s=config.duration_s, start_s=config.motion_start_s,
                           mapping_path=config.motion_map or None, rate_hz=config.gt_rate_hz)

    def poses(t_s: np.ndarray) -> np.ndarray:  # built-in performances loop: any start time lies inside them
        t = np.asarray(t_s, dtype=np.float64) + float(config.motion_start_s)
        return sequence_poses(motions, t, seed=config.seed, speed=config.speed,
                              amplitude=config.amplitude, template=template)

    return poses


def simulate_synthetic(template: Template, camera: Camera, background: np.ndarray, config: CaptureConfig,
                       progress: Callable[[int, int], None] | None = None) -> SyntheticCapture:
    """Film ``template`` performing ``config.motions`` with ``camera`` (events, frames, exact ground truth)."""
    t_start = time.perf_counter()
    poses_at = motion_function(config, template)
    t1_us = int(round(config.duration_s * 1e6))
    if t1_us <= 0:
        raise ValueError(f"capture duration must be > 0 s, got {config.duration_s}")
    faces, albedo = template.faces, template.vertex_albedo
    # Renders need poses at arbitrary microseconds; evaluating the motion once per render costs ~2 ms, so poses
    # are tabulated every POSE_GRID_US and interpolated linearly (measured error < 1e-7 rad: far below anything
    # visible). Ground truth below is evaluated exactly.
    grid_t = np.arange(0, t1_us + POSE_GRID_US, POSE_GRID_US, dtype=np.int64)
    grid_S = poses_in_chunks(poses_at, grid_t * 1e-6)

    def pose_at(t_us: int) -> np.ndarray:
        i = min(int(t_us // POSE_GRID_US), len(grid_t) - 2)
        w = (t_us - grid_t[i]) / POSE_GRID_US
        return (1.0 - w) * grid_S[i] + w * grid_S[i + 1]

    def render_intensity(t_us: int) -> np.ndarray:
        verts = skin(pose_at(t_us), template)
        return render(camera, verts, faces, albedo, background, config.light, supersample=config.supersample).intensity

    events, images, centres, exposures = [], [], [], []
    n_renders = 0
    for chunk in simulate_capture(render_intensity, 0, t1_us, config.sensor, config.frames):
        events.append(chunk.events.events)
        n_renders += chunk.events.n_renders
        for fr in chunk.frames:
            images.append(fr.image)
            centres.append(fr.t_us)
            exposures.append(fr.exposure_us)
        if progress is not None:
            progress(int(chunk.events.t_end_us), t1_us)
    t_sim = time.perf_counter() - t_start
    ev = np.concatenate(events) if events else np.empty(0, EVENT_DTYPE)
    frame_t = np.asarray(centres, dtype=np.int64)
    sharp = np.stack([render_intensity(int(t)) for t in frame_t]) if len(frame_t) else \
        np.zeros((0, camera.height, camera.width), np.float32)

    # Ground truth at the ground-truth rate, and at frame centres.
    step_us = int(round(1e6 / config.gt_rate_hz))
    gt_t = np.arange(0, t1_us + 1, step_us, dtype=np.int64)
    gt_poses = poses_in_chunks(poses_at, gt_t * 1e-6)
    frame_poses = poses_at(frame_t * 1e-6)
    tri, bary = _pick_track_points(template, camera, poses_at, frame_t if len(frame_t) else gt_t[:1],
                                   config.n_track_points, config.seed)
    px, visible = _track_points(template, camera, gt_poses, tri, bary)
    stats = {
        "renders": n_renders,
        "events": int(ev.size),
        "events_per_s": ev.size / config.duration_s,
        "simulate_s": round(t_sim, 3),
        "total_s": round(time.perf_counter() - t_start, 3),
    }
    return SyntheticCapture(
        events=ev, frame_images=np.stack(images) if images else np.zeros((0, camera.height, camera.width), np.uint8),
        frame_t_us=frame_t, frame_exposure_us=np.asarray(exposures, dtype=np.int64), sharp_images=sharp,
        gt_t_us=gt_t, gt_poses=gt_poses, gt_joints=joint_positions(gt_poses, template.rest_joints),
        gt_landmarks=landmark_positions(gt_poses, template.rest_joints, template.landmark_joint,
                                        template.landmark_offset),
        frame_poses=frame_poses, frame_joints=joint_positions(frame_poses, template.rest_joints),
        track_tri=tri, track_bary=bary.astype(np.float32), track_px=px.astype(np.float32), track_visible=visible,
        stats=stats,
    )


def _pick_track_points(template, camera, poses_at, times_us, n_points, seed):
    """Surface points visible at the intensity frames, spread over the frames (seeded)."""
    rng = np.random.default_rng([seed, 7])
    per = max(1, int(np.ceil(n_points / len(times_us))))
    tris, barys = [], []
    for t in times_us:
        verts = skin(poses_at(np.array([t * 1e-6]))[0], template)
        depth, tri_id, bary = rasterize(camera, verts, template.faces)
        ys, xs = np.nonzero(tri_id >= 0)
        if xs.size == 0:
            continue
        pick = rng.choice(xs.size, size=min(per, xs.size), replace=False)
        # sub-pixel positions inside the chosen pixels
        uv = np.stack([xs[pick], ys[pick]], axis=1) + rng.uniform(-0.4, 0.4, size=(pick.size, 2))
        from eventcap.imaging.render import Render

        rd = Render(intensity=np.zeros_like(depth), depth=depth, tri_id=tri_id, bary=bary)
        tri, b = pick_surface_points(camera, verts, template.faces, rd, uv)
        ok = tri >= 0
        tris.append(tri[ok])
        barys.append(np.clip(b[ok], 0.0, None) / np.clip(b[ok], 0.0, None).sum(axis=1, keepdims=True))
    tri = np.concatenate(tris)[:n_points].astype(np.int32) if tris else np.zeros(0, np.int32)
    bary = np.concatenate(barys)[:n_points] if barys else np.zeros((0, 3))
    return tri, bary


def _track_points(template, camera, poses, tri, bary, chunk=64):
    """Projections (T,P,2) and visibility (T,P) of the surface points at every ground-truth time."""
    T, P = poses.shape[0], tri.shape[0]
    px = np.zeros((T, P, 2))
    vis = np.zeros((T, P), dtype=bool)
    if P == 0:
        return px, vis
    from eventcap.imaging.render import Render

    for a in range(0, T, chunk):
        verts = skin(poses[a:a + chunk], template)
        for i in range(verts.shape[0]):
            depth, tri_id, b = rasterize(camera, verts[i], template.faces)
            rd = Render(intensity=depth, depth=depth, tri_id=tri_id, bary=b)
            sp = surface_points(camera, verts[i], template.faces, tri, bary, rd)
            px[a + i] = np.nan_to_num(sp.pixels, nan=-1.0)
            vis[a + i] = sp.visible
    return px, vis
