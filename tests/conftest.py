"""Shared fixtures: the toy test stages (tests/toy_stages.py) and a toy pipeline config."""

from __future__ import annotations

import copy
import functools
import os
import sys
from pathlib import Path

# One BLAS/OpenMP thread, as the CLI pins them: the solvers' many small products run much slower when threads
# oversubscribe the 2-core CI machine. Set before numpy is first imported (pytest itself does not import it).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import pytest  # noqa: E402

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent
#: The real DAVIS346 recording (MIT, 1.2 MB) shipped with the tests; origin and licence in tests/data/real/SOURCE.md.
REAL_DAVIS346 = TESTS / "data" / "real" / "davis346_lab_aps.aedat4"

TOY_PIPELINE = {
    "nodes": {
        "signal": {},
        "smooth": {"inputs": {"series": "signal.series", "batches": "signal.batches"}},
        "scale": {"inputs": {"chunk": "smooth.chunk"}},
        "total": {"inputs": {"chunks": "scale.chunk"}},
    }
}
TOY_STAGES = {
    "signal": {"stage": "toy_signal", "n_batches": 4, "samples_per_batch": 50, "seed": 0},
    "smooth": {"stage": "toy_smooth", "window": 5},
    "scale": {"stage": "toy_scale", "factor": 2.0},
    "total": {"stage": "toy_sum"},
}


def toy_env() -> dict[str, str]:
    """Environment for subprocesses that should see the toy stages."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(TESTS), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env["EVENTCAP_STAGES"] = "toy_stages:SPECS"
    return env


def run_concurrently(cmds: list[list[str]], cwd) -> list[tuple[bytes, bytes]]:
    """Start every command at once (the toy stages' environment, in cwd), wait for all; each must exit 0.
    Returns their (stdout, stderr)."""
    import subprocess

    procs = [subprocess.Popen(c, cwd=cwd, env=toy_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
             for c in cmds]
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), outs
    return outs


def _stages_in_process(monkeypatch, specs: str):
    """Register the test stages ``specs`` (EVENTCAP_STAGES syntax, modules in tests/) for one test."""
    from eventcap.core.runner import reset_process_caches

    monkeypatch.setenv("EVENTCAP_STAGES", specs)
    monkeypatch.syspath_prepend(str(TESTS))
    reset_process_caches()
    yield
    reset_process_caches()


@pytest.fixture
def toy(monkeypatch):
    """Register the toy stages in this process."""
    monkeypatch.setenv("PYTHONPATH", toy_env()["PYTHONPATH"])
    yield from _stages_in_process(monkeypatch, "toy_stages:SPECS")


@pytest.fixture
def known_poses(monkeypatch):
    """Register tests/output_stages.py (a 'solve' returning known poses) in this process."""
    yield from _stages_in_process(monkeypatch, "output_stages:SPECS")


def assert_derivatives_match_fd(f, gradient, x, g, H, coords, rel_g: float, label, h: float = 1e-6) -> None:
    """Central finite differences at ``x`` along the coordinates ``coords``: of the objective ``f`` against the
    gradient ``g``, and of ``gradient`` (x -> gradient vector) against the Hessian columns ``H[:, k]``."""
    import numpy as np

    for k in coords:
        e = np.zeros_like(x)
        e[k] = h
        fd = (f(x + e) - f(x - e)) / (2 * h)
        assert fd == pytest.approx(g[k], rel=rel_g, abs=1e-7 * max(1.0, np.abs(g).max())), (label, k)
        np.testing.assert_allclose(H[:, k], (gradient(x + e) - gradient(x - e)) / (2 * h), rtol=1e-4,
                                   atol=1e-6 * max(1.0, np.abs(H).max()), err_msg=f"{label} Hessian column {k}")


@pytest.fixture
def toy_cfg(tmp_path, toy):
    """A fresh toy pipeline config (plain dict) with its own cache directory."""

    def make(**stage_changes):
        stages = copy.deepcopy(TOY_STAGES)
        for node, changes in stage_changes.items():
            stages[node].update(changes)
        return {"pipeline": copy.deepcopy(TOY_PIPELINE), "stages": stages, "cache_dir": str(tmp_path / "cache")}

    return make


def eventcap_cmd() -> list[str]:
    return [sys.executable, "-m", "eventcap.apps.cli"]


@functools.lru_cache(maxsize=1)
def small_capture_config() -> dict:
    """The composed default config of a tiny synthetic capture (0.09 s, 2 batches, light template): callers copy it
    and swap in their own pipeline, cache and outputs."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["experiment=quick", "source.duration_s=0.09",
                                                       "template=procedural", "template.target_faces=2000", "source.n_track_points=20"])
    return OmegaConf.to_container(cfg, resolve=True)
