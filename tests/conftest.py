"""Shared fixtures: the toy test stages (tests/toy_stages.py) and a toy pipeline config.

Shared code that tests import lives in tests/helpers (tests import no test module and not this file).
"""

from __future__ import annotations

import copy
import os

# One BLAS/OpenMP thread, as the CLI pins them: the solvers' many small products run much slower when threads
# oversubscribe the 2-core CI machine. Set before numpy is first imported (pytest itself does not import it).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import pytest  # noqa: E402

from helpers.paths import TESTS  # noqa: E402
from helpers.toy import TOY_PIPELINE, TOY_STAGES, toy_env  # noqa: E402

#: tests/fixtures holds packages that tests install (a plugin's own tests run inside it, once it is installed)
collect_ignore = ["fixtures"]


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


@pytest.fixture
def toy_cfg(tmp_path, toy):
    """A fresh toy pipeline config (plain dict) with its own cache directory."""

    def make(**stage_changes):
        stages = copy.deepcopy(TOY_STAGES)
        for node, changes in stage_changes.items():
            stages[node].update(changes)
        return {"pipeline": copy.deepcopy(TOY_PIPELINE), "stages": stages, "cache_dir": str(tmp_path / "cache")}

    return make
