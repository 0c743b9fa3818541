"""The rigged, textured actor template every body source (procedural, SMPL, scanned mesh) produces.

A :class:`Template` is a rest-pose mesh in the world frame of :mod:`eventcap.body.skeleton` (metres, y up,
feet on y=0, facing +z, actor's left +x, T-pose) rigged to the shared 24-joint skeleton by linear blend
skinning weights. Faces are triangles wound counter-clockwise when seen from outside the body, so
``cross(v1 - v0, v2 - v0)`` points outwards (a closed template has positive signed volume).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from eventcap.artifact import Artifact, array, attr
from eventcap.body.skeleton import NUM_JOINTS, NUM_LANDMARKS, check_rest_joints

#: Tolerance on |sum of a vertex's skinning weights - 1|; within it rows are renormalised exactly.
WEIGHT_SUM_TOL = 1e-3


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Template(Artifact):
    """A rigged actor template in rest pose.

    Fields (arrays are copied, cast to the dtypes below and made read-only):
        name: human-readable identifier (e.g. "procedural-1.75m", "smpl:basicModel_m").
        rest_joints: (24, 3) float64, rest joint positions in metres, SMPL joint order.
        vertices: (V, 3) float64, rest mesh vertices in metres.
        faces: (F, 3) int32, triangles, counter-clockwise seen from outside (outward normals).
        weights: (V, 24) float64, skinning weights, non-negative, rows sum to 1.
        vertex_albedo: (V,) float32 in [0, 1], grey-level reflectance (texture / clothing pattern).
        landmark_joint: (L,) int64, joint each landmark of skeleton.LANDMARK_NAMES follows, L = 25.
        landmark_offset: (L, 3) float64, landmark position minus its joint's position, rest space, metres.
        rest_spread: (K, 24, 3) float64 or None, how uncertain the rest joints are (a body estimated from the
            detections, eventcap.body.proportions.rest_spread): K independent one-sigma deviations, metres.
    """

    schema_version: ClassVar[int] = 1
    name: str = attr()
    rest_joints: np.ndarray = array("float64", (NUM_JOINTS, 3), units="m")
    vertices: np.ndarray = array("float64", ("v", 3), units="m")
    faces: np.ndarray = array("int32", ("f", 3), doc="vertex indices, CCW seen from outside")
    weights: np.ndarray = array("float64", ("v", NUM_JOINTS), doc="skinning weights, rows sum to 1")
    vertex_albedo: np.ndarray = array("float32", ("v",), units="reflectance [0,1]")
    landmark_joint: np.ndarray = array("int64", ("l",), doc="joint each landmark follows")
    landmark_offset: np.ndarray = array("float64", ("l", 3), units="m")
    stated: tuple = attr(default=(), doc="what of this body the user stated: the template keys given (height_m, "
                                         "build, muscle, sex), or 'shape' for a whole body (a scan, a model file); "
                                         "the body stage keeps what is stated and estimates the rest")
    rest_spread: np.ndarray = array("float64", ("k", NUM_JOINTS, 3), units="m", optional=True,
                                    doc="K independent one-sigma deviations of the rest joints (the body stage's "
                                        "posterior: rest + sum of eps_k x these, eps_k ~ N(0, 1)); None: exact")

    def __post_init__(self) -> None:
        where = f"Template {self.name!r}"
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"Template: name must be a non-empty string, got {self.name!r}")
        try:
            rest = check_rest_joints(self.rest_joints)
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from None

        v = np.asarray(self.vertices, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] < 3:
            raise ValueError(f"{where}: vertices must have shape (V, 3) with V >= 3, got {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{where}: vertices contain NaN or inf")
        n_v = v.shape[0]

        f_in = np.asarray(self.faces)
        if f_in.ndim != 2 or f_in.shape[1] != 3 or f_in.shape[0] < 1:
            raise ValueError(f"{where}: faces must have shape (F, 3) with F >= 1, got {f_in.shape}")
        if not np.issubdtype(f_in.dtype, np.integer):
            raise ValueError(f"{where}: faces must be integer vertex indices, got dtype {f_in.dtype}")
        if f_in.min() < 0 or f_in.max() >= n_v:
            raise ValueError(
                f"{where}: face indices must lie in [0, {n_v - 1}] (V = {n_v}), got range "
                f"[{int(f_in.min())}, {int(f_in.max())}]"
            )
        f = f_in.astype(np.int32)

        w = np.asarray(self.weights, dtype=np.float64)
        if w.shape != (n_v, NUM_JOINTS):
            raise ValueError(f"{where}: weights must have shape (V, 24) = ({n_v}, 24), got {w.shape}")
        if not np.all(np.isfinite(w)) or w.min() < 0:
            raise ValueError(f"{where}: weights must be finite and non-negative (min {np.nanmin(w):.3g})")
        sums = w.sum(axis=1)
        bad = np.flatnonzero(np.abs(sums - 1.0) > WEIGHT_SUM_TOL)
        if bad.size:
            raise ValueError(
                f"{where}: skinning weight rows must sum to 1 (tolerance {WEIGHT_SUM_TOL}); "
                f"{bad.size} rows do not, e.g. vertex {bad[0]} sums to {sums[bad[0]]:.6g}"
            )
        # Renormalise only rows that are off by more than rounding, so a stored template reloads bit-identically.
        off = np.abs(sums - 1.0) > 1e-12
        if off.any():
            w = w.copy()
            w[off] /= sums[off, None]

        a = np.asarray(self.vertex_albedo, dtype=np.float32)
        if a.shape != (n_v,):
            raise ValueError(f"{where}: vertex_albedo must have shape (V,) = ({n_v},), got {a.shape}")
        if not np.all(np.isfinite(a)) or a.min() < 0 or a.max() > 1:
            raise ValueError(
                f"{where}: vertex_albedo must lie in [0, 1], got range [{np.nanmin(a):.3g}, {np.nanmax(a):.3g}]"
            )

        lj = np.asarray(self.landmark_joint)
        if lj.shape != (NUM_LANDMARKS,) or not np.issubdtype(lj.dtype, np.integer):
            raise ValueError(
                f"{where}: landmark_joint must be integer with shape ({NUM_LANDMARKS},), got {lj.dtype} {lj.shape}"
            )
        if lj.min() < 0 or lj.max() >= NUM_JOINTS:
            raise ValueError(f"{where}: landmark_joint entries must lie in [0, 23], got [{lj.min()}, {lj.max()}]")
        lo = np.asarray(self.landmark_offset, dtype=np.float64)
        if lo.shape != (NUM_LANDMARKS, 3) or not np.all(np.isfinite(lo)):
            raise ValueError(f"{where}: landmark_offset must be finite with shape ({NUM_LANDMARKS}, 3), got {lo.shape}")
        if self.rest_spread is not None:
            sp = np.asarray(self.rest_spread, dtype=np.float64)
            if sp.ndim != 3 or sp.shape[1:] != (NUM_JOINTS, 3) or not np.all(np.isfinite(sp)):
                raise ValueError(f"{where}: rest_spread must be finite with shape (K, {NUM_JOINTS}, 3), got {sp.shape}")
            object.__setattr__(self, "rest_spread", _readonly(sp))

        for field, value in (
            ("rest_joints", rest),
            ("vertices", v),
            ("faces", f),
            ("weights", w),
            ("vertex_albedo", a),
            ("landmark_joint", lj.astype(np.int64)),
            ("landmark_offset", lo),
        ):
            object.__setattr__(self, field, _readonly(value))
        Artifact.validate(self)

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def rest_landmarks(self) -> np.ndarray:
        """Rest-pose landmark positions, (L, 3) metres."""
        return self.rest_joints[self.landmark_joint] + self.landmark_offset

    @property
    def dominant_joint(self) -> np.ndarray:
        """Joint with the largest skinning weight of each vertex, (V,) int64 (body-part labels)."""
        return np.argmax(self.weights, axis=1)

    def outward(self) -> Template:
        """This template with faces wound outwards: flipped if its signed volume is negative (inward-wound files)."""
        if self.signed_volume() >= 0:
            return self
        return replace(self, faces=self.faces[:, ::-1])

    def geometry_digest(self) -> str:
        """sha1 of the geometry that posing depends on (rest joints, mesh, skinning weights, landmarks): a key for
        per-process caches of things built from a template (e.g. a solver's NLP). Computed once per template (its
        arrays are read-only): the spline solve asks for it per window and per frame fit."""
        import hashlib

        cached = self.__dict__.get("_geometry_digest")
        if cached is not None:
            return cached
        h = hashlib.sha1()
        for name in ("rest_joints", "vertices", "faces", "weights", "landmark_joint", "landmark_offset"):
            a = np.ascontiguousarray(getattr(self, name))
            h.update(name.encode() + str(a.dtype).encode() + str(a.shape).encode() + a.tobytes())
        object.__setattr__(self, "_geometry_digest", h.hexdigest())
        return self.__dict__["_geometry_digest"]

    def signed_volume(self) -> float:
        """Signed volume in m³ enclosed by the faces (positive when outward-oriented and closed)."""
        tri = self.vertices[self.faces]
        return float(np.einsum("fi,fi->", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6.0)


def pattern_albedo(
    vertices: np.ndarray, weights: np.ndarray, rest_joints: np.ndarray, stripe_period_m: float = 0.08
) -> np.ndarray:
    """A simple synthetic clothing pattern as per-vertex albedo, (V,) float32 in [0, 1].

    Skin (head, hands, forearms) light, shirt mid-grey with horizontal stripes of ``stripe_period_m``,
    trousers dark with a lighter vertical seam band, shoes very dark. Parts come from the dominant skinning
    joint; the stripes give the texture edges that photometric feature tracking needs.
    vertices (V, 3) metres rest pose, weights (V, 24), rest_joints (24, 3).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    rest_joints = check_rest_joints(rest_joints)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or weights.shape != (vertices.shape[0], NUM_JOINTS):
        raise ValueError(
            f"pattern_albedo: expected vertices (V, 3) and weights (V, 24), got {vertices.shape} and {weights.shape}"
        )
    part = np.argmax(weights, axis=1)
    skin = np.isin(part, [12, 15, 18, 19, 20, 21, 22, 23])  # neck, head, forearms (elbow joint), wrists, hands
    shoes = np.isin(part, [7, 8, 10, 11])
    legs = np.isin(part, [1, 2, 4, 5])
    shirt = ~(skin | shoes | legs)
    albedo = np.empty(vertices.shape[0])
    albedo[skin] = 0.72
    albedo[shoes] = 0.08
    # Horizontal stripes on the shirt, smooth-edged so they alias less in low-resolution renders.
    phase = 2 * np.pi * vertices[:, 1] / stripe_period_m
    albedo[shirt] = 0.45 + 0.2 * np.tanh(3.0 * np.sin(phase[shirt]))
    # Trousers: dark with a light band down the outer side of each leg.
    side = np.abs(vertices[:, 0]) - np.abs(rest_joints[1, 0])
    albedo[legs] = 0.18 + 0.3 * (side[legs] > 0.05)
    return np.clip(albedo, 0.0, 1.0).astype(np.float32)


#: Landmarks that lie on the body surface, with the joints whose skin may carry them.
SURFACE_LANDMARK_PARTS: dict[str, tuple[int, ...]] = {
    "nose": (15,),
    "l_eye": (15,),
    "r_eye": (15,),
    "l_ear": (15,),
    "r_ear": (15,),
    "l_big_toe": (7, 10),
    "l_small_toe": (7, 10),
    "l_heel": (7, 10),
    "r_big_toe": (8, 11),
    "r_small_toe": (8, 11),
    "r_heel": (8, 11),
}


def snap_landmarks_to_surface(
    vertices: np.ndarray,
    weights: np.ndarray,
    rest_joints: np.ndarray,
    landmark_joint: np.ndarray,
    landmark_offset: np.ndarray,
) -> np.ndarray:
    """Move the surface landmarks (face and feet) onto the nearest mesh vertex of their body part.

    Used for meshes without known landmark vertices: the skeleton's generic face/foot offsets are replaced
    by the nearest vertex whose dominant skinning joint is the head (face) or the ankle/foot (feet), so
    that the landmarks lie on this actor's skin. Returns new offsets (L, 3) metres; other landmarks and parts
    without vertices are left as given.
    """
    from eventcap.body.skeleton import LANDMARK_NAMES

    vertices = np.asarray(vertices, dtype=np.float64)
    part = np.argmax(np.asarray(weights), axis=1)
    rest_joints = check_rest_joints(rest_joints)
    offsets = np.array(landmark_offset, dtype=np.float64, copy=True)
    for i, name in enumerate(LANDMARK_NAMES):
        parts = SURFACE_LANDMARK_PARTS.get(name)
        if parts is None:
            continue
        cand = np.flatnonzero(np.isin(part, parts))
        if cand.size == 0:
            continue
        j = int(landmark_joint[i])
        target = rest_joints[j] + offsets[i]
        best = cand[np.argmin(np.linalg.norm(vertices[cand] - target, axis=1))]
        offsets[i] = vertices[best] - rest_joints[j]
    return offsets
