"""Build a Template from a scanned mesh plus a rig file (the paper's scanned, SMPL-rigged template, Sec. 3).

The mesh (OBJ, PLY, or anything trimesh reads) must be in metres in the skeleton's frame: y up, facing +z,
actor's left +x, in the rest pose of its rig. The vertex order is kept exactly as in the file. The rig is an
``.npz`` with:

- ``joints`` (24, 3) rest joint positions in metres, SMPL joint order;
- ``weights`` (V, 24) skinning weights (rows summing to 1), V = the mesh's vertex count;
- optional ``joint_names`` (24,) strings, checked against SMPL's order (``skeleton.JOINT_NAMES``);
- optional ``landmark_offset`` (25, 3) metres relative to each landmark's joint (``skeleton.LANDMARK_JOINT``);
  without it the generic offsets are snapped to the nearest head/foot vertex.

Albedo comes from the mesh's vertex colours (luminance) or its texture sampled at the vertices when present,
otherwise a uniform grey. With ``recentre=True`` (default) mesh and joints are shifted together so that the
pelvis is above the origin and the lowest vertex is on y=0.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from eventcap.body.skeleton import JOINT_NAMES, LANDMARK_JOINT, NUM_LANDMARKS, default_landmarks
from eventcap.body.template import Template, snap_landmarks_to_surface

#: Plausible standing heights in metres; outside, the mesh is probably in other units.
_HEIGHT_RANGE_M = (0.3, 3.0)


def _mesh_albedo(mesh, default: float) -> np.ndarray:
    """Per-vertex luminance in [0, 1] from vertex colours or texture; uniform ``default`` without either."""
    n_v = len(mesh.vertices)
    visual = getattr(mesh, "visual", None)
    colors = None
    if visual is not None and visual.kind == "vertex":
        colors = np.asarray(visual.vertex_colors)
    elif visual is not None and visual.kind == "texture":
        try:
            colors = np.asarray(visual.to_color().vertex_colors)
        except Exception:  # noqa: BLE001 - a texture trimesh cannot sample falls back to grey
            colors = None
    if colors is None or colors.shape[0] != n_v:
        return np.full(n_v, default, dtype=np.float32)
    rgb = colors[:, :3].astype(np.float64) / 255.0
    return (rgb @ np.array([0.299, 0.587, 0.114])).astype(np.float32)


def load_mesh_template(
    mesh_path, rig_path, name: str | None = None, recentre: bool = True, default_albedo: float = 0.5
) -> Template:
    """Load a scanned mesh (OBJ/PLY via trimesh) and its rig (.npz) as a Template."""
    import trimesh

    mesh_path, rig_path = Path(mesh_path), Path(rig_path)
    for p in (mesh_path, rig_path):
        if not p.is_file():
            raise ValueError(f"file not found: {p}")
    try:
        mesh = trimesh.load(mesh_path, process=False, force="mesh")
    except Exception as e:  # noqa: BLE001 - trimesh raises many kinds; report them uniformly
        raise ValueError(f"{mesh_path}: cannot read as a triangle mesh ({type(e).__name__}: {e})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{mesh_path}: expected a triangle mesh with faces, got {type(mesh).__name__}")
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)

    if rig_path.suffix.lower() != ".npz":
        raise ValueError(f"{rig_path}: expected a rig file ending in .npz, got {rig_path.suffix!r}")
    with np.load(rig_path, allow_pickle=False) as z:
        rig = {k: z[k] for k in z.files}
    for key in ("joints", "weights"):
        if key not in rig:
            raise ValueError(f"{rig_path}: rig is missing key {key!r}; found {sorted(rig)}")
    joints = np.asarray(rig["joints"], dtype=np.float64)
    weights = np.asarray(rig["weights"], dtype=np.float64)
    if joints.shape != (24, 3):
        raise ValueError(f"{rig_path}: joints must have shape (24, 3), got {joints.shape}")
    if weights.ndim != 2 or weights.shape[1] != 24:
        raise ValueError(f"{rig_path}: weights must have shape (V, 24), got {weights.shape}")
    if weights.shape[0] != verts.shape[0]:
        raise ValueError(
            f"vertex count mismatch: {mesh_path} has {verts.shape[0]} vertices but the weights in {rig_path} "
            f"have {weights.shape[0]} rows"
        )
    if "joint_names" in rig:
        names = [str(n) for n in np.asarray(rig["joint_names"]).ravel()]
        if names != list(JOINT_NAMES):
            diff = next((i for i, (a, b) in enumerate(zip(names, JOINT_NAMES)) if a != b), min(len(names), 24))
            got = names[diff] if diff < len(names) else "<missing>"
            raise ValueError(
                f"{rig_path}: joint_names must be SMPL's order; joint {diff} is {got!r}, expected "
                f"{JOINT_NAMES[diff] if diff < 24 else '<none>'!r}"
            )

    height = float(np.ptp(verts[:, 1]))
    if not _HEIGHT_RANGE_M[0] <= height <= _HEIGHT_RANGE_M[1]:
        raise ValueError(
            f"{mesh_path}: mesh is {height:.3g} units tall; expected metres (a height in {_HEIGHT_RANGE_M}) with y up"
        )
    if recentre:
        shift = np.array([-joints[0, 0], -verts[:, 1].min(), -joints[0, 2]])
        verts = verts + shift
        joints = joints + shift

    lj, lo = default_landmarks(joints)
    if "landmark_offset" in rig:
        lo = np.asarray(rig["landmark_offset"], dtype=np.float64)
        if lo.shape != (NUM_LANDMARKS, 3):
            raise ValueError(f"{rig_path}: landmark_offset must have shape ({NUM_LANDMARKS}, 3), got {lo.shape}")
        lj = LANDMARK_JOINT.copy()
    else:
        lo = snap_landmarks_to_surface(verts, weights, joints, lj, lo)

    tpl = Template(
        name=name or f"mesh:{mesh_path.stem}",
        rest_joints=joints,
        vertices=verts,
        faces=faces,
        weights=weights,
        vertex_albedo=_mesh_albedo(mesh, default_albedo),
        landmark_joint=lj,
        landmark_offset=lo,
    )
    return tpl.outward()  # an inward-wound file is flipped to the outward convention
