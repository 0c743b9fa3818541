"""Tests of the Template dataclass and the SMPL / scanned-mesh template loaders (stand-in files made here)."""

from __future__ import annotations

import dataclasses
import pickle
import sys
import types

import numpy as np
import pytest
import scipy.sparse
import trimesh

from eventcap.body import kinematics as K
from eventcap.body import skeleton as sk
from eventcap.body.mesh import load_mesh_template
from eventcap.body.smpl import SMPL_NUM_VERTICES, load_smpl
from eventcap.body.template import Template, pattern_albedo
from eventcap.core.stage import StageContext, StageFailed
from eventcap.core.testing import StageConformance

#: The stand-in model lives in SMPL's own placement: pelvis near the origin, feet around y = -1.
SMPL_SHIFT = np.array([0.02, -1.17, 0.01])


def stand_in_body(shift=(0.0, 0.0, 0.0)):
    """A few-hundred-vertex stand-in body: an ellipsoid per bone plus a head, rigged to the default skeleton.

    Returns vertices (V, 3), faces (F, 3) outward CCW, weights (V, 24), joints (24, 3), all shifted by ``shift``.
    """
    rest = sk.DEFAULT_REST_JOINTS
    sphere = trimesh.creation.icosphere(subdivisions=1)
    verts, faces, weights = [], [], []
    parts = [(int(sk.PARENTS[c]), c) for c in range(1, 24)] + [(15, -1)]
    for p, c in parts:
        if c == -1:  # the head: a 0.1 m sphere above the head joint, fully on the head
            centre, axis, half, radius = rest[15] + np.array([0, 0.08, 0.02]), np.array([0, 1.0, 0]), 0.11, 0.095
        else:
            d = rest[c] - rest[p]
            centre, half = 0.5 * (rest[c] + rest[p]), 0.5 * np.linalg.norm(d) + 0.02
            axis = d / np.linalg.norm(d)
            radius = 0.05 if p not in (0, 3, 6, 9) else 0.09
        # Orthonormal frame with the bone axis first.
        a = np.cross(axis, [0.3, 0.5, 0.81])
        a /= np.linalg.norm(a)
        b = np.cross(axis, a)
        local = sphere.vertices
        v = centre + local[:, :1] * half * axis + local[:, 1:2] * radius * a + local[:, 2:3] * radius * b
        f = sphere.faces if np.linalg.det(np.stack([axis, a, b])) > 0 else sphere.faces[:, ::-1]
        w = np.zeros((len(v), 24))
        if c == -1:
            w[:, 15] = 1.0
        else:
            u = np.clip((v - rest[p]) @ axis / np.linalg.norm(rest[c] - rest[p]), 0, 1)
            w[:, p] = 1.0 - 0.3 * u
            w[:, c] += 0.3 * u
        faces.append(f + sum(len(x) for x in verts))
        verts.append(v)
        weights.append(w)
    shift = np.asarray(shift, dtype=np.float64)
    return np.concatenate(verts) + shift, np.concatenate(faces), np.concatenate(weights), rest + shift


def stand_in_smpl_arrays(n_betas: int = 10, seed: int = 0, pad_to: int | None = None) -> dict:
    """SMPL-layout arrays of the stand-in body (placed like SMPL's template), optionally padded to V vertices."""
    rng = np.random.default_rng(seed)
    v, f, w, joints = stand_in_body(SMPL_SHIFT)
    if pad_to is not None:
        extra = pad_to - len(v)
        head = joints[15] + np.array([0, 0.08, 0.02])
        v = np.concatenate([v, head + rng.normal(0, 0.03, (extra, 3))])
        we = np.zeros((extra, 24))
        we[:, 15] = 1.0
        w = np.concatenate([w, we])
    n_v = len(v)
    # Joint regressor: each joint is the mean of its 6 nearest vertices (a sparse, row-stochastic regressor).
    jr = np.zeros((24, n_v))
    for j in range(24):
        near = np.argsort(np.linalg.norm(v - joints[j], axis=1))[:6]
        jr[j, near] = 1.0 / 6
    kintree = np.stack([sk.PARENTS, np.arange(24)]).astype(np.int64)
    kintree[0, 0] = 2**32 - 1  # as in the official files
    return {
        "v_template": v,
        "weights": w,
        "J_regressor": jr,
        "kintree_table": kintree,
        "shapedirs": rng.normal(0, 0.005, (n_v, 3, n_betas)),
        "f": f.astype(np.uint32),
        "posedirs": np.zeros((n_v, 3, 207)),  # present in real files, unused
    }


@pytest.fixture()
def smpl_npz(tmp_path):
    d = stand_in_smpl_arrays()
    path = tmp_path / "SMPL_STANDIN.npz"
    np.savez(path, **d)
    return path, d


def write_fake_chumpy_pickle(path, d: dict, expression: bool = False):
    """Pickle like the official SMPL files: sparse J_regressor, shapedirs as a chumpy Ch (chumpy not needed)."""
    ch_module = types.ModuleType("chumpy.ch")
    reorder_module = types.ModuleType("chumpy.reordering")

    class Ch:
        def __init__(self, x):
            self.x = x
            self.dterms = ["x"]

        def __getstate__(self):
            return dict(self.__dict__)

    class Select(Ch):
        pass

    Ch.__module__, Ch.__qualname__ = "chumpy.ch", "Ch"
    Select.__module__, Select.__qualname__ = "chumpy.reordering", "Select"
    ch_module.Ch = Ch
    reorder_module.Select = Select
    saved = {k: sys.modules.get(k) for k in ("chumpy", "chumpy.ch", "chumpy.reordering")}
    sys.modules.update(
        {"chumpy": types.ModuleType("chumpy"), "chumpy.ch": ch_module, "chumpy.reordering": reorder_module}
    )
    try:
        out = dict(d)
        out["J_regressor"] = scipy.sparse.csc_matrix(d["J_regressor"])
        out["shapedirs"] = (Select if expression else Ch)(d["shapedirs"])
        with open(path, "wb") as fh:
            pickle.dump(out, fh, protocol=2)
    finally:
        for k, m in saved.items():
            if m is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = m


# --- Template ---------------------------------------------------------------------------------------------------


def make_template(**changes) -> Template:
    v, f, w, joints = stand_in_body()
    lj, lo = sk.default_landmarks(joints)
    fields = {
        "name": "standin",
        "rest_joints": joints,
        "vertices": v,
        "faces": f,
        "weights": w,
        "vertex_albedo": pattern_albedo(v, w, joints),
        "landmark_joint": lj,
        "landmark_offset": lo,
    }
    fields.update(changes)
    return Template(**fields)


def test_template_is_valid_and_readonly():
    t = make_template()
    assert t.vertices.dtype == np.float64 and t.faces.dtype == np.int32 and t.vertex_albedo.dtype == np.float32
    assert t.landmark_joint.dtype == np.int64 and t.weights.shape == (t.num_vertices, 24)
    assert 200 < t.num_vertices < 1200
    assert t.signed_volume() > 0  # outward winding
    with pytest.raises(ValueError):
        t.vertices[0, 0] = 1.0
    assert t.rest_landmarks.shape == (25, 3)
    assert np.all((t.vertex_albedo >= 0) & (t.vertex_albedo <= 1)) and np.ptp(t.vertex_albedo) > 0.3


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"vertices": np.zeros((5, 2))}, r"vertices must have shape \(V, 3\)"),
        ({"faces": np.array([[0, 1, 100000]])}, r"face indices must lie in \[0, \d+\]"),
        ({"faces": np.array([[0.0, 1.0, 2.0]])}, "faces must be integer"),
        ({"rest_joints": np.zeros((23, 3))}, r"expected shape \(24, 3\)"),
        ({"vertex_albedo": np.full(5, 0.5)}, r"vertex_albedo must have shape"),
        ({"landmark_offset": np.zeros((24, 3))}, r"landmark_offset must be finite with shape \(25, 3\)"),
        ({"landmark_joint": np.full(25, 30)}, r"landmark_joint entries must lie in \[0, 23\]"),
        ({"name": ""}, "name must be a non-empty string"),
    ],
)
def test_template_validation_errors(changes, message):
    with pytest.raises(ValueError, match=message):
        make_template(**changes)


def test_template_weight_rows_must_sum_to_one():
    _, _, w, _ = stand_in_body()
    bad = w.copy()
    bad[7] *= 1.5
    with pytest.raises(ValueError, match="rows must sum to 1.*vertex 7 sums to 1.5"):
        make_template(weights=bad)
    with pytest.raises(ValueError, match="albedo must lie in"):
        make_template(vertex_albedo=np.full(len(w), 1.5))


def test_template_skins_rigidly_with_zero_pose():
    t = make_template()
    assert np.allclose(K.skin(np.zeros(33), t), t.vertices, atol=1e-14)


# --- SMPL -------------------------------------------------------------------------------------------------------


def test_load_smpl_npz(smpl_npz):
    path, d = smpl_npz
    t = load_smpl(path)
    assert t.name == "smpl:SMPL_STANDIN" and t.num_vertices == len(d["v_template"])
    shift = t.vertices[0] - d["v_template"][0]
    assert np.allclose(t.vertices, d["v_template"] + shift)
    assert t.vertices[:, 1].min() == pytest.approx(0.0, abs=1e-12)  # feet on the floor
    assert np.allclose(t.rest_joints[0, [0, 2]], 0.0, atol=1e-12)  # pelvis above the origin
    assert np.allclose(t.rest_joints, d["J_regressor"] @ t.vertices, atol=1e-12)  # joints regressed
    assert np.allclose(t.weights, d["weights"])
    assert np.array_equal(t.faces, d["f"])  # already outward: kept as is
    # Face landmarks moved onto head vertices, following the head joint.
    for name in ("l_eye", "r_eye", "l_ear", "r_ear", "nose"):
        i = sk.LANDMARK_INDEX[name]
        assert t.landmark_joint[i] == sk.JOINT_INDEX["head"]
        p = t.rest_landmarks[i]
        assert np.min(np.linalg.norm(t.vertices[t.dominant_joint == 15] - p, axis=1)) < 1e-12
    le, re = t.rest_landmarks[sk.LANDMARK_INDEX["l_eye"]], t.rest_landmarks[sk.LANDMARK_INDEX["r_eye"]]
    assert le[0] > re[0]  # left eye on the actor's left (+x)


def test_load_smpl_betas_change_the_shape(smpl_npz):
    path, d = smpl_npz
    betas = np.array([1.5, -0.7, 0.3])
    t0, t1 = load_smpl(path), load_smpl(path, betas=betas)
    expected = d["v_template"] + d["shapedirs"][:, :, :3] @ betas
    assert np.allclose(t1.vertices - t1.vertices[0], expected - expected[0], atol=1e-12)
    assert np.abs(t1.vertices - t0.vertices).max() > 0.005
    assert np.allclose(t1.rest_joints, d["J_regressor"] @ t1.vertices, atol=1e-12)
    with pytest.raises(ValueError, match="has 10 shape coefficients, got 11"):
        load_smpl(path, betas=np.zeros(11))


def test_load_smpl_pkl_with_sparse_and_chumpy(tmp_path, smpl_npz):
    path_npz, d = smpl_npz
    pkl = tmp_path / "basicModel_standin.pkl"
    write_fake_chumpy_pickle(pkl, d)
    assert "chumpy" not in sys.modules
    a, b = load_smpl(path_npz, betas=[0.5]), load_smpl(pkl, betas=[0.5])
    for field in ("rest_joints", "vertices", "faces", "weights", "landmark_offset", "vertex_albedo"):
        assert np.allclose(getattr(a, field), getattr(b, field), atol=1e-12, rtol=0), field


def test_load_smpl_pkl_with_chumpy_expression_explains(tmp_path, smpl_npz):
    _, d = smpl_npz
    pkl = tmp_path / "expr.pkl"
    write_fake_chumpy_pickle(pkl, d, expression=True)
    with pytest.raises(ValueError, match=r"'shapedirs' is a chumpy expression \(chumpy.reordering.Select\).*\.npz"):
        load_smpl(pkl)


def test_load_smpl_errors(tmp_path):
    d = stand_in_smpl_arrays()
    missing = {k: v for k, v in d.items() if k != "J_regressor"}
    np.savez(tmp_path / "missing.npz", **missing)
    with pytest.raises(ValueError, match=r"missing key\(s\) \['J_regressor'\]"):
        load_smpl(tmp_path / "missing.npz")
    bad_tree = dict(d)
    bad_tree["kintree_table"] = d["kintree_table"].copy()
    bad_tree["kintree_table"][0, 12] = 6
    np.savez(tmp_path / "tree.npz", **bad_tree)
    with pytest.raises(ValueError, match=r"not SMPL's 24-joint tree: joint 12 \(neck\) has parent 6, expected 9"):
        load_smpl(tmp_path / "tree.npz")
    (tmp_path / "model.obj").write_text("v 0 0 0\n")
    with pytest.raises(ValueError, match="expected an SMPL model file ending in .npz or .pkl, got '.obj'"):
        load_smpl(tmp_path / "model.obj")
    with pytest.raises(ValueError, match="not found"):
        load_smpl(tmp_path / "nope.npz")
    np.savez(tmp_path / "good.npz", **d)
    with pytest.raises(ValueError, match="albedo: expected 'pattern' or 'uniform', got 'red'"):
        load_smpl(tmp_path / "good.npz", albedo="red")


def test_load_smpl_full_topology_snaps_face_landmarks_to_head(tmp_path):
    d = stand_in_smpl_arrays(pad_to=SMPL_NUM_VERTICES)
    np.savez(tmp_path / "full.npz", **d)
    t = load_smpl(tmp_path / "full.npz", albedo="uniform")
    head = t.vertices[t.dominant_joint == sk.JOINT_INDEX["head"]]
    for name in ("nose", "l_eye", "r_eye", "l_ear", "r_ear"):
        p = t.rest_landmarks[sk.LANDMARK_INDEX[name]]
        assert np.min(np.linalg.norm(head - p, axis=1)) < 1e-9  # on a head vertex
    assert np.all(t.vertex_albedo == 0.5)


def test_smpl_template_poses_consistently(smpl_npz):
    t = load_smpl(smpl_npz[0])
    S = np.zeros((2, 33))
    S[1, sk.DOF_INDEX["l_knee_flex"]] = 1.2
    v = K.skin(S, t)
    lower_leg = t.dominant_joint == sk.JOINT_INDEX["l_knee"]
    assert (v[1, lower_leg, 2] - v[0, lower_leg, 2]).mean() < -0.1  # the shank swings back
    assert np.allclose(v[1, t.dominant_joint == 15], v[0, t.dominant_joint == 15])


# --- scanned mesh + rig -----------------------------------------------------------------------------------------


def write_scan(tmp_path, colours=True, suffix="ply", shift=(0.3, 0.0, -0.2), inward=False):
    v, f, w, joints = stand_in_body(shift)
    if inward:
        f = f[:, ::-1]
    rgb = None
    if colours:
        rgb = np.zeros((len(v), 4), dtype=np.uint8)
        rgb[:, 0] = np.arange(len(v)) % 256
        rgb[:, 1] = 128
        rgb[:, 2] = 255 - np.arange(len(v)) % 256
        rgb[:, 3] = 255
    mesh = trimesh.Trimesh(v, f, vertex_colors=rgb, process=False)
    mesh_path = tmp_path / f"scan.{suffix}"
    mesh.export(mesh_path)
    rig_path = tmp_path / "rig.npz"
    np.savez(rig_path, joints=joints, weights=w, joint_names=np.array(sk.JOINT_NAMES))
    return mesh_path, rig_path, v, f, w, joints, rgb


def test_load_mesh_template_with_vertex_colours(tmp_path):
    mesh_path, rig_path, v, f, _, joints, rgb = write_scan(tmp_path)
    t = load_mesh_template(mesh_path, rig_path)
    shift = t.rest_joints[0] - joints[0]
    assert np.allclose(t.vertices, v + shift, atol=1e-6)  # vertex order kept (PLY stores float32)
    assert np.allclose(t.rest_joints, joints + shift, atol=1e-12)
    assert t.vertices[:, 1].min() == pytest.approx(0.0, abs=1e-9) and abs(t.rest_joints[0, 0]) < 1e-9
    assert np.array_equal(t.faces, f)
    lum = (rgb[:, :3] / 255.0) @ np.array([0.299, 0.587, 0.114])
    assert np.allclose(t.vertex_albedo, lum, atol=1e-6)
    assert t.name == "mesh:scan"


def test_load_mesh_template_obj_without_colours_and_inward_faces(tmp_path):
    mesh_path, rig_path, v, f, *_ = write_scan(tmp_path, colours=False, suffix="obj", inward=True)
    t = load_mesh_template(mesh_path, rig_path, default_albedo=0.4, recentre=False)
    assert np.allclose(t.vertices, v, atol=1e-6)
    assert np.allclose(t.vertex_albedo, 0.4)
    assert t.signed_volume() > 0 and np.array_equal(t.faces, f[:, ::-1])  # flipped back outward


def test_load_mesh_template_uses_rig_landmarks(tmp_path):
    mesh_path, _, _, _, w, joints, _ = write_scan(tmp_path)
    lo = np.full((25, 3), 0.01)
    np.savez(tmp_path / "rig2.npz", joints=joints, weights=w, landmark_offset=lo)
    t = load_mesh_template(mesh_path, tmp_path / "rig2.npz")
    assert np.allclose(t.landmark_offset, lo) and np.array_equal(t.landmark_joint, sk.LANDMARK_JOINT)


def test_load_mesh_template_errors(tmp_path):
    mesh_path, rig_path, v, f, w, joints, _ = write_scan(tmp_path)
    np.savez(tmp_path / "short.npz", joints=joints, weights=w[:-3])
    with pytest.raises(
        ValueError, match=rf"vertex count mismatch: .*scan.ply has {len(v)} vertices .* {len(v) - 3} rows"
    ):
        load_mesh_template(mesh_path, tmp_path / "short.npz")
    names = list(sk.JOINT_NAMES)
    names[4], names[5] = names[5], names[4]
    np.savez(tmp_path / "names.npz", joints=joints, weights=w, joint_names=np.array(names))
    with pytest.raises(ValueError, match="joint 4 is 'r_knee', expected 'l_knee'"):
        load_mesh_template(mesh_path, tmp_path / "names.npz")
    np.savez(tmp_path / "nojoints.npz", weights=w)
    with pytest.raises(ValueError, match="rig is missing key 'joints'"):
        load_mesh_template(mesh_path, tmp_path / "nojoints.npz")
    mm = trimesh.Trimesh(v * 1000, f, process=False)
    mm.export(tmp_path / "mm.ply")
    with pytest.raises(ValueError, match="expected metres"):
        load_mesh_template(tmp_path / "mm.ply", rig_path)
    with pytest.raises(ValueError, match="file not found"):
        load_mesh_template(tmp_path / "none.ply", rig_path)


# --- the template stages (smpl, mesh) -----------------------------------------------------------------------------
class TestSmplStage(StageConformance):
    stage_name = "smpl"
    sensitive = ("betas", [0.5])

    @pytest.fixture(autouse=True)
    def _model(self, tmp_path):
        path = tmp_path / "SMPL_STANDIN.npz"
        np.savez(path, **stand_in_smpl_arrays())
        self.config_overrides = {"path": str(path)}

    def make_inputs(self):
        return {}

    def test_the_stage_gives_the_loaders_template_and_needs_its_file(self):
        t = self.run_once()["template"]
        # a scanned body states its whole shape: the body stage keeps it
        assert t.name == "smpl:SMPL_STANDIN" and t.stated == ("shape",)
        assert t.equals(dataclasses.replace(load_smpl(self.config_overrides["path"]), stated=("shape",)))
        with pytest.raises(StageFailed, match=r"template=smpl needs template.path=<SMPL model file>"):
            self.spec().load_run()({}, self.config(path=""), StageContext(node="template", stage="smpl"))


class TestMeshStage(StageConformance):
    stage_name = "mesh"

    @pytest.fixture(autouse=True)
    def _scan(self, tmp_path):
        mesh_path, rig_path, *_ = write_scan(tmp_path)
        (tmp_path / "other").mkdir()
        other_mesh, *_ = write_scan(tmp_path / "other", shift=(0.0, 0.0, 0.0))
        self.config_overrides = {"mesh_path": str(mesh_path), "rig_path": str(rig_path)}
        self.sensitive = ("mesh_path", str(other_mesh))  # another file: another key (its content is hashed)

    def make_inputs(self):
        return {}

    def test_the_stage_gives_the_loaders_template_and_needs_both_files(self):
        t = self.run_once()["template"]
        assert t.name == "mesh:scan"
        assert t.stated == ("shape",)  # a scanned body states its whole shape: the body stage keeps it
        assert t.equals(dataclasses.replace(load_mesh_template(self.config_overrides["mesh_path"],
                                                               self.config_overrides["rig_path"]), stated=("shape",)))
        with pytest.raises(StageFailed, match=r"template=mesh needs template.mesh_path and template.rig_path"):
            self.spec().load_run()({}, self.config(rig_path=""), StageContext(node="template", stage="mesh"))
