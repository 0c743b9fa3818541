"""What is in view and the detect checks (issue 35, item 2) against the ground truth of synthetic captures.

    python benchmarks/accuracy/bench_view_checks.py [--cases suite,upper,face,hands,dvs128] [--modes frames,events]
                                           [--duration 1] [--cache runs/cache] [--json out.json] [--out DIR]

Cases (today's synthetic source keys; all 25 fps, seed 0, the ANNY actor):

- ``suite``: the 6 benchmark motions, the default camera (4 m away, DAVIS240C-like): every detection is good;
- ``upper``: an upper-body close-up, boxing_combo with the camera 1.0 m from the actor at 1.35 m (chest) height;
- ``face``: a face close-up of a turning head, dance_spin with the camera 0.6 m away at 1.6 m;
- ``hands``: arms and hands close up, boxing_combo with the camera 0.45 m away at 1.25 m;
- ``dvs128``: a DVS128-like 128 x 128 sensor (f = 115 px, no distortion, no frames on the real one) 6 m from a
  karate_kick.

Modes: ``frames`` runs BlazePose on the EDI latent images at the intensity frames (the default path with frames);
``events`` treats the capture as an event-only camera (the exported recording read back with ``pipeline=events_only
source=recording source.frames=false``: images reconstructed from the events every 40 ms, BlazePose ``at=frames`` on
them; the frames mode must run first). Each runs the detect stage through the
runner (template, source, sharpen or reconstruct and detect only; cached): with no check, with each check alone, then
with all of them (the default), ``min_found=0`` so that the stage reports instead of stopping.

Per run: images with a detection, rejections per check, and against the truth (the landmarks projected at the
image's time): the landmarks marked in view that are truly outside the image (``false in view``, the target is 0),
the share of truly visible landmarks marked in view, and the median 2D error of the in-view landmarks, px.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "plugins"))

import numpy as np  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from eventcap.body.skeleton import LANDMARK_NAMES  # noqa: E402
from eventcap.core.runner import Runner  # noqa: E402
from eventcap_detect.checks import CHECKS, inside_image  # noqa: E402

SUITE = ("karate_kick", "boxing_combo", "javelin_throw", "dance_spin", "fast_wave", "jumping_jack")
MAPPED = [i for i, n in enumerate(LANDMARK_NAMES) if "small_toe" not in n]  # BlazePose has no small toes
DVS128_CALIB = "115 115 63.5 63.5\n"  # fx fy cx cy: about a 4.6 mm lens on 40 um pixels (assumed, no datasheet)


def cases(names: list[str], calib: Path) -> list[tuple[str, list[str]]]:
    out = []
    for name in names:
        if name == "suite":
            out += [(m, [f"source.motion={m}"]) for m in SUITE]
        elif name == "upper":
            out.append(("upper", ["source.motion=boxing_combo", "source.camera_distance_m=1.0",
                                  "source.camera_height_m=1.35"]))
        elif name == "face":
            out.append(("face", ["source.motion=dance_spin", "source.camera_distance_m=0.6",
                                 "source.camera_height_m=1.6"]))
        elif name == "hands":
            out.append(("hands", ["source.motion=boxing_combo", "source.camera_distance_m=0.45",
                                  "source.camera_height_m=1.25"]))
        elif name == "dvs128":
            out.append(("dvs128", ["source.motion=karate_kick", "source.camera_distance_m=6",
                                   "source.camera_height_m=1.0", "source.width=128", "source.height=128",
                                   f"source.calibration={calib}", "source.distortion=false"]))
        else:
            raise SystemExit(f"unknown case {name!r}")
    return out


def detect_run(overrides: list[str], mode: str, checks: list[str], cache: str, out: Path):
    """(detections, recording, failure message or None) of the detect node only. The frames mode exports the
    synthetic recording to ``out``; the events mode reads it back as an event-only recording (the same events,
    its frames left out: simulating again with source.frames=false would give the same events at a cost)."""
    base = ["stages/detect=blazepose", f"cache_dir={cache}", "log_level=WARNING", f"stages.detect.checks={checks}",
            "stages.detect.min_found=0"]
    if mode == "events":
        base += ["pipeline=events_only", "source=recording", f"source.path={out / 'source.recording.zarr'}",
                 "source.frames=false", "stages.detect.at=frames"]
        overrides = [o for o in overrides if not o.startswith("source.")]
    else:
        base += ["export=[source.recording]"]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = OmegaConf.to_container(compose(config_name="config", overrides=[*base, *overrides]), resolve=True)
    keep = {"template", "source", "sharpen" if mode == "frames" else "reconstruct", "detect"}
    cfg["pipeline"]["nodes"] = {k: v for k, v in cfg["pipeline"]["nodes"].items() if k in keep}
    runner = Runner(cfg)
    result = runner.run(out if mode == "frames" else None)
    rep = result.nodes["detect"]
    if rep.failed:
        return None, None, rep.failed[0]["error"]
    det = runner.load_output(result, "detect.detections")[None]
    rec = runner.load_output(result, "source.recording")[None]
    return det, rec, None


def score(det, rec) -> dict:
    """Counts and errors of one run against the truth."""
    gt = rec.ground_truth
    k = np.clip(np.searchsorted(gt.t_us, det.t_us), 0, gt.t_us.size - 1)
    pts = gt.landmarks[k]  # (n, L, 3)
    depth = rec.camera.depth(pts)
    px = rec.camera.project(pts)
    truly = (depth > 0) & inside_image(px, rec.width, rec.height)
    iv = det.observed()
    err = np.linalg.norm(det.keypoints_2d - px, axis=-1)
    status = list(det.image_status)
    # recall over the images the detector answered and the landmarks it has (BlazePose: no small toes)
    seen = truly[[s != "no_person" for s in status]][:, MAPPED]
    return {"images": len(status), "status": {s: status.count(s) for s in sorted(set(status))},
            "in_view": int(iv.sum()), "false_in_view": int((iv & ~truly).sum()),
            "false_share": float((iv & ~truly).sum() / max(iv.sum(), 1)),
            "recall": float((iv & truly)[:, MAPPED].sum() / max(seen.sum(), 1)),
            "err_px": float(np.median(err[iv & truly])) if (iv & truly).any() else float("nan")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default="suite,upper,face,hands,dvs128")
    ap.add_argument("--modes", default="frames,events")
    ap.add_argument("--duration", type=float, default=1.0)
    ap.add_argument("--cache", default=str(ROOT / "runs" / "cache"))
    ap.add_argument("--json", default="")
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_view_checks"), help="recordings exported here")
    args = ap.parse_args()
    calib = Path(args.cache).parent / "dvs128_calib.txt"
    calib.parent.mkdir(parents=True, exist_ok=True)
    calib.write_text(DVS128_CALIB)
    rows = []
    variants = {"none": [], **{c: [c] for c in CHECKS}, "all": list(CHECKS)}
    for name, over in cases(args.cases.split(","), calib):
        over = [*over, f"source.duration_s={args.duration}", "source.seed=0"]
        out = Path(args.out) / name
        for mode in args.modes.split(","):
            for variant, checks in variants.items():
                det, rec, failed = detect_run(over, mode, checks, args.cache, out)
                row = {"case": name, "mode": mode, "checks": variant}
                row.update({"failed": failed} if failed else score(det, rec))
                rows.append(row)
                print(json.dumps(row), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
