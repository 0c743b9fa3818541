"""Compiled inner loops of E_sil (numba; the refinement and the spline solve): camera projection and residual derivatives, the sparse
skinning products of the energy, the silhouette boundary scan, the rest-point solve and the event search.

Each is checked in tests/test_refine.py against a plain reference: ``eventcap.energy.kernels.project_derivatives``
(camera model and its derivatives), ``eventcap.imaging.render.rasterize`` (projection), finite differences (the energy's
gradient and Hessian built from the sparse products), ``eventcap.energy.correspondences.rest_point`` (rest
points), the definition on a disc (boundary and normals) and a brute-force scan of all events (search, support).
"""

from __future__ import annotations

import numpy as np
from numba import njit


def camera_params(camera) -> np.ndarray:
    """(21,) float64: R (9, row-major), t (3), fx, fy, cx, cy, k1, k2, p1, p2, k3."""
    k1, k2, p1, p2, k3 = (float(v) for v in camera.dist)
    return np.concatenate([np.asarray(camera.R, np.float64).ravel(), np.asarray(camera.t, np.float64),
                           [camera.fx, camera.fy, camera.cx, camera.cy, k1, k2, p1, p2, k3]])


@njit(cache=True)
def residual_derivatives(pts, normal, target, cam, scale, order, r, gr, hr):
    """Point-to-line residuals r_p = scale · n_pᵀ(π(p) - u_p) of world points p (P, 3), with their gradient gr
    (P, 3) and Hessian hr (P, 3, 3) w.r.t. p (order >= 1, >= 2), written in place. π: pinhole + OpenCV
    distortion (k1 k2 p1 p2 k3), the camera model of :meth:`eventcap.camera.Camera.project`."""
    R00, R01, R02, R10, R11, R12, R20, R21, R22 = cam[0], cam[1], cam[2], cam[3], cam[4], cam[5], cam[6], cam[7], cam[8]
    fx, fy, cx, cy = cam[12], cam[13], cam[14], cam[15]
    k1, k2, p1, p2, k3 = cam[16], cam[17], cam[18], cam[19], cam[20]
    for p in range(pts.shape[0]):
        X, Y, Z = pts[p, 0], pts[p, 1], pts[p, 2]
        c0 = R00 * X + R01 * Y + R02 * Z + cam[9]
        c1 = R10 * X + R11 * Y + R12 * Z + cam[10]
        c2 = R20 * X + R21 * Y + R22 * Z + cam[11]
        iz = 1.0 / c2
        x = c0 * iz
        y = c1 * iz
        r2 = x * x + y * y
        rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * rad + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * rad + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        a0 = scale * normal[p, 0] * fx
        a1 = scale * normal[p, 1] * fy
        r[p] = a0 * xd + a1 * yd + scale * (normal[p, 0] * (cx - target[p, 0]) + normal[p, 1] * (cy - target[p, 1]))
        if order < 1:
            continue
        drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        d00 = rad + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x
        d01 = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
        d11 = rad + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x
        g0 = a0 * d00 + a1 * d01  # ∂r/∂x, ∂r/∂y (normalised image coordinates)
        g1 = a0 * d01 + a1 * d11
        # ∂r/∂c = Dnᵀ g with Dn = [[iz, 0, -x iz], [0, iz, -y iz]]
        gc0 = g0 * iz
        gc1 = g1 * iz
        gc2 = -(g0 * x + g1 * y) * iz
        gr[p, 0] = R00 * gc0 + R10 * gc1 + R20 * gc2  # Rᵀ ∂r/∂c
        gr[p, 1] = R01 * gc0 + R11 * gc1 + R21 * gc2
        gr[p, 2] = R02 * gc0 + R12 * gc1 + R22 * gc2
        if order < 2:
            continue
        d2rad = 2.0 * k2 + 6.0 * k3 * r2
        xd_xx = 6.0 * x * drad + 4.0 * x * x * x * d2rad + 6.0 * p2
        xd_xy = 2.0 * y * drad + 4.0 * x * x * y * d2rad + 2.0 * p1
        xd_yy = 2.0 * x * drad + 4.0 * x * y * y * d2rad + 2.0 * p2
        yd_yy = 6.0 * y * drad + 4.0 * y * y * y * d2rad + 6.0 * p1
        h00 = a0 * xd_xx + a1 * xd_xy  # ∂²r/∂(x, y)² (yd_xx = xd_xy, yd_xy = xd_yy)
        h01 = a0 * xd_xy + a1 * xd_yy
        h11 = a0 * xd_yy + a1 * yd_yy
        # ∂²r/∂c² = Dnᵀ H Dn + g0 ∂²x/∂c² + g1 ∂²y/∂c²
        iz2 = iz * iz
        D = np.empty((2, 3))
        D[0, 0] = iz
        D[0, 1] = 0.0
        D[0, 2] = -x * iz
        D[1, 0] = 0.0
        D[1, 1] = iz
        D[1, 2] = -y * iz
        Hc = np.empty((3, 3))
        for i in range(3):
            for j in range(3):
                Hc[i, j] = (D[0, i] * (h00 * D[0, j] + h01 * D[1, j]) + D[1, i] * (h01 * D[0, j] + h11 * D[1, j]))
        Hc[0, 2] -= g0 * iz2
        Hc[2, 0] -= g0 * iz2
        Hc[1, 2] -= g1 * iz2
        Hc[2, 1] -= g1 * iz2
        Hc[2, 2] += 2.0 * (g0 * x + g1 * y) * iz2
        # Rᵀ Hc R
        for i in range(3):
            for j in range(3):
                s = 0.0
                for a in range(3):
                    for b in range(3):
                        s += cam[3 * a + i] * Hc[a, b] * cam[3 * b + j]
                hr[p, i, j] = s


@njit(cache=True)
def nearest_in_time(keys, start, end, rel, half, none, dt):
    """For every occupied pixel q (CSR segment keys[start[q]:end[q]], low bits = time, sorted) and every frame
    time rel[f] (increasing), the time offset of the pixel's event nearest to rel[f] if within ``half``, written
    to dt[f, q] (else ``none``). Ties go to the earlier event. One pass over each pixel's events."""
    mask = (np.int64(1) << 40) - 1
    F = rel.shape[0]
    for q in range(start.shape[0]):
        i = start[q]
        e = end[q]
        for f in range(F):
            tf = rel[f]
            while i < e and (keys[i] & mask) < tf:
                i += 1
            best = half + 1
            val = 0
            if i > start[q]:
                d = tf - (keys[i - 1] & mask)
                if d < best:
                    best = d
                    val = -d
            if i < e:
                d = (keys[i] & mask) - tf
                if d < best:
                    best = d
                    val = d
            dt[f, q] = val if best <= half else none


@njit(cache=True)
def patch_search(dt, frame, px, py, width, height, h, lam, T, none, found, tx, ty, dto, cost):
    """Closest event (Eq. 12-13) of each boundary pixel: the minimum over the (2h+1)² pixels of its patch of
    λ (dt / T)² + dx² + dy², dt from the per-frame table dt (F, H·W). First minimum in row-major order wins."""
    for b in range(frame.shape[0]):
        f = frame[b]
        best = np.inf
        bx = 0
        by = 0
        bdt = 0
        for dy in range(-h, h + 1):
            y = py[b] + dy
            if y < 0 or y >= height:
                continue
            for dx in range(-h, h + 1):
                x = px[b] + dx
                if x < 0 or x >= width:
                    continue
                d = dt[f, y * width + x]
                if d == none:
                    continue
                s = d / T
                c = lam * s * s + dx * dx + dy * dy
                if c < best:
                    best = c
                    bx = x
                    by = y
                    bdt = d
        found[b] = best < np.inf
        tx[b] = bx
        ty[b] = by
        dto[b] = bdt
        cost[b] = best


@njit(cache=True)
def _fill_sparse(rest, weights, idx, val):
    for p in range(rest.shape[0]):
        k = 0
        for j in range(weights.shape[1]):
            w = weights[p, j]
            if w != 0.0:
                for c in range(3):
                    idx[p, k] = 4 * j + c
                    val[p, k] = w * rest[p, c]
                    k += 1
                idx[p, k] = 4 * j + 3
                val[p, k] = w
                k += 1


def sparse_premultiplied(rest_points: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The premultiplied weights WX (P, 96) of points — posed point = WX · G, entry 4j + c = w_j [x, 1]_c (see
    ``eventcap.energy.kernels.premultiplied_weights``) — as their nonzeros only: (P, K) column indices and values,
    padded with value 0 (K = 4 × the most joints any point is weighted to; a point has 2-9 of 24)."""
    weights = np.ascontiguousarray(weights, dtype=np.float64)
    rest_points = np.ascontiguousarray(rest_points, dtype=np.float64)
    K = 4 * int((weights != 0).sum(axis=1).max()) if weights.shape[0] else 0
    idx = np.zeros((weights.shape[0], K), dtype=np.int64)
    val = np.zeros((weights.shape[0], K))
    _fill_sparse(rest_points, weights, idx, val)
    return idx, val


@njit(cache=True)
def sparse_points(idx, val, frame, G, out):
    """out[p] = WX_p · G[frame[p]] for sparse WX rows (idx, val) and transforms G (F, 96, 3)."""
    for p in range(idx.shape[0]):
        f = frame[p]
        x = 0.0
        y = 0.0
        z = 0.0
        for k in range(idx.shape[1]):
            v = val[p, k]
            i = idx[p, k]
            x += v * G[f, i, 0]
            y += v * G[f, i, 1]
            z += v * G[f, i, 2]
        out[p, 0] = x
        out[p, 1] = y
        out[p, 2] = z


@njit(cache=True)
def sparse_accumulate(idx, val, frame, a, out):
    """out[frame[p]] += WX_pᵀ a_p for sparse WX rows (idx, val) and a (P, 3): ∂E/∂G from ∂E/∂point (in place)."""
    for p in range(idx.shape[0]):
        f = frame[p]
        for k in range(idx.shape[1]):
            v = val[p, k]
            i = idx[p, k]
            out[f, i, 0] += v * a[p, 0]
            out[f, i, 1] += v * a[p, 1]
            out[f, i, 2] += v * a[p, 2]


@njit(cache=True)
def point_jacobians(idx, val, f, dG, c2, gr, c1, hr, J3, BJ):
    """For the points of frame f: J3[p] = Σ_k val[p, k] · dG[f, idx[p, k]] as (3, n) — the Jacobian of point
    p = WX_p · G w.r.t. the pose, from the sparse rows of WX (:func:`sparse_premultiplied`) — and BJ[p] = B_p J3[p]
    with the point-space Hessian B_p = c2_p gr_p gr_pᵀ + c1_p hr_p. dG (F, 96, 3·n)."""
    m = dG.shape[2]
    n = m // 3
    B = np.empty((3, 3))
    for p in range(idx.shape[0]):
        row = J3[p]
        row[:] = 0.0
        for k in range(idx.shape[1]):
            v = val[p, k]
            if v == 0.0:
                continue
            src = dG[f, idx[p, k]]
            for c in range(m):
                row[c] += v * src[c]
        for i in range(3):
            for j in range(3):
                B[i, j] = c2[p] * gr[p, i] * gr[p, j] + c1[p] * hr[p, i, j]
        out = BJ[p]
        for i in range(3):
            b0, b1, b2 = B[i, 0], B[i, 1], B[i, 2]
            for c in range(n):
                out[i * n + c] = b0 * row[c] + b1 * row[n + c] + b2 * row[2 * n + c]


@njit(cache=True)
def _boundary_scan(masks, radius, taps, min_gradient, frame, px, py, nx, ny):
    """Boundary pixels of the masks (F, H, W) and their outward normals: see boundary.boundary_pixels. Writes up to
    len(frame) samples; returns how many there are (call again with larger arrays if more)."""
    F, H, W = masks.shape
    n = 0
    for f in range(F):
        for y in range(H):
            for x in range(W):
                if not masks[f, y, x]:
                    continue
                if not ((x > 0 and not masks[f, y, x - 1]) or (x < W - 1 and not masks[f, y, x + 1])
                        or (y > 0 and not masks[f, y - 1, x]) or (y < H - 1 and not masks[f, y + 1, x])):
                    continue
                # Gradient of the Gaussian-smoothed mask at (x, y): the mask convolved with the derivative of a
                # sampled Gaussian (taps[k] = g(k - radius)), image border replicated.
                gx = 0.0
                gy = 0.0
                for j in range(-radius, radius + 1):
                    yy = min(max(y + j, 0), H - 1)
                    for i in range(-radius, radius + 1):
                        if masks[f, yy, min(max(x + i, 0), W - 1)]:
                            w = taps[i + radius] * taps[j + radius]
                            gx += i * w
                            gy += j * w
                norm = np.sqrt(gx * gx + gy * gy)
                if norm < min_gradient:
                    continue
                if n < frame.shape[0]:
                    frame[n] = f
                    px[n] = x
                    py[n] = y
                    nx[n] = -gx / norm  # the mask grows inwards: minus its gradient points out
                    ny[n] = -gy / norm
                n += 1
    return n


def boundary_scan(masks: np.ndarray, sigma_px: float, min_gradient: float):
    """(frame, x, y, nx, ny) of the boundary pixels of a stack of masks (F, H, W) (compiled; see boundary.py)."""
    radius = max(1, int(np.ceil(3.0 * sigma_px)))
    k = np.arange(-radius, radius + 1, dtype=np.float64)
    taps = np.exp(-0.5 * (k / sigma_px) ** 2)
    taps /= taps.sum()
    # Derivative of the smoothed mask: Σ m(x+i, y+j) g_i g_j (i, j) / σ² (derivative-of-Gaussian weights).
    taps_scaled = taps / sigma_px  # (i g_i / σ)(g_j / σ) = i g_i g_j / σ²
    masks = np.ascontiguousarray(masks, dtype=np.bool_)
    cap = max(int(masks.sum()), 1)  # every boundary pixel is a mask pixel
    while True:
        out = (np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap),
               np.empty(cap))
        n = _boundary_scan(masks, radius, taps_scaled, float(min_gradient), *out)
        if n <= cap:
            return tuple(a[:n] for a in out)
        cap = n


@njit(cache=True)
def rest_points(posed, weights, frame, transforms, min_det, rest, w_out):
    """Rest points x with Σ_j w_j (R_j x + b_j) = posed (transforms (F, 24, 4, 4) of each point's frame); where
    |det Σ_j w_j R_j| < min_det the point is attached rigidly to its dominant joint instead (one-hot weights).
    The compiled, all-frames form of eventcap.energy.correspondences.rest_point."""
    J = weights.shape[1]
    A = np.empty((3, 3))
    c = np.empty(3)
    for p in range(posed.shape[0]):
        f = frame[p]
        A[:] = 0.0
        c[:] = 0.0
        best = 0
        for j in range(J):
            w = weights[p, j]
            w_out[p, j] = w
            if w > weights[p, best]:
                best = j
            if w == 0.0:
                continue
            for a in range(3):
                c[a] += w * transforms[f, j, a, 3]
                for b in range(3):
                    A[a, b] += w * transforms[f, j, a, b]
        det = (A[0, 0] * (A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]) - A[0, 1] * (A[1, 0] * A[2, 2] - A[1, 2] * A[2, 0])
               + A[0, 2] * (A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]))
        if abs(det) >= min_det:  # x = A⁻¹ (posed - c), by the adjugate
            r0, r1, r2 = posed[p, 0] - c[0], posed[p, 1] - c[1], posed[p, 2] - c[2]
            rest[p, 0] = ((A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]) * r0 + (A[0, 2] * A[2, 1] - A[0, 1] * A[2, 2]) * r1
                          + (A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]) * r2) / det
            rest[p, 1] = ((A[1, 2] * A[2, 0] - A[1, 0] * A[2, 2]) * r0 + (A[0, 0] * A[2, 2] - A[0, 2] * A[2, 0]) * r1
                          + (A[0, 2] * A[1, 0] - A[0, 0] * A[1, 2]) * r2) / det
            rest[p, 2] = ((A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]) * r0 + (A[0, 1] * A[2, 0] - A[0, 0] * A[2, 1]) * r1
                          + (A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]) * r2) / det
        else:
            for j in range(J):
                w_out[p, j] = 0.0
            w_out[p, best] = 1.0
            for a in range(3):
                s = 0.0
                for b in range(3):
                    s += transforms[f, best, b, a] * (posed[p, b] - transforms[f, best, b, 3])
                rest[p, a] = s  # Rᵀ (y - b)


@njit(cache=True)
def project_points(pts, cam, uv, z):
    """Pixels uv (P, 2) and camera depth z (P,) of world points (P, 3): the model of Camera.project (pinhole +
    OpenCV distortion); points with z <= 0 get uv = 0 (callers drop them by their depth)."""
    for p in range(pts.shape[0]):
        X, Y, Z = pts[p, 0], pts[p, 1], pts[p, 2]
        c0 = cam[0] * X + cam[1] * Y + cam[2] * Z + cam[9]
        c1 = cam[3] * X + cam[4] * Y + cam[5] * Z + cam[10]
        c2 = cam[6] * X + cam[7] * Y + cam[8] * Z + cam[11]
        z[p] = c2
        if not c2 > 0.0:
            uv[p, 0] = 0.0
            uv[p, 1] = 0.0
            continue
        x = c0 / c2
        y = c1 / c2
        k1, k2, p1, p2, k3 = cam[16], cam[17], cam[18], cam[19], cam[20]
        r2 = x * x + y * y
        rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        uv[p, 0] = cam[12] * (x * rad + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)) + cam[14]
        uv[p, 1] = cam[13] * (y * rad + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y) + cam[15]


@njit(cache=True)
def _lower_bound(keys, lo, hi, value):
    while lo < hi:
        mid = (lo + hi) // 2
        if keys[mid] < value:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True)
def supported_events(keys, pix_start, width, height, tau, keep):
    """keep[i]: event i (keys sorted by pixel, then time: key = pixel << 40 | t) has another event in its 3×3
    pixel neighbourhood within ±tau µs. pix_start (H·W + 1): CSR offsets of every pixel's events."""
    mask = (np.int64(1) << 40) - 1
    for i in range(keys.shape[0]):
        q = keys[i] >> 40
        t = keys[i] & mask
        x = q % width
        y = q // width
        ok = False
        for dy in range(-1, 2):
            yy = y + dy
            if yy < 0 or yy >= height or ok:
                continue
            for dx in range(-1, 2):
                xx = x + dx
                if xx < 0 or xx >= width:
                    continue
                r = yy * width + xx
                lo = pix_start[r]
                hi = pix_start[r + 1]
                if lo == hi:
                    continue
                j = _lower_bound(keys, lo, hi, (r << 40) | max(t - tau, 0))
                # the first event at or after t - tau; the event itself does not count
                while j < hi and j == i:
                    j += 1
                if j < hi and (keys[j] & mask) <= t + tau:
                    ok = True
                    break
        keep[i] = ok
