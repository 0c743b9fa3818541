"""Silhouette boundary of the posed template (paper Sec. 3.3): the pixels s_b, their 2D normals n_b and the surface
points v_b under them, in the form the refinement energy evaluates.

Per tracking frame the template is posed with the current estimate S_f (linear blend skinning) and rasterised
(z-buffer, as :func:`eventcap.imaging.render.rasterize`; :func:`rasterize_frames`).

- Boundary pixels s_b: pixels of the body mask with at least one background 4-neighbour inside the image (the
  image border is not a silhouette edge: a body cut off by the border has no boundary there).
- Normal n_b: minus the gradient of the mask smoothed by a Gaussian (σ = ``NORMAL_SIGMA_PX``), i.e. the mask
  correlated with the derivative of a sampled Gaussian (7×7 taps, image border replicated) at s_b, normalised: unit
  length, pointing out of the body. Pixels where that gradient vanishes (|∇| < ``MIN_GRADIENT``: e.g. a
  one-pixel-wide sliver seen from both sides) get no normal and are left out.
- Surface point v_b: the triangle under s_b's pixel centre and its perspective-correct barycentrics (from the
  rasteriser) give the 3D point seen there. It is stored as a rest-space point with skinning weights blended from
  the triangle's vertices; the rest point is solved so that LBS with S_f maps it *exactly* onto the picked point
  (as ``eventcap.energy.correspondences.rest_point`` does, compiled for all frames at once; rigid attachment to the
  dominant joint where the blended rotation is nearly singular), so π(v_b(S_f)) is s_b's pixel centre at the pose
  it was found with.

The boundary scan and the rest-point solves are compiled loops (:mod:`._sil_kernels`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from eventcap.body.kinematics import global_transforms, skin
from eventcap.body.template import Template
from eventcap.camera import Camera
from eventcap.imaging.render import rasterize

#: σ of the Gaussian smoothing the body mask before its gradient gives the boundary normals (pixels).
NORMAL_SIGMA_PX = 1.0
#: Boundary pixels where the smoothed mask's gradient is weaker than this (per pixel) get no normal.
MIN_GRADIENT = 1e-3


@dataclass(frozen=True)
class BoundarySamples:
    """Boundary samples of F frames, ordered by frame, then row-major pixel order. B samples."""

    frame: np.ndarray  #: (B,) int64, tracking frame index
    pixel: np.ndarray  #: (B, 2) int64, s_b = (x, y)
    normal: np.ndarray  #: (B, 2) float64, n_b, unit, outward
    rest_points: np.ndarray  #: (B, 3) float64, rest-space position of v_b (metres)
    weights: np.ndarray  #: (B, 24) float64, its skinning weights
    masks: np.ndarray  #: (F, H, W) bool, the rendered body masks (silhouettes) of the frames

    @property
    def n(self) -> int:
        return int(self.frame.shape[0])

    def take(self, keep: np.ndarray) -> BoundarySamples:
        """The samples where ``keep`` (B,) bool is true (masks unchanged)."""
        return BoundarySamples(self.frame[keep], self.pixel[keep], self.normal[keep], self.rest_points[keep],
                               self.weights[keep], self.masks)


def rasterize_frames(camera: Camera, verts: np.ndarray, faces: np.ndarray, near_m: float = 0.05):
    """``eventcap.imaging.render.rasterize`` of each mesh verts[f] (F, V, 3): (tri_id (F, H, W) int32, bary: list of F
    (H, W, 3) float32), depth left out. The same z-buffer (the renderer's compiled kernel) and vertex handling, with
    the camera projection of all frames' vertices in one compiled loop (numpy's projection of 41 × 6k vertices took
    as long as the z-buffer itself); the tests check it against ``rasterize``."""
    from eventcap.imaging.render import _rasterize

    from ._sil_kernels import camera_params, project_points

    F, V = verts.shape[:2]
    flat = np.ascontiguousarray(verts, dtype=np.float64).reshape(-1, 3)
    px, z = np.empty((flat.shape[0], 2)), np.empty(flat.shape[0])
    project_points(flat, camera_params(camera), px, z)
    r_max = camera.max_valid_radius
    if np.isfinite(r_max):  # beyond it the distortion folds back: such vertices drop their triangles
        pc = camera.to_camera(flat)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.hypot(pc[:, 0], pc[:, 1]) / pc[:, 2]
        z = np.where(r <= r_max, z, np.nan)
    px, z = px.reshape(F, V, 2), z.reshape(F, V)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    H, W = camera.height, camera.width
    tri_id = np.full((F, H, W), -1, dtype=np.int32)
    bary = []
    for f in range(F):
        depth = np.full((H, W), np.inf, dtype=np.float32)
        b = np.zeros((H, W, 3), dtype=np.float32)
        _rasterize(px[f], z[f], faces, H, W, float(near_m), False, depth, tri_id[f], b)
        bary.append(b)
    return tri_id, bary


def boundary_pixels(mask: np.ndarray, sigma_px: float = NORMAL_SIGMA_PX):
    """Boundary pixels and their outward unit normals of a bool mask (H, W) or a stack of masks (F, H, W).

    Returns (pixels (B, 2) int64 (x, y) row-major, normals (B, 2)) for one mask; for a stack also the frame of
    each pixel first: (frame (B,), pixels, normals), ordered by frame. Pixels without a normal are left out.
    """
    from ._sil_kernels import boundary_scan

    m = np.asarray(mask, dtype=bool)
    single = m.ndim == 2
    if single:
        m = m[None]
    if m.ndim != 3:
        raise ValueError(f"mask: expected a (height, width) bool image or a stack of them, got shape {m.shape}")
    if not sigma_px > 0:
        raise ValueError(f"sigma_px: expected a positive number of pixels, got {sigma_px!r}")
    frame, x, y, nx, ny = boundary_scan(m, float(sigma_px), MIN_GRADIENT)
    px, normal = np.stack([x, y], axis=1), np.stack([nx, ny], axis=1)
    return (px, normal) if single else (frame, px, normal)


def boundary_samples(template: Template, camera: Camera, poses: np.ndarray,
                     sigma_px: float = NORMAL_SIGMA_PX) -> BoundarySamples:
    """Boundary samples of the template posed with each row of ``poses`` (F, 33) (module doc)."""
    from eventcap.energy.correspondences import MIN_BLEND_DET

    from ._sil_kernels import rest_points

    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] != 33:
        raise ValueError(f"poses: expected shape (F, 33), got {poses.shape}")
    F = poses.shape[0]
    verts = skin(poses, template)  # (F, V, 3)
    transforms = global_transforms(poses, template)  # (F, 24, 4, 4)
    faces = np.asarray(template.faces, dtype=np.int64)
    tri_id, bary = rasterize_frames(camera, verts, faces)
    masks = tri_id >= 0
    frame, px, normal = boundary_pixels(masks, sigma_px)
    tri = tri_id[frame, px[:, 1], px[:, 0]]
    b = np.empty((frame.size, 3))
    bounds = np.searchsorted(frame, np.arange(F + 1))
    for f in range(F):
        sl = slice(bounds[f], bounds[f + 1])
        b[sl] = bary[f][px[sl, 1], px[sl, 0]]
    corner = faces[tri]  # (B, 3) vertex ids
    posed = np.einsum("pk,pkd->pd", b, verts[frame[:, None], corner])  # the surface point under the pixel centre
    bc = np.clip(b, 0.0, None)
    bc /= bc.sum(axis=1, keepdims=True)
    w = np.einsum("pk,pkj->pj", bc, template.weights[corner])
    rest, w_out = np.empty_like(posed), np.empty_like(w)
    rest_points(posed, w, frame, np.ascontiguousarray(transforms), float(MIN_BLEND_DET), rest, w_out)
    return BoundarySamples(frame, px, normal, rest, w_out, masks)


def silhouette_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Intersection over union of two stacks of masks (F, H, W) per frame (F,); 1 where both are empty."""
    a, b = np.asarray(a, dtype=bool), np.asarray(b, dtype=bool)
    inter = (a & b).sum(axis=(-2, -1))
    union = (a | b).sum(axis=(-2, -1))
    return np.where(union > 0, inter / np.maximum(union, 1), 1.0)


def silhouettes(template: Template, camera: Camera, poses: np.ndarray) -> np.ndarray:
    """(F, H, W) bool body masks of the template posed with each row of ``poses`` (F, 33)."""
    poses = np.atleast_2d(np.asarray(poses, dtype=np.float64))
    verts = skin(poses, template)
    faces = np.asarray(template.faces, dtype=np.int64)
    return np.stack([rasterize(camera, v, faces)[1] >= 0 for v in verts])
