"""A term that is on but reads what the solve does not provide fails when the solve is built (issue 56, item 3):
the message names the term and the setting that turns it off. What a rule withholds (the smoothing evidence below
``smoothing.min_fps``, the floor where no fit succeeded) and what a window holds none of (nobody detected: a gap)
is not missing."""

from __future__ import annotations

import dataclasses
import re
from types import SimpleNamespace

import numpy as np
import pytest

from eventcap.core.stage import StageFailed
from eventcap.energy.errors import EnergyError
from eventcap.energy.spline import UniformCubicBSpline
from eventcap.energy.terms import TermSet
from eventcap_spline import _impl
from eventcap_spline.solve import solve_window
from helpers.spline_scene import H_US, run_stage, scene, scene_inputs, silhouette_events, spline_config, stage_inputs

EVENTS = "events"  # the scene's events stand in wherever a case is not about them


def _spline():
    t_det = scene()[2]
    return UniformCubicBSpline(int(t_det[0]), H_US, int((t_det[-1] - t_det[0]) // H_US))


def _inputs(det=None, events=EVENTS, tracks=True):
    """The scene's window with these detections (None: the scene's), events (None: none) and tracks (False: none)."""
    rec, scene_det, _, t_us, _, xy, valid = scene()
    inputs = scene_inputs(_spline(), xy, valid, silhouette_events() if events is EVENTS else events)
    inputs.detections = scene_det if det is None else det
    if not tracks:
        inputs.tracks = None
    return inputs


def _check(inputs, **changes):
    TermSet.decode(spline_config(changes).terms).check(inputs, "stages.solve")


def _fails(message: str, inputs, **changes):
    with pytest.raises(EnergyError, match="^" + re.escape(message) + "$") as info:
        _check(inputs, **changes)
    assert info.value.status == "invalid_config"


def _only_2d(det):
    return dataclasses.replace(det, confidence_3d=np.zeros_like(det.confidence_3d))


def _only_3d(det):
    return dataclasses.replace(det, confidence_2d=np.zeros_like(det.confidence_2d))


def test_the_scene_provides_what_every_default_term_reads():
    _check(_inputs())  # nothing raised: the default terms all have their data
    assert [t.name for t in TermSet.decode(spline_config().terms).on] == [
        "landmarks_2d", "joints_3d", "cor", "sil", "still", "prior", "floor", "slide"]


def test_e3d_on_detections_of_2d_landmarks_only():
    det = _only_2d(scene()[1])
    _fails("stages.solve.terms.joints_3d is on (gain 1), but the window's detections hold no 3D joints "
           "(confidence_3d 0 at every frame: a detector of 2D landmarks only): set stages.solve.terms.joints_3d.gain=0 "
           "to solve without it", _inputs(det))
    _check(_inputs(det), **{"terms.joints_3d.gain": 0.0})  # turned off: nothing is missing
    _fails("stages.solve.terms.bones is on (gain 0.5), but the window's detections hold no 3D joints (confidence_3d "
           "0 at every frame: a detector of 2D landmarks only): set stages.solve.terms.bones.gain=0 to solve without "
           "it", _inputs(det), **{"terms.joints_3d.gain": 0.0, "terms.bones.gain": 0.5})


def test_e2d_on_detections_of_3d_joints_only():
    _fails("stages.solve.terms.landmarks_2d is on (gain 1), but the window's detections hold no 2D landmarks "
           "(confidence_2d 0 at every frame: a detector of 3D joints only): set "
           "stages.solve.terms.landmarks_2d.gain=0 to solve without it", _inputs(_only_3d(scene()[1])))


def test_a_detection_term_without_a_noise_model():
    det = scene()[1]
    _fails("stages.solve.terms.landmarks_2d is on (gain 1), but the window's detections state no 2D noise model: "
           "set stages.solve.terms.landmarks_2d.gain=0 to solve without it, or "
           "stages.solve.terms.landmarks_2d.sigma_px=<px>", _inputs(dataclasses.replace(det, sigma_2d_px=None)))
    _check(_inputs(dataclasses.replace(det, sigma_2d_px=None)), **{"terms.landmarks_2d.sigma_px": 3.0})
    _fails("stages.solve.terms.joints_3d is on (gain 1), but the window's detections state no 3D noise model: "
           "set stages.solve.terms.joints_3d.gain=0 to solve without it, or stages.solve.terms.joints_3d.sigma_mm=<mm>",
           _inputs(dataclasses.replace(det, sigma_3d_m=None)))


def test_the_event_terms_without_tracks_or_events():
    _fails("stages.solve.terms.cor is on (gain 1), but it reads the window's tracks, which this solve does not "
           "provide: set stages.solve.terms.cor.gain=0 to solve without it", _inputs(tracks=False))
    _fails("stages.solve.terms.sil is on (gain 1), but it reads the window's events, which this solve does not "
           "provide: set stages.solve.terms.sil.gain=0 to solve without it", _inputs(events=None))
    _fails("stages.solve.terms.still is on (gain 1), but it reads the window's events, which this solve does not "
           "provide: set stages.solve.terms.still.gain=0 to solve without it", _inputs(events=None),
           **{"terms.sil.gain": 0.0})
    _check(_inputs(events=None), **{"terms.sil.gain": 0.0, "terms.still.gain": 0.0})
    # tracks and events that are there but hold nothing (a still scene) are data, not a missing input
    rec, det, _, t_us = scene()[:4]
    empty = scene_inputs(_spline(), np.zeros((t_us.size, 0, 2)), np.zeros((t_us.size, 0), bool),
                         silhouette_events()[:0])
    _check(empty)


def test_what_a_rule_withholds_or_nobody_detected_is_not_missing():
    # the context pull on, with no smoothing evidence offered (below smoothing.min_fps), and the floor terms with no
    # floor offered: they hold nothing there, by rule (the node's log says so)
    inputs = _inputs()
    assert not inputs.provides("smoothing") and not inputs.provides("floor_y")
    _check(inputs, **{"terms.context.gain": 1.0})
    # nobody detected in the window: a gap (NothingObserved when it is solved), not a detector without a kind
    det = scene()[1]
    nobody = dataclasses.replace(det, confidence_2d=np.zeros_like(det.confidence_2d),
                                 confidence_3d=np.zeros_like(det.confidence_3d), sigma_2d_px=None)
    _check(_inputs(nobody), **{"terms.bones.gain": 1.0})


def test_solve_window_checks_before_it_measures_anything():
    """solve_window asks its solver for nothing but the terms and their key before the check fails."""
    terms = TermSet.decode(spline_config().terms)
    with pytest.raises(EnergyError, match=r"^stages\.solve\.terms\.cor is on \(gain 1\), but it reads the window's "
                                          r"tracks"):
        solve_window(SimpleNamespace(terms=terms, where="stages.solve"), _spline(), _inputs(tracks=False))


def test_the_stage_fails_before_it_builds_anything(monkeypatch):
    """Through the stage: a detector of 2D landmarks only with E_3D on fails naming the window, the term and the
    setting, before the capture's template and the solver are built."""
    def built(*args, **kw):
        raise AssertionError("built before the check")

    monkeypatch.setattr(_impl, "capture_template", built)
    monkeypatch.setattr(_impl, "solver_for", built)
    inputs = stage_inputs()
    inputs = {**inputs, "detections": dataclasses.replace(
        inputs["detections"], confidence_3d=np.zeros_like(inputs["detections"].confidence_3d))}
    b = inputs["batches"].batch(1)
    with pytest.raises(StageFailed) as info:
        run_stage(inputs, b)
    assert str(info.value) == (
        "batch 1 (window of batches 0..2): stages.solve.terms.joints_3d is on (gain 1), but the window's detections "
        "hold no 3D joints (confidence_3d 0 at every frame: a detector of 2D landmarks only): set "
        "stages.solve.terms.joints_3d.gain=0 to solve without it")
    assert info.value.status == "invalid_config"
