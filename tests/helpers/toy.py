"""The toy stages (tests/toy_stages.py): their pipeline, their config and the environment that registers them."""

from __future__ import annotations

import os
import subprocess

from .paths import TESTS

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
    procs = [subprocess.Popen(c, cwd=cwd, env=toy_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
             for c in cmds]
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), outs
    return outs
