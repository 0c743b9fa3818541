"""A detector's noise model, measured on tuning captures: each landmark's 2D error and each joint's 3D error as the
solve's E_3D sees it (root-relative, a free translation per image, along the camera's axes: x right, y down, z the
line of sight), split into what changes from image to image (white noise, per kind of image: the raw frames, the EDI
latent images at the frames, latent images between the frames, images made from the events of an event-only camera) and what stays over a capture (the offset's spread
over captures: one capture's mean error), written as the table the detector states
(`plugins/eventcap_detect/models/blazepose_noise.json`, read by the detect stage into the detections' noise model).

    python benchmarks/accuracy/detector_noise.py RUN_DIR [RUN_DIR ...] [--write plugins/eventcap_detect/models/blazepose_noise.json]

Each RUN_DIR is a run folder whose detect node ran the detector on a synthetic capture (e.g. the `e default` and
`e linear` rows of `eventcap benchmark benchmark=ladder`: BlazePose on the latent images and on the raw frames); its
detections and the ground truth come back from the cache (nothing upstream recomputed). TUNING captures only: the
figures become the detector's stated noise. White: robust sigma (1.4826 x the median absolute deviation) of each
error about its capture's median, per axis, over the images where the detector gave the point (a landmark outside
the ground truth's view is left out); offset: the root mean square over captures of each capture's median error;
outliers: the share of 2D errors beyond 5 robust sigmas. The points of one image err together (a lean of the whole
body, a shift of the limbs): their white errors' covariance across the points (each standardised) has an effective
number of independent components n_eff = (Σλ)² / Σλ² (its eigenvalues' participation ratio) of the d coordinates,
and the solve must count each point's noise as its spread times √(d / n_eff) (`inflation_2d`, `inflation_3d`: the
factor on the variance, d / n_eff), as a design effect does.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from eventcap.core.runner import Runner  # noqa: E402


def outputs_of(run_dir: Path):
    data = OmegaConf.to_container(OmegaConf.load(run_dir / "config.yaml"), resolve=True)
    data.update(log_level="WARNING", executor={"kind": "serial"}, outputs={})
    keep = ("template", "source", "sharpen", "reconstruct", "detect")
    data["pipeline"]["nodes"] = {k: v for k, v in data["pipeline"]["nodes"].items() if k in keep}
    runner = Runner(data)
    with tempfile.TemporaryDirectory() as tmp:
        result = runner.run(Path(tmp))
        rec = data["pipeline"]["nodes"]["detect"]["inputs"].get("recording", "source.recording")  # event-only: the
        # recording with the images made from the events (reconstruct.recording)
        return runner.load_output(result, rec)[None], runner.load_output(result, "detect.detections")[None]


def errors(run_dir: Path) -> dict:
    """Per image kind: 2D errors (n, 25, 2) px and 3D errors (n, 24, 3) m (NaN where not observed)."""
    from eventcap.worldframe import upright
    from eventcap_detect.simulated import interpolate_at

    rec, det = outputs_of(run_dir)
    rec = upright(rec, det)
    gt = rec.ground_truth
    t = np.asarray(det.t_us, dtype=np.int64)
    ok = (t >= gt.t_us[0]) & (t <= gt.t_us[-1])
    t = t[ok]
    lm = rec.camera.project(interpolate_at(gt.t_us, gt.landmarks, t))  # (n, 25, 2)
    J = interpolate_at(gt.t_us, gt.joints, t)
    J = J - J[:, :1]
    e2 = np.asarray(det.keypoints_2d, np.float64)[ok] - lm
    e2[~(np.asarray(det.confidence_2d)[ok] > 0)] = np.nan
    P = np.asarray(det.joints_3d, np.float64)[ok]
    seen3 = np.asarray(det.confidence_3d)[ok] > 0
    r3 = P - J
    r3[~seen3] = np.nan
    r3 = r3 - np.nanmean(r3[:, 1:], axis=1, keepdims=True)  # E_3D's free translation per image
    r3[:, 0] = np.nan  # the pelvis is exact (the joints are relative to it)
    r3 = r3 @ np.asarray(rec.camera.R, dtype=np.float64).T  # along the camera's axes
    frames = rec.frames.t_us if rec.frames is not None else np.zeros(0, np.int64)
    at = str(OmegaConf.load(run_dir / "config.yaml").stages.detect.get("at", "latent"))
    kind = np.full(t.size, "frames" if at == "frames" else "latent", dtype=object)
    if rec.images_from_events:  # an event-only camera's images
        kind[:] = "events"
    elif at == "tracking":
        kind[~np.isin(t, frames)] = "between"
    return {k: (e2[kind == k], r3[kind == k]) for k in np.unique(kind)}


def inflation(errors: np.ndarray) -> float:
    """d / n_eff of the images' errors (n, points, axes) about their capture's median (module doc): coordinates
    observed in at most half the images are left out, the rest standardised, an image's missing ones counted 0."""
    X = errors.reshape(errors.shape[0], -1)
    X = X[:, np.mean(np.isfinite(X), axis=0) > 0.5]
    X = np.nan_to_num(X[np.mean(np.isfinite(X), axis=1) > 0.8])
    X = X[:, np.std(X, axis=0) > 0]
    if X.shape[0] < 2 or X.shape[1] < 2:
        return 1.0
    lam = np.linalg.eigvalsh(np.corrcoef(X.T))
    return float(X.shape[1] / (lam.sum() ** 2 / (lam ** 2).sum()))


def robust(x: np.ndarray, axis=None) -> np.ndarray:
    return 1.4826 * np.nanmedian(np.abs(x), axis=axis)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--write", type=Path, default=None, help="write the detector's noise table here")
    ap.add_argument("--source", default="", help="what to say the table comes from (the captures, the commit)")
    ap.add_argument("--add-to", type=Path, default=None, help="add the kinds measured here to this table (the "
                    "shipped one) instead of writing a new one: their 2D figures as measured, their 3D the table's "
                    "effective figure for the raw frames (the measured 3D kept under measured_3d), the rest of the "
                    "table untouched; --source is appended to its source")
    args = ap.parse_args()
    pooled: dict[str, list] = {}
    for run in args.runs:
        for kind, (e2, r3) in errors(run).items():
            pooled.setdefault(kind, []).append((e2, r3))
            print(f"{run} {kind}: {e2.shape[0]} images, 2D sigma {float(robust(e2)):.2f} px, 3D sigma "
                  f"{1000 * float(robust(r3)):.1f} mm")
    table: dict = {"landmarks_2d_px": {}, "bias_2d_px": {}, "joints_3d_mm": {}, "bias_3d_mm": {}, "images": {},
                   "inflation_2d": {}, "inflation_3d": {}}
    shares = []
    for kind, parts in pooled.items():
        # white: about each capture's median; offset: the captures' medians
        med2 = [np.nanmedian(p[0], axis=0) for p in parts]  # (25, 2) per capture
        med3 = [np.nanmedian(p[1], axis=0) for p in parts]  # (24, 3)
        e2 = np.concatenate([p[0] - m for p, m in zip(parts, med2)])
        r3 = np.concatenate([p[1] - m for p, m in zip(parts, med3)])
        s2 = robust(e2.transpose(1, 0, 2).reshape(e2.shape[1], -1), axis=1)  # (25,) both image axes
        s3 = robust(r3, axis=0)  # (24, 3) per camera axis
        b2 = np.sqrt(np.nanmean(np.stack(med2) ** 2, axis=(0, 2)))  # (25,)
        b3 = np.sqrt(np.nanmean(np.stack(med3) ** 2, axis=0))  # (24, 3)
        all2 = float(robust(e2))
        s2 = np.where(np.isfinite(s2), s2, all2)
        s3 = np.where(np.isfinite(s3), s3, np.nanmedian(s3, axis=0))
        b2 = np.where(np.isfinite(b2), b2, float(np.nanmedian(b2)))
        b3 = np.where(np.isfinite(b3), b3, np.nanmedian(b3, axis=0))
        s3[0], b3[0] = 0.0, 0.0  # the pelvis: the joints are relative to it
        table["landmarks_2d_px"][kind] = [round(float(v), 2) for v in s2]
        table["joints_3d_mm"][kind] = [[round(1000 * float(v), 1) for v in row] for row in s3]
        table["images"][kind] = int(e2.shape[0])
        table["inflation_2d"][kind], table["inflation_3d"][kind] = round(inflation(e2), 2), round(inflation(r3), 2)
        if len(parts) > 1:  # an offset needs captures to spread over
            table["bias_2d_px"][kind] = [round(float(v), 2) for v in b2]
            table["bias_3d_mm"][kind] = [[round(1000 * float(v), 1) for v in row] for row in b3]
        fin = np.abs(e2[np.isfinite(e2)])
        shares.append(float(np.mean(fin > 5 * all2)) if fin.size else 0.0)
        print(f"pooled {kind}: {e2.shape[0]} images of {len(parts)} captures; 2D white median over landmarks "
              f"{np.median(s2):.2f} px, offset {np.median(b2):.2f} px; 3D white median over joints (x, y, z) "
              f"{np.round(1000 * np.median(s3[1:], axis=0), 1)} mm, offset {np.round(1000 * np.median(b3[1:], axis=0), 1)}"
              f" mm; 2D beyond 5 sigma {100 * shares[-1]:.1f}%; variance inflation 2D {table['inflation_2d'][kind]}, "
              f"3D {table['inflation_3d'][kind]}")
    table["outlier_share"] = round(float(np.mean(shares)), 3) if shares else 0.0
    table["source"] = args.source or f"measured by benchmarks/accuracy/detector_noise.py on {len(args.runs)} runs"
    if args.add_to:
        add_kinds(args.add_to, table, args.source)
    elif args.write:
        order = ("source", "landmarks_2d_px", "bias_2d_px", "joints_3d_mm", "bias_3d_mm", "inflation_2d",
                 "inflation_3d", "images", "outlier_share")
        args.write.write_text(json.dumps({k: table[k] for k in order}, indent=1) + "\n")
        print(f"wrote {args.write}")


def add_kinds(path: Path, measured: dict, source: str) -> None:
    """Add the measured kinds of image to the table at ``path`` (``--add-to``)."""
    table = json.loads(path.read_text())
    for kind in measured["images"]:
        for key in ("landmarks_2d_px", "bias_2d_px", "inflation_2d", "images"):
            if kind in measured[key]:
                table.setdefault(key, {})[kind] = measured[key][kind]
        table["joints_3d_mm"][kind] = table["joints_3d_mm"]["frames"]
        for key in ("joints_3d_mm", "bias_3d_mm", "inflation_3d"):
            if kind in measured[key]:
                table.setdefault("measured_3d", {}).setdefault(key, {})[kind] = measured[key][kind]
        print(f"added the {kind!r} images to {path}")
    if source:
        table["source"] = f"{table['source']}. {source}"
    path.write_text(json.dumps(table, indent=1) + "\n")


if __name__ == "__main__":
    main()
