"""Body segments' inertia per pose parameter (eventcap.body.segments): hand-computed values, invariants, errors."""

from __future__ import annotations

import numpy as np
import pytest

from eventcap.body.segments import SEGMENTS, dof_inertia, inertia_prior_gain, joint_inertia
from eventcap.body.skeleton import DEFAULT_REST_JOINTS, DOF_INDEX, JOINT_INDEX, PARENTS

J = JOINT_INDEX


def test_segment_masses_are_de_levas_and_sum_to_the_body():
    m = {name: mass for name, _, _, mass, _ in SEGMENTS}
    assert sum(m.values()) == pytest.approx(1.0, abs=1e-3)
    assert m["l_forearm"] == m["r_forearm"] == 0.0162 and m["l_thigh"] == 0.1416 and m["head_neck"] == 0.0694


def test_elbow_inertia_is_the_forearm_and_hand_by_hand():
    """The elbow turns the forearm (centre 45.74% of the way to the wrist, plus its own m L²/12) and the hand
    (centre halfway from the wrist to the hand joint)."""
    x = np.asarray(DEFAULT_REST_JOINTS)
    for s in ("l", "r"):
        e, w, h = x[J[f"{s}_elbow"]], x[J[f"{s}_wrist"]], x[J[f"{s}_hand"]]
        lf, lh = np.linalg.norm(w - e), np.linalg.norm(h - w)
        dh = np.linalg.norm(w + 0.5 * (h - w) - e)
        expect = 0.0162 * ((0.4574 * lf) ** 2 + lf ** 2 / 12) + 0.0061 * (dh ** 2 + lh ** 2 / 12)
        assert joint_inertia(x)[J[f"{s}_elbow"]] == pytest.approx(expect, rel=1e-9)
        assert dof_inertia(x)[DOF_INDEX[f"{s}_elbow_flex"]] == pytest.approx(expect, rel=1e-9)


def test_inertia_grows_towards_the_root_is_symmetric_and_scales_with_size_squared():
    x = np.asarray(DEFAULT_REST_JOINTS)
    I = joint_inertia(x)
    for k in range(1, 24):
        assert I[PARENTS[k]] >= I[k]  # a parent turns everything its child turns
    assert I[0] == pytest.approx(0.189, abs=0.01)  # the whole body about the pelvis (fraction of mass × m²)
    for a, b in (("l_elbow", "r_elbow"), ("l_knee", "r_knee"), ("l_shoulder", "r_shoulder")):
        assert I[J[a]] == pytest.approx(I[J[b]], rel=1e-6)
    assert joint_inertia(1.2 * x) == pytest.approx(1.44 * I, rel=1e-9)
    D = dof_inertia(x)
    assert D.shape == (30,) and np.all(D[27:] == I[0])


def test_prior_gains_keep_the_mean_strength_and_weaken_the_light_parts():
    x = np.asarray(DEFAULT_REST_JOINTS)
    assert np.all(inertia_prior_gain(x, 0) == 1.0)
    g = inertia_prior_gain(x, 1.0)
    assert g.shape == (33,) and np.all(g[30:] == 1.0)  # the root's translation is not a rotation
    assert np.exp(np.log(g[:30]).mean()) == pytest.approx(1.0, rel=1e-12)
    assert g[DOF_INDEX["r_elbow_flex"]] == pytest.approx(0.13, abs=0.01)
    assert g[27] == pytest.approx(29.5, abs=0.5)  # the root's rotations turn the whole body
    assert inertia_prior_gain(x, 0.5) == pytest.approx(np.sqrt(g), rel=1e-12)
    assert inertia_prior_gain(1.3 * x, 1.0) == pytest.approx(g, rel=1e-9)  # only the proportions count
    held = inertia_prior_gain(x, 1.0, cap=1.0)  # lighter than the mean: held less; heavier: as before
    assert np.all(held == np.minimum(g, 1.0)) and held[DOF_INDEX["spine_twist"]] == 1.0 and held[27] == 1.0
    assert held[DOF_INDEX["l_ankle_flex"]] == pytest.approx(0.01, abs=0.005)
    floored = inertia_prior_gain(x, 1.0, cap=1.0, floor=0.05)  # nothing held less than 1/20 of the trunk
    assert np.all(floored == np.clip(g, 0.05, 1.0)) and floored[DOF_INDEX["l_ankle_flex"]] == 0.05
    assert floored[DOF_INDEX["r_elbow_flex"]] == held[DOF_INDEX["r_elbow_flex"]]  # above the floor: unchanged


def test_bad_exponent_and_degenerate_joints_are_refused():
    with pytest.raises(ValueError, match=r"inertia exponent: expected a number >= 0, got -1"):
        inertia_prior_gain(DEFAULT_REST_JOINTS, -1)
    with pytest.raises(ValueError, match=r"inertia exponent: expected a number >= 0, got nan"):
        inertia_prior_gain(DEFAULT_REST_JOINTS, float("nan"))
    with pytest.raises(ValueError, match=r"inertia cap: expected a number >= 1, got 0.5"):
        inertia_prior_gain(DEFAULT_REST_JOINTS, 1.0, cap=0.5)
    with pytest.raises(ValueError, match=r"inertia floor: expected a number in \[0, 1\], got 1.5"):
        inertia_prior_gain(DEFAULT_REST_JOINTS, 1.0, floor=1.5)
    flat = np.zeros((24, 3))
    with pytest.raises(ValueError):
        inertia_prior_gain(flat, 1.0)
