"""Build a Template from a user's SMPL model file (the paper rigs its template with SMPL, Sec. 3).

SMPL files cannot ship with this tool (license); the user points at their own copy. Accepted layouts:

- ``.npz`` with the arrays ``v_template`` (V, 3), ``weights`` (V, 24), ``J_regressor`` (24, V),
  ``kintree_table`` (2, 24), ``shapedirs`` (V, 3, B), ``f`` (F, 3);
- ``.pkl`` as the official SMPL files ship (Python 2 pickles, read with latin-1), with the same keys.
  ``J_regressor`` may be a scipy.sparse matrix. Arrays stored as chumpy ``Ch`` objects are read *without*
  chumpy by recovering their stored array; a pickle holding a chumpy expression that is not a plain stored
  array cannot be read without chumpy, and the error says how to convert the file to .npz.

SMPL's own frame is y up, facing +z, actor's left +x, like ours; the mesh is only shifted so that the pelvis
is above the origin and the lowest vertex is on y=0. SMPL's rest pose (arms out, legs slightly apart) is the
template's rest pose. Landmarks: the generic skeleton offsets of the face and foot key points (nose, eyes,
ears, toes, heels) are snapped to the nearest head/foot vertex of the mesh, whatever its topology.
Albedo: ``"pattern"`` (default) paints :func:`eventcap.body.template.pattern_albedo` clothing, ``"uniform"``
a constant 0.5.
"""

from __future__ import annotations

import importlib
import pickle
from pathlib import Path

import numpy as np

from eventcap.body.skeleton import (
    JOINT_NAMES,
    NUM_JOINTS,
    PARENTS,
    default_landmarks,
)
from eventcap.body.template import Template, pattern_albedo, snap_landmarks_to_surface

REQUIRED_KEYS = ("v_template", "weights", "J_regressor", "kintree_table", "shapedirs", "f")

#: Number of vertices of the standard SMPL mesh topology.
SMPL_NUM_VERTICES = 6890


class _ChumpyPlaceholder:
    """Stands in for a chumpy class while unpickling; keeps the pickled state for inspection."""

    _chumpy_name = "chumpy.?"

    def __new__(cls, *args, **kwargs):
        return object.__new__(cls)

    def __init__(self, *args, **kwargs):
        pass

    def __setstate__(self, state):
        self.__dict__["_state"] = state


class _SmplUnpickler(pickle.Unpickler):
    """Unpickler that needs neither chumpy nor old scipy module paths."""

    def find_class(self, module, name):
        if module.split(".")[0] == "chumpy":
            return type(name, (_ChumpyPlaceholder,), {"_chumpy_name": f"{module}.{name}"})
        try:
            return super().find_class(module, name)
        except (ImportError, AttributeError):
            if module.startswith("scipy.sparse"):
                return getattr(importlib.import_module("scipy.sparse"), name)
            raise


def _plain(value, key: str, path: Path):
    """A pickled value as numpy / scipy.sparse; a chumpy Ch becomes its stored array."""
    if isinstance(value, _ChumpyPlaceholder):
        state = value.__dict__.get("_state")
        x = state.get("x") if isinstance(state, dict) else None
        if type(value)._chumpy_name.endswith(".Ch") and isinstance(x, np.ndarray):
            return x
        raise ValueError(
            f"{path}: key {key!r} is a chumpy expression ({type(value)._chumpy_name}), not a stored array, and "
            "cannot be evaluated without chumpy. Convert the file once where chumpy is installed: load the pickle "
            "with encoding='latin1', turn each of the keys " + ", ".join(REQUIRED_KEYS) + " into a numpy array "
            "(np.array(v) for chumpy values, v.toarray() for scipy.sparse ones), save them with np.savez and pass "
            "the .npz file instead."
        )
    return value


def read_smpl_arrays(path) -> dict[str, np.ndarray]:
    """Read the SMPL arrays named in REQUIRED_KEYS from a .npz or .pkl file, as dense float/int arrays."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"SMPL model file not found: {path}")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            raw = {k: z[k] for k in z.files}
    elif suffix == ".pkl":
        try:
            with open(path, "rb") as fh:
                raw = _SmplUnpickler(fh, encoding="latin1").load()
        except (pickle.UnpicklingError, EOFError, ImportError, AttributeError) as e:
            raise ValueError(f"{path}: cannot read as an SMPL pickle ({type(e).__name__}: {e})") from None
        if not isinstance(raw, dict):
            raise ValueError(f"{path}: expected a pickled dict of SMPL arrays, got {type(raw).__name__}")
    else:
        raise ValueError(f"{path}: expected an SMPL model file ending in .npz or .pkl, got {suffix!r}")
    missing = [k for k in REQUIRED_KEYS if k not in raw]
    if missing:
        raise ValueError(f"{path}: SMPL model is missing key(s) {missing}; found {sorted(raw)}")
    out = {}
    for k in REQUIRED_KEYS:
        v = _plain(raw[k], k, path)
        if hasattr(v, "toarray"):  # scipy.sparse
            v = v.toarray()
        out[k] = np.asarray(v)
    return out


def load_smpl(path, betas=None, albedo: str = "pattern", name: str | None = None) -> Template:
    """Load an SMPL model file as a Template, optionally with shape coefficients ``betas`` (B',), B' <= B.

    The rest mesh is ``v_template + shapedirs[..., :B'] @ betas``, joints are regressed from it with
    ``J_regressor``, and everything is shifted so that the pelvis is above the origin and the feet touch y=0.
    """
    path = Path(path)
    d = read_smpl_arrays(path)
    v = d["v_template"].astype(np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"{path}: v_template must have shape (V, 3), got {v.shape}")
    n_v = v.shape[0]
    sd = d["shapedirs"].astype(np.float64)
    if sd.ndim != 3 or sd.shape[:2] != (n_v, 3):
        raise ValueError(f"{path}: shapedirs must have shape ({n_v}, 3, B), got {sd.shape}")
    if betas is not None:
        betas = np.asarray(betas, dtype=np.float64).ravel()
        if betas.size > sd.shape[2]:
            raise ValueError(f"betas: the model has {sd.shape[2]} shape coefficients, got {betas.size}")
        v = v + sd[:, :, : betas.size] @ betas
    jr = d["J_regressor"].astype(np.float64)
    if jr.shape != (NUM_JOINTS, n_v):
        raise ValueError(f"{path}: J_regressor must have shape (24, {n_v}), got {jr.shape}")
    kt = d["kintree_table"].astype(np.int64)
    if kt.shape != (2, NUM_JOINTS):
        raise ValueError(f"{path}: kintree_table must have shape (2, 24) (SMPL's 24 joints), got {kt.shape}")
    parents = kt[0].copy()
    if parents[0] < 0 or parents[0] >= NUM_JOINTS:  # the root's parent is stored as -1 or 2**32 - 1
        parents[0] = -1
    if not np.array_equal(kt[1], np.arange(NUM_JOINTS)) or not np.array_equal(parents, PARENTS):
        bad = int(np.flatnonzero(parents != PARENTS)[0]) if not np.array_equal(parents, PARENTS) else None
        detail = (
            f"joint {bad} ({JOINT_NAMES[bad]}) has parent {parents[bad]}, expected {PARENTS[bad]}"
            if bad is not None
            else f"joint ids {kt[1].tolist()}"
        )
        raise ValueError(f"{path}: kintree_table is not SMPL's 24-joint tree: {detail}")
    w = d["weights"].astype(np.float64)
    if w.shape != (n_v, NUM_JOINTS):
        raise ValueError(f"{path}: weights must have shape ({n_v}, 24), got {w.shape}")
    faces = d["f"].astype(np.int64)

    joints = jr @ v
    shift = np.array([-joints[0, 0], -v[:, 1].min(), -joints[0, 2]])
    v = v + shift
    joints = joints + shift
    if not (joints[1, 0] > joints[2, 0] and joints[10, 2] > joints[7, 2] and joints[15, 1] > joints[0, 1]):
        raise ValueError(
            f"{path}: the model is not in SMPL's frame (y up, facing +z, left hip at +x): "
            f"l_hip x={joints[1, 0]:.3f}, r_hip x={joints[2, 0]:.3f}, head y={joints[15, 1]:.3f}"
        )

    lj, lo = default_landmarks(joints)
    lo = snap_landmarks_to_surface(v, w, joints, lj, lo)

    if albedo == "pattern":
        alb = pattern_albedo(v, w / w.sum(axis=1, keepdims=True), joints)
    elif albedo == "uniform":
        alb = np.full(n_v, 0.5, dtype=np.float32)
    else:
        raise ValueError(f"albedo: expected 'pattern' or 'uniform', got {albedo!r}")

    tpl = Template(
        name=name or f"smpl:{path.stem}",
        rest_joints=joints,
        vertices=v,
        faces=faces,
        weights=w,
        vertex_albedo=alb,
        landmark_joint=lj,
        landmark_offset=lo,
    )
    return tpl.outward()  # an inward-wound file is flipped to the outward convention
