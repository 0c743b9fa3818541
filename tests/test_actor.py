"""A person who is not our template (issue 43, item 1): ``source.actor`` films a body of its own.

Without an actor the source's config, key material and inputs are those of before the group existed (so its cache
entries stay valid); with one, the capture's ground truth is the actor's skeleton, its recording carries no
template, and a change of the template does not recompute it. A template key the user leaves unsaid (null) builds
the same body and key as before, and the template says what was stated."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from helpers.runs import small_capture_config
from eventcap.body.anny import anny_from_json, anny_rest_joints, anny_template
from eventcap.body.proportions import rest_skeleton_from_motion, segment_lengths
from eventcap.core.config import ConfigError, build_config, result_config
from eventcap.core.registry import load_registry
from eventcap.core.runner import Runner

#: The synthetic source's key material before source.actor existed had exactly these fields.
OLD_FIELDS = {"motion", "motion_start_s", "motion_map", "duration_s", "seed", "speed", "amplitude", "fps",
              "exposure_us", "camera", "contrast_threshold", "threshold_sigma", "refractory_us", "noise_rate_hz",
              "leak_rate_hz", "bandwidth", "cutoff_hz_at_1klux", "hot_pixel_fraction", "min_step_us", "supersample",
              "calibration", "width", "height", "lens_mm", "roi", "distortion", "frames", "camera_distance_m",
              "camera_height_m", "camera_tilt_deg", "illuminance_lux", "background", "background_seed", "gt_rate_hz",
              "n_track_points"}


def spec(name):
    return load_registry().get(name)


def test_an_unset_actor_keeps_the_key_material_and_reads_the_template():
    syn = spec("synthetic")
    plain = build_config(syn, {}, "source")
    assert set(result_config(syn, plain)) == OLD_FIELDS
    assert syn.used_inputs(plain) == ["template"]
    given = build_config(syn, {"actor": {"height_m": 1.6}}, "source")
    key = result_config(syn, given)
    assert {k: v for k, v in key.items() if k.startswith("actor.")} == {
        "actor.height_m": 1.6, "actor.build": None, "actor.muscle": None, "actor.sex": None, "actor.seed": None}
    assert set(key) == OLD_FIELDS | {"actor.height_m", "actor.build", "actor.muscle", "actor.sex", "actor.seed"}
    assert syn.used_inputs(given) == []  # the template is neither loaded nor part of the key
    with pytest.raises(ConfigError, match=r"source\.actor\.sex: expected a finite number in \[-1, 1\], got 2"):
        build_config(syn, {"actor": {"sex": 2}}, "source")


def test_unsaid_template_keys_build_the_same_body_and_key_and_the_template_says_what_was_stated():
    anny = spec("anny")
    unsaid, said = build_config(anny, {}, "template"), build_config(anny, {"height_m": 1.75}, "template")
    # the key material of an unsaid config is that of before (1.75 m, the mean body); a stated one names it
    assert result_config(anny, unsaid) == {"height_m": 1.75, "build": 0.0, "muscle": 0.0, "sex": 0.0, "seed": 0}
    assert result_config(anny, said) == {**result_config(anny, unsaid), "given": ["height_m"]}


def _run_template(values):
    from eventcap.core.stage import StageContext
    from eventcap_synthetic._impl import run_anny

    return run_anny({}, build_config(spec("anny"), values, "template"), StageContext("template", "anny"))["template"]


def test_the_template_stage_marks_what_was_stated():
    a, b = _run_template({}), _run_template({"height_m": 1.75, "sex": -0.5})
    assert tuple(a.stated) == () and tuple(b.stated) == ("height_m", "sex")
    assert np.array_equal(a.rest_joints, anny_template().rest_joints)
    assert np.array_equal(b.rest_joints, anny_template(sex=-0.5).rest_joints)


def simulate_config(tmp_path, **source):
    data = copy.deepcopy(small_capture_config())
    data["pipeline"] = {"nodes": {"template": {"config": "template"},
                                  "source": {"config": "source", "inputs": {"template": "template.template"}}}}
    data["cache_dir"] = str(tmp_path / "cache")
    data["template"] = {"stage": "anny", "height_m": None, "build": None, "muscle": None, "sex": None, "seed": 0}
    data["source"].update({"duration_s": 0.04, "n_track_points": 5, "supersample": 1, **source})
    return data


def run(data):
    runner = Runner(data)
    result = runner.run(None)
    assert result.ok
    return result, runner.load_output(result, "source.recording")[None]


def test_an_actor_is_filmed_its_truth_is_its_skeleton_and_the_template_does_not_recompute_it(tmp_path):
    actor = {"height_m": 1.58, "sex": -0.8, "muscle": 0.4, "build": None, "seed": 3}
    res, rec = run(simulate_config(tmp_path, actor=actor))
    gt = rec.ground_truth
    assert rec.template is None and json.loads(gt.actor) == {"model": "anny", "height_m": 1.58, "build": 0.0,
                                                             "muscle": 0.4, "sex": -0.8, "seed": 3}
    # the ground truth is the actor's skeleton: its rest skeleton, recovered from the posed joints, is the actor's
    truth = segment_lengths(rest_skeleton_from_motion(gt.poses, gt.joints))
    want = segment_lengths(anny_rest_joints(1.58, 0.0, 0.4, -0.8))
    assert max(abs(truth[n] - want[n]) for n in want) < 1e-9
    default = segment_lengths(anny_rest_joints())
    assert max(abs(truth[n] - default[n]) for n in want) > 0.02  # not the template's (1.75 m, mean body)
    assert np.array_equal(anny_from_json(gt.actor).rest_joints, anny_template(1.58, 0.0, 0.4, -0.8).rest_joints)
    # another template: the capture is not recomputed (the source does not read it)
    other = simulate_config(tmp_path, actor=actor)
    other["template"]["height_m"] = 1.9
    res2, rec2 = run(other)
    assert res2.nodes["source"].cached == 1 and res2.nodes["template"].computed == 1
    assert np.array_equal(rec2.events.events, rec.events.events)


def test_without_an_actor_the_template_is_filmed_as_before(tmp_path):
    res, rec = run(simulate_config(tmp_path))
    assert rec.ground_truth.actor == "" and rec.template is not None
    truth = segment_lengths(rest_skeleton_from_motion(rec.ground_truth.poses, rec.ground_truth.joints))
    assert max(abs(truth[n] - v) for n, v in segment_lengths(rec.template.rest_joints).items()) < 1e-9
    other = simulate_config(tmp_path)
    other["template"]["height_m"] = 1.9
    res2, _ = run(other)
    assert res2.nodes["source"].computed == 1  # the template is what it films
