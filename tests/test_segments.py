"""Body segments' inertia per pose parameter (eventcap.body.segments): hand-computed values, invariants, errors."""

from __future__ import annotations

import numpy as np
import pytest

from eventcap.body.segments import SEGMENTS, dof_inertia, joint_inertia
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
