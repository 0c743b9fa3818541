"""Warnings where a stage's result is doubtful: EDI's C at the edge of its search range, a solve with 0
correspondences, a refinement with 0 matched boundary pixels (each in the log and in ctx.stats)."""

from __future__ import annotations

import dataclasses
import functools
import logging

import numpy as np
import pytest

from eventcap.core.config import build_config
from eventcap.core.registry import load_registry
from eventcap.core.stage import StageContext


@functools.lru_cache(maxsize=1)
def _edi_recording():
    from helpers import edi_scenes as scenes

    from eventcap.artifacts.recording import EventStream, FrameStack, Recording
    from eventcap.camera import Camera

    events, frames = scenes.capture(scenes.scenes()["checkerboard 360 px/s"], 90_000)
    images = np.stack([f.image for f in frames]).astype(np.float32)
    images = images / 255.0 if images.max() > 1 else images
    h, w = images.shape[1:]
    return Recording(events=EventStream(events=events, width=w, height=h),
                     camera=Camera(w, h, 200.0, 200.0, w / 2, h / 2),
                     frames=FrameStack(images=images, t_us=np.array([f.t_us for f in frames], np.int64),
                                       exposure_us=np.array([f.exposure_us for f in frames], np.int64), height=h,
                                       width=w))


@pytest.mark.parametrize("c_range,at_edge", [((0.05, 0.5), False), ((0.3, 0.6), True)])
def test_edi_contrast_at_the_edge_of_its_range_warns(caplog, c_range, at_edge):
    # The simulated sensor's C is 0.2: a search over [0.3, 0.6] ends at its lower edge.
    spec = load_registry().get("edi")
    ctx = StageContext(node="sharpen", stage="edi")
    cfg = build_config(spec, {"c_min": c_range[0], "c_max": c_range[1]}, "stages.sharpen")
    with caplog.at_level(logging.INFO, logger="eventcap.core.stage"):
        spec.load_run()({"recording": _edi_recording()}, cfg, ctx)
    assert ctx.stats["contrast_at_range_edge"] is at_edge
    warned = [r for r in caplog.records if r.levelno == logging.WARNING and "edge of its search range" in r.message]
    assert len(warned) == int(at_edge)
    if at_edge:
        assert ctx.stats["contrast"] == pytest.approx(0.3, abs=0.02)
        assert "[0.3, 0.6]" in warned[0].message
    else:
        assert 0.16 <= ctx.stats["contrast"] <= 0.24


def test_solve_with_zero_correspondences_warns(caplog):
    from helpers.batch_scene import N, T0, stage_inputs

    from eventcap.artifacts import Batch

    inputs = stage_inputs()
    s = inputs["sliced"]
    inputs["sliced"] = dataclasses.replace(s, valid=np.zeros_like(s.valid),
                                           xy=np.full_like(s.xy, np.nan))
    spec = load_registry().get("batch")
    ctx = StageContext(node="solve", stage="batch", batch=Batch(0, T0, T0 + 1000 * N, 0))
    with caplog.at_level(logging.INFO, logger="eventcap.core.stage"):
        spec.load_run()(inputs, build_config(spec, {"icp_rounds": 1}, "stages.solve"), ctx)
    assert ctx.stats["n_correspondences"] == 0
    assert any(r.levelno == logging.WARNING and "batch 0: 0 track-to-mesh correspondences" in r.message
               for r in caplog.records)


@pytest.mark.slow  # builds the refinement NLP (~10 s)
def test_refine_with_zero_matched_boundary_pixels_warns(caplog):
    from helpers.refine_scene import run_stage, stage_inputs

    from eventcap.artifacts.recording import EventStream

    inputs = stage_inputs()
    rec = inputs["recording"]
    ev = rec.events.events.copy()
    ev["t"] += 10_000_000  # every event far outside the batch's window: nothing to match
    inputs["recording"] = dataclasses.replace(rec, events=EventStream(events=ev, width=rec.events.width,
                                                                      height=rec.events.height))
    with caplog.at_level(logging.INFO, logger="eventcap.core.stage"):
        _, ctx = run_stage(inputs)
    assert ctx.stats["matched"][-1] == 0 and ctx.stats["boundary_pixels"][-1] > 5000
    assert any(r.levelno == logging.WARNING and "silhouette boundary pixels has an event" in r.message
               for r in caplog.records)
