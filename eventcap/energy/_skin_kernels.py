"""Compiled skinning kernels (numba): the per-frame skinning transforms G(S), their Jacobian and their second
derivatives contracted with a weight Λ, in closed form.

Every DOF of the pose moves the joints below it rigidly: a rotation DOF i turns them about its world axis a_i (its
rest axis carried by the rotations above it) through the joint's position o_i, a translation DOF shifts them all.
So with the transform T_j = [R_j b_j] of joint j (x' = R_j x + b_j), ∂T_j/∂θ_i = ξ̂_i T_j for every joint j below
DOF i (its own joint included), ξ̂_i = [[a_i]×, -[a_i]× o_i] (rotation) or [0, e_c] (translation). The second
derivative of a product of exponentials is ∂²T_j/∂θ_s∂θ_t = ξ̂_s ξ̂_t T_j when DOF s comes before DOF t on the chain
(the translation first, then the root's yaw, pitch, roll, then each joint's DOFs from the pelvis outwards; joint j
below t's joint). Contracted with Λ (∂E/∂G), Σ_j ⟨Λ_j, ξ̂_s ξ̂_t T_j⟩ = tr(E_st P) with P the sum over the joints
below t of T_j Λ_j, accumulated from the leaves once per frame: the Hessian costs O(DOF²) per frame, not a symbolic
graph's evaluation.

These are the kernels of :class:`eventcap.energy.kernels.SkinningKernels`; tests/test_skin_kernels.py holds them
against the CasADi graph of :func:`eventcap.body.kinematics.global_transforms` (the reference) and finite
differences. Compiled once per machine: numba caches the machine code beside this file (``cache=True``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from eventcap.body.skeleton import DOF_AXIS, DOF_JOINT, NUM_JOINTS, NUM_POSE_PARAMS, PARENTS

_NP = NUM_POSE_PARAMS
_NJ = NUM_JOINTS
_ROOT_DOFS = (27, 28, 29)  # yaw (y), pitch (x), roll (z): R_root = R_y R_x R_z


def _tables():
    """The skeleton as arrays for the kernels: the DOFs of each joint in order (CSR), every DOF's signed rest axis
    (the root's three as coordinate axes), and whether DOF t lies on the chain below DOF s (``below[s, t]``)."""
    start = np.zeros(_NJ + 1, dtype=np.int64)
    for j in DOF_JOINT:
        start[j + 1] += 1
    start = np.cumsum(start)
    order = np.argsort(DOF_JOINT, kind="stable").astype(np.int64)
    axis = np.zeros((30, 3))
    axis[:27] = DOF_AXIS
    axis[27, 1] = axis[28, 0] = axis[29, 2] = 1.0
    joint = np.zeros(30, dtype=np.int64)
    joint[:27] = DOF_JOINT
    # rank on the chain: the root's rotations before every joint DOF; within a joint, DOF order
    ancestors = [set() for _ in range(_NJ)]
    for j in range(1, _NJ):
        ancestors[j] = ancestors[int(PARENTS[j])] | {int(PARENTS[j])}
    below = np.zeros((30, 30), dtype=np.bool_)
    for s in range(30):
        for t in range(30):
            if s >= 27:
                below[s, t] = t >= 27 and t >= s or t < 27  # root rotations: in order, then every joint DOF
            elif t < 27:
                js, jt = joint[s], joint[t]
                below[s, t] = js in ancestors[jt] or (js == jt and t >= s)
    return start, order, axis, joint, below


_DOF_START, _DOF_ORDER, _AXIS, _JOINT, _BELOW = _tables()
_PARENTS = np.ascontiguousarray(PARENTS, dtype=np.int64)


@njit(cache=True)
def _rot(axis, angle, R):
    """R = the rotation by ``angle`` about the unit coordinate axis ``axis`` (signed), right-hand rule."""
    k = 0
    for i in range(3):
        if axis[i] != 0.0:
            k = i
    c = np.cos(angle)
    s = np.sin(angle) * (1.0 if axis[k] > 0 else -1.0)
    u = (k + 1) % 3
    v = (k + 2) % 3
    for a in range(3):
        for b in range(3):
            R[a, b] = 0.0
    R[k, k] = 1.0
    R[u, u] = c
    R[v, v] = c
    R[u, v] = -s
    R[v, u] = s


@njit(cache=True)
def _matmul3(A, B, out):
    for a in range(3):
        for b in range(3):
            out[a, b] = A[a, 0] * B[0, b] + A[a, 1] * B[1, b] + A[a, 2] * B[2, b]


@njit(cache=True)
def _frame(S, rest, parents, dof_start, dof_order, axis, rot, pos, wax, piv):
    """Forward kinematics of one pose S (33,): global rotations rot (24, 3, 3), positions pos (24, 3), and every
    rotation DOF's world axis wax (30, 3) and pivot piv (30, 3) — eventcap.body.kinematics._forward's tree."""
    A = np.empty((3, 3))
    R = np.empty((3, 3))
    tmp = np.empty((3, 3))
    # root: R_y(S27) R_x(S28) R_z(S29); each axis is the product so far times its own
    for a in range(3):
        for b in range(3):
            A[a, b] = 1.0 if a == b else 0.0
    for i in range(27, 30):
        for c in range(3):
            wax[i, c] = A[c, 0] * axis[i, 0] + A[c, 1] * axis[i, 1] + A[c, 2] * axis[i, 2]
        _rot(axis[i], S[i], R)
        _matmul3(A, R, tmp)
        A[:, :] = tmp
    for c in range(3):
        pos[0, c] = rest[0, c] + S[30 + c]
        for i in range(27, 30):
            piv[i, c] = pos[0, c]
    for j in range(_NJ):
        if j > 0:
            p = parents[j]
            for c in range(3):
                d0 = rest[j, 0] - rest[p, 0]
                d1 = rest[j, 1] - rest[p, 1]
                d2 = rest[j, 2] - rest[p, 2]
                pos[j, c] = pos[p, c] + rot[p, c, 0] * d0 + rot[p, c, 1] * d1 + rot[p, c, 2] * d2
            A[:, :] = rot[p]
        for k in range(dof_start[j], dof_start[j + 1]):
            i = dof_order[k]
            for c in range(3):
                wax[i, c] = A[c, 0] * axis[i, 0] + A[c, 1] * axis[i, 1] + A[c, 2] * axis[i, 2]
                piv[i, c] = pos[j, c]
            _rot(axis[i], S[i], R)
            _matmul3(A, R, tmp)
            A[:, :] = tmp
        rot[j] = A


@njit(cache=True)
def _write_transforms(rot, pos, rest, Gf):
    """Gf (96, 3): each joint's [R_jᵀ; b_jᵀ] (rows 4j..4j+3), b_j = p_j - R_j r_j."""
    for j in range(_NJ):
        for c in range(3):
            for r in range(3):
                Gf[4 * j + r, c] = rot[j, c, r]
            Gf[4 * j + 3, c] = pos[j, c] - (rot[j, c, 0] * rest[j, 0] + rot[j, c, 1] * rest[j, 1]
                                            + rot[j, c, 2] * rest[j, 2])


@njit(cache=True)
def skin_transforms(S, rest, parents, dof_start, dof_order, axis, G):
    """G (F, 96, 3): per frame, each joint's [R_jᵀ; b_jᵀ] (rows 4j..4j+3), b_j = p_j - R_j r_j."""
    rot = np.empty((_NJ, 3, 3))
    pos = np.empty((_NJ, 3))
    wax = np.empty((30, 3))
    piv = np.empty((30, 3))
    for f in range(S.shape[0]):
        _frame(S[f], rest, parents, dof_start, dof_order, axis, rot, pos, wax, piv)
        _write_transforms(rot, pos, rest, G[f])


@njit(cache=True)
def skin_jacobian(S, rest, parents, dof_start, dof_order, axis, joint, G, dG):
    """G (F, 96, 3) as :func:`skin_transforms` and dG (F, 96, 3, 33) = ∂G/∂S: for a rotation DOF i and a joint j
    below it, ∂R_j = [a_i]× R_j and ∂b_j = a_i × (b_j - o_i); a translation shifts every b_j."""
    F = S.shape[0]
    rot = np.empty((_NJ, 3, 3))
    pos = np.empty((_NJ, 3))
    wax = np.empty((30, 3))
    piv = np.empty((30, 3))
    inside = np.empty(_NJ, dtype=np.bool_)
    for f in range(F):
        _frame(S[f], rest, parents, dof_start, dof_order, axis, rot, pos, wax, piv)
        _write_transforms(rot, pos, rest, G[f])
        dG[f] = 0.0
        for i in range(30):
            a0, a1, a2 = wax[i, 0], wax[i, 1], wax[i, 2]
            o0, o1, o2 = piv[i, 0], piv[i, 1], piv[i, 2]
            top = joint[i] if i < 27 else 0
            for j in range(_NJ):  # the joints below DOF i's joint (parents precede children)
                inside[j] = j == top or (j > top and parents[j] >= 0 and inside[parents[j]])
                if not inside[j]:
                    continue
                for r in range(3):  # column r of R_j is row 4j + r of G
                    x0, x1, x2 = G[f, 4 * j + r, 0], G[f, 4 * j + r, 1], G[f, 4 * j + r, 2]
                    dG[f, 4 * j + r, 0, i] = a1 * x2 - a2 * x1
                    dG[f, 4 * j + r, 1, i] = a2 * x0 - a0 * x2
                    dG[f, 4 * j + r, 2, i] = a0 * x1 - a1 * x0
                x0 = G[f, 4 * j + 3, 0] - o0
                x1 = G[f, 4 * j + 3, 1] - o1
                x2 = G[f, 4 * j + 3, 2] - o2
                dG[f, 4 * j + 3, 0, i] = a1 * x2 - a2 * x1
                dG[f, 4 * j + 3, 1, i] = a2 * x0 - a0 * x2
                dG[f, 4 * j + 3, 2, i] = a0 * x1 - a1 * x0
        for j in range(_NJ):
            for c in range(3):
                dG[f, 4 * j + 3, c, 30 + c] = 1.0


@njit(cache=True)
def skin_contracted_hessian(S, lam, rest, parents, dof_start, dof_order, axis, joint, below, H):
    """H (F, 33, 33) = Σ_{a,c} lam[f, a, c] ∂²G[f, a, c]/∂S∂S for lam (F, 96, 3) (∂E/∂G). The translation's rows
    and columns are zero (G is affine in it, the pivots moving along)."""
    rot = np.empty((_NJ, 3, 3))
    pos = np.empty((_NJ, 3))
    wax = np.empty((30, 3))
    piv = np.empty((30, 3))
    P = np.empty((_NJ, 4, 3))  # Σ over the joints below j (j included) of T_j Λ_j, T_j 4×4 and Λ_j 4×3
    M = np.empty((30, 3, 4))  # every rotation DOF's ξ̂ (top three rows): [[a]×, -[a]× o]
    Gf = np.empty((4 * _NJ, 3))
    for f in range(S.shape[0]):
        _frame(S[f], rest, parents, dof_start, dof_order, axis, rot, pos, wax, piv)
        _write_transforms(rot, pos, rest, Gf)
        for j in range(_NJ):
            for r in range(4):
                for c in range(3):
                    if r < 3:  # row r of T_j Λ_j: Σ_k T_j[r, k] Λ_j[k, c], T_j[r, k] = G[4j + k, r]
                        P[j, r, c] = (Gf[4 * j, r] * lam[f, 4 * j, c] + Gf[4 * j + 1, r] * lam[f, 4 * j + 1, c]
                                      + Gf[4 * j + 2, r] * lam[f, 4 * j + 2, c]
                                      + Gf[4 * j + 3, r] * lam[f, 4 * j + 3, c])
                    else:
                        P[j, r, c] = lam[f, 4 * j + 3, c]
        for j in range(_NJ - 1, 0, -1):  # children follow their parents: accumulate from the leaves
            p = parents[j]
            for r in range(4):
                for c in range(3):
                    P[p, r, c] += P[j, r, c]
        for i in range(30):
            a0, a1, a2 = wax[i, 0], wax[i, 1], wax[i, 2]
            o0, o1, o2 = piv[i, 0], piv[i, 1], piv[i, 2]
            M[i, 0, 0] = 0.0
            M[i, 0, 1] = -a2
            M[i, 0, 2] = a1
            M[i, 1, 0] = a2
            M[i, 1, 1] = 0.0
            M[i, 1, 2] = -a0
            M[i, 2, 0] = -a1
            M[i, 2, 1] = a0
            M[i, 2, 2] = 0.0
            M[i, 0, 3] = -(a1 * o2 - a2 * o1)
            M[i, 1, 3] = -(a2 * o0 - a0 * o2)
            M[i, 2, 3] = -(a0 * o1 - a1 * o0)
        H[f] = 0.0
        for t in range(30):
            jt = joint[t] if t < 27 else 0
            for s in range(30):
                if not below[s, t]:  # DOF t is not on the chain below s (nor s itself)
                    continue
                # E = (ξ̂_s ξ̂_t)[:3] = M_s[:, :3] · M_t (the 4th row of ξ̂ is zero); H[s, t] = tr(E P_jt)
                acc = 0.0
                for c in range(3):
                    for r in range(4):
                        e = M[s, c, 0] * M[t, 0, r] + M[s, c, 1] * M[t, 1, r] + M[s, c, 2] * M[t, 2, r]
                        acc += e * P[jt, r, c]
                H[f, s, t] = acc
                H[f, t, s] = acc


def tables():
    """The skeleton arrays the kernels take after S and rest: (parents, dof_start, dof_order, axis, joint, below)."""
    return _PARENTS, _DOF_START, _DOF_ORDER, _AXIS, _JOINT, _BELOW
