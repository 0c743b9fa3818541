"""Forward kinematics and linear blend skinning of the shared skeleton, one implementation for two backends.

Every function takes the pose either as a numpy array ``S`` of shape (T, 33) or (33,) — vectorised over
frames, results get a leading T axis only if S had one — or as a CasADi ``SX``/``MX`` with 33 entries (one
frame, symbolic; results are CasADi matrices with one row per joint / landmark / point). The pose layout and
angle conventions are those of :mod:`eventcap.body.skeleton`.

One kernel serves both backends: the tree traversal and skinning formula are written once against a tiny
backend shim (rotation about a coordinate axis, matrix product, stacking). In CasADi the rotations keep
structural zeros, so the symbolic graphs are as small as hand-written ones (every DOF axis is a coordinate
axis).

The skinning transform of joint j maps rest space to posed space: ``x' = R_j x + b_j`` with
``b_j = p_j - R_j r_j`` (R_j global rotation, p_j posed and r_j rest joint position), and a point with
skinning weights w (24,) is posed as ``sum_j w_j (R_j x + b_j)``.
"""

from __future__ import annotations

import weakref
from typing import Any

import numpy as np

from eventcap.body.skeleton import (
    DOF_AXIS,
    DOF_JOINT,
    NUM_JOINTS,
    NUM_POSE_PARAMS,
    PARENTS,
    check_rest_joints,
    default_landmarks,
)
from eventcap.body.template import Template

#: Frames skinned at once by :func:`skin` (bounds the temporaries to a few MB).
_SKIN_CHUNK_FRAMES = 64

# ---------------------------------------------------------------------------------------------------------
# Backend shim: the handful of primitive operations that differ between numpy and CasADi. Everything else
# (tree traversal, DOF composition, conventions, skinning formula) is written once below.


def _is_casadi(x) -> bool:
    return type(x).__module__.split(".")[0] == "casadi"


class _NumpyOps:
    """Rotations are (T, 3, 3) arrays, vectors (T, 3) arrays."""

    casadi = False

    def __init__(self, S):
        S = np.asarray(S, dtype=np.float64)
        if S.shape[-1:] != (NUM_POSE_PARAMS,) or S.ndim > 2:
            raise ValueError(f"pose S: expected shape (T, 33) or (33,), got {S.shape}")
        self.batched = S.ndim == 2
        self.S = S if self.batched else S[None, :]
        self.T = self.S.shape[0]

    def rotation(self, axis: np.ndarray, i: int):
        """Rotation by the angle S[:, i] about a signed coordinate axis (right-hand rule)."""
        a = self.S[:, i]
        k = int(np.flatnonzero(axis)[0])
        c, s = np.cos(a), np.sin(a) * np.sign(axis[k])
        u, v = (k + 1) % 3, (k + 2) % 3
        R = np.zeros((self.T, 3, 3))
        R[:, k, k] = 1.0
        R[:, u, u] = c
        R[:, v, v] = c
        R[:, u, v] = -s
        R[:, v, u] = s
        return R

    def matmul(self, A, B):
        return A @ B

    def matvec(self, A, v: np.ndarray):
        return A @ v

    def translation(self):
        return self.S[:, 30:33]

    def stack_vectors(self, vecs):
        """List of N vectors (T, 3) -> (T, N, 3) [(N, 3) for an unbatched pose]."""
        out = np.stack(np.broadcast_arrays(*vecs), axis=1)
        return out if self.batched else out[0]

    def skin_rows(self, rot, b):
        """(T, 24, 12): each joint's R row-major then b."""
        G = np.empty((self.T, NUM_JOINTS, 12))
        G[..., :9] = np.stack(rot, axis=1).reshape(self.T, NUM_JOINTS, 9)
        G[..., 9:] = np.stack(b, axis=1)
        return G


class _CasadiOps:
    """Rotations are 3×3 CasADi matrices with structural zeros, vectors 3×1; one frame."""

    casadi = True
    batched = False

    def __init__(self, S):
        import casadi

        self.ca = casadi
        if S.numel() != NUM_POSE_PARAMS:
            raise ValueError(f"pose S: expected 33 entries (one frame), got CasADi shape {S.shape}")
        self.S = casadi.reshape(S, NUM_POSE_PARAMS, 1)
        self.kind = casadi.MX if isinstance(S, casadi.MX) else casadi.SX

    def rotation(self, axis: np.ndarray, i: int):
        a = self.S[i]
        k = int(np.flatnonzero(axis)[0])
        c, s = self.ca.cos(a), self.ca.sin(a) * float(np.sign(axis[k]))
        u, v = (k + 1) % 3, (k + 2) % 3
        R = self.kind(3, 3)  # all-structural-zero
        R[k, k] = 1.0
        R[u, u] = c
        R[v, v] = c
        R[u, v] = -s
        R[v, u] = s
        return R

    def matmul(self, A, B):
        return self.ca.mtimes(A, B)

    def matvec(self, A, v: np.ndarray):
        return self.ca.mtimes(A, self.ca.sparsify(self.ca.DM(v)))

    def translation(self):
        return self.S[30:33]

    def stack_vectors(self, vecs):
        """List of N 3×1 vectors -> (N, 3)."""
        return self.ca.horzcat(*vecs).T

    def skin_rows(self, rot, b):
        """(24, 12): each joint's R row-major then b."""
        ca = self.ca
        return ca.vertcat(*[ca.horzcat(ca.reshape(R.T, 1, 9), bj.T) for R, bj in zip(rot, b)])


def _ops(S):
    return _CasadiOps(S) if _is_casadi(S) else _NumpyOps(S)


def _rest_joints_of(body) -> np.ndarray:
    if isinstance(body, Template):
        return body.rest_joints
    return check_rest_joints(body)


# ---------------------------------------------------------------------------------------------------------
# The kernel (backend-agnostic)


def _forward(ops, rest: np.ndarray):
    """Global rotations and posed positions of the 24 joints (lists indexed by joint)."""
    local: list = [None] * NUM_JOINTS
    for i in range(DOF_JOINT.shape[0]):
        j = int(DOF_JOINT[i])
        Ri = ops.rotation(DOF_AXIS[i], i)
        local[j] = Ri if local[j] is None else ops.matmul(local[j], Ri)
    # Root: R_y(yaw) @ R_x(pitch) @ R_z(roll), yaw about the world vertical applied last.
    root = ops.matmul(ops.matmul(ops.rotation(_AXES[1], 27), ops.rotation(_AXES[0], 28)), ops.rotation(_AXES[2], 29))
    rot: list = [None] * NUM_JOINTS
    pos: list = [None] * NUM_JOINTS
    rot[0] = root if local[0] is None else ops.matmul(root, local[0])
    pos[0] = rest[0] + ops.translation()
    for j in range(1, NUM_JOINTS):
        p = int(PARENTS[j])
        pos[j] = pos[p] + ops.matvec(rot[p], rest[j] - rest[p])
        rot[j] = rot[p] if local[j] is None else ops.matmul(rot[p], local[j])
    return rot, pos


def _skin_matrix(ops, rot, pos, rest):
    """The 24 skinning transforms x' = R_j x + b_j as rows [R_j row-major, b_j]: (T, 24, 12) / (24, 12)."""
    b = [pos[j] - ops.matvec(rot[j], rest[j]) for j in range(NUM_JOINTS)]
    return ops.skin_rows(rot, b)


def _premultiplied(X: np.ndarray, W: np.ndarray) -> np.ndarray:
    """(P, 96) products W_pj * [x_p, 1]_k, so that posed points are one matrix product with the transforms."""
    Xh = np.concatenate([X, np.ones((X.shape[0], 1))], axis=1)
    return (W[:, :, None] * Xh[:, None, :]).reshape(X.shape[0], NUM_JOINTS * 4)


def _blend_numpy(G: np.ndarray, WX: np.ndarray) -> np.ndarray:
    """Posed points (T, P, 3) from transforms G (T, 24, 12) and premultiplied weights WX (P, 96)."""
    T = G.shape[0]
    M = np.empty((T, NUM_JOINTS, 4, 3))
    M[:, :, :3, :] = G[..., :9].reshape(T, NUM_JOINTS, 3, 3).transpose(0, 1, 3, 2)
    M[:, :, 3, :] = G[..., 9:]
    out = WX @ M.reshape(T, NUM_JOINTS * 4, 3).transpose(1, 0, 2).reshape(NUM_JOINTS * 4, T * 3)
    return out.reshape(-1, T, 3).transpose(1, 0, 2)


def _blend_casadi(ca, G, X, W):
    """Posed points (P, 3) from transforms G (24, 12), rest points X (P, 3), weights W (P, 24)."""
    A = ca.mtimes(W, G)
    cols = [
        A[:, 3 * i] * X[:, 0] + A[:, 3 * i + 1] * X[:, 1] + A[:, 3 * i + 2] * X[:, 2] + A[:, 9 + i] for i in range(3)
    ]
    return ca.horzcat(*cols)


_AXES = np.eye(3)
_PREMULTIPLIED_CACHE: weakref.WeakKeyDictionary[Template, np.ndarray] = weakref.WeakKeyDictionary()
_INCIDENCE_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _template_premultiplied(template: Template) -> np.ndarray:
    WX = _PREMULTIPLIED_CACHE.get(template)
    if WX is None:
        WX = _premultiplied(template.vertices, template.weights)
        _PREMULTIPLIED_CACHE[template] = WX
    return WX


# ---------------------------------------------------------------------------------------------------------
# Public API


def global_transforms(S, rest_joints) -> Any:
    """Skinning transforms of the 24 joints (rest space -> posed space) as homogeneous 4×4 matrices.

    S: (T, 33) / (33,) numpy or 33-entry CasADi. rest_joints: (24, 3) metres or a Template.
    Returns numpy (T, 24, 4, 4) [(24, 4, 4) for unbatched S]; for CasADi, a list of 24 (4, 4) matrices.
    """
    rest = _rest_joints_of(rest_joints)
    ops = _ops(S)
    rot, pos = _forward(ops, rest)
    G = _skin_matrix(ops, rot, pos, rest)
    if ops.casadi:
        ca = ops.ca
        return [
            ca.vertcat(ca.horzcat(ca.reshape(G[j, 0:9], 3, 3).T, G[j, 9:12].T), ca.DM([[0, 0, 0, 1]]))
            for j in range(NUM_JOINTS)
        ]
    M = np.zeros((ops.T, NUM_JOINTS, 4, 4))
    M[..., :3, :3] = G[..., :9].reshape(ops.T, NUM_JOINTS, 3, 3)
    M[..., :3, 3] = G[..., 9:]
    M[..., 3, 3] = 1.0
    return M if ops.batched else M[0]


def joint_positions(S, rest_joints) -> Any:
    """Posed 3D joint positions in metres: numpy (T, 24, 3) [or (24, 3)], CasADi (24, 3).

    rest_joints: (24, 3) metres or a Template.
    """
    rest = _rest_joints_of(rest_joints)
    ops = _ops(S)
    _, pos = _forward(ops, rest)
    return ops.stack_vectors(pos)


def landmark_positions(S, rest_joints, landmark_joint=None, landmark_offset=None) -> Any:
    """Posed landmark positions (skeleton.LANDMARK_NAMES order) in metres: numpy (T, L, 3), CasADi (L, 3).

    rest_joints: a Template (its landmarks are used) or (24, 3) metres with optional landmark_joint (L,)
    and landmark_offset (L, 3) (default: skeleton.default_landmarks of the rest joints).
    """
    if isinstance(rest_joints, Template):
        rest = rest_joints.rest_joints
        lj = rest_joints.landmark_joint if landmark_joint is None else landmark_joint
        lo = rest_joints.landmark_offset if landmark_offset is None else landmark_offset
    else:
        rest = check_rest_joints(rest_joints)
        if landmark_joint is None or landmark_offset is None:
            dj, do = default_landmarks(rest)
            lj = dj if landmark_joint is None else landmark_joint
            lo = do if landmark_offset is None else landmark_offset
        else:
            lj, lo = landmark_joint, landmark_offset
    lj = np.asarray(lj, dtype=np.int64)
    lo = np.asarray(lo, dtype=np.float64)
    if lj.ndim != 1 or lo.shape != (lj.shape[0], 3):
        raise ValueError(f"landmarks: expected joint (L,) and offset (L, 3), got {lj.shape} and {lo.shape}")
    if lj.size and (lj.min() < 0 or lj.max() >= NUM_JOINTS):
        raise ValueError(f"landmarks: joint indices must lie in [0, 23], got [{lj.min()}, {lj.max()}]")
    ops = _ops(S)
    rot, pos = _forward(ops, rest)
    return ops.stack_vectors([pos[j] + ops.matvec(rot[j], o) for j, o in zip(lj, lo)])


def skin_points(S, rest_points, point_weights, rest_joints) -> Any:
    """Linear blend skinning of arbitrary rest-space surface points.

    S: pose (numpy (T, 33)/(33,) or CasADi 33). rest_points (P, 3) metres and point_weights (P, 24) (rows
    summing to 1, e.g. barycentric blends of a face's vertices and weights); with a CasADi pose they may be
    numpy arrays or CasADi parameters (SX/MX of the pose's kind) of those shapes.
    rest_joints: (24, 3) metres or a Template.
    Returns numpy (T, P, 3) [or (P, 3)], CasADi (P, 3).
    """
    rest = _rest_joints_of(rest_joints)
    ops = _ops(S)
    symbolic_data = _is_casadi(rest_points) or _is_casadi(point_weights)
    if symbolic_data and not ops.casadi:
        raise ValueError("skin_points: CasADi points/weights need a CasADi pose S")
    if symbolic_data:
        X, W = rest_points, point_weights
        shapes = (tuple(X.shape), tuple(W.shape))
    else:
        X = np.asarray(rest_points, dtype=np.float64)
        W = np.asarray(point_weights, dtype=np.float64)
        shapes = (X.shape, W.shape)
    if len(shapes[0]) != 2 or shapes[0][1] != 3 or shapes[1] != (shapes[0][0], NUM_JOINTS):
        raise ValueError(f"skin_points: expected points (P, 3) and weights (P, 24), got {shapes[0]}, {shapes[1]}")
    rot, pos = _forward(ops, rest)
    G = _skin_matrix(ops, rot, pos, rest)
    if ops.casadi:
        if not symbolic_data:
            X, W = ops.ca.DM(X), ops.ca.DM(W)
        return _blend_casadi(ops.ca, G, X, W)
    out = _blend_numpy(G, _premultiplied(X, W))
    return out if ops.batched else out[0]


def skin(S, template: Template, normals: bool = False):
    """Posed mesh vertices of a template, numpy only: S (T, 33) -> (T, V, 3) metres [(V, 3) for S (33,)].

    With ``normals=True`` also returns unit vertex normals of the posed mesh (area-weighted face normals,
    outward for the template's CCW winding), same shape.
    """
    if not isinstance(template, Template):
        raise TypeError(f"skin: expected a Template, got {type(template).__name__}")
    if _is_casadi(S):
        raise ValueError("skin: full-mesh skinning is numpy only; use skin_points for CasADi poses")
    ops = _NumpyOps(S)
    rot, pos = _forward(ops, template.rest_joints)
    G = _skin_matrix(ops, rot, pos, template.rest_joints)
    WX = _template_premultiplied(template)
    out = np.empty((ops.T, template.num_vertices, 3))
    for a in range(0, ops.T, _SKIN_CHUNK_FRAMES):
        out[a : a + _SKIN_CHUNK_FRAMES] = _blend_numpy(G[a : a + _SKIN_CHUNK_FRAMES], WX)
    if not normals:
        return out if ops.batched else out[0]
    faces = template.faces.astype(np.int64)
    incidence = _INCIDENCE_CACHE.get(template)
    if incidence is None:
        incidence = _incidence(faces, template.num_vertices)
        _INCIDENCE_CACHE[template] = incidence
    nrm = _vertex_normals(out, faces, incidence)
    return (out, nrm) if ops.batched else (out[0], nrm[0])


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit area-weighted vertex normals of a triangle mesh: vertices (..., V, 3), faces (F, 3) -> (..., V, 3).

    Outward for counter-clockwise (seen from outside) faces. Isolated vertices get a zero normal.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    return _vertex_normals(vertices, faces, _incidence(faces, vertices.shape[-2]))


def _incidence(faces: np.ndarray, n_vertices: int):
    """Sparse (V, F) vertex-face incidence: summing face vectors onto vertices is one sparse product."""
    import scipy.sparse

    rows = faces.ravel()
    cols = np.repeat(np.arange(faces.shape[0]), 3)
    return scipy.sparse.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n_vertices, faces.shape[0]))


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray, incidence) -> np.ndarray:
    lead = vertices.shape[:-2]
    V = vertices.shape[-2]
    vv = vertices.reshape((-1, V, 3))
    out = np.empty_like(vv)
    for t in range(vv.shape[0]):
        v0, v1, v2 = (vv[t].take(faces[:, k], axis=0) for k in range(3))
        a, b = v1 - v0, v2 - v0
        # Cross product by components (np.cross is several times slower); length = 2 × area: area weighting.
        fn = np.empty_like(a)
        fn[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
        fn[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
        fn[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
        out[t] = incidence @ fn
    n = np.linalg.norm(out, axis=-1, keepdims=True)
    out = np.divide(out, n, out=np.zeros_like(out), where=n > 0)
    return out.reshape((*lead, V, 3))
