"""A setting's help text says what it is, its unit and its range; measurements go to docs/results/ (settings.md).

The rule (:func:`figures`) looks for the signs of a measurement log: a before/after between numbers ("60.5 -> 58.0",
"37 iterations instead of 64"), an error measure with a value ("AE 26.0", "MPJVE +3.5"), a value in mm or % ("55.0
mm", "16%"), a verdict ("measured better", "as measured", "gave"), a time per unit of work ("15 ms per image", "5x
cheaper"), where it was measured ("the full suite", "our captures", "seed 0", "at 10 fps"), a median error, and a
pointer to a log ("docs/", "NOTES.md", "benchmarks/"). A unit ("ms", "px", "in mm", "m | mm"), a range ("7-25 fps", "0
= off", "1.2-2.3") and an example value do not count. It checks every field of every registered stage, and each
stage's description.
"""

from __future__ import annotations

import dataclasses
import re

import pytest

from eventcap.params import is_group

from eventcap.core.registry import load_registry

SIGNS = {
    "a before/after": re.compile(r"\d\s*%?\s*(->|→)\s*[+\-]?\d|\d\s*(\w+\s+)?instead of\s+\d"),
    "an error measure with a value": re.compile(r"\b(AE|MPJVE|MPJPE|PSNR|RMSE|error)\s*[+\-]?\d"),
    "a value in mm or %": re.compile(r"\d\s*(mm/s|mm|%)(?![\w/])"),
    "a verdict": re.compile(r"\bmeasured\s+(better|best|worse|on)\b|\bas measured\b|\bgave\b|\bwas (better|worse)\b"),
    "a time per unit of work": re.compile(r"\d\s*(ms|s|us)\s+per\s+(image|frame|batch|window|solve)\b"
                                          r"|\d+(\.\d+)?\s*x\s+(cheaper|faster|slower)\b"),
    "where it was measured": re.compile(r"\bsuite\b|\bour (captures|actor)\b|\btuning (captures|seeds)\b|\bseed \d"
                                        r"|\b(at|the) \d+ fps\b"),
    "a median error": re.compile(r"\bmedian\b[^.;)]*\berror\b"),
    "a pointer to a log": re.compile(r"docs/|NOTES\.md|benchmarks/"),
}



def figures(text: str) -> list[str]:
    """The signs of a measurement that ``text`` holds (empty: none)."""
    return [name for name, rx in SIGNS.items() if rx.search(text)]


#: Help text as it was before the clean-up (every measurement `eventcap stages` showed in it): each must be caught.
MEASUREMENT_LOGS = [
    "landmark network: full (15 ms per image here) | lite (faster, less exact)",
    "the networks get linear intensity ** (1 / gamma) (1: linear, as measured best on our captures)",
    "a detected landmark supports its joint as exp(-(r/r0)²), r the estimate's reprojection residual, r0 this "
    "fraction of the person's height in the image (0.05: 4 px on an 85 px actor, twice BlazePose's median 2D error "
    "there)",
    "how lam is chosen from the fits alone: gcv (generalised cross-validation) | reml (restricted likelihood). GCV "
    "measured better on the 2 s suite (REML flattened jumping_jack at 10 fps); with few fits (0.4 s at 25 fps) GCV "
    "may interpolate, REML does not",
    "decay rate of the per-pixel high-pass filter (Scheerlinck et al. 2018), rad/s: the images remember about 1/cutoff "
    "s of events; 0 = direct integration (chosen by benchmarks/accuracy/bench_events_only.py)",
    "weight of the motion prior, the integral of the squared acceleration (or jerk) of the poses (rad and m, time in "
    "s); 5e-4 until the event-silence term held the resting joints, 1e-4 measured better with it (docs/spline-solve.md)",
    "smallest of those gains (0.04: the ankles, ~0.002 by their inertia, are held like the elbows; their jitter was "
    "most of the 25 fps velocity error the lighter prior added)",
    "how each parameter's fits choose its smoothing for those gains: gcv | reml (eventcap.analysis.smoothing; REML "
    "held fast_wave's waving arm at 25 fps)",
    "choose those gains (and the context pull) only when the intensity frames come at least this often (frames per "
    "second; 0 = always): at 10 fps the fits undersample the punches and kicks, whose parameters would be held as if "
    "at rest",
    "weight of the floor term: each sole point (heels, toes) in contact on the floor, none below it (m²; "
    "eventcap.energy.floor); the floor's height is estimated over the capture from the per-frame fits; 0 = off. "
    "BlazePose, karate_kick seed 0 at 10 fps, with lambda_slide 1: AE 60.5 -> 55.0 mm, depth error 58.6 -> 50.9 mm "
    "(docs/spline-solve.md)",
    "weight of the foreshortening term: each limb bone's depth extent from its length and its 2D points, the sign "
    "(which end is nearer) from the 3D detections (m²; eventcap.energy.bones); 0 = off. BlazePose, karate_kick seed 0 "
    "at 10 fps: 10 alone AE 60.5 -> 58.0 mm, depth 58.6 -> 54.4 mm; with the widths and the floor 53.9 -> 55.2, "
    "49.0 -> 52.4: off",
    "foreshortening: the 2D points' noise, px (BlazePose on our actor: median 2D error 1.7-2.6 px, NOTES.md): a bone "
    "whose depth extent this noise spreads by more than bones_sign_m weighs less",
    "the hip and shoulder landmarks of E_2D: the template's joints (template), or where the detector puts them on "
    "this person, their widths measured over the capture from the detections and the per-frame fits (widths; "
    "eventcap.energy.landmarks). BlazePose, karate_kick seed 0 at 10 fps: AE 60.5 -> 58.4 mm, depth error 58.6 -> "
    "55.3 mm",
    "weight of E_cor, the event correspondences of this batch's tracks (measured on karate_kick, 25 fps, with "
    "cor_step 5: EKLT 50 / 500 / 2000 gave AE 26.0 / 25.8 / 26.0 mm, exact tracks 25.8 / 24.5 / 24.1 mm)",
    "tracking frames between the two frames of a correspondence (1 = adjacent frames, as the batch solve; 5 measured "
    "better and 5x cheaper: larger displacements against the same pixel noise)",
    "whose event tracks E_cor uses: only the batches the window keeps (own: its run of window_step batches), or every "
    "batch of the window (window; about twice the solve time). Measured on the full suite at 10 fps: with EKLT tracks "
    "window is no better (lambda_cor 100: a wash; 500: worse), with exact tracks (stages/track=oracle) it cut MPJVE "
    "210 -> 184 mm/s and the median peak-speed error 16% -> 12% (docs/spline-solve.md)",
    "weight of E_sil (paper Sec. 3.3, not in its batch solve): the silhouette boundary of the estimate at the batch's "
    "frames every sil_step_ms against its closest events, point-to-line, focal-normalised (0 = off). Full suite, 10 "
    "fps: 0 / 10 gave AE 27.0 / 25.5 mm, MPJVE 248 / 235 mm/s; 25 fps: 23.8 / 22.8 mm, 265 / 247 mm/s; 3 and 20 on "
    "karate and boxing no better",
    "IPOPT's options for every solve of a window (adaptive barrier: a chunk's long window needs 37 iterations "
    "instead of 64)",
    "end the ICP rounds early when a round's correspondence search has settled (...); 0 = every round. Tuning "
    "captures at 25 fps: 0.003 / 0.03 / 0.1 px skipped 18 / 47 / 69% of the second solves, MPJVE +3.5 / +4.0 / +4.9% "
    "(docs/spline-solve.md)",
]

#: Help text that states a unit, a range, a default's meaning or an example: none may be caught.
PLAIN = [
    "stature of the actor in metres (1.2-2.3)",
    "intensity frame rate (DAVIS APS: 7-25 fps)",
    "focal length in mm: fx = fy = lens_mm / pixel pitch, principal point at the centre, no distortion",
    "unit of the 3D joints in the files: m | mm",
    "overrides of the layout's keypoint -> landmark mapping: file keypoint (index '4' or layout name 'RWrist') -> "
    "landmark name or '' (ignore it)",
    "scene illuminance: drives the photoreceptor bandwidth and the frames' noise (500 office, 50 dim room, 5 "
    "night-time interior)",
    "joints whose peak speed per batch is measured (feet, wrists, hands)",
    "AE and STD over every n-th tracking frame of the joined motion (paper: 10)",
    "std of the Gaussian 2D error per image axis, pixels (before blur scaling)",
    "a (batch, end effector) pair counts in the peak-speed error only if its true peak speed exceeds this, m/s",
    "MPJVE and acceleration error: central differences over this window (x(t+h) - x(t-h)) / 2h, h = half of it, ms",
    "Cauchy loss scale of E_2D per landmark, px (0 = least squares)",
    "time bins of the event support, ms",
    "IPOPT iteration limit per solve; reaching it fails the batch",
    "subtract each pixel's median over the recording (removes the fading traces where the actor was)",
    "mean per-joint 3D error (AE, Procrustes-aligned) and its STD on every 10th frame, data rate (MB/s) against 1000 "
    "fps frames",
]


@pytest.mark.parametrize("text", MEASUREMENT_LOGS, ids=range(len(MEASUREMENT_LOGS)))
def test_the_rule_catches_each_measurement_log(text):
    assert figures(text), text


@pytest.mark.parametrize("text", PLAIN, ids=range(len(PLAIN)))
def test_the_rule_leaves_units_ranges_and_examples_alone(text):
    assert figures(text) == [], text


def help_texts():
    """(stage, dotted key, help) of every stage's description, setting and group of settings (groups opened)."""
    for spec in load_registry().specs():
        yield spec.name, "(description)", spec.description
        yield from _helps(spec.name, spec.config, "")


def _helps(stage: str, config_class, prefix: str):
    for f in dataclasses.fields(config_class):
        yield stage, f"{prefix}{f.name}", f.metadata.get("help", "")
        if is_group(f):
            yield from _helps(stage, f.metadata["group"], f"{prefix}{f.name}.")


def test_no_help_text_carries_a_measurement():
    found = {f"{stage}.{key}": figures(text) for stage, key, text in help_texts() if figures(text)}
    assert not found, (f"help text says what a setting is, its unit and its range; move the figures to "
                       f"docs/results/settings.md: {found}")
