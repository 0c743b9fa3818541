"""Tests of the shared skeleton (eventcap.body.skeleton) and forward kinematics / skinning (kinematics)."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from eventcap.body import kinematics as K
from eventcap.body import skeleton as sk
from eventcap.body.template import Template, pattern_albedo

REST = sk.DEFAULT_REST_JOINTS


def random_poses(n: int, seed: int) -> np.ndarray:
    """Random in-bound poses with arbitrary root rotation and translation, (n, 33)."""
    rng = np.random.default_rng(seed)
    S = np.zeros((n, 33))
    S[:, :27] = rng.uniform(sk.THETA_LOWER, sk.THETA_UPPER, (n, 27))
    S[:, 27:30] = rng.uniform(-np.pi, np.pi, (n, 3))
    S[:, 30:33] = rng.normal(0, 0.5, (n, 3))
    return S


def blob_template(n_vertices: int = 600, seed: int = 0) -> Template:
    """A synthetic template: points scattered around the bones, weights from distance to the joints."""
    rng = np.random.default_rng(seed)
    child = np.arange(1, 24)
    pick = rng.integers(0, 23, n_vertices)
    u = rng.uniform(0, 1, (n_vertices, 1))
    verts = REST[sk.PARENTS[child[pick]]] * (1 - u) + REST[child[pick]] * u + rng.normal(0, 0.04, (n_vertices, 3))
    d = np.linalg.norm(verts[:, None, :] - REST[None], axis=-1)
    w = np.exp(-((d / 0.06) ** 2))
    w /= w.sum(axis=1, keepdims=True)
    faces = rng.integers(0, n_vertices, (2 * n_vertices, 3))
    lj, lo = sk.default_landmarks(REST)
    return Template("blob", REST, verts, faces, w, pattern_albedo(verts, w, REST), lj, lo)


def pose(**dofs) -> np.ndarray:
    S = np.zeros(33)
    for name, value in dofs.items():
        if name in sk.DOF_INDEX:
            S[sk.DOF_INDEX[name]] = value
        else:
            S[27 + (sk.ROOT_ROTATION_NAMES + sk.ROOT_TRANSLATION_NAMES).index(name)] = value
    return S


def J(S, name):
    return K.joint_positions(S, REST)[sk.JOINT_INDEX[name]]


def L(S, name):
    return K.landmark_positions(S, REST)[sk.LANDMARK_INDEX[name]]


# --- skeleton tables ------------------------------------------------------------------------------------------


def test_skeleton_tables():
    assert len(sk.JOINT_NAMES) == 24 and sk.PARENTS.shape == (24,) and sk.PARENTS[0] == -1
    assert all(sk.PARENTS[j] < j for j in range(1, 24))
    assert sk.THETA_LOWER.shape == (27,) and sk.THETA_UPPER.shape == (27,)
    assert np.all(sk.THETA_LOWER < 0.0 + 1e-12) and np.all(sk.THETA_UPPER > 0)  # rest pose is inside
    assert np.all(sk.THETA_LOWER < sk.THETA_UPPER)
    assert np.all(sk.THETA_UPPER - sk.THETA_LOWER < 2 * np.pi)
    counts = {n: int(np.sum(sk.DOF_JOINT == sk.JOINT_INDEX[n])) for n in sk.JOINT_NAMES}
    expected = {
        "spine1": 3,
        "neck": 2,
        "l_collar": 1,
        "r_collar": 1,
        "l_shoulder": 3,
        "r_shoulder": 3,
        "l_elbow": 1,
        "r_elbow": 1,
        "l_hip": 3,
        "r_hip": 3,
        "l_knee": 1,
        "r_knee": 1,
        "l_ankle": 2,
        "r_ankle": 2,
    }
    assert counts == {n: expected.get(n, 0) for n in sk.JOINT_NAMES}
    assert np.allclose(np.abs(sk.DOF_AXIS).sum(axis=1), 1.0)  # signed coordinate axes
    lo, hi = sk.pose_bounds()
    assert lo.shape == (33,) and np.all(np.isinf(lo[27:])) and np.array_equal(hi[:27], sk.THETA_UPPER)
    assert len(sk.LANDMARK_NAMES) == 25 and len(sk.FACE_LANDMARKS) == 4
    assert [sk.LANDMARK_NAMES[i] for i in sk.FACE_LANDMARKS] == ["l_eye", "r_eye", "l_ear", "r_ear"]


def test_default_skeleton_proportions():
    assert REST[[7, 8], 1].min() > 0.0 and REST[[10, 11], 1].min() >= 0.0  # feet above the floor
    assert sk.stature(REST) == pytest.approx(1.75)
    assert np.allclose(REST[:, 0], -REST[sk.MIRROR_JOINTS, 0]) and np.allclose(REST[:, 1:], REST[sk.MIRROR_JOINTS, 1:])
    top = K.landmark_positions(np.zeros(33), REST)[:, 1].max()
    assert 1.6 < top < 1.75


def test_check_rest_joints_error():
    with pytest.raises(ValueError, match=r"expected shape \(24, 3\).*got \(23, 3\)"):
        sk.check_rest_joints(np.zeros((23, 3)))


# --- forward kinematics --------------------------------------------------------------------------------------


def test_zero_pose_is_rest():
    tpl = blob_template()
    assert np.allclose(K.joint_positions(np.zeros(33), REST), REST, atol=1e-14, rtol=0)
    assert np.allclose(K.skin(np.zeros(33), tpl), tpl.vertices, atol=1e-14, rtol=0)
    assert np.allclose(K.landmark_positions(np.zeros(33), tpl), tpl.rest_landmarks, atol=1e-14, rtol=0)
    assert np.allclose(K.global_transforms(np.zeros(33), REST), np.eye(4), atol=1e-15)


def test_shapes_batched_and_unbatched():
    tpl = blob_template()
    S = random_poses(4, 1)
    assert K.joint_positions(S, REST).shape == (4, 24, 3)
    assert K.joint_positions(S[0], REST).shape == (24, 3)
    assert K.landmark_positions(S, tpl).shape == (4, 25, 3)
    assert K.skin(S, tpl).shape == (4, tpl.num_vertices, 3)
    v, n = K.skin(S[1], tpl, normals=True)
    assert v.shape == n.shape == (tpl.num_vertices, 3)
    assert np.allclose(K.skin(S, tpl)[1], v)
    assert np.allclose(n, K.vertex_normals(v, tpl.faces)) and np.allclose(np.linalg.norm(n, axis=1), 1.0)
    assert K.global_transforms(S, REST).shape == (4, 24, 4, 4)


def test_bone_lengths_preserved():
    S = random_poses(50, 2)
    got = sk.bone_lengths(K.joint_positions(S, REST))
    assert np.allclose(got, sk.bone_lengths(REST)[None], atol=1e-12)


def test_transforms_are_rigid():
    G = K.global_transforms(random_poses(10, 3), REST)
    R = G[..., :3, :3]
    assert np.allclose(R @ np.swapaxes(R, -1, -2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    joints = K.joint_positions(random_poses(10, 3), REST)
    # A joint's transform maps its rest position onto its posed position.
    assert np.allclose(np.einsum("tjab,jb->tja", R, REST) + G[..., :3, 3], joints, atol=1e-12)


def test_skinning_rigid_part_moves_with_its_joint():
    # A point fully weighted to one joint moves exactly like a landmark on that joint.
    S = random_poses(6, 4)
    j = sk.JOINT_INDEX["l_wrist"]
    offset = np.array([0.05, -0.02, 0.03])
    w = np.zeros((1, 24))
    w[0, j] = 1.0
    p = K.skin_points(S, REST[j : j + 1] + offset, w, REST)[:, 0]
    q = K.landmark_positions(S, REST, np.array([j]), offset[None])[:, 0]
    assert np.allclose(p, q, atol=1e-12)


def test_root_translation_and_rotation():
    t = np.array([0.3, -0.1, 2.0])
    assert np.allclose(K.joint_positions(pose(root_tx=t[0], root_ty=t[1], root_tz=t[2]), REST), REST + t)
    # Yaw of +90° turns the actor to its left: the face (+z) now points to +x.
    nose = L(pose(root_yaw=np.pi / 2), "nose") - REST[0]
    assert nose[0] > 0.09 and abs(nose[2]) < 1e-12
    assert L(pose(root_pitch=0.3), "nose")[2] > L(pose(), "nose")[2]  # lean forward
    assert J(pose(root_roll=0.3), "head")[0] < -0.1  # lean to the actor's right (-x)


@pytest.mark.parametrize(
    "dof, value, point, axis, sign",
    [
        ("l_knee_flex", 1.0, "l_ankle", 2, -1),  # flexion moves the ankle backwards
        ("r_knee_flex", 1.0, "r_ankle", 2, -1),
        ("l_hip_flex", 0.8, "l_knee", 2, +1),  # thigh forward
        ("r_hip_flex", 0.8, "r_knee", 2, +1),
        ("l_hip_abd", 0.5, "l_knee", 0, +1),  # away from the midline
        ("r_hip_abd", 0.5, "r_knee", 0, -1),
        ("l_hip_rot", 0.5, "l_big_toe", 0, -1),  # internal: toes towards the midline
        ("r_hip_rot", 0.5, "r_big_toe", 0, +1),
        ("l_ankle_flex", 0.3, "l_big_toe", 1, +1),  # dorsiflexion: toes up
        ("l_ankle_inv", 0.3, "l_small_toe", 1, -1),  # inversion: lateral edge down
        ("r_ankle_inv", 0.3, "r_small_toe", 1, -1),
        ("spine_flex", 0.5, "neck", 2, +1),
        ("spine_lat", 0.3, "neck", 0, +1),  # side bend to the actor's left (+x)
        ("spine_twist", 0.5, "l_shoulder", 2, -1),  # chest turns left: left shoulder goes back
        ("neck_flex", 0.5, "nose", 1, -1),
        ("neck_twist", 0.5, "nose", 0, +1),
        ("l_collar_elev", 0.3, "l_shoulder", 1, +1),
        ("r_collar_elev", 0.3, "r_shoulder", 1, +1),
        ("l_shoulder_flex", 0.6, "l_wrist", 2, +1),  # arm forward
        ("r_shoulder_flex", 0.6, "r_wrist", 2, +1),
        ("l_shoulder_elev", 0.6, "l_wrist", 1, +1),  # arm up
        ("r_shoulder_elev", 0.6, "r_wrist", 1, +1),
        ("l_elbow_flex", 1.0, "l_wrist", 2, +1),  # forearm forward
        ("r_elbow_flex", 1.0, "r_wrist", 2, +1),
    ],
)
def test_single_dof_direction(dof, value, point, axis, sign):
    before = L(pose(), point)
    after = L(pose(**{dof: value}), point)
    assert sign * (after[axis] - before[axis]) > 0.01


def test_shoulder_twist_internal_rotation_lowers_flexed_forearm():
    for side in "lr":
        base = {f"{side}_elbow_flex": np.pi / 2}
        y0 = L(pose(**base), f"{side}_wrist")[1]
        y1 = L(pose(**base, **{f"{side}_shoulder_twist": 0.5}), f"{side}_wrist")[1]
        assert y1 < y0 - 0.05


def test_mirror_pose_mirrors_joints():
    S = random_poses(8, 5)
    a = K.landmark_positions(S, REST)
    b = K.landmark_positions(sk.mirror_pose(S), REST)
    mirrored = b[:, sk.MIRROR_LANDMARKS] * np.array([-1.0, 1.0, 1.0])
    assert np.allclose(a, mirrored, atol=1e-12)
    assert np.allclose(sk.mirror_pose(sk.mirror_pose(S)), S)


def test_bad_pose_shape():
    with pytest.raises(ValueError, match=r"expected shape \(T, 33\) or \(33,\), got \(5, 32\)"):
        K.joint_positions(np.zeros((5, 32)), REST)
    with pytest.raises(ValueError, match="33 entries"):
        K.joint_positions(ca.SX.sym("S", 30), REST)
    with pytest.raises(ValueError, match=r"points \(P, 3\) and weights \(P, 24\)"):
        K.skin_points(np.zeros(33), np.zeros((4, 3)), np.zeros((4, 23)), REST)


# --- numpy vs CasADi ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", [ca.SX, ca.MX])
def test_numpy_and_casadi_agree(kind):
    tpl = blob_template(200)
    S = random_poses(10, 6)
    x = kind.sym("S", 33)
    P = kind.sym("P", 30, 3)
    W = kind.sym("W", 30, 24)
    f = ca.Function(
        "f",
        [x, P, W],
        [
            K.joint_positions(x, tpl),
            K.landmark_positions(x, tpl),
            K.skin_points(x, P, W, tpl),
            K.skin_points(x, tpl.vertices[:30], tpl.weights[:30], tpl),
        ],
    )
    jn = K.joint_positions(S, tpl)
    ln = K.landmark_positions(S, tpl)
    vn = K.skin(S, tpl)
    for t in range(S.shape[0]):
        jc, lc, pc, qc = (np.array(o) for o in f(S[t], tpl.vertices[:30], tpl.weights[:30]))
        assert np.abs(jc - jn[t]).max() < 1e-9
        assert np.abs(lc - ln[t]).max() < 1e-9
        assert np.abs(pc - vn[t, :30]).max() < 1e-9
        assert np.abs(qc - vn[t, :30]).max() < 1e-9
    gt = ca.Function("g", [x], K.global_transforms(x, tpl))(S[0])
    assert np.abs(np.stack([np.array(g) for g in gt]) - K.global_transforms(S[0], tpl)).max() < 1e-9


def test_casadi_jacobian_matches_finite_differences():
    x = ca.SX.sym("S", 33)
    lm = K.landmark_positions(x, REST)
    jac = ca.Function("landmark_jacobian", [x], [ca.jacobian(ca.vec(lm), x)])
    S = random_poses(3, 7)
    eps = 1e-6
    for s in S:
        Jc = np.array(jac(s))
        Jn = np.empty_like(Jc)
        for k in range(33):
            d = np.zeros(33)
            d[k] = eps
            # ca.vec stacks column-major: all x, then all y, then all z.
            Jn[:, k] = (K.landmark_positions(s + d, REST).T.ravel() - K.landmark_positions(s - d, REST).T.ravel()) / (
                2 * eps
            )
        assert np.abs(Jc - Jn).max() < 1e-7


def test_symbolic_graph_is_small():
    x = ca.SX.sym("S", 33)
    f = ca.Function("f", [x], [K.joint_positions(x, REST)])
    # Structural zeros fold away: well under the ~24 dense 3x3 products' worth of operations.
    assert f.n_instructions() < 1500


# --- normals --------------------------------------------------------------------------------------------------


def test_vertex_normals_of_a_cube_point_outward():
    import trimesh

    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    n = K.vertex_normals(box.vertices, box.faces)
    assert np.all(np.einsum("vi,vi->v", n, box.vertices) > 0)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
