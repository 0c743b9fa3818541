"""Clips with fewer joints play (issue 43, item 4): a 15-joint BVH rig without a neck (hand-written,
tests/fixtures/rig15_no_neck.bvh) or without a chest takes those joints from their neighbours (the neck: the
shoulders' midpoint; the chest: the joint both shoulders hang from), and the retargeted limbs follow the clip's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from eventcap.body.bvh_clip import BvhError, forward_kinematics, read_bvh, resample
from eventcap.body.kinematics import joint_positions
from eventcap.body.retarget import clip_motion, retarget
from eventcap.body.skeleton import DEFAULT_REST_JOINTS, JOINT_INDEX

NO_NECK = Path(__file__).resolve().parent / "fixtures" / "rig15_no_neck.bvh"
#: (ours, the clip's) joints whose lines the retargeted motion must follow
LIMBS = (("l_shoulder", "l_elbow", "LeftArm", "LeftForeArm"), ("l_elbow", "l_wrist", "LeftForeArm", "LeftHand"),
         ("r_shoulder", "r_elbow", "RightArm", "RightForeArm"), ("r_elbow", "r_wrist", "RightForeArm", "RightHand"),
         ("l_hip", "l_knee", "LeftUpLeg", "LeftLeg"), ("l_knee", "l_ankle", "LeftLeg", "LeftFoot"),
         ("r_hip", "r_knee", "RightUpLeg", "RightLeg"), ("r_knee", "r_ankle", "RightLeg", "RightFoot"))


def no_chest(tmp_path) -> Path:
    """The same rig with its chest joint ('Spine') renamed 'Neck' and the head's offset shortened: 15 joints, the
    arms hanging from the neck, no chest."""
    text = NO_NECK.read_text().replace("JOINT Spine", "JOINT Neck").replace("OFFSET 0.00 24.00 0.00",
                                                                          "OFFSET 0.00 10.00 0.00")
    path = tmp_path / "rig15_no_chest.bvh"
    path.write_text(text)
    return path


def limb_angles_deg(path: Path, t: np.ndarray) -> np.ndarray:
    """(T, 8) angle between each retargeted limb and the clip's (world frames agree: the clip is y up, faces +z)."""
    clip = read_bvh(path)
    out = retarget(clip, t)
    J = joint_positions(out.poses, DEFAULT_REST_JOINTS)
    pos, _ = forward_kinematics(clip, *resample(clip, t))
    idx = {n: i for i, n in enumerate(clip.joint_names)}
    ang = []
    for a, b, ca, cb in LIMBS:
        u = J[:, JOINT_INDEX[b]] - J[:, JOINT_INDEX[a]]
        v = pos[:, idx[cb]] - pos[:, idx[ca]]
        cos = np.sum(u * v, axis=1) / np.linalg.norm(u, axis=1) / np.linalg.norm(v, axis=1)
        ang.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    return np.stack(ang, axis=1), out.stats


def test_a_rig_without_a_neck_plays_with_the_neck_from_the_shoulders():
    clip = read_bvh(NO_NECK)
    assert len(clip.joint_names) == 15 and not any("neck" in n.lower() for n in clip.joint_names)
    t = np.linspace(0.0, clip.duration_s, 31)
    ang, stats = limb_angles_deg(NO_NECK, t)
    assert stats["from_neighbours"] == ["spine3", "neck"]
    # the limbs bend as the clip's (hip flexion to 40 degrees, knees to 45, elbows to 70) within a few degrees (measured: median 0.7, at most 2.3)
    assert np.median(ang) < 1.5 and ang.max() < 5.0, np.round(ang.max(axis=0), 1)


def test_a_rig_without_a_chest_plays_with_the_chest_the_shoulders_hang_from(tmp_path):
    path = no_chest(tmp_path)
    clip = read_bvh(path)
    assert len(clip.joint_names) == 15 and "Spine" not in clip.joint_names
    ang, stats = limb_angles_deg(path, np.linspace(0.0, clip.duration_s, 31))
    assert stats["from_neighbours"] == ["spine3"]
    assert np.median(ang) < 1.5 and ang.max() < 5.0, np.round(ang.max(axis=0), 1)


def test_the_clip_plays_through_the_capture_motion_and_a_missing_head_still_stops_it(tmp_path):
    poses = clip_motion(str(NO_NECK), None, duration_s=0.1)(np.linspace(0.0, 0.1, 11))
    assert poses.shape == (11, 33) and np.isfinite(poses).all()
    headless = tmp_path / "headless.bvh"
    headless.write_text(NO_NECK.read_text().replace("JOINT Head", "JOINT Skull"))
    with pytest.raises(BvhError, match=r"headless\.bvh: no joint found for head \(BVH joints: .*motion_map"):
        retarget(read_bvh(headless), np.array([0.0, 0.05]))
