"""Recorded motion drives the simulator: BVH clips read, retargeted onto the template, placed and played.

A BVH written by eventcap.export.bvh from known poses comes back to the same poses; Z-up, cm/inch-scaled, Mixamo-named
and mapping-file variants of it (written here from the clip itself) give the same motion; bad files, joints and
start times give errors naming the file and what is wrong; the shipped CMU clips play through the capture.
"""

from __future__ import annotations

import functools
import json
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from eventcap.body import clips
from eventcap.body.bvh_clip import BvhClip, BvhError, forward_kinematics, infer_units, read_bvh
from eventcap.body.kinematics import joint_positions
from eventcap.body.motions import motion_poses
from eventcap.body.retarget import clip_motion, retarget
from eventcap.body.skeleton import DEFAULT_REST_JOINTS, JOINT_NAMES, THETA_LOWER, THETA_UPPER
from eventcap.export.bvh import write_bvh

FPS = 120.0


@functools.lru_cache(maxsize=1)
def truth() -> tuple[np.ndarray, np.ndarray]:
    """0.4 s of simulated jumping jacks at 120 fps: times and poses S."""
    t = np.arange(48) / FPS
    return t, motion_poses("jumping_jack", t, seed=1)


@pytest.fixture(scope="module")
def clip_path(tmp_path_factory):
    t, S = truth()
    return write_bvh(tmp_path_factory.mktemp("bvh") / "jj_cm.bvh", S, DEFAULT_REST_JOINTS, frame_time_s=1 / FPS,
                     scale=100.0)


@functools.lru_cache(maxsize=4)
def fitted(path: str, mapping: str | None = None):
    return retarget(read_bvh(path), truth()[0], mapping_path=mapping)


def write_variant(path, clip: BvhClip, names=None, A=np.eye(3), scale=1.0):
    """The clip as another BVH: joints renamed, axes turned by A (e.g. to z up), lengths scaled, ZYX channels."""
    names = names or clip.joint_names
    children = {j: [k for k in range(len(names)) if clip.parents[k] == j] for j in range(len(names))}
    lines = ["HIERARCHY"]

    def emit(j, depth):
        pad = "  " * depth
        off = A @ clip.offsets[j] * scale
        lines.append(f"{pad}{'ROOT' if j == 0 else 'JOINT'} {names[j]}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}  OFFSET {off[0]:.9f} {off[1]:.9f} {off[2]:.9f}")
        pos = "Xposition Yposition Zposition " if j == 0 else ""
        lines.append(f"{pad}  CHANNELS {6 if j == 0 else 3} {pos}Zrotation Yrotation Xrotation")
        for c in children[j]:
            emit(c, depth + 1)
        if j in clip.end_sites:
            e = A @ clip.end_sites[j] * scale
            lines.extend([f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET {e[0]:.9f} {e[1]:.9f} {e[2]:.9f}",
                          f"{pad}  }}"])
        lines.append(f"{pad}}}")

    emit(0, 0)
    F, J = clip.rotations.shape[:2]
    local = Rotation.from_quat(clip.rotations.reshape(-1, 4)).as_matrix().reshape(F, J, 3, 3)
    euler = Rotation.from_matrix((A @ local @ A.T).reshape(-1, 3, 3)).as_euler("ZYX", degrees=True).reshape(F, -1)
    rows = np.concatenate([(clip.root_positions - clip.offsets[0]) @ A.T * scale, euler], axis=1)
    lines += ["MOTION", f"Frames: {F}", f"Frame Time: {clip.frame_time_s!r}"]
    lines += [" ".join(f"{v:.9f}" for v in row) for row in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def theta_error_deg(S: np.ndarray, ref: np.ndarray) -> np.ndarray:
    return np.degrees(np.abs(S[:, :27] - ref[:, :27]))


# ---------------------------------------------------------------------------------------------------------------


def test_written_clip_comes_back_to_the_same_poses(clip_path):
    t, S = truth()
    out = fitted(str(clip_path))
    err = theta_error_deg(out.poses, S)
    assert err.max() < 1.5 and np.median(err) < 0.05, (err.max(), np.median(err))
    # the whole motion differs from the truth by one rigid placement: a constant yaw and translation
    dyaw = np.degrees(out.poses[:, 27] - S[:, 27])
    assert np.ptp(dyaw) < 0.5 and np.degrees(np.abs(out.poses[:, 28:30] - S[:, 28:30])).max() < 0.5
    J, J0 = joint_positions(out.poses, DEFAULT_REST_JOINTS), joint_positions(S, DEFAULT_REST_JOINTS)
    moved = np.linalg.norm((J - J[:1]) - (J0 - J0[:1]) @ Rotation.from_euler("y", dyaw[0], degrees=True).as_matrix().T,
                           axis=-1)
    assert moved.max() < 0.01, moved.max()  # every joint's path since the first frame, to 1 cm
    assert out.stats["units"] == "cm" and out.stats["up_axis"] == "+y (from the rest pose)"
    assert out.stats["clipped_samples"] == 0


def test_first_sample_faces_the_camera_at_the_origin_feet_on_the_floor(clip_path):
    out = fitted(str(clip_path))
    J = joint_positions(out.poses, DEFAULT_REST_JOINTS)
    mid = 0.5 * (J[0, JOINT_NAMES.index("l_hip")] + J[0, JOINT_NAMES.index("r_hip")])
    assert np.abs(mid[[0, 2]]).max() < 1e-3
    left = J[0, JOINT_NAMES.index("l_hip")] - J[0, JOINT_NAMES.index("r_hip")]
    assert left[0] > 0.15 and abs(left[2]) < 1e-3  # left hip at +x: facing +z
    assert abs(out.stats["lowest_sole_m"]) < 0.01  # this clip stands: its soles are on y = 0


@pytest.mark.parametrize("variant", ["z_up_inch", "y_up_m"])
def test_z_up_and_other_units_give_the_same_motion(tmp_path, clip_path, variant):
    clip = read_bvh(clip_path)
    if variant == "z_up_inch":  # y up -> z up (x stays): (x, y, z) -> (x, -z, y)
        A, scale, unit, axis = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]), 1 / 2.54, "inch", "+z"
    else:
        A, scale, unit, axis = np.eye(3), 0.01, "m", "+y"
    path = write_variant(tmp_path / f"{variant}.bvh", clip, A=A, scale=scale)
    out, ref = fitted(str(path)), fitted(str(clip_path))
    assert out.stats["units"] == unit and out.stats["up_axis"] == f"{axis} (from the rest pose)"
    assert np.abs(out.poses - ref.poses).max() < 1e-4


MIXAMO = {"pelvis": "Hips", "l_hip": "LeftUpLeg", "l_knee": "LeftLeg", "l_ankle": "LeftFoot", "l_foot": "LeftToeBase",
          "spine1": "Spine", "spine2": "Spine1", "spine3": "Spine2", "neck": "Neck", "head": "Head",
          "l_collar": "LeftShoulder", "l_shoulder": "LeftArm", "l_elbow": "LeftForeArm", "l_wrist": "LeftHand",
          "l_hand": "LeftHandIndex1"}


def mixamo_name(ours: str) -> str:
    if ours.startswith("r_"):
        return "mixamorig:" + MIXAMO["l_" + ours[2:]].replace("Left", "Right")
    return "mixamorig:" + MIXAMO[ours]


def test_mixamo_names_are_understood(tmp_path, clip_path):
    clip = read_bvh(clip_path)
    path = write_variant(tmp_path / "mixamo.bvh", clip, names=[mixamo_name(n) for n in clip.joint_names])
    assert np.abs(fitted(str(path)).poses - fitted(str(clip_path)).poses).max() < 1e-6


@pytest.mark.parametrize("fmt", ["yaml", "json"])
def test_a_mapping_file_covers_any_other_convention(tmp_path, clip_path, fmt):
    clip = read_bvh(clip_path)
    names = [f"bone{i:02d}" for i in range(len(clip.joint_names))]
    path = write_variant(tmp_path / "odd.bvh", clip, names=names)
    with pytest.raises(BvhError, match=r"odd\.bvh: no joint found for pelvis, spine3, l_hip.*motion_map"):
        retarget(read_bvh(path), truth()[0])
    table = dict(zip(names, clip.joint_names))
    mapping = tmp_path / f"map.{fmt}"
    mapping.write_text(json.dumps(table) if fmt == "json" else "".join(f"{k}: {v}\n" for k, v in table.items()))
    assert np.abs(fitted(str(path), str(mapping)).poses - fitted(str(clip_path)).poses).max() < 1e-6
    bad = tmp_path / f"bad.{fmt}"
    bad.write_text("bone00: hips\n")
    with pytest.raises(BvhError, match=r"bad\.\w+: entry 'bone00': 'hips' is not one of our joints"):
        retarget(read_bvh(path), truth()[0], mapping_path=str(bad))
    ghost = tmp_path / "ghost.yaml"
    ghost.write_text("Spine9: spine3\n")
    with pytest.raises(BvhError, match=r"ghost\.yaml: BVH joint 'Spine9' is not in .*odd\.bvh"):
        retarget(read_bvh(path), truth()[0], mapping_path=str(ghost))


def test_malformed_files_name_the_file_and_line(tmp_path, clip_path):
    lines = clip_path.read_text().splitlines()
    motion = next(i for i, s in enumerate(lines) if s.startswith("Frame Time")) + 1
    cut = tmp_path / "cut.bvh"
    cut.write_text("\n".join(lines[:-5]) + "\n")
    with pytest.raises(BvhError, match=r"cut\.bvh: .*48 frames.*43"):
        read_bvh(cut)
    short = tmp_path / "short.bvh"
    short.write_text("\n".join(lines[:motion + 3] + [lines[motion + 3].rsplit(" ", 2)[0]] + lines[motion + 4:]) + "\n")
    with pytest.raises(BvhError, match=rf"short\.bvh: line {motion + 4}: "):
        read_bvh(short)
    word = tmp_path / "word.bvh"
    word.write_text("\n".join(lines[:motion + 2] + ["x" + lines[motion + 2]] + lines[motion + 3:]) + "\n")
    with pytest.raises(BvhError, match=rf"word\.bvh: line {motion + 3}: "):
        read_bvh(word)
    hier = tmp_path / "hier.bvh"
    hier.write_text("\n".join(lines[:4] + ["    OFFSET 1 2"] + lines[5:]) + "\n")
    with pytest.raises(BvhError, match=r"hier\.bvh: .*line"):
        read_bvh(hier)
    with pytest.raises(BvhError, match=r"nope\.bvh: BVH file not found"):
        read_bvh(tmp_path / "nope.bvh")


def test_clip_plays_from_its_first_frame_and_motion_start_shifts_it(clip_path):
    default = clip_motion(str(clip_path), None, duration_s=0.1)
    late = clip_motion(str(clip_path), None, duration_s=0.1, start_s=0.2)
    ref = fitted(str(clip_path)).poses  # the clip at its own frames, 0 to 0.39 s
    assert theta_error_deg(default(np.array([0.0])), ref[:1]).max() < 2.0  # a 1 kHz fit against the fit at the clip frames
    assert theta_error_deg(late(np.array([0.0, 0.1])), ref[[24, 36]]).max() < 2.0  # 0.2 s = frame 24
    assert theta_error_deg(late(np.array([0.1])), default(np.array([0.1]))).max() > 5.0  # 0.3 s is not 0.1 s


def test_start_beyond_the_clip_and_too_long_a_capture_are_refused(clip_path):
    with pytest.raises(BvhError, match=r"jj_cm\.bvh: source\.motion_start_s=0\.5 lies outside the clip, which "
                                       r"lasts 0\.392 s \(48 frames at 120\.0 fps\)"):
        clip_motion(str(clip_path), None, duration_s=0.1, start_s=0.5)
    with pytest.raises(BvhError, match=r"jj_cm\.bvh: a capture of 0\.3 s from 0\.2 s is longer than the clip .* "
                                       r"at most 0\.192 s"):
        clip_motion(str(clip_path), None, duration_s=0.3, start_s=0.2)


def test_units_are_inferred_from_the_legs():
    assert infer_units(82.0) == ("cm", 0.01) and infer_units(0.8) == ("m", 1.0) and infer_units(32.0)[0] == "inch"
    assert infer_units(14.5)[0] == "cmu" and infer_units(820.0)[0] == "mm"


# ---------------------------------------------------------------------------------------------------------------
# The shipped CMU clips


def test_shipped_clips_are_listed_and_read_at_120_fps():
    names = clips.shipped_clips()
    assert len(names) >= 6 and all(n.startswith("cmu/") for n in names)
    for n in names:
        c = read_bvh(clips.clip_path(n))
        assert c.fps == pytest.approx(120.0) and c.duration_s >= 2.0 and len(c.joint_names) == 31
    with pytest.raises(FileNotFoundError, match="no such shipped clip; shipped: cmu/"):
        clips.clip_path("cmu/99_99")


@functools.lru_cache(maxsize=1)
def cmu_fit():
    c = read_bvh(clips.clip_path("cmu/05_06"))
    return c, retarget(c, np.arange(0.0, 0.5, 1 / 120))


def test_a_cmu_clip_keeps_the_joint_limits_and_says_what_it_clipped():
    c, out = cmu_fit()
    theta = out.poses[:, :27]
    assert np.all(theta >= THETA_LOWER - 1e-9) and np.all(theta <= THETA_UPPER + 1e-9)
    assert out.stats["units"] == "cmu" and out.stats["up_axis"] == "+y (from the rest pose)"
    assert 0 < out.stats["clipped_samples"] <= out.stats["samples"] and out.stats["clipped_dofs"]
    # the dancer's elbows are matched: the forearm's direction of the truth against the clip's own
    pos, rot = forward_kinematics(c, c.rotations[:60], c.root_positions[:60])
    J = joint_positions(out.poses, DEFAULT_REST_JOINTS)
    for side, (e, w) in {"l": ("LeftForeArm", "LeftHand"), "r": ("RightForeArm", "RightHand")}.items():
        clip_fore = pos[:, c.joint_names.index(w)] - pos[:, c.joint_names.index(e)]
        ours = J[:, JOINT_NAMES.index(f"{side}_wrist")] - J[:, JOINT_NAMES.index(f"{side}_elbow")]
        # placement turns the clip about the vertical (both are y up): compare how far each forearm points up
        up_clip = clip_fore[:, 1] / np.linalg.norm(clip_fore, axis=1)
        up_ours = ours[:, 1] / np.linalg.norm(ours, axis=1)
        assert np.abs(up_clip - up_ours).max() < 0.1


def test_mixing_a_clip_with_built_in_motions_is_refused():
    from eventcap.sim.capture import CaptureConfig, motion_function

    cfg = CaptureConfig(motions=(("karate_kick", 0.5), ("cmu/05_06", 0.5)))
    with pytest.raises(ValueError, match=r"cmu/05_06\) plays alone; it cannot be combined"):
        motion_function(cfg, None)


def test_a_cmu_clip_films_end_to_end():
    from eventcap.body.procedural import procedural_template
    from eventcap.camera import davis240c_default
    from eventcap.imaging.render import textured_background
    from eventcap.sim.capture import CaptureConfig, simulate_synthetic

    tpl = procedural_template(seed=0, target_faces=3000)
    cam = davis240c_default(eye=(0.0, 1.0, 3.0), target=(0.0, 1.0, 0.0))
    cfg = CaptureConfig(motions=(("cmu/90_05", 0.08),), motion_start_s=1.0, n_track_points=20, supersample=1)
    cap = simulate_synthetic(tpl, cam, textured_background(180, 240, seed=0), cfg)
    assert cap.events.size > 500 and cap.gt_poses.shape == (81, 33)
    direct = clip_motion("cmu/90_05", tpl, duration_s=0.08, start_s=1.0)(cap.gt_t_us * 1e-6)
    assert np.abs(cap.gt_poses - direct).max() < 1e-9  # the ground truth is the retargeted clip
    px = cam.project(cap.gt_joints.reshape(-1, 3)).reshape(81, 24, 2)
    assert np.all((px[..., 0] > 0) & (px[..., 0] < 240) & (px[..., 1] > 0) & (px[..., 1] < 180))  # in view


def test_the_clip_file_enters_the_cache_key(tmp_path, clip_path):
    from eventcap.core.config import build_config, file_digests
    from eventcap.core.registry import load_registry

    spec = load_registry().get("synthetic")
    assert file_digests(spec, build_config(spec, {}, "source"), "source") == {}  # built-in motions: no file
    copy = tmp_path / "copy.bvh"
    copy.write_bytes(clip_path.read_bytes())
    a = file_digests(spec, build_config(spec, {"motion": str(copy)}, "source"), "source")
    copy.write_text(copy.read_text().replace("Frame Time: 0.008333333333333333", "Frame Time: 0.01"))
    b = file_digests(spec, build_config(spec, {"motion": str(copy)}, "source"), "source")
    assert set(a) == {"motion"} and a != b
    assert "motion" in file_digests(spec, build_config(spec, {"motion": "cmu/05_06"}, "source"), "source")


def test_simulate_cli_films_a_cmu_clip(tmp_path):
    cmd = [sys.executable, "-m", "eventcap.apps.cli", "simulate", "motion=cmu/135_06", "motion_start_s=0.5",
           "duration_s=0.05", "supersample=1", "n_track_points=10", "hydra.run.dir=runs/sim", "template=procedural",
           "template.target_faces=3000"]
    p = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    log = (tmp_path / "runs" / "sim" / "eventcap.log").read_text()
    assert "motion cmu/135_06: 301 frames at 120.0 fps, units cmu" in log and "up axis +y (from the rest pose)" in log
    assert "played from 0.500 s for 0.050 s" in log and "joint limits clipped" in log
