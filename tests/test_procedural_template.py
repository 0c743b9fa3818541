"""Tests of eventcap.body.procedural: a closed, rigged, textured generated actor that renders sensibly."""

import cv2
import numpy as np
import pytest
import trimesh

from eventcap.body.kinematics import skin
from eventcap.body.procedural import procedural_template
from eventcap.body.skeleton import DOF_INDEX, JOINT_INDEX, LANDMARK_JOINT, LANDMARK_NAMES, PARENTS
from eventcap.body.template import Template
from eventcap.camera import davis240c_default
from eventcap.imaging.render import render, silhouette, textured_background


@pytest.fixture(scope="module")
def actor() -> Template:
    return procedural_template(seed=0)


@pytest.fixture(scope="module")
def small_actor() -> Template:
    return procedural_template(seed=1, height_m=1.6, target_faces=5000)


def _edges(faces):
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def _segment_distance(points, a, b):
    ab = b - a
    h = np.clip((points - a) @ ab / (ab @ ab), 0, 1)
    closest = a + h[:, None] * ab
    return np.linalg.norm(points - closest, axis=1), h, closest


def test_mesh_is_closed_genus0_and_outward(actor):
    m = trimesh.Trimesh(actor.vertices, actor.faces, process=False)
    assert m.is_watertight and m.is_winding_consistent
    assert m.euler_number == 2 and m.body_count == 1
    assert 0.045 < m.volume < 0.09  # m³: a ~65 kg adult
    assert actor.signed_volume() == pytest.approx(m.volume)
    assert m.area_faces.min() > 1e-8


@pytest.mark.parametrize("which, target", [("actor", 12000), ("small_actor", 5000)])
def test_face_count_near_target(which, target, request):
    t = request.getfixturevalue(which)
    assert abs(t.num_faces - target) < 0.15 * target
    assert t.faces.dtype == np.int32 and t.vertex_albedo.dtype == np.float32


@pytest.mark.parametrize("which, height", [("actor", 1.75), ("small_actor", 1.6)])
def test_stature_and_placement(which, height, request):
    t = request.getfixturevalue(which)
    lo, hi = t.vertices.min(axis=0), t.vertices.max(axis=0)
    assert hi[1] == pytest.approx(height, abs=0.015)  # top of the head
    assert -0.006 < lo[1] < 0.01  # soles on the floor
    assert abs(hi[0] + lo[0]) < 0.01  # left/right symmetric T-pose
    assert 0.95 * height < hi[0] - lo[0] < 1.1 * height  # arm span ≈ stature
    assert hi[2] - lo[2] < 0.2 * height  # thin front to back
    np.testing.assert_allclose(t.rest_joints[JOINT_INDEX["head"], 1], 1.56 * height / 1.75)


def test_normals_point_away_from_the_bones(actor):
    """Outward winding, checked per vertex: on the limbs the normal points away from the bone's axis."""
    m = trimesh.Trimesh(actor.vertices, actor.faces, process=False)
    n = m.vertex_normals
    checked = 0
    for joint in ("l_shoulder", "r_elbow", "l_hip", "r_knee"):
        j = JOINT_INDEX[joint]
        child = int(np.flatnonzero(PARENTS == j)[0])
        dist, h, closest = _segment_distance(actor.vertices, actor.rest_joints[j], actor.rest_joints[child])
        sel = (actor.dominant_joint == j) & (h > 0.2) & (h < 0.8)
        assert sel.sum() > 50
        out = actor.vertices[sel] - closest[sel]
        assert np.mean(np.einsum("ij,ij->i", n[sel], out) > 0) > 0.995
        checked += sel.sum()
    assert checked > 500


def test_skinning_weights_valid_dominant_and_smooth(actor):
    W = actor.weights
    assert W.shape == (actor.num_vertices, 24) and W.min() >= 0
    np.testing.assert_allclose(W.sum(axis=1), 1.0, atol=1e-9)
    # Each vertex is dominated by its nearest bone: limb vertices clearly (by ≥ 4 cm) nearer to one bone than to
    # any other, and ≥ 8 cm from its ends, have that bone's joint as their largest weight (> 0.5).
    bones = [(j, int(c)) for c in range(1, 24) for j in [int(PARENTS[c])]]
    dist = np.stack([_segment_distance(actor.vertices, actor.rest_joints[j], actor.rest_joints[c])[0]
                     for j, c in bones], axis=1)
    for joint in ("l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_hip", "r_hip", "l_knee", "r_knee"):
        j = JOINT_INDEX[joint]
        child = int(np.flatnonzero(PARENTS == j)[0])
        b = bones.index((j, child))
        others = np.delete(dist, b, axis=1).min(axis=1)
        from_ends = np.minimum(*(np.linalg.norm(actor.vertices - actor.rest_joints[q], axis=1) for q in (j, child)))
        sel = (dist[:, b] + 0.04 < others) & (from_ends > 0.08)
        assert sel.sum() > 50
        assert np.all(actor.dominant_joint[sel] == j) and np.all(W[sel, j] > 0.5), joint
        assert W[sel, j].mean() > 0.8, joint
    # Smooth across joints: between the two ends of any edge (≈ 2 cm) the weights move by at most 0.5 (L1);
    # the steepest places are the seams between sibling parts (crotch midline, neck/collar), ~0.4–0.47.
    e = _edges(actor.faces)
    diff = np.abs(W[e[:, 0]] - W[e[:, 1]]).sum(axis=1)
    assert diff.max() < 0.5 and np.percentile(diff, 99) < 0.35
    # Blends happen at joints: the elbow region mixes upper arm and forearm.
    near_elbow = np.linalg.norm(actor.vertices - actor.rest_joints[JOINT_INDEX["l_elbow"]], axis=1) < 0.07
    mixed = W[near_elbow][:, [JOINT_INDEX["l_shoulder"], JOINT_INDEX["l_elbow"]]]
    assert np.any((mixed > 0.3).all(axis=1))
    # No leakage between the legs: weights spread along the surface (through the crotch), not across the gap.
    right = [JOINT_INDEX[n] for n in ("r_hip", "r_knee", "r_ankle", "r_foot")]
    x, y = actor.vertices[:, 0], actor.vertices[:, 1]
    assert W[np.ix_((x > 0.03) & (y < 0.7), right)].max() < 0.01  # crotch at ~0.82 m
    assert W[np.ix_((x > 0.03) & (y < 0.6), right)].max() == 0.0


def test_posed_mesh_stays_connected(actor):
    """A 90° elbow and knee bend: no edge collapses or stretches wildly (weights blend over the joint)."""
    e = _edges(actor.faces)
    rest_len = np.linalg.norm(actor.vertices[e[:, 0]] - actor.vertices[e[:, 1]], axis=1)
    S = np.zeros(33)
    S[DOF_INDEX["l_elbow_flex"]] = np.pi / 2
    S[DOF_INDEX["r_knee_flex"]] = np.pi / 2
    V = skin(S, actor)
    ratio = np.linalg.norm(V[e[:, 0]] - V[e[:, 1]], axis=1) / rest_len
    assert 0.1 < ratio.min() and ratio.max() < 2.0
    hand = actor.dominant_joint == JOINT_INDEX["l_hand"]
    assert V[hand, 2].mean() > 0.2  # the forearm swung forward (+z)


def test_landmarks_on_the_head_and_feet(actor):
    np.testing.assert_array_equal(actor.landmark_joint, LANDMARK_JOINT)
    lm = {n: actor.rest_landmarks[i] for i, n in enumerate(LANDMARK_NAMES)}
    for name in ("nose", "l_eye", "r_eye", "l_ear", "r_ear", "l_big_toe", "r_heel"):
        d = np.linalg.norm(actor.vertices - lm[name], axis=1).min()
        assert d < 0.015, name  # on the surface (mesh edges are ~2 cm)
    head = actor.rest_joints[JOINT_INDEX["head"]]
    assert lm["nose"][2] > max(lm["l_eye"][2], lm["l_ear"][2]) and lm["nose"][2] > head[2] + 0.09
    assert lm["l_eye"][0] > 0.02 and lm["r_eye"][0] < -0.02 and lm["l_eye"][2] > head[2] + 0.07
    assert lm["l_ear"][0] > 0.07 and lm["r_ear"][0] < -0.07
    assert lm["l_big_toe"][2] > lm["l_heel"][2] + 0.2


def test_renders_as_an_actor_with_corners(actor):
    cam = davis240c_default()
    r = render(cam, actor.vertices, actor.faces, actor.vertex_albedo, textured_background(180, 240, seed=0))
    mask = silhouette(r)
    assert 0.02 < mask.mean() < 0.1
    ys, xs = np.nonzero(mask)
    # ~87 px tall and as wide (T-pose), centred, feet near the bottom with room to jump and kick.
    assert 80 < ys.max() - ys.min() < 100 and 75 < xs.max() - xs.min() < 100
    assert 60 < ys.min() and ys.max() < 170 and abs(xs.mean() - cam.cx) < 10
    assert 0.05 < r.intensity[mask].mean() < 0.7 and r.intensity[mask].std() > 0.08
    # Texture with corners: Shi–Tomasi finds ≥ 30 with their centres ≥ 1 px inside the body (min distance 3 px;
    # the body covers only ~1,300 px at 4 m on this sensor).
    inner = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8))
    corners = cv2.goodFeaturesToTrack(r.intensity, 300, 0.01, 3, mask=inner)
    assert corners is not None and len(corners) >= 30


def test_seed_determinism(actor, small_actor):
    again = procedural_template(seed=0)
    np.testing.assert_array_equal(again.vertices, actor.vertices)
    np.testing.assert_array_equal(again.vertex_albedo, actor.vertex_albedo)
    np.testing.assert_array_equal(again.weights, actor.weights)
    assert actor.name == "procedural-seed0-1.75m" and small_actor.name == "procedural-seed1-1.60m"


@pytest.mark.parametrize("kwargs, message", [
    ({"height_m": 0.5}, r"height_m must be a human stature in \[1.0, 2.3\] m, got 0.5"),
    ({"target_faces": 100}, r"target_faces must lie in \[2000, 60000\], got 100"),
    ({"blend_m": 0.0}, r"blend_m and weight_softness_m must be positive"),
])
def test_bad_arguments(kwargs, message):
    with pytest.raises(ValueError, match=message):
        procedural_template(**kwargs)
