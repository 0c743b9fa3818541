"""The pose graph of benchmarks/bench_fusion.py: what it returns is the least-squares fusion the script reports."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_fusion import innovation_rho, pose_graph  # noqa: E402


def _objective(X, fits, steps, rho):
    return float(np.sum((X - fits) ** 2) + rho * np.sum((np.diff(X, axis=0) - steps) ** 2))


def test_pose_graph_keeps_the_fits_without_odometry_weight():
    rng = np.random.default_rng(0)
    fits, steps = rng.normal(size=(7, 33)), rng.normal(size=(6, 33))
    np.testing.assert_allclose(pose_graph(fits, steps, 0.0), fits, atol=1e-12)


def test_pose_graph_with_exact_odometry_averages_the_fit_errors():
    rng = np.random.default_rng(1)
    truth = np.cumsum(rng.normal(size=(11, 33)), axis=0)
    err = rng.normal(scale=0.1, size=truth.shape)
    X = pose_graph(truth + err, np.diff(truth, axis=0), 1e8)
    # exact steps tie all frames together: every frame gets the sequence's mean fit error
    np.testing.assert_allclose(X, truth + err.mean(axis=0), atol=1e-5)


def test_pose_graph_is_the_minimum_of_its_objective():
    rng = np.random.default_rng(2)
    fits, steps, rho = rng.normal(size=(9, 4)), rng.normal(size=(8, 4)), 2.5
    X = pose_graph(fits, steps, rho)
    best = _objective(X, fits, steps, rho)
    h = 1e-6
    for i, j in [(0, 0), (4, 2), (8, 3)]:  # zero gradient, by central differences
        E = np.zeros_like(X)
        E[i, j] = h
        grad = (_objective(X + E, fits, steps, rho) - _objective(X - E, fits, steps, rho)) / (2 * h)
        assert abs(grad) < 1e-6
    for _ in range(20):  # and no random nearby point is lower
        assert _objective(X + rng.normal(scale=1e-2, size=X.shape), fits, steps, rho) > best


def test_innovation_rho_recovers_the_variance_ratio_without_ground_truth():
    rng = np.random.default_rng(3)
    truth = np.cumsum(rng.normal(scale=0.2, size=(4001, 33)), axis=0)
    for sigma_e, sigma_o in [(0.1, 0.05), (0.05, 0.1)]:
        fits = truth + rng.normal(scale=sigma_e, size=truth.shape)
        steps = np.diff(truth, axis=0) + rng.normal(scale=sigma_o, size=(4000, 33))
        expected = sigma_e ** 2 / sigma_o ** 2  # 4 and 0.25
        assert abs(innovation_rho(fits, steps) / expected - 1) < 0.1
