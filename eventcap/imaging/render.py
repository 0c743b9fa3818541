"""Z-buffered triangle rasteriser for the synthetic event camera, and the look-ups ground truth needs on it.

What it does and where it approximates:

- Vertices are projected with the camera's full model (distortion included); each triangle is then filled as a
  straight-edged triangle in pixel space. Real distortion bends edges, but for the small triangles of a body mesh
  (a few pixels) the error is far below a pixel. Big triangles near the image border would be off by more.
- A pixel is covered when its centre lies inside the triangle (edges inclusive). Pixel ``(x, y)`` covers
  ``[x - 0.5, x + 0.5] × [y - 0.5, y + 0.5]``: integer coordinates are pixel centres (OpenCV convention).
  No anti-aliasing: one sample per pixel.
- Depth test is exact per sample: ``1/z`` is interpolated linearly in screen space (exact for a pinhole camera),
  the nearest surface wins, ties keep the triangle drawn first (lower index).
- Barycentrics are perspective-correct: they are the 3D barycentric coordinates of the surface point seen
  through the pixel centre, so ``sum(bary[..., i] * V[faces[tri, i]])`` is that 3D point.
- Triangles with a vertex closer than ``near_m`` (or behind the camera), or beyond the radius where the lens
  distortion stops being monotonic, are dropped whole, not clipped: fine for an actor metres away.
- Shading: Lambertian, one directional light plus ambient, on per-vertex albedo; normals are interpolated vertex
  normals (smooth shading) so a faceted mesh does not produce edge texture of its own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from eventcap.camera import Camera


@dataclass(frozen=True)
class Light:
    """A directional light plus ambient term (linear intensity units, albedo 1 facing the light gets
    ``ambient + diffuse``)."""

    #: (3,) world direction from the surface *towards* the light; normalised on use. Default: above, in front
    #: of the actor (who faces +z) and a little to their left, so the front of the body is lit.
    direction: tuple[float, float, float] = (0.3, 0.8, 0.6)
    ambient: float = 0.35
    diffuse: float = 0.65


@dataclass(frozen=True)
class Render:
    """One rendered frame. All arrays (H, W[, 3]); H = camera.height, W = camera.width."""

    intensity: np.ndarray  #: (H,W) float32, linear intensity in [0, 1]; background where no surface
    depth: np.ndarray  #: (H,W) float32, camera z in metres; +inf where no surface
    tri_id: np.ndarray  #: (H,W) int32, index of the visible triangle; -1 where no surface
    bary: np.ndarray  #: (H,W,3) float32, perspective-correct barycentrics of the pixel centre; 0 where empty


@dataclass(frozen=True)
class SurfacePoints:
    """Surface points of a posed mesh as seen by a camera. P points."""

    world: np.ndarray  #: (P,3) float64 world positions, metres
    pixels: np.ndarray  #: (P,2) float64 projections, pixels (NaN behind the camera)
    depth: np.ndarray  #: (P,) float64 camera z, metres
    visible: np.ndarray  #: (P,) bool: in the image, in front of the camera and not occluded


# --------------------------------------------------------------------------------------------------- kernels
@njit(cache=True)
def _rasterize(px, z, faces, height, width, near, cull_backfaces, depth, tri_id, bary):
    """Fill depth/tri_id/bary in place. px (V,2) pixels, z (V,) camera depth (NaN-free where z ≥ near)."""
    for f in range(faces.shape[0]):
        i0 = faces[f, 0]
        i1 = faces[f, 1]
        i2 = faces[f, 2]
        z0 = z[i0]
        z1 = z[i1]
        z2 = z[i2]
        # `not (z >= near)` also drops NaN depths (vertices flagged invalid by the caller).
        if not (z0 >= near and z1 >= near and z2 >= near):
            continue
        x0 = px[i0, 0]
        y0 = px[i0, 1]
        x1 = px[i1, 0]
        y1 = px[i1, 1]
        x2 = px[i2, 0]
        y2 = px[i2, 1]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if not (abs(area) > 1e-12):
            continue
        # In pixel coordinates (y down) a triangle whose outward normal faces the camera has area < 0.
        if cull_backfaces and area > 0.0:
            continue
        xmin = max(int(np.ceil(min(x0, x1, x2))), 0)
        xmax = min(int(np.floor(max(x0, x1, x2))), width - 1)
        ymin = max(int(np.ceil(min(y0, y1, y2))), 0)
        ymax = min(int(np.floor(max(y0, y1, y2))), height - 1)
        if xmin > xmax or ymin > ymax:
            continue
        inv_area = 1.0 / area
        iz0 = 1.0 / z0
        iz1 = 1.0 / z1
        iz2 = 1.0 / z2
        # Inclusive edges with a tiny slack so that a pixel centre exactly on a shared edge is never missed by
        # both neighbours; the depth test settles double coverage.
        eps = -1e-9
        for y in range(ymin, ymax + 1):
            for x in range(xmin, xmax + 1):
                w0 = ((x1 - x) * (y2 - y) - (x2 - x) * (y1 - y)) * inv_area
                if w0 < eps:
                    continue
                w1 = ((x2 - x) * (y0 - y) - (x0 - x) * (y2 - y)) * inv_area
                if w1 < eps:
                    continue
                w2 = ((x0 - x) * (y1 - y) - (x1 - x) * (y0 - y)) * inv_area
                if w2 < eps:
                    continue
                q0 = w0 * iz0
                q1 = w1 * iz1
                q2 = w2 * iz2
                s = q0 + q1 + q2
                zz = 1.0 / s
                if zz < depth[y, x]:
                    depth[y, x] = zz
                    tri_id[y, x] = f
                    bary[y, x, 0] = q0 / s
                    bary[y, x, 1] = q1 / s
                    bary[y, x, 2] = q2 / s


@njit(cache=True)
def _vertex_normals(vertices, faces):
    """(V,3) unit area-weighted vertex normals (outward for counter-clockwise faces seen from outside)."""
    n = np.zeros_like(vertices)
    for f in range(faces.shape[0]):
        a = faces[f, 0]
        b = faces[f, 1]
        c = faces[f, 2]
        e1x = vertices[b, 0] - vertices[a, 0]
        e1y = vertices[b, 1] - vertices[a, 1]
        e1z = vertices[b, 2] - vertices[a, 2]
        e2x = vertices[c, 0] - vertices[a, 0]
        e2y = vertices[c, 1] - vertices[a, 1]
        e2z = vertices[c, 2] - vertices[a, 2]
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        for v in (a, b, c):
            n[v, 0] += nx
            n[v, 1] += ny
            n[v, 2] += nz
    for v in range(n.shape[0]):
        norm = np.sqrt(n[v, 0] ** 2 + n[v, 1] ** 2 + n[v, 2] ** 2)
        if norm > 0.0:
            n[v, 0] /= norm
            n[v, 1] /= norm
            n[v, 2] /= norm
    return n


@njit(cache=True)
def _shade(tri_id, bary, faces, normals, albedo, light_dir, ambient, diffuse, intensity):
    """Write Lambertian intensity into covered pixels of ``intensity`` (in place), clipped to [0, 1]."""
    height, width = tri_id.shape
    for y in range(height):
        for x in range(width):
            f = tri_id[y, x]
            if f < 0:
                continue
            a = 0.0
            nx = 0.0
            ny = 0.0
            nz = 0.0
            for k in range(3):
                v = faces[f, k]
                b = bary[y, x, k]
                a += b * albedo[v]
                nx += b * normals[v, 0]
                ny += b * normals[v, 1]
                nz += b * normals[v, 2]
            norm = np.sqrt(nx * nx + ny * ny + nz * nz)
            lam = 0.0
            if norm > 0.0:
                lam = (nx * light_dir[0] + ny * light_dir[1] + nz * light_dir[2]) / norm
            val = a * (ambient + diffuse * max(lam, 0.0))
            intensity[y, x] = min(max(val, 0.0), 1.0)


@njit(cache=True)
def _box_downsample(img, s):
    """Mean over s×s blocks: (H·s, W·s) float32 -> (H, W) float32."""
    height = img.shape[0] // s
    width = img.shape[1] // s
    out = np.empty((height, width), dtype=np.float32)
    inv = 1.0 / (s * s)
    for y in range(height):
        for x in range(width):
            acc = 0.0
            for i in range(s):
                for j in range(s):
                    acc += img[y * s + i, x * s + j]
            out[y, x] = acc * inv
    return out


# --------------------------------------------------------------------------------------------------- API
def _check_mesh(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    V = np.ascontiguousarray(vertices, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] != 3:
        raise ValueError(f"vertices: expected shape (V, 3) in metres, got {V.shape}")
    F = np.asarray(faces)
    if F.ndim != 2 or F.shape[1] != 3 or not np.issubdtype(F.dtype, np.integer):
        raise ValueError(f"faces: expected an integer array of shape (F, 3), got {F.dtype} {F.shape}")
    if F.size and (F.min() < 0 or F.max() >= V.shape[0]):
        raise ValueError(f"faces: vertex indices must lie in [0, {V.shape[0]}), got [{F.min()}, {F.max()}]")
    return V, np.ascontiguousarray(F, dtype=np.int64)


def rasterize(camera: Camera, vertices, faces, cull_backfaces: bool = False,
              near_m: float = 0.05) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Geometry pass only: ``(depth (H,W) float32, tri_id (H,W) int32, bary (H,W,3) float32)``; see module doc."""
    V, F = _check_mesh(vertices, faces)
    if not near_m > 0:
        raise ValueError(f"near_m: expected a positive distance in metres, got {near_m}")
    px = camera.project(V)
    z = camera.depth(V)
    r_max = camera.max_valid_radius
    if np.isfinite(r_max):
        pc = camera.to_camera(V)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.hypot(pc[:, 0], pc[:, 1]) / pc[:, 2]
        z = np.where(r <= r_max, z, np.nan)
    px = np.nan_to_num(px, nan=0.0, posinf=0.0, neginf=0.0)  # such vertices already fail the depth check
    # Computed in float64, stored in float32 (1e-6 m at 4 m: far below anything the pipeline resolves).
    depth = np.full((camera.height, camera.width), np.inf, dtype=np.float32)
    tri_id = np.full((camera.height, camera.width), -1, dtype=np.int32)
    bary = np.zeros((camera.height, camera.width, 3), dtype=np.float32)
    _rasterize(px, z, F, camera.height, camera.width, float(near_m), bool(cull_backfaces), depth, tri_id, bary)
    return depth, tri_id, bary


def render(camera: Camera, vertices, faces, vertex_albedo, background=None, light: Light = Light(),
           cull_backfaces: bool = False, near_m: float = 0.05, supersample: int = 1) -> Render:
    """Render a mesh: vertices (V,3) world metres, faces (F,3) int, vertex_albedo (V,) in [0,1].

    background: (H,W) float image (linear intensity) shown where no surface is, or None for 0.
    Faces are counter-clockwise seen from outside (outward normals); only ``cull_backfaces`` relies on it.
    supersample: odd s ≥ 1; with s > 1 the intensity is the mean of s×s samples spread over each pixel's
    area (what a sensor pixel integrates: no stair-stepped edges flickering as they move), at ~s²× the cost
    per covered pixel. depth, tri_id and bary always describe the pixel centre (the middle sample).
    """
    V, F = _check_mesh(vertices, faces)
    albedo = np.ascontiguousarray(vertex_albedo, dtype=np.float64)
    if albedo.shape != (V.shape[0],):
        raise ValueError(f"vertex_albedo: expected shape ({V.shape[0]},), got {albedo.shape}")
    if int(supersample) != supersample or supersample < 1 or supersample % 2 == 0:
        raise ValueError(f"supersample: expected an odd integer ≥ 1, got {supersample!r}")
    s = int(supersample)
    shape = (camera.height, camera.width)
    if background is None:
        bg = np.zeros(shape, dtype=np.float32)
    else:
        bg = np.asarray(background)
        if bg.shape != shape:
            raise ValueError(f"background: expected shape (height, width) = {shape}, got {bg.shape}")
        bg = bg.astype(np.float32)
    light_dir = np.asarray(light.direction, dtype=np.float64)
    norm = np.linalg.norm(light_dir)
    if light_dir.shape != (3,) or not norm > 0:
        raise ValueError(f"light.direction: expected a non-zero 3-vector, got {light.direction!r}")
    # Sample i of pixel x sits at x - 1/2 + (i + 1/2)/s, i.e. at s·x + (s-1)/2 on an s-times finer grid.
    fine = camera if s == 1 else Camera(camera.width * s, camera.height * s, camera.fx * s, camera.fy * s,
                                        camera.cx * s + (s - 1) / 2, camera.cy * s + (s - 1) / 2,
                                        camera.dist, camera.R, camera.t)
    depth, tri_id, bary = rasterize(fine, V, F, cull_backfaces, near_m)
    intensity = bg if s == 1 else np.repeat(np.repeat(bg, s, axis=0), s, axis=1)
    normals = _vertex_normals(V, F)
    _shade(tri_id, bary, F, normals, albedo, light_dir / norm, float(light.ambient), float(light.diffuse),
           intensity)
    if s > 1:
        intensity = _box_downsample(intensity, s)
        c = s // 2
        depth, tri_id, bary = (np.ascontiguousarray(a[c::s, c::s]) for a in (depth, tri_id, bary))
    return Render(intensity=intensity, depth=depth, tri_id=tri_id, bary=bary)


def silhouette(rendered: Render) -> np.ndarray:
    """(H,W) bool mask of pixels covered by the mesh."""
    return rendered.tri_id >= 0


def surface_points(camera: Camera, vertices, faces, tri_id, bary, rendered: Render,
                   depth_tol_m: float = 0.02) -> SurfacePoints:
    """World positions, projections and visibility of surface points given as (triangle, barycentrics).

    tri_id (P,) int and bary (P,3) (3D barycentrics, rows summing to 1) refer to ``faces``; ``vertices`` (V,3)
    is the posed mesh that ``rendered`` was made from. A point is visible when it is in front of the camera,
    its projection rounds to a pixel inside the image, and that pixel shows the point's own triangle or a
    surface within ``depth_tol_m`` of the point's depth (neighbouring triangles of the same surface).
    """
    V, F = _check_mesh(vertices, faces)
    tri = np.asarray(tri_id)
    b = np.asarray(bary, dtype=np.float64)
    if tri.ndim != 1 or not np.issubdtype(tri.dtype, np.integer):
        raise ValueError(f"tri_id: expected an integer array of shape (P,), got {tri.dtype} {tri.shape}")
    if b.shape != (tri.shape[0], 3):
        raise ValueError(f"bary: expected shape ({tri.shape[0]}, 3), got {b.shape}")
    if tri.size and (tri.min() < 0 or tri.max() >= F.shape[0]):
        raise ValueError(f"tri_id: expected indices in [0, {F.shape[0]}), got [{tri.min()}, {tri.max()}]")
    world = np.einsum("pk,pkd->pd", b, V[F[tri]])
    pixels = camera.project(world)
    depth = camera.depth(world)
    with np.errstate(invalid="ignore"):
        ix = np.floor(pixels[:, 0] + 0.5)
        iy = np.floor(pixels[:, 1] + 0.5)
        inside = (depth > 0) & (ix >= 0) & (ix < camera.width) & (iy >= 0) & (iy < camera.height)
    ixi = np.where(inside, ix, 0).astype(np.intp)
    iyi = np.where(inside, iy, 0).astype(np.intp)
    shown_tri = rendered.tri_id[iyi, ixi]
    shown_depth = rendered.depth[iyi, ixi].astype(np.float64)
    visible = inside & ((shown_tri == tri) | (np.abs(shown_depth - depth) <= depth_tol_m))
    return SurfacePoints(world=world, pixels=pixels, depth=depth, visible=visible)


def pick_surface_points(camera: Camera, vertices, faces, rendered: Render, pixels) -> tuple[np.ndarray, np.ndarray]:
    """The surface points seen at sub-pixel positions: ``(tri_id (P,) int32, bary (P,3) float64)``.

    Takes the triangle shown at the nearest pixel centre and the perspective-correct barycentrics of the exact
    position in it (they may be slightly negative when the position lies just past that triangle's edge).
    ``tri_id`` is -1 (and bary 0) where no surface is shown or the position is outside the image.
    """
    V, F = _check_mesh(vertices, faces)
    uv = np.asarray(pixels, dtype=np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"pixels: expected shape (P, 2), got {uv.shape}")
    with np.errstate(invalid="ignore"):
        ix = np.floor(uv[:, 0] + 0.5)
        iy = np.floor(uv[:, 1] + 0.5)
        inside = (ix >= 0) & (ix < camera.width) & (iy >= 0) & (iy < camera.height)
    tri = np.full(uv.shape[0], -1, dtype=np.int32)
    tri[inside] = rendered.tri_id[iy[inside].astype(np.intp), ix[inside].astype(np.intp)]
    bary = np.zeros((uv.shape[0], 3))
    ok = tri >= 0
    if not ok.any():
        return tri, bary
    corners = V[F[tri[ok]]]  # (P,3,3)
    p = camera.project(corners)  # (P,3,2)
    z = camera.depth(corners)  # (P,3)
    q = uv[ok]
    area = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 2, 0] - p[:, 0, 0]) * (p[:, 1, 1] - p[:, 0, 1])
    w = np.empty((q.shape[0], 3))
    for k in range(3):
        a, b = p[:, (k + 1) % 3], p[:, (k + 2) % 3]
        w[:, k] = ((a[:, 0] - q[:, 0]) * (b[:, 1] - q[:, 1]) - (b[:, 0] - q[:, 0]) * (a[:, 1] - q[:, 1])) / area
    wz = w / z
    bary[ok] = wz / wz.sum(axis=1, keepdims=True)
    return tri, bary


#: Backdrops of the synthetic capture (:func:`background`).
BACKGROUNDS = ("textured", "low_texture", "plain")


def background(kind: str, height: int, width: int, seed: int = 0) -> np.ndarray:
    """A static backdrop (H,W) float32 of linear intensity: ``textured`` (:func:`textured_background`),
    ``low_texture`` (the same room at a quarter of its contrast around its mean: faint edges, few events) or
    ``plain`` (a seamless studio backdrop: one uniform grey, no edge at all)."""
    if kind == "textured":
        return textured_background(height, width, seed)
    if kind == "low_texture":
        img = textured_background(height, width, seed)
        mean = np.float32(img.mean())
        return (mean + np.float32(0.25) * (img - mean)).astype(np.float32)
    if kind == "plain":
        if int(height) != height or int(width) != width or height < 1 or width < 1:
            raise ValueError(f"background: expected integer height, width ≥ 1, got {height}, {width}")
        return np.full((int(height), int(width)), 0.35, np.float32)
    raise ValueError(f"background: expected one of {' | '.join(BACKGROUNDS)}, got {kind!r}")


def textured_background(height: int, width: int, seed: int = 0) -> np.ndarray:
    """A static synthetic backdrop (H,W) float32, linear intensity ~0.05–0.75: a textured wall with framed
    panels and a door, a dark skirting board, and a tiled floor in perspective below a horizon."""
    import cv2

    if int(height) != height or int(width) != width or height < 8 or width < 8:
        raise ValueError(f"textured_background: expected integer height, width ≥ 8, got {height}, {width}")
    height, width = int(height), int(width)
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)

    def smooth_noise(scale_px: float) -> np.ndarray:
        n = rng.standard_normal((height, width))
        n = cv2.GaussianBlur(n, (0, 0), scale_px)
        return n / (n.std() + 1e-12)

    horizon = height * rng.uniform(0.58, 0.66)
    img = 0.38 + 0.03 * smooth_noise(width / 8) + 0.012 * smooth_noise(1.5)  # plaster wall

    # Framed panels / posters and a door: rectangles with their own tone and a darker frame.
    for _ in range(rng.integers(3, 6)):
        w = rng.uniform(0.08, 0.22) * width
        h = rng.uniform(0.12, 0.3) * height
        x0 = rng.uniform(0, width - w)
        y0 = rng.uniform(0.05 * height, max(horizon - h - 0.05 * height, 0.06 * height))
        inner = (xx >= x0) & (xx < x0 + w) & (yy >= y0) & (yy < y0 + h)
        frame = (xx >= x0 - 2) & (xx < x0 + w + 2) & (yy >= y0 - 2) & (yy < y0 + h + 2) & ~inner
        img[frame] = rng.uniform(0.1, 0.2)
        img[inner] = rng.uniform(0.25, 0.7) + 0.04 * smooth_noise(3.0)[inner]
    door_x = rng.uniform(0.05, 0.8) * width
    door = (xx >= door_x) & (xx < door_x + 0.12 * width) & (yy >= horizon - 0.45 * height) & (yy < horizon)
    img[door] = 0.22 + 0.02 * np.sin(xx[door] * 0.9)

    # Skirting board and floor tiles: rows below the horizon at ground distance ∝ 1 / (row - horizon).
    img[(yy >= horizon - 3) & (yy < horizon)] = 0.12
    below = yy >= horizon
    dist = 0.5 * height / np.maximum(yy - horizon + 3.0, 1.0)  # in tile units: ~10 rows of tiles in view
    lateral = (xx - width / 2) * dist / (0.25 * width)
    tiles = (np.floor(dist) + np.floor(lateral)) % 2
    floor = 0.3 + 0.08 * tiles + 0.015 * smooth_noise(2.0)
    img[below] = floor[below]

    img = cv2.GaussianBlur(img, (0, 0), 0.6)  # the lens' point spread: no single-pixel aliasing
    return np.clip(img, 0.03, 0.9).astype(np.float32)
