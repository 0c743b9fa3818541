"""Analytic derivatives against central finite differences."""

from __future__ import annotations

import numpy as np
import pytest


def assert_derivatives_match_fd(f, gradient, x, g, H, coords, rel_g: float, label, h: float = 1e-6) -> None:
    """Central finite differences at ``x`` along the coordinates ``coords``: of the objective ``f`` against the
    gradient ``g``, and of ``gradient`` (x -> gradient vector) against the Hessian columns ``H[:, k]``."""
    for k in coords:
        e = np.zeros_like(x)
        e[k] = h
        fd = (f(x + e) - f(x - e)) / (2 * h)
        assert fd == pytest.approx(g[k], rel=rel_g, abs=1e-7 * max(1.0, np.abs(g).max())), (label, k)
        np.testing.assert_allclose(H[:, k], (gradient(x + e) - gradient(x - e)) / (2 * h), rtol=1e-4,
                                   atol=1e-6 * max(1.0, np.abs(H).max()), err_msg=f"{label} Hessian column {k}")
