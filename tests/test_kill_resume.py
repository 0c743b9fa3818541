"""A run killed with SIGKILL at random moments and resumed ends with identical outputs and recomputes nothing
committed. The quick version runs 3 trials; the full 20-trial soak is `slow` (and benchmarks/robustness/kill_resume.py;
the harness: tests/helpers/kill_resume.py)."""

from __future__ import annotations

import pytest

from helpers import kill_resume


def test_kill_resume_quick(capsys):
    assert kill_resume.main(["--trials", "3", "--executor", "mixed", "--seed", "1"]) == 0
    out = capsys.readouterr().out
    assert "3 passed, 0 failed" in out


@pytest.mark.slow
def test_kill_resume_soak(capsys):
    assert kill_resume.main(["--trials", "20", "--executor", "mixed", "--seed", "7"]) == 0
    assert "20 passed, 0 failed" in capsys.readouterr().out


@pytest.mark.slow
def test_kill_the_driver_alone_every_executor(capsys):
    # the pool / Dask workers of a driver killed by SIGKILL must exit by themselves, and the resume is still exact
    assert kill_resume.main(["--trials", "6", "--executor", "all", "--kill", "driver", "--seed", "3"]) == 0
    out = capsys.readouterr().out
    assert "6 passed, 0 failed" in out and "orphaned processes: 0" in out
