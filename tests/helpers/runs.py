"""Small runs through the real runner: a tiny synthetic capture's config, and a run whose solve returns known poses
(tests/output_stages.py) with its outputs written."""

from __future__ import annotations

import functools
import json
from pathlib import Path

from eventcap.apps.outputs import check_outputs_config, write_run_outputs
from eventcap.core.runner import Runner

from .paths import ROOT

POSES_PIPELINE = {"nodes": {
    "template": {"config": "template"},
    "source": {"config": "source", "inputs": {"template": "template.template"}},
    "solve": {"inputs": {"recording": "source.recording", "batches": "source.batches"}},
}}


def known_poses_config(cache: Path, **outputs) -> dict:
    """A small synthetic capture (0.09 s: 2 batches) whose 'solve' node returns the poses of a known motion."""
    data = json.loads(json.dumps(small_capture_config()))
    data.update(pipeline=json.loads(json.dumps(POSES_PIPELINE)), cache_dir=str(cache),
                stages={"solve": {"stage": "known_poses"}})
    data["outputs"].update({"poses": "solve.poses", **outputs})
    return data


def run_with_outputs(cfg: dict, run_dir: Path):
    runner = Runner(cfg)
    checked = check_outputs_config(runner)
    result = runner.run(run_dir)
    return runner, result, write_run_outputs(runner, result, run_dir, checked)



@functools.lru_cache(maxsize=1)
def small_capture_config() -> dict:
    """The composed default config of a tiny synthetic capture (0.09 s, 2 batches, light template): callers copy it
    and swap in their own pipeline, cache and outputs."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["experiment=quick", "source.duration_s=0.09",
                                                       "template=procedural", "template.target_faces=2000",
                                                       "source.n_track_points=20"])
    return OmegaConf.to_container(cfg, resolve=True)


#: A tiny run of the spline pipeline (0.13 s of a synthetic capture, windows of 3 batches) for resume and window tests.
TINY_SPLINE_RUN = ["pipeline=spline", "experiment=quick", "source.duration_s=0.13", "template=procedural",
                   "template.target_faces=2000", "source.n_track_points=20", "stages.solve.half_window=1",
                   "outputs.video=false", "stages.chunk.seconds=0.04"]  # a chunk per batch: a window each
