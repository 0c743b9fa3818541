"""Event correspondences of E_cor (paper Eq. 5) and the temporal-stabilisation indicator φ of E_temp (Eq. 8).

Correspondence search (one ICP step). For every tracking frame i = 1..N-1 of a batch, the template is posed with
the current estimate S_i and rasterised (z-buffered, :func:`eventcap.imaging.render.rasterize`). For every track h valid at
frame i, the surface point under its pixel p_{i,h} is picked (triangle + perspective-correct barycentrics,
:func:`eventcap.imaging.render.pick_surface_points`); τ(p_{i,h}) = 0 — no correspondence — where no mesh lies under the
pixel. The point then yields one correspondence per neighbour j ∈ {i-1, i+1} at which the track is valid too: the
point, carried by the skeleton with the pose S_j, should project onto p_{j,h}.

A correspondence is stored in the form the solver evaluates: a rest-space point and skinning weights, posed by
linear blend skinning with S_j. The weights are the barycentric blend of the triangle's vertex weights; the rest
point is the one that this blend maps *exactly* onto the picked surface point at S_i (one 3×3 solve per point), so
that at the frame where it was found the correspondence reprojects onto its pixel without any approximation error
(a residual there would pull a static body part). Where the blended rotation is nearly singular
(|det| < ``MIN_BLEND_DET``: skin between strongly bent segments), the point is attached rigidly to its dominant
joint instead — exact at S_i as well.

Body parts (for φ). Each correspondence is labelled with the dominant joint of its blended weights (the same
labels as :attr:`Template.dominant_joint`). A joint's position relative to the body is set by the angles of its
nearest ancestor with degrees of freedom, a(l) (the knee for the ankle, the elbow for wrist and hand, spine1 for
the neck); a correspondence on any segment hanging from a(l) observes those angles. So the *body part of joint l*
is the subtree of a(l) (for the root and the hips — placed by the root pose — the whole body), and φ(l) = 1 (hold
the joint still, Eq. 8) when no correspondence lies on it. (Tried first: only the segments adjacent to the joint;
on sparse tracks it held hands and feet that had no track of their own but were swung by a tracked limb, and
the batch result got worse than without E_temp.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from eventcap.body.kinematics import global_transforms, skin
from eventcap.body.skeleton import DOF_JOINT, NUM_JOINTS, NUM_POSE_PARAMS, PARENTS
from eventcap.body.template import Template
from eventcap.camera import Camera
from eventcap.imaging.render import Render, pick_surface_points, rasterize

from .settings import PHI_SCOPES

#: Below this |det| of the blended rotation Σ_j w_j R_j a point is attached rigidly to its dominant joint instead of
#: being solved for (the blend of strongly different rotations degenerates).
MIN_BLEND_DET = 0.3

#: Tracks nearer than this to a silhouette or self-occlusion edge (pixels) give no correspondence: a feature on an
#: occluding contour does not follow one surface point, and the estimate's edge is off by its error.
EDGE_MARGIN_PX = 1.0
#: Depth step between neighbouring pixels that marks a self-occlusion edge (metres).
DEPTH_JUMP_M = 0.1


@dataclass(frozen=True)
class Correspondences:
    """E_cor data of one batch: one row per (source frame i, neighbour frame j, track h) with τ = 1. P rows.

    frame: (P,) int64, j — the tracking frame whose pose S_j moves the point.
    source: (P,) int64, i — the frame at which the point was found under the track's pixel.
    track: (P,) int64, h — column of the sliced tracks.
    rest_points: (P, 3) float64, rest-space position, metres.
    weights: (P, 24) float64, skinning weights, rows sum to 1.
    target_px: (P, 2) float64, p_{j,h}: where the point should project at frame j, pixels.
    source_px: (P, 2) float64, p_{i,h}: where it was found at frame i, pixels.
    part: (P,) int64, dominant joint of the weights (body-part label).
    """

    frame: np.ndarray
    source: np.ndarray
    track: np.ndarray
    rest_points: np.ndarray
    weights: np.ndarray
    target_px: np.ndarray
    source_px: np.ndarray
    part: np.ndarray

    @property
    def n(self) -> int:
        return int(self.frame.shape[0])

    @classmethod
    def empty(cls) -> Correspondences:
        z = np.zeros(0, np.int64)
        return cls(z, z.copy(), z.copy(), np.zeros((0, 3)), np.zeros((0, NUM_JOINTS)), np.zeros((0, 2)),
                   np.zeros((0, 2)), z.copy())


def check_tracks(xy, valid, n_frames: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Sliced tracks as (F, H, 2) float64 pixels and (F, H) bool; ValueError naming the problem otherwise."""
    xy = np.asarray(xy, dtype=np.float64)
    valid = np.asarray(valid)
    if xy.ndim != 3 or xy.shape[2] != 2:
        raise ValueError(f"tracks xy: expected shape (frames, tracks, 2) in pixels, got {xy.shape}")
    if valid.shape != xy.shape[:2] or valid.dtype != bool:
        raise ValueError(f"tracks valid: expected a bool array of shape {xy.shape[:2]}, got {valid.dtype} {valid.shape}")
    if n_frames is not None and xy.shape[0] != n_frames:
        raise ValueError(f"tracks: expected {n_frames} tracking frames (N+1), got {xy.shape[0]}")
    return xy, valid


def edge_distance(depth: np.ndarray, tri_id: np.ndarray, jump_m: float = DEPTH_JUMP_M) -> np.ndarray:
    """(H, W) float32: distance in pixels from each pixel of the rendered body to the nearest silhouette or
    self-occlusion edge (a depth jump > ``jump_m`` between 4-neighbours); 0 off the body."""
    import cv2

    inside = tri_id >= 0
    d = np.where(inside, depth, np.inf).astype(np.float64)
    jump = np.zeros_like(inside)
    with np.errstate(invalid="ignore"):
        dx = np.abs(np.diff(d, axis=1)) > jump_m
        dy = np.abs(np.diff(d, axis=0)) > jump_m
    # Mark the farther pixel of each jump as edge: the nearer surface keeps its pixels.
    jump[:, 1:] |= dx & (d[:, 1:] > d[:, :-1])
    jump[:, :-1] |= dx & (d[:, :-1] > d[:, 1:])
    jump[1:, :] |= dy & (d[1:, :] > d[:-1, :])
    jump[:-1, :] |= dy & (d[:-1, :] > d[1:, :])
    core = (inside & ~jump).astype(np.uint8)
    return cv2.distanceTransform(core, cv2.DIST_L2, 3)


def find_correspondences(template: Template, camera: Camera, poses: np.ndarray, xy: np.ndarray,
                         valid: np.ndarray, edge_margin_px: float = EDGE_MARGIN_PX) -> Correspondences:
    """Correspondences of Eq. 5 for the current pose estimate (see module doc).

    poses: (N+1, 33) current estimates S_0..S_N. xy: (N+1, H, 2) sliced track positions, pixels; valid: (N+1, H)
    bool (positions where not valid are ignored, NaN allowed there). edge_margin_px: tracks closer than this to a
    silhouette or self-occlusion edge of the render at frame i give no correspondence (0 keeps all). Rows are ordered by source frame i, then
    neighbour j (i-1 before i+1), then track h: the result is a deterministic function of the inputs.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] != NUM_POSE_PARAMS:
        raise ValueError(f"poses: expected shape (N+1, 33), got {poses.shape}")
    F = poses.shape[0]
    xy, valid = check_tracks(xy, valid, F)
    if F < 3:
        return Correspondences.empty()
    # Frames with at least one track valid there and at a neighbour: only those need a render.
    has_pair = valid[1:-1] & (valid[:-2] | valid[2:])
    frames = [i for i in range(1, F - 1) if has_pair[i - 1].any()]
    if not frames:
        return Correspondences.empty()
    faces = template.faces
    verts = skin(poses[frames], template)  # (n, V, 3)
    transforms = global_transforms(poses[frames], template)  # (n, 24, 4, 4)
    out = {k: [] for k in ("frame", "source", "track", "rest", "w", "target", "src_px")}
    for n, i in enumerate(frames):
        hs = np.flatnonzero(has_pair[i - 1])
        depth, tri_id, bary = rasterize(camera, verts[n], faces)
        tri, b = pick_surface_points(camera, verts[n], faces, Render(depth, depth, tri_id, bary), xy[i, hs])
        on = tri >= 0
        if edge_margin_px > 0 and on.any():
            dist = edge_distance(depth, tri_id)
            px = np.clip(np.rint(xy[i, hs]).astype(np.int64), 0, [camera.width - 1, camera.height - 1])
            on &= dist[px[:, 1], px[:, 0]] >= edge_margin_px
        if not on.any():
            continue
        hs, tri, b = hs[on], tri[on], b[on]
        corner = faces[tri]  # (p, 3) vertex ids
        posed = np.einsum("pk,pkd->pd", b, verts[n][corner])  # the surface point under the pixel, exactly
        bc = np.clip(b, 0.0, None)
        bc /= bc.sum(axis=1, keepdims=True)
        w = np.einsum("pk,pkj->pj", bc, template.weights[corner])
        rest, w = rest_point(posed, w, transforms[n])
        for j in (i - 1, i + 1):
            ok = valid[j, hs]
            if not ok.any():
                continue
            out["frame"].append(np.full(int(ok.sum()), j, np.int64))
            out["source"].append(np.full(int(ok.sum()), i, np.int64))
            out["track"].append(hs[ok].astype(np.int64))
            out["rest"].append(rest[ok])
            out["w"].append(w[ok])
            out["target"].append(xy[j, hs[ok]])
            out["src_px"].append(xy[i, hs[ok]])
    if not out["frame"]:
        return Correspondences.empty()
    w = np.concatenate(out["w"])
    return Correspondences(
        frame=np.concatenate(out["frame"]), source=np.concatenate(out["source"]),
        track=np.concatenate(out["track"]), rest_points=np.concatenate(out["rest"]), weights=w,
        target_px=np.concatenate(out["target"]), source_px=np.concatenate(out["src_px"]),
        part=np.argmax(w, axis=1).astype(np.int64),
    )


def rest_point(posed: np.ndarray, w: np.ndarray, transforms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rest points x with Σ_j w_j (R_j x + b_j) = posed, and the weights to use; (P, 3), (P, 24).

    transforms (24, 4, 4) of the frame. Where the blended rotation is nearly singular the point is attached rigidly
    to its dominant joint instead (one-hot weights), which is exact at this frame too.
    """
    A = np.einsum("pj,jab->pab", w, transforms[:, :3, :3])
    c = np.einsum("pj,ja->pa", w, transforms[:, :3, 3])
    ok = np.abs(np.linalg.det(A)) >= MIN_BLEND_DET
    rest = np.empty_like(posed)
    w = w.copy()
    if ok.any():
        rest[ok] = np.linalg.solve(A[ok], (posed[ok] - c[ok])[..., None])[..., 0]
    if not ok.all():
        bad = np.flatnonzero(~ok)
        dom = np.argmax(w[bad], axis=1)
        R, b = transforms[dom, :3, :3], transforms[dom, :3, 3]
        rest[bad] = np.einsum("pba,pb->pa", R, posed[bad] - b)  # R^T (y - b)
        w[bad] = 0.0
        w[bad, dom] = 1.0
    return rest, w


def joint_parts() -> np.ndarray:
    """(24, 24) bool: ``[l, k]`` — points labelled k lie on the body part of joint l (module doc)."""
    has_dofs = np.zeros(NUM_JOINTS, dtype=bool)
    has_dofs[DOF_JOINT] = True
    has_dofs[0] = True  # the root's rotation and translation
    # Subtree membership: sub[a, k] — k is a or a descendant of a (parents precede children).
    sub = np.eye(NUM_JOINTS, dtype=bool)
    for k in range(1, NUM_JOINTS):
        sub[:, k] |= sub[:, PARENTS[k]]
    m = np.zeros((NUM_JOINTS, NUM_JOINTS), dtype=bool)
    m[0] = True  # the root moves with everything
    for j in range(1, NUM_JOINTS):
        a = PARENTS[j]
        while not has_dofs[a]:
            a = PARENTS[a]
        m[j] = sub[a]
    return m


def temporal_indicator(corr: Correspondences, n_frames: int, scope: str = "batch") -> np.ndarray:
    """φ of Eq. 8 per frame pair (i, i+1) and joint: (N, 24) float64 of 0/1, N = n_frames - 1.

    scope: "batch" (paper: a joint is held at every pair when its body part has no correspondence in the batch)
    or "pair" (only pairs where its part has no correspondence evaluated at S_i or S_{i+1}). Parts: module doc.
    """
    if scope not in PHI_SCOPES:
        raise ValueError(f"phi scope: expected one of {PHI_SCOPES}, got {scope!r}")
    if n_frames < 2:
        raise ValueError(f"temporal_indicator: expected at least 2 tracking frames, got {n_frames}")
    n_pairs = n_frames - 1
    parts = joint_parts().astype(np.float64)  # (l, k)
    if scope == "batch":
        has = np.zeros(NUM_JOINTS)
        has[np.unique(corr.part)] = 1.0
        covered = (parts @ has) > 0  # (l,)
        return np.repeat((~covered)[None, :].astype(np.float64), n_pairs, axis=0)
    # Per frame: which labels have a correspondence evaluated there; a pair is covered by either of its frames.
    at = np.zeros((n_frames, NUM_JOINTS))
    np.add.at(at, (corr.frame, corr.part), 1.0)
    covered_f = (at @ parts.T) > 0  # (F, l)
    covered = covered_f[:-1] | covered_f[1:]
    return (~covered).astype(np.float64)


def correspondence_change_px(old: Correspondences, r_old: np.ndarray, new: Correspondences,
                             r_new: np.ndarray) -> float:
    """How much a new correspondence search changed E_cor, in pixels: the RMS over the union of the two sets of the
    change of each correspondence's image residual at the same poses (r_old (P_old, 2), r_new (P_new, 2), e.g.
    ``EventCorrespondences.residuals_px_of``). A correspondence is the same one in both when its (source frame,
    neighbour frame, track) is: it counts with ‖r_new - r_old‖; one found only now counts with ‖r_new‖ (the pull it
    adds), one no longer found with ‖r_old‖ (the pull it takes away). 0: the search found what the last solve
    already fitted; 0 as well when neither set has a correspondence."""
    r_old = np.asarray(r_old, dtype=np.float64).reshape(old.n, 2)
    r_new = np.asarray(r_new, dtype=np.float64).reshape(new.n, 2)
    if old.n + new.n == 0:
        return 0.0
    width = int(max(old.track.max(initial=0), new.track.max(initial=0))) + 1
    frames = int(max(old.frame.max(initial=0), old.source.max(initial=0), new.frame.max(initial=0),
                     new.source.max(initial=0))) + 1

    def keys(c: Correspondences) -> np.ndarray:
        return (c.source * frames + c.frame) * width + c.track

    k_old, k_new = keys(old), keys(new)
    _, i_old, i_new = np.intersect1d(k_old, k_new, assume_unique=False, return_indices=True)
    only_old = np.ones(old.n, dtype=bool)
    only_old[i_old] = False
    only_new = np.ones(new.n, dtype=bool)
    only_new[i_new] = False
    sq = (np.sum((r_new[i_new] - r_old[i_old]) ** 2) + np.sum(r_old[only_old] ** 2) + np.sum(r_new[only_new] ** 2))
    return float(np.sqrt(sq / (i_old.size + only_old.sum() + only_new.sum())))
