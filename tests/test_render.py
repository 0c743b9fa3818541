"""Tests of eventcap.imaging.render: coverage, depth test, perspective-correct barycentrics, clipping, look-ups."""

import numpy as np
import pytest
import trimesh

from eventcap.camera import Camera, davis240c_default
from eventcap.imaging.render import (Light, pick_surface_points, rasterize, render, silhouette, surface_points,
                             textured_background)

# Camera at the world origin looking down +z (world = camera frame, y down); principal point off the pixel grid
# so that no edge of the test shapes passes exactly through a pixel centre.
PINHOLE = Camera(240, 180, 200.0, 200.0, 120.3, 90.2)
FRONT_LIGHT = Light(direction=(0.0, 0.0, -1.0), ambient=0.2, diffuse=0.5)


def _quad(half: float, z: float, offset=(0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """A square facing the camera (outward normal −z): 4 vertices, 2 counter-clockwise faces seen from it."""
    ox, oy = offset
    V = np.array([[-half, -half, z], [-half, half, z], [half, half, z], [half, -half, z]]) + [ox, oy, 0.0]
    F = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)
    return V, F


def test_quad_coverage_depth_and_shading():
    V, F = _quad(0.3, 2.0)
    r = render(PINHOLE, V, F, np.full(4, 0.8), light=FRONT_LIGHT)
    # Columns whose centre satisfies |x - cx| ≤ f·half/z = 30 px: 91..150; rows 61..120.
    expected = np.zeros((180, 240), bool)
    expected[61:121, 91:151] = True
    np.testing.assert_array_equal(silhouette(r), expected)
    assert r.intensity.dtype == np.float32 and r.depth.dtype == np.float32 and r.tri_id.dtype == np.int32
    np.testing.assert_allclose(r.depth[expected], 2.0, rtol=1e-6)
    assert np.all(np.isinf(r.depth[~expected])) and np.all(r.tri_id[~expected] == -1)
    np.testing.assert_allclose(r.intensity[expected], 0.8 * (0.2 + 0.5), rtol=1e-6)
    assert np.all(r.intensity[~expected] == 0.0)
    np.testing.assert_allclose(r.bary[expected].sum(axis=1), 1.0, atol=1e-6)
    assert set(np.unique(r.tri_id[expected])) == {0, 1}


def test_supersampling_integrates_pixel_area():
    V, F = _quad(0.3, 2.0)
    one = render(PINHOLE, V, F, np.full(4, 0.8), light=FRONT_LIGHT)
    three = render(PINHOLE, V, F, np.full(4, 0.8), light=FRONT_LIGHT, supersample=3)
    # Geometry is that of the pixel centres, whatever the sampling.
    np.testing.assert_array_equal(three.tri_id, one.tri_id)
    np.testing.assert_array_equal(three.depth, one.depth)
    np.testing.assert_allclose(three.bary, one.bary, atol=1e-6)
    # Intensity = value × fraction of the 3×3 samples (at offsets -1/3, 0, 1/3) inside [90.3, 150.3]×[60.2, 120.2].
    offsets = np.array([-1 / 3, 0.0, 1 / 3])
    cols = ((np.arange(240)[:, None] + offsets >= 90.3) & (np.arange(240)[:, None] + offsets <= 150.3)).mean(1)
    rows = ((np.arange(180)[:, None] + offsets >= 60.2) & (np.arange(180)[:, None] + offsets <= 120.2)).mean(1)
    np.testing.assert_allclose(three.intensity, 0.8 * 0.7 * np.outer(rows, cols), atol=1e-6)
    assert three.intensity[60, 100] == pytest.approx(0.56 / 3, abs=1e-6)  # a third of the edge row's samples
    with pytest.raises(ValueError, match="odd integer"):
        render(PINHOLE, V, F, np.ones(4), supersample=2)


def test_single_triangle_barycentrics_known_values():
    # Fronto-parallel right triangle: barycentrics are affine in the pixel coordinates.
    V = np.array([[0.0, 0.0, 2.0], [0.0, 0.5, 2.0], [0.5, 0.5, 2.0]])  # image: (cx,cy), (cx,cy+50), (cx+50,cy+50)
    r = render(PINHOLE, V, np.array([[0, 1, 2]]), np.ones(3), light=FRONT_LIGHT)
    x, y = 130, 130  # pixel centre: 9.7 px right, 39.8 px below the first vertex
    u, v = (x - 120.3) / 50.0, (y - 90.2) / 50.0
    np.testing.assert_allclose(r.bary[y, x], [1 - v, v - u, u], atol=1e-6)
    # Coverage: rows 91..140 (centre inside [90.2, 140.2]); in row y, columns with x - cx ≤ y - cy.
    rows, cols = np.nonzero(silhouette(r))
    assert rows.min() == 91 and rows.max() == 140
    assert np.all(cols - 120.3 <= rows - 90.2) and np.all(cols >= 121)
    assert silhouette(r).sum() == sum(int(np.floor(y - 90.2 + 120.3)) - 120 for y in range(91, 141))


@pytest.mark.parametrize("cam", [PINHOLE, davis240c_default(distortion=False)], ids=["origin", "placed"])
def test_barycentric_reconstruction_reprojects_to_pixel_centre(cam):
    """Perspective-correct barycentrics: the interpolated 3D point lies on the pixel centre's ray."""
    target = cam.backproject(np.array([[cam.cx, cam.cy]]), np.array([3.0]))[0]
    # A strongly slanted triangle (depth varies by 1.6 m across it), so affine interpolation would be visibly off.
    V = target + np.array([[-0.6, -0.5, -0.8], [0.7, -0.4, 0.8], [0.0, 0.6, 0.1]])
    r = render(cam, V, np.array([[0, 1, 2]]), np.ones(3))
    ys, xs = np.nonzero(silhouette(r))
    assert len(xs) > 1000
    points = np.einsum("pk,kd->pd", r.bary[ys, xs].astype(np.float64), V)
    err = np.linalg.norm(cam.project(points) - np.stack([xs, ys], axis=1), axis=1)
    assert err.max() < 1e-3
    np.testing.assert_allclose(cam.depth(points), r.depth[ys, xs], rtol=1e-5)


def test_depth_ordering_independent_of_draw_order():
    near_V, near_F = _quad(0.2, 2.0, offset=(0.1, 0.0))
    far_V, far_F = _quad(0.3, 3.0)
    V = np.vstack([near_V, far_V])
    for F in (np.vstack([near_F, far_F + 4]), np.vstack([far_F + 4, near_F])):
        depth, tri, _ = rasterize(PINHOLE, V, F)
        near_faces = set(np.flatnonzero(F.max(axis=1) < 4))
        # Near quad: columns 111..150, rows 71..110 (20 px half-size at z = 2, shifted 10 px right);
        # far quad: columns 101..140, rows 71..110.
        assert set(np.unique(tri[71:111, 111:151])) == near_faces
        np.testing.assert_allclose(depth[71:111, 111:151], 2.0, rtol=1e-6)
        np.testing.assert_allclose(depth[71:111, 101:111], 3.0, rtol=1e-6)  # only the far quad there


def test_interpenetrating_triangles_depth_is_per_pixel_minimum():
    # Two large triangles crossing each other along a line: the visible one changes across the image.
    a = np.array([[-2.0, -2.0, 2.0], [-2.0, 2.0, 2.0], [2.0, 0.0, 4.0]])  # depth grows to the right
    b = np.array([[2.0, -2.0, 2.0], [2.0, 2.0, 2.0], [-2.0, 0.0, 4.0]])  # depth grows to the left
    V, F = np.vstack([a, b]), np.array([[0, 1, 2], [3, 5, 4]])
    depth, tri, _ = rasterize(PINHOLE, V, F)
    assert set(np.unique(tri[80:100, 100:140])) == {0, 1}
    ys, xs = np.mgrid[80:100, 100:140]
    rays = PINHOLE.undistort_points(np.stack([xs, ys], axis=-1))  # (…, 2) x/z, y/z
    # Plane of a: z = 3 + x/2  ⇒  z = 3 / (1 - rx/2); plane of b: z = 3 - x/2  ⇒  z = 3 / (1 + rx/2).
    za, zb = 3 / (1 - rays[..., 0] / 2), 3 / (1 + rays[..., 0] / 2)
    np.testing.assert_allclose(depth[80:100, 100:140], np.minimum(za, zb), rtol=1e-5)
    np.testing.assert_array_equal(tri[80:100, 100:140], np.where(za < zb, 0, 1))


def test_clipping_off_screen_and_behind_camera():
    # 100 px per metre at z = 2. Fully off-screen to the left: x in [-109.7, -49.7].
    V, F = _quad(0.3, 2.0, offset=(-2.0, 0.0))
    assert silhouette(render(PINHOLE, V, F, np.ones(4))).sum() == 0
    # Partially off-screen: x in [-29.7, 30.3], so columns 0..30 only (no wrap-around), rows 61..120.
    V, F = _quad(0.3, 2.0, offset=(-1.2, 0.0))
    mask = silhouette(render(PINHOLE, V, F, np.ones(4)))
    assert mask[:, :31].any(axis=0).all() and not mask[:, 31:].any()
    assert mask.sum() == 31 * 60
    # Fully behind the camera: nothing (and no mirror image).
    V, F = _quad(0.3, -2.0)
    assert silhouette(render(PINHOLE, V, F, np.ones(4))).sum() == 0
    # Straddling the near plane: dropped whole (documented), the rest of the scene still renders.
    V = np.array([[-0.3, -0.3, -1.0], [-0.3, 0.3, 2.0], [0.3, 0.3, 2.0]])
    depth, tri, _ = rasterize(PINHOLE, V, np.array([[0, 1, 2]]))
    assert (tri >= 0).sum() == 0 and np.isinf(depth).all()


def test_empty_scene_returns_background():
    bg = textured_background(180, 240, seed=3)
    r = render(PINHOLE, np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), np.zeros(0), background=bg)
    np.testing.assert_array_equal(r.intensity, bg)
    assert np.isinf(r.depth).all() and (r.tri_id == -1).all() and not silhouette(r).any()
    assert r.bary.shape == (180, 240, 3)


def test_backface_culling():
    V, F = _quad(0.3, 2.0)
    assert silhouette(render(PINHOLE, V, F, np.ones(4), cull_backfaces=True)).sum() == 3600
    assert silhouette(render(PINHOLE, V, F[:, ::-1], np.ones(4), cull_backfaces=True)).sum() == 0
    assert silhouette(render(PINHOLE, V, F[:, ::-1], np.ones(4))).sum() == 3600


def test_closed_mesh_culling_does_not_change_image():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    V = sphere.vertices + [0.0, 1.0, 0.0]
    cam = davis240c_default()
    alb = 0.5 + 0.3 * np.sin(20 * V[:, 0])
    a = render(cam, V, sphere.faces, alb)
    b = render(cam, V, sphere.faces, alb, cull_backfaces=True)
    np.testing.assert_array_equal(a.tri_id, b.tri_id)
    np.testing.assert_array_equal(a.intensity, b.intensity)
    # Lit from the default light: values inside (0, 1], brighter at the top (light from above).
    ys, xs = np.nonzero(silhouette(a))
    assert a.intensity[silhouette(a)].max() <= 1.0 and a.intensity[silhouette(a)].min() > 0.0
    assert a.intensity[ys.min() + 3, int(np.median(xs))] > a.intensity[ys.max() - 3, int(np.median(xs))]


def test_render_rejects_bad_inputs():
    V, F = _quad(0.3, 2.0)
    with pytest.raises(ValueError, match=r"vertices: expected shape \(V, 3\)"):
        render(PINHOLE, V[:, :2], F, np.ones(4))
    with pytest.raises(ValueError, match=r"vertex indices must lie in \[0, 4\)"):
        render(PINHOLE, V, F + 2, np.ones(4))
    with pytest.raises(ValueError, match=r"vertex_albedo: expected shape \(4,\)"):
        render(PINHOLE, V, F, np.ones(3))
    with pytest.raises(ValueError, match=r"background: expected shape \(height, width\) = \(180, 240\)"):
        render(PINHOLE, V, F, np.ones(4), background=np.zeros((240, 180)))


def test_surface_points_visibility():
    front_V, front_F = _quad(0.2, 2.0)
    back_V, back_F = _quad(0.4, 3.0)
    V, F = np.vstack([front_V, back_V]), np.vstack([front_F, back_F + 4])
    r = render(PINHOLE, V, F, np.ones(8))
    third = np.full(3, 1 / 3)
    # Centroids: of the front faces (visible), the back faces (hidden behind the front quad).
    sp = surface_points(PINHOLE, V, F, np.array([0, 1, 2, 3]), np.tile(third, (4, 1)), r)
    assert sp.visible.tolist() == [True, True, False, False]
    np.testing.assert_allclose(sp.world[0], V[F[0]].mean(axis=0))
    np.testing.assert_allclose(sp.depth, [2, 2, 3, 3])
    # A corner region of the back quad outside the front quad is visible; a point moved off-screen is not.
    corner = np.array([[0.9, 0.05, 0.05]])  # near back vertex 0 at (-0.4, -0.4, 3)
    assert surface_points(PINHOLE, V, F, np.array([2]), corner, r).visible.tolist() == [True]
    far = V.copy()
    far[4:] += [5.0, 0.0, 0.0]
    assert not surface_points(PINHOLE, far, F, np.array([2]), corner, r).visible[0]


def test_pick_surface_points_round_trip():
    cam = davis240c_default()
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.4)
    V = sphere.vertices + [0.1, 1.2, 0.0]
    r = render(cam, V, sphere.faces, np.ones(len(V)))
    rng = np.random.default_rng(0)
    ys, xs = np.nonzero(silhouette(r))
    pick = rng.choice(len(xs), 200, replace=False)
    px = np.stack([xs[pick], ys[pick]], axis=1) + rng.uniform(-0.45, 0.45, (200, 2))
    px = np.vstack([px, [[-5.0, 10.0], [2.0, 2.0]]])  # outside the image; background
    tri, bary = pick_surface_points(cam, V, sphere.faces, r, px)
    assert tri[-2] == -1 and tri[-1] == -1
    sp = surface_points(cam, V, sphere.faces, tri[:-2], bary[:-2], r)
    # The mesh edges are straight in pixel space only approximately (distortion), hence 0.01 px.
    assert np.abs(sp.pixels - px[:-2]).max() < 0.01
    assert sp.visible.all()


def test_textured_background():
    a = textured_background(180, 240, seed=0)
    assert a.shape == (180, 240) and a.dtype == np.float32
    assert 0.03 <= a.min() and a.max() <= 0.9 and 0.2 < a.mean() < 0.5
    np.testing.assert_array_equal(a, textured_background(180, 240, seed=0))
    assert np.abs(a - textured_background(180, 240, seed=1)).mean() > 0.01
    gy, gx = np.gradient(a)
    assert (np.hypot(gx, gy) > 0.03).mean() > 0.01  # some real edges, not a flat wall
    with pytest.raises(ValueError, match="height, width"):
        textured_background(4, 240)
