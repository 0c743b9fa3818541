"""A generated actor template: a smooth, closed, skinned and textured human mesh built from the rest skeleton.

No external files. The body is the zero level set of a smooth union of capsules, tapered capsules and
ellipsoids placed on the bones of :data:`eventcap.body.skeleton.DEFAULT_REST_JOINTS` (scaled to the
requested stature). The level set is meshed with *surface nets* (one vertex per grid cell the surface crosses,
one quad per grid edge it crosses; vertices then projected onto the surface and relaxed along it), which
gives a closed, consistently wound mesh without lookup tables; a grid whose sign pattern is ambiguous (it
would give a non-manifold mesh) is shifted by a fraction of a cell and meshed again.

Skinning weights come from the parts' distance fields: each vertex blends the parts near it (softmin of the
part distances), restricted to the nearest part's joint and its kinematic neighbours (so the inner thigh never
follows the other leg), then diffused along the mesh (σ ≈ 5 cm) so that they vary smoothly over the surface.

The albedo is a simulated outfit: a checked shirt with a chest print, dark trousers with a belt, pockets and
knee patches, shoes with light soles and laces, skin-coloured face, forearms and hands, dark hair, eyes and
mouth, and random blob prints — texture with corners, as the feature tracker needs on a real actor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from eventcap.body.skeleton import (
    DEFAULT_HEIGHT_M,
    DEFAULT_REST_JOINTS,
    JOINT_INDEX,
    LANDMARK_NAMES,
    NUM_JOINTS,
    PARENTS,
    default_landmarks,
)
from eventcap.body.template import Template

J = JOINT_INDEX

#: Landmarks placed on the generated surface (ray from their joint along the default offset).
_SURFACE_LANDMARKS = ("nose", "l_eye", "r_eye", "l_ear", "r_ear", "l_big_toe", "l_small_toe", "l_heel",
                      "r_big_toe", "r_small_toe", "r_heel")


@dataclass(frozen=True)
class _Part:
    """One primitive of the body. kind 'capsule': segment a→b with radius ra at a, rb at b (tapered);
    kind 'ellipsoid': centre a, semi-axes b (3,). Metres, rest pose."""

    name: str
    joint: int
    kind: str
    a: np.ndarray
    b: np.ndarray
    ra: float = 0.0
    rb: float = 0.0
    material: str = "shirt"


# --------------------------------------------------------------------------------------------------- shape
def _parts(rest: np.ndarray, scale: float, rng: np.random.Generator) -> list[_Part]:
    """The body's primitives for rest joints ``rest`` (24,3) of an actor ``scale`` × 1.75 m tall."""
    torso_g = rng.uniform(0.93, 1.08)  # build variation per seed: girth of torso and limbs
    limb_g = rng.uniform(0.92, 1.08)
    s = scale

    def P(x, y, z):
        return np.array([x, y, z], dtype=np.float64) * s

    parts = [
        _Part("pelvis", J["pelvis"], "ellipsoid", P(0, 0.93, -0.01), P(0.165 * torso_g, 0.11, 0.11 * torso_g),
              material="trousers"),
        _Part("abdomen", J["spine1"], "ellipsoid", P(0, 1.06, 0.0), P(0.15 * torso_g, 0.12, 0.105 * torso_g)),
        _Part("chest_low", J["spine2"], "ellipsoid", P(0, 1.19, 0.0), P(0.165 * torso_g, 0.11, 0.115 * torso_g)),
        _Part("chest_up", J["spine3"], "ellipsoid", P(0, 1.32, -0.01), P(0.175 * torso_g, 0.12, 0.11 * torso_g)),
        _Part("neck", J["neck"], "capsule", P(0, 1.40, -0.02), P(0, 1.58, 0.0), 0.055 * s, 0.052 * s, "skin"),
        _Part("head", J["head"], "ellipsoid", rest[J["head"]] + P(0, 0.085, 0.01), P(0.075, 0.105, 0.095),
              material="skin"),
        _Part("nose", J["head"], "ellipsoid", rest[J["head"]] + P(0, 0.062, 0.098), P(0.014, 0.024, 0.02),
              material="skin"),
    ]
    for side, sx in (("l", 1.0), ("r", -1.0)):
        def j(name, _side=side):
            return rest[J[f"{_side}_{name}"]]

        def Q(x, y, z, _sx=sx):
            return P(_sx * x, y, z)

        lg = limb_g
        parts += [
            _Part(f"{side}_ear", J["head"], "ellipsoid", rest[J["head"]] + Q(0.074, 0.065, -0.005),
                  P(0.012, 0.03, 0.02), material="skin"),
            _Part(f"{side}_collar", J[f"{side}_collar"], "capsule", Q(0.03, 1.42, -0.02), j("shoulder"),
                  0.06 * s * torso_g, 0.058 * s * lg),
            _Part(f"{side}_upper_arm", J[f"{side}_shoulder"], "capsule", j("shoulder"), j("elbow"),
                  0.055 * s * lg, 0.043 * s * lg),
            _Part(f"{side}_forearm", J[f"{side}_elbow"], "capsule", j("elbow"), j("wrist"), 0.042 * s * lg,
                  0.03 * s * lg, "skin"),
            _Part(f"{side}_palm", J[f"{side}_wrist"], "ellipsoid", j("wrist") + Q(0.045, 0, 0),
                  P(0.05, 0.022, 0.045), material="skin"),
            _Part(f"{side}_thumb", J[f"{side}_wrist"], "capsule", j("wrist") + Q(0.03, 0, 0.035),
                  j("wrist") + Q(0.075, 0, 0.07), 0.014 * s, 0.012 * s, "skin"),
            _Part(f"{side}_fingers", J[f"{side}_hand"], "ellipsoid", j("hand") + Q(0.03, 0, 0.005),
                  P(0.055, 0.016, 0.04), material="skin"),
            _Part(f"{side}_thigh", J[f"{side}_hip"], "capsule", j("hip"), j("knee"), 0.085 * s * lg,
                  0.052 * s * lg, "trousers"),
            _Part(f"{side}_shin", J[f"{side}_knee"], "capsule", j("knee"), j("ankle"), 0.05 * s * lg,
                  0.035 * s * lg, "trousers"),
            _Part(f"{side}_calf", J[f"{side}_knee"], "ellipsoid", Q(0.10, 0.36, -0.015), P(0.05, 0.11, 0.055) * lg,
                  material="trousers"),
            _Part(f"{side}_foot", J[f"{side}_ankle"], "ellipsoid", Q(0.105, 0.045, 0.035), P(0.045, 0.045, 0.115),
                  material="shoe"),
            _Part(f"{side}_toes", J[f"{side}_foot"], "ellipsoid", Q(0.11, 0.03, 0.13), P(0.045, 0.03, 0.05),
                  material="shoe"),
        ]
    return parts


def _part_distances(parts: list[_Part], points: np.ndarray) -> np.ndarray:
    """Approximate signed distances (N, P) metres of points (N,3) to each part (negative inside)."""
    out = np.empty((points.shape[0], len(parts)))
    for i, part in enumerate(parts):
        if part.kind == "capsule":
            ab = part.b - part.a
            ap = points - part.a
            h = np.clip(ap @ ab / (ab @ ab), 0.0, 1.0)
            r = part.ra + (part.rb - part.ra) * h
            out[:, i] = np.linalg.norm(ap - h[:, None] * ab, axis=1) - r
        else:
            # Ellipsoid bound of Quilez: exact on the surface, good near it, never an overestimate by much.
            q = (points - part.a) / part.b
            k0 = np.linalg.norm(q, axis=1)
            k1 = np.linalg.norm(q / part.b, axis=1)
            out[:, i] = np.where(k1 > 0, k0 * (k0 - 1.0) / np.maximum(k1, 1e-12), -part.b.min())
    return out


def _smooth_union(d: np.ndarray, k: float) -> np.ndarray:
    """Exponential smooth minimum over the last axis: −k log Σ exp(−d/k) (symmetric, blends within ~k)."""
    m = d.min(axis=-1)
    return m - k * np.log(np.exp(-(d - m[..., None]) / k).sum(axis=-1))


def _body_sdf(parts: list[_Part], points: np.ndarray, k: float, chunk: int = 65536) -> np.ndarray:
    """Signed distance-like field (N,) of the whole body at points (N,3)."""
    out = np.empty(points.shape[0])
    for a in range(0, points.shape[0], chunk):
        out[a:a + chunk] = _smooth_union(_part_distances(parts, points[a:a + chunk]), k)
    return out


def _body_bounds(parts: list[_Part]) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for p in parts:
        if p.kind == "capsule":
            r = max(p.ra, p.rb)
            lo = np.minimum(lo, np.minimum(p.a, p.b) - r)
            hi = np.maximum(hi, np.maximum(p.a, p.b) + r)
        else:
            lo = np.minimum(lo, p.a - p.b)
            hi = np.maximum(hi, p.a + p.b)
    return lo, hi


# --------------------------------------------------------------------------------------------------- meshing
def _surface_nets(field: np.ndarray, origin: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Mesh the zero level set of a grid (nx,ny,nz) of values (negative inside) with spacing h, origin (3,).

    Returns (vertices (V,3), quads (Q,4)) with quads counter-clockwise seen from outside, or None if the sign
    pattern has an ambiguous grid face (alternating corners), which would make the mesh non-manifold.
    The grid border must be outside.
    """
    inside = field < 0
    # Ambiguous faces: the two diagonals of a grid square have equal signs but differ from each other.
    for ax in range(3):
        b, c = [a for a in range(3) if a != ax]
        s00 = inside
        s10 = np.roll(inside, -1, axis=b)
        s01 = np.roll(inside, -1, axis=c)
        s11 = np.roll(s10, -1, axis=c)
        amb = (s00 == s11) & (s10 == s01) & (s00 != s10)
        if amb[tuple(slice(0, -1) if a != ax else slice(None) for a in range(3))].any():
            return None
    n = np.array(field.shape)
    cell_shape = tuple(n - 1)
    sums = np.zeros(cell_shape + (3,))
    counts = np.zeros(cell_shape)
    idx = np.indices(field.shape).transpose(1, 2, 3, 0).astype(np.float64)
    crossings = []
    for ax in range(3):
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[ax] = slice(0, -1)
        hi[ax] = slice(1, None)
        fa, fb = field[tuple(lo)], field[tuple(hi)]
        cross = (fa < 0) != (fb < 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(cross, fa / (fa - fb), 0.0)
        pos = idx[tuple(lo)].copy()
        pos[..., ax] += t
        crossings.append((cross, fa < 0))
        others = [a for a in range(3) if a != ax]
        for d0 in (0, 1):
            for d1 in (0, 1):
                sl = [slice(None)] * 3
                sl[others[0]] = slice(d0, d0 + n[others[0]] - 1)
                sl[others[1]] = slice(d1, d1 + n[others[1]] - 1)
                sl = tuple(sl)
                sums += np.where(cross[sl][..., None], pos[sl], 0.0)
                counts += cross[sl]
    active = counts > 0
    vid = np.full(cell_shape, -1, dtype=np.int64)
    vid[active] = np.arange(int(active.sum()))
    vertices = origin + h * (sums[active] / counts[active][:, None])

    quads = []
    for ax, (cross, inside_lo) in enumerate(crossings):
        b, c = [(ax + 1) % 3, (ax + 2) % 3]  # (b, c, ax) is a right-handed cyclic order
        e = np.argwhere(cross)
        e = e[(e[:, b] >= 1) & (e[:, b] <= n[b] - 2) & (e[:, c] >= 1) & (e[:, c] <= n[c] - 2)]
        if e.size == 0:
            continue
        ring = []
        for db, dc in ((-1, -1), (0, -1), (0, 0), (-1, 0)):  # counter-clockwise about +ax in the (b, c) plane
            cell = e.copy()
            cell[:, b] += db
            cell[:, c] += dc
            ring.append(vid[cell[:, 0], cell[:, 1], cell[:, 2]])
        q = np.stack(ring, axis=1)
        outward_neg = ~inside_lo[e[:, 0], e[:, 1], e[:, 2]]  # inside is at the upper node: normal −ax
        q[outward_neg] = q[outward_neg][:, ::-1]
        quads.append(q)
    return vertices, np.concatenate(quads)


def _project_to_surface(parts, vertices, k, h, iterations=3):
    """Newton steps onto the zero level set along the field gradient, each step capped at h/2."""
    eps = 0.01 * h
    v = vertices.copy()
    for _ in range(iterations):
        f = _body_sdf(parts, v, k)
        g = np.stack([(_body_sdf(parts, v + eps * e, k) - _body_sdf(parts, v - eps * e, k)) / (2 * eps)
                      for e in np.eye(3)], axis=1)
        step = -(f / np.maximum((g * g).sum(axis=1), 1e-12))[:, None] * g
        norm = np.linalg.norm(step, axis=1, keepdims=True)
        v += step * np.minimum(1.0, 0.5 * h / np.maximum(norm, 1e-12))
    return v


def _polygon_edges(polygons: np.ndarray) -> np.ndarray:
    """(E,2) edges of polygons (N,k), each edge once per polygon side (shared edges appear twice)."""
    return np.concatenate([polygons[:, [i, (i + 1) % polygons.shape[1]]] for i in range(polygons.shape[1])])


def _neighbour_mean(edges: np.ndarray, n: int):
    """Sparse (n,n) operator: the mean over each vertex's mesh neighbours."""
    from scipy.sparse import coo_matrix, diags

    adj = coo_matrix((np.ones(2 * len(edges)), (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])),
                     shape=(n, n))
    adj = (adj.tocsr() > 0).astype(np.float64)
    return diags(1.0 / np.asarray(adj.sum(axis=1)).ravel()) @ adj


def _relax(parts, vertices, quads, k, h, iterations=3):
    """Even out vertex spacing: move each vertex halfway to its quad neighbours' mean, then back onto the
    surface. Surface-net vertices can bunch up (edges of micrometres) where the surface grazes a cell corner."""
    avg = _neighbour_mean(_polygon_edges(quads), vertices.shape[0])
    for _ in range(iterations):
        vertices = _project_to_surface(parts, 0.5 * vertices + 0.5 * (avg @ vertices), k, h, iterations=2)
    return vertices


def _triangulate(vertices, quads):
    """Split each quad along its shorter diagonal; keeps the winding."""
    p = vertices[quads]
    d02 = np.linalg.norm(p[:, 0] - p[:, 2], axis=1)
    d13 = np.linalg.norm(p[:, 1] - p[:, 3], axis=1)
    use02 = d02 <= d13
    t02 = np.concatenate([quads[use02][:, [0, 1, 2]], quads[use02][:, [0, 2, 3]]])
    t13 = np.concatenate([quads[~use02][:, [0, 1, 3]], quads[~use02][:, [1, 2, 3]]])
    return np.concatenate([t02, t13]).astype(np.int32)


def _is_closed_sphere(vertices, faces) -> bool:
    """Every edge shared by exactly two faces with opposite directions, one component, Euler characteristic 2."""
    e = _polygon_edges(faces).astype(np.int64)
    nv = vertices.shape[0]
    directed = e[:, 0] * nv + e[:, 1]
    if np.unique(directed).size != directed.size:
        return False  # an edge used twice in the same direction: inconsistent winding or non-manifold
    undirected = np.minimum(e[:, 0], e[:, 1]) * nv + np.maximum(e[:, 0], e[:, 1])
    _, cnt = np.unique(undirected, return_counts=True)
    if np.any(cnt != 2):
        return False
    if nv - cnt.size + faces.shape[0] != 2:
        return False
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    adj = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(nv, nv))
    return connected_components(adj, directed=False)[0] == 1


def _mesh(parts, k, h, rng, project=True, max_tries=8):
    """Closed genus-0 triangle mesh (vertices (V,3), faces (F,3) int32) of the body at cell size h."""
    lo, hi = _body_bounds(parts)
    for attempt in range(max_tries):
        # A shifted grid changes which sign patterns occur; ambiguous ones are rare, so a retry clears them.
        shift = rng.uniform(0.0, 1.0, 3) * h if attempt else np.zeros(3)
        origin = lo - 2.5 * h + shift
        n = np.ceil((hi + 2.5 * h - origin) / h).astype(int) + 1
        axes = [origin[a] + h * np.arange(n[a]) for a in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        field = _body_sdf(parts, grid, k).reshape(tuple(n))
        meshed = _surface_nets(field, origin, h)
        if meshed is None:
            continue
        vertices, quads = meshed
        if project:
            vertices = _project_to_surface(parts, vertices, k, h)
            vertices = _relax(parts, vertices, quads, k, h)
        faces = _triangulate(vertices, quads)
        if _is_closed_sphere(vertices, faces):
            return vertices, faces
    raise RuntimeError(f"procedural body: no manifold surface-nets mesh at cell size {h:.4f} m after "
                       f"{max_tries} grid shifts")


# --------------------------------------------------------------------------------------------------- rigging
def _joint_neighbours() -> np.ndarray:
    """(24,24) bool: joint itself, its parent and its children."""
    a = np.eye(NUM_JOINTS, dtype=bool)
    for j, p in enumerate(PARENTS):
        if p >= 0:
            a[j, p] = a[p, j] = True
    return a


def _skinning_weights(parts, vertices, faces, part_d, softness_m, smoothing_m):
    """(V,24) weights: softmin of part distances among the nearest part's kinematic neighbours, diffused
    along the mesh over ~``smoothing_m`` (the restriction switches where the nearest part does; this blurs it)."""
    part_joint = np.array([p.joint for p in parts])
    nearest = np.argmin(part_d, axis=1)
    allowed = _joint_neighbours()[part_joint[nearest]][:, part_joint]  # (V, P)
    rel = part_d - part_d[np.arange(len(nearest)), nearest][:, None]
    w_part = np.where(allowed, np.exp(-rel / softness_m), 0.0)
    W = np.zeros((vertices.shape[0], NUM_JOINTS))
    for i, jnt in enumerate(part_joint):
        W[:, jnt] += w_part[:, i]
    W /= W.sum(axis=1, keepdims=True)
    e = _polygon_edges(faces)
    avg = _neighbour_mean(e, len(vertices))
    # A lazy random walk spreads by σ ≈ ℓ √n / 2 after n steps on edges of length ℓ.
    edge_m = np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1).mean()
    for _ in range(int(math.ceil(4.0 * (smoothing_m / edge_m) ** 2))):
        W = 0.5 * W + 0.5 * (avg @ W)
    W[W < 1e-4] = 0.0  # keep rows sparse; what is dropped is far below any visible effect
    return W / W.sum(axis=1, keepdims=True)


def _surface_landmarks(parts, rest, k, scale):
    """Landmark joints and offsets (25,3): face and foot landmarks moved onto the surface, along the ray from
    their joint through the default offset (first exit from the body, bisected to ~1e-9 m)."""
    joints, offsets = default_landmarks(rest)
    idx = np.array([LANDMARK_NAMES.index(n) for n in _SURFACE_LANDMARKS])
    origin = rest[joints[idx]]  # (M,3)
    direction = offsets[idx] / np.linalg.norm(offsets[idx], axis=1, keepdims=True)
    ts = np.linspace(0.0, 0.3 * scale, 301)
    f = _body_sdf(parts, (origin[:, None, :] + ts[None, :, None] * direction[:, None, :]).reshape(-1, 3), k)
    outside = f.reshape(len(idx), len(ts)) > 0
    first = np.argmax(outside, axis=1)
    # A joint outside the body, or a ray that never leaves it, keeps the default offset.
    ok = outside.any(axis=1) & (first > 0)
    a, b = ts[np.maximum(first - 1, 0)], ts[first]
    for _ in range(40):
        m = 0.5 * (a + b)
        out = _body_sdf(parts, origin + m[:, None] * direction, k) > 0
        a, b = np.where(out, a, m), np.where(out, m, b)
    offsets[idx[ok]] = (0.5 * (a + b))[ok, None] * direction[ok]
    return joints, offsets


# --------------------------------------------------------------------------------------------------- texture
def _smoothstep(edge0, edge1, x):
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _albedo(parts, vertices, part_d, rest, landmarks, scale, rng):
    """(V,) simulated outfit albedo in [0,1] (see module doc)."""
    s = scale
    nearest = np.argmin(part_d, axis=1)
    material = np.array([p.material for p in parts])[nearest]
    name = np.array([p.name for p in parts])[nearest]
    x, y, z = vertices.T
    albedo = np.zeros(len(vertices))

    # Sleeves end partway down the upper arm; the pelvis part above the belt is shirt.
    belt_y = 0.99 * s
    is_pelvis = name == "pelvis"
    material = np.where(is_pelvis & (y > belt_y + 0.035 * s), "shirt", material)
    arm = np.char.endswith(name.astype(str), "upper_arm")
    shoulder_x = abs(rest[J["l_shoulder"], 0])
    elbow_x = abs(rest[J["l_elbow"], 0])
    material = np.where(arm & (np.abs(x) > shoulder_x + 0.6 * (elbow_x - shoulder_x)), "skin", material)

    # Shirt: two-tone checks, planar on the torso (square seen from the front), around the arm on sleeves.
    shirt = material == "shirt"
    base = rng.uniform(0.45, 0.55)
    period = rng.uniform(0.095, 0.11) * s  # ≥ 5 px at 4 m on a 240×180 sensor, or the checks alias away
    on_arm = np.abs(x) > shoulder_x
    u = np.where(on_arm, np.arctan2(z, y - rest[J["l_shoulder"], 1]) * 0.05 * s, x + 0.5 * period)
    v = np.where(on_arm, x, y)
    checks = (np.floor(u / period) + np.floor(v / period)) % 2
    albedo[shirt] = (base + 0.4 * (checks - 0.5))[shirt]
    chest = shirt & (z > 0) & (np.abs(x - 0.05 * s) < 0.06 * s) & (np.abs(y - 1.27 * s) < 0.045 * s)
    albedo[chest] = 0.85
    frame = shirt & (z > 0) & (np.abs(x - 0.05 * s) < 0.075 * s) & (np.abs(y - 1.27 * s) < 0.06 * s) & ~chest
    albedo[frame] = 0.1

    # Trousers: dark, black belt with a light buckle, light knee patches and back pockets.
    trousers = material == "trousers"
    albedo[trousers] = rng.uniform(0.14, 0.22)
    belt = trousers & (y > belt_y) & (y <= belt_y + 0.035 * s)
    albedo[belt] = 0.05
    albedo[belt & (z > 0.08 * s) & (np.abs(x) < 0.025 * s)] = 0.8
    knee_y = rest[J["l_knee"], 1]
    patch = trousers & (z > 0.02 * s) & (np.abs(y - knee_y) < 0.05 * s) & (np.abs(np.abs(x) - 0.1 * s) < 0.035 * s)
    albedo[patch] = 0.5
    front_pocket = trousers & (z > 0.03 * s) & (np.abs(y - 0.76 * s) < 0.04 * s) & (np.abs(np.abs(x) - 0.1 * s) < 0.035 * s)
    albedo[front_pocket] = 0.42
    cuff = trousers & (np.abs(y - 0.2 * s) < 0.025 * s)
    albedo[cuff] = 0.5
    pocket = trousers & (z < -0.05 * s) & (np.abs(y - 0.88 * s) < 0.05 * s) & (np.abs(np.abs(x) - 0.08 * s) < 0.045 * s)
    albedo[pocket] = 0.35

    # Shoes: near black, light soles and laces.
    shoe = material == "shoe"
    albedo[shoe] = 0.07
    albedo[shoe & (y < 0.018 * s)] = 0.65
    laces = shoe & (y > 0.06 * s) & (np.sin(z / (0.022 * s) * np.pi) > 0.3) & (z > 0.0) & (z < 0.12 * s)
    albedo[laces] = 0.6

    # Skin; dark hair on the top and back of the head; eyes, eyebrows and mouth; a watch on the left wrist.
    skin = material == "skin"
    albedo[skin] = rng.uniform(0.55, 0.7)
    head = rest[J["head"]]
    head_part = (name == "head") | (name == "l_ear") | (name == "r_ear")
    eye_y = landmarks[LANDMARK_NAMES.index("l_eye"), 1]
    hair = head_part & ((y > eye_y + 0.045 * s) | ((z < head[2] - 0.01 * s) & (y > eye_y - 0.07 * s)))
    hair &= ~((name == "l_ear") | (name == "r_ear"))
    albedo[hair] = 0.1
    for eye in ("l_eye", "r_eye"):
        p = landmarks[LANDMARK_NAMES.index(eye)]
        d = np.linalg.norm(vertices - p, axis=1)
        albedo[head_part & (d < 0.013 * s)] = 0.08
        brow = head_part & (np.abs(x - p[0]) < 0.02 * s) & (np.abs(y - p[1] - 0.022 * s) < 0.006 * s) & (z > 0)
        albedo[brow] = 0.12
    mouth_y = landmarks[LANDMARK_NAMES.index("nose"), 1] - 0.045 * s
    albedo[head_part & (z > head[2]) & (np.abs(x) < 0.022 * s) & (np.abs(y - mouth_y) < 0.006 * s)] = 0.25
    wrist = rest[J["l_wrist"]]
    watch = (name == "l_forearm") & (np.abs(x - wrist[0] + 0.025 * s) < 0.012 * s)
    albedo[watch] = 0.05

    # Blob prints on the clothes: soft-edged spots of random size and tone at random surface points.
    clothes = np.flatnonzero(shirt | trousers)
    for c in rng.choice(clothes, size=min(28, clothes.size), replace=False):
        radius = rng.uniform(0.02, 0.045) * s
        d = np.linalg.norm(vertices - vertices[c], axis=1)
        mask = (shirt | trousers) & (d < radius * 1.3) & (material == material[c])
        tone = rng.choice([0.08, 0.75]) if material[c] == "shirt" else rng.uniform(0.4, 0.6)
        a = 1.0 - _smoothstep(0.7 * radius, radius * 1.3, d[mask])
        albedo[mask] = (1 - a) * albedo[mask] + a * tone
    return np.clip(albedo, 0.0, 1.0).astype(np.float32)


# --------------------------------------------------------------------------------------------------- API
def procedural_template(seed: int = 0, height_m: float = DEFAULT_HEIGHT_M, target_faces: int = 12000,
                        blend_m: float = 0.012, weight_softness_m: float = 0.02,
                        weight_smoothing_m: float = 0.05) -> Template:
    """Generate a closed, skinned, textured actor template (simulated; no scan behind it).

    seed: varies build (torso and limb girth ±8 %), outfit tones, check size and print placement.
    height_m: stature (top of the head); the default skeleton is scaled uniformly, feet stay on y = 0.
    target_faces: wanted triangle count (the result lands within ~15 %); 2,000–60,000.
    blend_m: width of the smooth union between body parts (at 1.75 m; scaled with height).
    weight_softness_m: distance over which skinning weights fall off between neighbouring parts;
    weight_smoothing_m: spread (σ, along the surface) of the weight diffusion; 0 switches it off.
    Lengths are for a 1.75 m actor and scale with ``height_m``.
    """
    if not 1.0 <= float(height_m) <= 2.3:
        raise ValueError(f"procedural_template: height_m must be a human stature in [1.0, 2.3] m, got {height_m}")
    if not 2000 <= int(target_faces) <= 60000:
        raise ValueError(f"procedural_template: target_faces must lie in [2000, 60000], got {target_faces}")
    if not (blend_m > 0 and weight_softness_m > 0 and weight_smoothing_m >= 0):
        raise ValueError("procedural_template: blend_m and weight_softness_m must be positive and "
                         f"weight_smoothing_m ≥ 0, got {blend_m}, {weight_softness_m}, {weight_smoothing_m}")
    scale = float(height_m) / DEFAULT_HEIGHT_M
    rest = DEFAULT_REST_JOINTS * scale
    rng = np.random.default_rng(seed)
    parts = _parts(rest, scale, rng)
    k = blend_m * scale

    # Quad count scales as 1/h²: a coarse pass calibrates the cell size for the wanted triangle count.
    h0 = 0.035 * scale
    _, faces0 = _mesh(parts, k, h0, rng, project=False)
    h = h0 * math.sqrt(len(faces0) / int(target_faces))
    vertices, faces = _mesh(parts, k, h, rng)

    part_d = _part_distances(parts, vertices)
    weights = _skinning_weights(parts, vertices, faces, part_d, weight_softness_m * scale,
                                 weight_smoothing_m * scale)
    landmark_joint, landmark_offset = _surface_landmarks(parts, rest, k, scale)
    landmarks = rest[landmark_joint] + landmark_offset
    albedo = _albedo(parts, vertices, part_d, rest, landmarks, scale, rng)
    return Template(name=f"procedural-seed{seed}-{float(height_m):.2f}m", rest_joints=rest, vertices=vertices,
                    faces=faces, weights=weights, vertex_albedo=albedo, landmark_joint=landmark_joint,
                    landmark_offset=landmark_offset)
