"""Surface markers on a template: the 39 markers of Vicon's Plug-in Gait full-body set, placed on the mesh.

Optical mocap tracks markers taped to the skin, not joint centres. Exporting joint centres alone under marker-like
labels (what C3D users would take for markers) misleads; this module places the markers a C3D user expects on the
template's own surface, so they move with the skinned mesh (:func:`eventcap.body.kinematics.skin_points`).

Each marker is defined, as in the Plug-in Gait guide, by the anatomical landmark it sits on (front of the head
above the temple, the 7th cervical vertebra, the anterior superior iliac spine, the lateral knee epicondyle,
...). Here a landmark is a point inside the body (a joint centre, or a point between two joints) and a direction
in the rest pose (T-pose, facing +z, the actor's left +x, y up: :mod:`eventcap.body.skeleton`); the marker is
where a ray from that point along that direction leaves the mesh: the first hit (``trimesh``). Its skinning
weights are the hit face's vertices' weights blended by the hit's barycentric coordinates, exactly as the mesh
surface moves. A marker taped on the skin has a marker radius (7 mm balls are common) and sits on soft tissue:
the positions are the skin surface, without ball radius and without soft-tissue motion.

The directions are simplified to the T-pose's axes (e.g. lateral knee = +x for the left knee); a template whose
mesh no ray leaves (an open or broken mesh) is refused with the marker's name.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .skeleton import JOINT_INDEX
from .template import Template

#: (name, description, anchor: joint name or (joint a, joint b, fraction from a to b), direction (x, y, z)).
#: Left-side markers; right-side ones mirror them (x -> -x). Central markers follow the list.
_SIDED = (
    ("FHD", "front head, above the temple", "head", (0.45, 0.35, 1.0)),
    ("BHD", "back head, level with the front head marker", "head", (0.45, 0.35, -1.0)),
    ("SHO", "acromio-clavicular joint (top of the shoulder)", ("l_collar", "l_shoulder", 0.85), (0.0, 1.0, 0.0)),
    ("UPA", "upper arm, between shoulder and elbow", ("l_shoulder", "l_elbow", 0.5), (0.0, 0.3, -1.0)),
    ("ELB", "lateral epicondyle of the elbow", "l_elbow", (0.0, 0.3, -1.0)),
    ("FRM", "forearm, between elbow and wrist", ("l_elbow", "l_wrist", 0.5), (0.0, 0.3, -1.0)),
    ("WRA", "wrist, thumb side", "l_wrist", (0.0, 0.0, 1.0)),
    ("WRB", "wrist, little-finger side", "l_wrist", (0.0, 0.0, -1.0)),
    ("FIN", "back of the hand, below the head of the 2nd metacarpal", "l_hand", (0.0, 1.0, 0.0)),
    ("ASI", "anterior superior iliac spine", ("pelvis", "l_hip", 1.0), (0.35, 0.35, 1.0)),
    ("PSI", "posterior superior iliac spine", ("pelvis", "l_hip", 0.4), (0.2, 0.35, -1.0)),
    ("THI", "lateral thigh, lower third", ("l_hip", "l_knee", 0.65), (1.0, 0.0, 0.0)),
    ("KNE", "lateral epicondyle of the knee", "l_knee", (1.0, 0.0, 0.0)),
    ("TIB", "lateral shank, lower third", ("l_knee", "l_ankle", 0.65), (1.0, 0.0, 0.0)),
    ("ANK", "lateral malleolus", "l_ankle", (1.0, 0.0, 0.0)),
    ("HEE", "calcaneus, at the height of the toe marker", "l_ankle", (0.0, -0.4, -1.0)),
    ("TOE", "second metatarsal head, top of the foot", "l_foot", (0.0, 1.0, 0.35)),
)
_CENTRAL = (
    ("C7", "7th cervical vertebra", "neck", (0.0, 0.0, -1.0)),
    ("T10", "10th thoracic vertebra", "spine2", (0.0, 0.0, -1.0)),
    ("CLAV", "jugular notch, where the clavicles meet the sternum", ("spine3", "neck", 0.6), (0.0, 0.0, 1.0)),
    ("STRN", "xiphoid process of the sternum", "spine2", (0.0, 0.0, 1.0)),
    ("RBAK", "middle of the right scapula (asymmetry marker)", ("spine3", "r_shoulder", 0.55), (0.0, 0.0, -1.0)),
)


def _mirror(anchor):
    swap = {"l_": "r_", "r_": "l_"}
    if isinstance(anchor, str):
        return swap.get(anchor[:2], anchor[:2]) + anchor[2:] if anchor[:2] in swap else anchor
    a, b, f = anchor
    return (_mirror(a), _mirror(b), f)


def _definitions() -> list[tuple[str, str, object, tuple[float, float, float]]]:
    out = []
    for side, sign, word in (("L", 1.0, "left"), ("R", -1.0, "right")):
        for name, desc, anchor, (dx, dy, dz) in _SIDED:
            out.append((side + name, f"{word} {desc}", anchor if side == "L" else _mirror(anchor),
                        (sign * dx, dy, dz)))
    return out + list(_CENTRAL)


#: Plug-in Gait full-body marker names (39), in the order the C3D export lists them.
MARKER_NAMES: tuple[str, ...] = tuple(d[0] for d in _definitions())


@dataclass(frozen=True)
class SurfaceMarkers:
    """Markers on a template's surface: ``rest_points`` (M, 3) metres and ``weights`` (M, 24) skinning weights, for
    :func:`eventcap.body.kinematics.skin_points`; ``names`` and ``descriptions`` (M,)."""

    names: tuple[str, ...]
    descriptions: tuple[str, ...]
    rest_points: np.ndarray
    weights: np.ndarray

    def positions(self, S: np.ndarray, template: Template) -> np.ndarray:
        """Posed marker positions (T, M, 3) metres for poses S (T, 33)."""
        from .kinematics import skin_points

        return skin_points(np.asarray(S, dtype=np.float64), self.rest_points, self.weights, template)


def _anchor_point(anchor, rest: np.ndarray) -> np.ndarray:
    if isinstance(anchor, str):
        return rest[JOINT_INDEX[anchor]]
    a, b, f = anchor
    return (1.0 - f) * rest[JOINT_INDEX[a]] + f * rest[JOINT_INDEX[b]]


def plug_in_gait_markers(template: Template) -> SurfaceMarkers:
    """The 39 Plug-in Gait markers placed on ``template``'s rest mesh (see the module docstring)."""
    import trimesh

    defs = _definitions()
    origins = np.array([_anchor_point(d[2], template.rest_joints) for d in defs])
    dirs = np.array([d[3] for d in defs], dtype=np.float64)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    mesh = trimesh.Trimesh(template.vertices, template.faces, process=False)
    locations, ray_idx, tri_idx = mesh.ray.intersects_location(origins, dirs, multiple_hits=True)
    points = np.empty((len(defs), 3))
    weights = np.empty((len(defs), template.weights.shape[1]))
    for i, (name, *_rest) in enumerate(defs):
        hits = np.flatnonzero(ray_idx == i)
        dist = (locations[hits] - origins[i]) @ dirs[i]
        hits, dist = hits[dist > 0], dist[dist > 0]
        if hits.size == 0:
            raise ValueError(f"template {template.name!r}: marker {name}: no surface along its ray from inside the "
                             f"body (is the mesh closed?)")
        h = hits[int(np.argmin(dist))]
        face = template.faces[tri_idx[h]]
        bary = trimesh.triangles.points_to_barycentric(template.vertices[face][None], locations[h][None])[0]
        points[i] = locations[h]
        weights[i] = bary @ template.weights[face]
    weights /= weights.sum(axis=1, keepdims=True)
    return SurfaceMarkers(names=MARKER_NAMES, descriptions=tuple(d[1] for d in defs), rest_points=points,
                          weights=weights)
