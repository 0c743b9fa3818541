"""benchmarks/accuracy/calibrate_uncertainty.py fits the calibration on the uncertainty the confidence stage makes:
its own sum of the cues must be the stage's (eventcap.analysis.uncertainty.joint_uncertainty and out_of_view) for any
entry, an estimated body's own uncertainty included (it was once left out, which fitted the open suite's factors on
an uncertainty smaller than the one shipped)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from eventcap.analysis.uncertainty import UncertaintyModel, joint_uncertainty, out_of_view

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks" / "accuracy"))
import calibrate_uncertainty as cu  # noqa: E402


def cues(rng, T: int = 9, body: bool = True) -> dict:
    """A run's cues as run_cues keeps them (arrays (T, 24), mm), with NaN where a residual is missing."""
    r2 = rng.uniform(0, 40, (T, 24))
    r2[0, :3] = np.nan
    return {"sig": rng.uniform(5, 120, (T, 24)), "r2": r2, "r3": rng.uniform(0, 90, (T, 24)),
            "gap": rng.uniform(0, 30, (T, 24)), "between": rng.uniform(0, 1, T), "step": rng.uniform(0, 60, (T, 24)),
            "body": rng.uniform(0, 50, (T, 24)) if body else np.zeros((T, 24)), "body_weight": np.array(1.0),
            "edge": rng.uniform(-20, 60, (T, 24)), "radius_px": np.full((T, 24), 3.0),
            "f_over_z": np.full((T, 24), 80.0), "fps": np.array(25.0), "view": np.array("close_up")}


@pytest.mark.parametrize("kind", ["blazepose", "simulated"])
@pytest.mark.parametrize("body", [True, False])
def test_the_scripts_uncertainty_is_the_stages(kind, body):
    table = json.loads((ROOT / "plugins" / "eventcap_confidence" / "calibration.json").read_text())
    entry = table["detectors"][kind]
    w, factor, by_fps = cu.entry_weights(entry)
    by_view = entry.get("factor_by_view", {})
    c = cues(np.random.default_rng(3), body=body)
    f = factor * cu.rate_of(c, by_fps, by_view)  # the calibrated parts' factor at this rate and view
    model = UncertaintyModel(scale=f, detection_2d=f * w["detection_2d"], detection_3d=f * w["detection_3d"],
                             events=f * w["events"], unseen_mm=float(entry["unseen_mm"]), floor_mm=f * w["floor_mm"],
                             fallback_mm=500.0, body=1.0, motion=f * w["motion"], speed=f * w["speed"],
                             between_mm=f * w["between_mm"])
    T = c["sig"].shape[0]
    stage = joint_uncertainty(model, c["sig"], c["r2"], c["r3"], c["gap"], np.ones(T, bool), c["body"], c["between"],
                              c["step"])
    script = cu.uncertainty(c, w, f)
    np.testing.assert_allclose(script, stage, rtol=1e-12)
    # and out of view, as shipped() makes it: the stage's rule with the script's in-view test
    full = cu.shipped(w, factor, by_fps, by_view, float(entry["unseen_mm"]), 1.0)(c)
    seen = cu.in_view(c, stage, 1.0)
    np.testing.assert_allclose(full, out_of_view(stage, seen, float(entry["unseen_mm"])), rtol=1e-12)
    assert (~seen).any() and seen.any()
    if body:  # the body's part is not scaled by the calibration: the same with any factor on the rest
        assert np.all(cu.uncertainty(c, w, 1e-9) >= c["body"] * 0.999)
