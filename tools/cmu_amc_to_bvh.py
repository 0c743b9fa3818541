"""Regenerate a shipped CMU clip (eventcap/body/assets/cmu/*.bvh) from the CMU database's original ASF/AMC files.

The output is the BVH that B. Hahne's 2010 MotionBuilder-friendly conversion (cgspeed; the one mirrored in
una-dinosauria/cmu-mocap) holds for the same frames, without its added T-pose frame: the same joint names and
hierarchy, the subject's bone vectors as OFFSETs, ``Zrotation Yrotation Xrotation`` channels, lengths in the CMU
unit (1/0.45 inch), 120 fps. Each bone's local rotation is ``C M C^-1`` (C from the ASF ``axis``, M from the AMC
angles, both x-then-y-then-z about fixed axes), decomposed into intrinsic Z-Y-X angles. Checked against the cgspeed
file of trial 05_07: the first two frames agree to the file's 4 decimals.

Inputs: an ASF file for the bone axes and degrees of freedom (these are the same for every CMU subject: subjects 01
and 08 differ by < 1e-13 degrees), the subject's bone vectors (tools/cmu_subject_offsets.json, read from the cgspeed
BVH headers of that subject), the trial's AMC file and a frame range (AMC frame numbers, 1-based, inclusive).

    python tools/cmu_amc_to_bvh.py --asf 01.asf --amc 90_02.amc --subject 90 --frames 200 560 \\
        --out eventcap/body/assets/cmu/90_02.bvh
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

# cgspeed joint -> (parent, CMU bone whose rotation it carries or None, End Site key or None), in file order.
_TREE = [
    ("Hips", None, "root", None),
    ("LHipJoint", "Hips", "lhipjoint", None), ("LeftUpLeg", "LHipJoint", "lfemur", None),
    ("LeftLeg", "LeftUpLeg", "ltibia", None), ("LeftFoot", "LeftLeg", "lfoot", None),
    ("LeftToeBase", "LeftFoot", "ltoes", "LeftToeBase_end"),
    ("RHipJoint", "Hips", "rhipjoint", None), ("RightUpLeg", "RHipJoint", "rfemur", None),
    ("RightLeg", "RightUpLeg", "rtibia", None), ("RightFoot", "RightLeg", "rfoot", None),
    ("RightToeBase", "RightFoot", "rtoes", "RightToeBase_end"),
    ("LowerBack", "Hips", "lowerback", None), ("Spine", "LowerBack", "upperback", None),
    ("Spine1", "Spine", "thorax", None), ("Neck", "Spine1", "lowerneck", None), ("Neck1", "Neck", "upperneck", None),
    ("Head", "Neck1", "head", "Head_end"),
    ("LeftShoulder", "Spine1", "lclavicle", None), ("LeftArm", "LeftShoulder", "lhumerus", None),
    ("LeftForeArm", "LeftArm", "lradius", None), ("LeftHand", "LeftForeArm", "lwrist", None),
    ("LeftFingerBase", "LeftHand", "lhand", None), ("LeftHandIndex1", "LeftFingerBase", "lfingers",
                                                   "LeftHandIndex1_end"),
    ("LThumb", "LeftHand", "lthumb", "LThumb_end"),
    ("RightShoulder", "Spine1", "rclavicle", None), ("RightArm", "RightShoulder", "rhumerus", None),
    ("RightForeArm", "RightArm", "rradius", None), ("RightHand", "RightForeArm", "rwrist", None),
    ("RightFingerBase", "RightHand", "rhand", None), ("RightHandIndex1", "RightFingerBase", "rfingers",
                                                     "RightHandIndex1_end"),
    ("RThumb", "RightHand", "rthumb", "RThumb_end"),
]


def read_asf(path: Path) -> dict[str, dict]:
    """Bone -> {axis (degrees), dof (names), vector (direction * length)} of an ASF file."""
    out: dict[str, dict] = {}
    bone: dict = {}
    for line in path.read_text().splitlines():
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "begin":
            bone = {"axis": np.zeros(3), "dof": [], "direction": np.zeros(3), "length": 0.0}
        elif tok[0] == "name" and bone is not None:
            bone["name"] = tok[1]
        elif tok[0] == "axis" and len(tok) >= 4:
            bone["axis"] = np.array([float(v) for v in tok[1:4]])
        elif tok[0] == "direction":
            bone["direction"] = np.array([float(v) for v in tok[1:4]])
        elif tok[0] == "length":
            bone["length"] = float(tok[1])
        elif tok[0] == "dof":
            bone["dof"] = tok[1:]
        elif tok[0] == "end" and bone.get("name"):
            out[bone["name"]] = {**bone, "vector": bone["direction"] * bone["length"]}
    return out


def offsets_from_asf(asf: dict[str, dict]) -> dict[str, list[float]]:
    """The subject's OFFSETs as the cgspeed conversion (amc2bvh) lays them out: a joint sits at the end of its
    parent bone, except below a bone with several children (thorax: neck and clavicles; wrist: hand and thumb),
    whose children start where that bone starts."""
    bone_of = {name: bone for name, _, bone, _ in _TREE}
    n_children = {p: sum(1 for _, q, _, _ in _TREE if q == p) for p in bone_of}
    out: dict[str, list[float]] = {}
    for name, parent, _, end in _TREE[1:]:
        at_start = bone_of[parent] == "root" or n_children[parent] > 1
        out[name] = [0.0, 0.0, 0.0] if at_start else [float(v) for v in asf[bone_of[parent]]["vector"]]
        if end:
            out[end] = [float(v) for v in asf[bone_of[name]]["vector"]]
    return out


def read_amc(path: Path) -> dict[int, dict[str, list[float]]]:
    """AMC frame number -> bone -> values."""
    frames: dict[int, dict[str, list[float]]] = {}
    cur = None
    for line in path.read_text().splitlines():
        tok = line.split()
        if not tok or tok[0].startswith(("#", ":")):
            continue
        if len(tok) == 1 and tok[0].isdigit():
            cur = frames.setdefault(int(tok[0]), {})
        elif cur is not None:
            cur[tok[0]] = [float(v) for v in tok[1:]]
    return frames


def _local_euler(axis_deg: np.ndarray, dofs: list[str], values: list[float]) -> np.ndarray:
    """Intrinsic Z-Y-X degrees of C M C^-1."""
    rx = ry = rz = 0.0
    for d, v in zip(dofs, values):
        rx, ry, rz = (v, ry, rz) if d == "rx" else (rx, v, rz) if d == "ry" else (rx, ry, v)
    C = Rotation.from_euler("xyz", axis_deg, degrees=True)
    M = Rotation.from_euler("xyz", [rx, ry, rz], degrees=True)
    return (C * M * C.inv()).as_euler("ZYX", degrees=True)


def hierarchy(offsets: dict[str, list[float]]) -> str:
    children: dict[str, list[str]] = {}
    for name, parent, _, _ in _TREE:
        children.setdefault(parent, []).append(name)
    ends = {name: end for name, _, _, end in _TREE}
    lines = ["HIERARCHY"]

    def emit(name: str, depth: int) -> None:
        pad = "\t" * depth
        off = offsets.get(name, [0.0, 0.0, 0.0])
        lines.append(f"{pad}{'ROOT' if depth == 0 else 'JOINT'} {name}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}\tOFFSET {off[0]:.5f} {off[1]:.5f} {off[2]:.5f}")
        pos = "Xposition Yposition Zposition " if depth == 0 else ""
        lines.append(f"{pad}\tCHANNELS {6 if depth == 0 else 3} {pos}Zrotation Yrotation Xrotation")
        for c in children.get(name, []):
            emit(c, depth + 1)
        if ends[name]:
            e = offsets[ends[name]]
            lines.extend([f"{pad}\tEnd Site", f"{pad}\t{{", f"{pad}\t\tOFFSET {e[0]:.5f} {e[1]:.5f} {e[2]:.5f}",
                          f"{pad}\t}}"])
        lines.append(f"{pad}}}")

    emit("Hips", 0)
    return "\n".join(lines) + "\n"


def motion_rows(asf: dict, amc: dict, first: int, last: int) -> list[str]:
    rows = []
    for k in range(first, last + 1):
        fr = amc[k]
        vals = list(fr["root"][:3])
        vals += list(_local_euler(np.zeros(3), ["rx", "ry", "rz"], fr["root"][3:6]))
        for _, _, bone, _ in _TREE[1:]:
            axis, dofs = asf[bone]["axis"], asf[bone]["dof"]
            vals += list(_local_euler(axis, dofs, fr.get(bone, [])) if dofs else [0.0, 0.0, 0.0])
        rows.append(" ".join(f"{v:.4f}" for v in np.round(vals, 4) + 0.0))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--asf", type=Path, required=True, help="the subject's ASF, or any CMU subject's ASF (bone axes "
                    "and dofs) together with --subject")
    ap.add_argument("--amc", type=Path, required=True)
    ap.add_argument("--subject", help="take the bone vectors from tools/cmu_subject_offsets.json (e.g. 90) instead "
                    "of the ASF")
    ap.add_argument("--frames", type=int, nargs=2, required=True, metavar=("FIRST", "LAST"))
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    asf, amc = read_asf(a.asf), read_amc(a.amc)
    offsets = (json.loads((Path(__file__).parent / "cmu_subject_offsets.json").read_text())[a.subject]
               if a.subject else offsets_from_asf(asf))
    rows = motion_rows(asf, amc, a.frames[0], a.frames[1])
    a.out.write_text(hierarchy(offsets) + f"MOTION\nFrames: {len(rows)}\nFrame Time: .0083333\n" + "\n".join(rows)
                     + "\n")
    print(f"{a.out}: {len(rows)} frames ({a.frames[0]}-{a.frames[1]} of {a.amc.name})")


if __name__ == "__main__":
    main()
