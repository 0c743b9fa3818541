"""The event terms' noise, measured as a detector's is: each event term's residuals at the TRUE motion of tuning
captures (what is left when the poses are exactly right is the noise of what the term reads: tracks that drift,
events matched to the wrong outline point, joints called still that move). These are the sigmas the spline solve's
defaults state (`stages.solve.terms.cor.sigma_px`, `terms.sil.sigma_px`, `terms.still.sigma_px_s`).

    python benchmarks/accuracy/event_noise.py RUN_DIR [RUN_DIR ...]

Each RUN_DIR is the run folder of a default-pipeline run on a synthetic capture (e.g. the `a default` rows of
`eventcap benchmark benchmark=ladder`, whose folders are <out>/runs/<capture>/adefault/). Its recording, detections,
tracks and batches come back from the cache its config names (nothing upstream is recomputed); the window is the
spline solve's own (its first chunk), built by the stage's code with the run's settings; the true motion is the
ground truth's poses as the window's spline (a least-squares fit at every 1 ms sample). A diagnosis with the ground
truth: nothing here is used by a run. Robust sigma = 1.4826 x the median absolute residual per image axis.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import tempfile
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from eventcap.core.runner import Runner  # noqa: E402

KEEP = ("template", "source", "sharpen", "detect", "body", "track", "slice", "chunk")


def outputs_of(run_dir: Path) -> dict:
    """The run's recording (with its body), detections, every batch's sliced tracks, batches and chunks, from the
    cache."""
    data = OmegaConf.to_container(OmegaConf.load(run_dir / "config.yaml"), resolve=True)
    data.update(log_level="WARNING", executor={"kind": "serial"}, outputs={})
    data["pipeline"]["nodes"] = {k: v for k, v in data["pipeline"]["nodes"].items() if k in KEEP}
    runner = Runner(data)
    with tempfile.TemporaryDirectory() as tmp:
        result = runner.run(Path(tmp))
        get = lambda port: runner.load_output(result, port)  # noqa: E731
        sliced = get("slice.sliced")
        return {"recording": get("body.recording")[None], "detections": get("detect.detections")[None],
                "sliced": [sliced[k] for k in sorted(sliced)], "batches": get("source.batches")[None],
                "chunks": get("chunk.chunks")[None], "config": data}


class _Seq(list):
    """The tracks of every batch as the runner hands them to the stage (``.batches`` names them)."""

    def __init__(self, items, plan):
        super().__init__(items)
        self.batches = [plan.batch(k) for k in range(len(items))]


def robust_sigma(r: np.ndarray) -> float:
    r = np.asarray(r, dtype=np.float64).ravel()
    return float(1.4826 * np.median(np.abs(r))) if r.size else float("nan")


def measure(run_dir: Path, at: str = "truth") -> dict:
    from eventcap.core.config import build_settings
    from eventcap.energy.terms import TermSet
    from eventcap.energy.window import Estimate
    from eventcap.worldframe import upright
    from eventcap_spline import _impl as impl
    from eventcap_spline.plan import plan_window
    from eventcap_spline.spec import SPLINE

    out = outputs_of(run_dir)
    config = build_settings(SPLINE.config, {}, "stages.solve", SPLINE.renamed, "spline")  # today's defaults
    rec = upright(out["recording"], out["detections"])
    plan, chunks = out["batches"], out["chunks"]
    unit = chunks.batch(0)
    inputs = {"recording": rec, "detections": out["detections"], "batches": plan,
              "sliced": _Seq(out["sliced"], plan)}
    _, role = impl.unit_role(plan, unit, int(config.half_window), 1)
    terms = TermSet.decode(config.terms)
    window = plan_window(inputs, config, terms, "m", role, logging.getLogger("event_noise"))
    spline, data = window.spline, window.inputs()
    if at == "truth":
        gt = rec.ground_truth
        t_p, poses = gt.t_us, np.asarray(gt.poses, dtype=np.float64)
    else:  # the run's own solution: the residuals the solve lives with (its associations, its model errors)
        with np.load(run_dir / "motion.npz") as z:
            t_p, poses = np.asarray(z["t_us"], np.int64), np.asarray(z["poses"], np.float64)
        ok = np.isfinite(poses).all(axis=1)
        t_p, poses = t_p[ok], poses[ok]
    inside = (t_p >= spline.t0_us) & (t_p <= spline.t1_us)
    poses = poses[inside].copy()
    poses[:, 27:30] = np.unwrap(poses[:, 27:30], axis=0)
    C = spline.fit(t_p[inside], poses, smooth=1e-12)
    curve = lambda t, deriv=0: spline.evaluate(C, t, deriv)  # noqa: E731
    data.start = curve
    from eventcap.energy.silence import measure_stillness

    data.offer("stillness", lambda: measure_stillness(curve, data.knots_us, rec.template, rec.camera, data.events,
                                                      config.stillness))
    factors = {f.name: f for f in terms.factors(rec.template, rec.camera, dict(window.layout.sizes))}
    est = Estimate(curve, 1, data, rec.template, rec.camera)
    res: dict = {"run": str(run_dir)}
    f = factors.get("cor")
    if f is not None:
        f.collect(data)
        f.relinearize(est)
        r = f.residuals_px(curve(f.t_us))
        res["cor"] = {"n": int(r.shape[0]), "sigma_px": robust_sigma(r), "rms_px": float(np.sqrt(np.mean(r**2)))
                      if r.size else None}
    f = factors.get("sil")
    if f is not None:
        f.collect(data)
        f.relinearize(est)
        pts = f._points(f.kernels.transforms(curve(f.t_us)))
        r = f.residuals(pts)[0] / f.scale
        res["sil"] = {"n": int(r.size), "sigma_px": robust_sigma(r), "rms_px": float(np.sqrt(np.mean(r**2)))
                      if r.size else None}
    f = factors.get("still")
    if f is not None:
        f.collect(data)
        f.relinearize(est)
        v = curve(f.t_us, 1)
        energy = float(np.einsum("qa,qab,qb->", v, f.M, v))
        still = f.stillness
        seconds = float(np.sum(f._w_q[:, None] * still[f._seg])) if still is not None else 0.0
        res["still"] = {"sigma_px_s": math.sqrt(energy / (2.0 * seconds)) if seconds > 0 else None,
                        "still_joint_seconds": seconds}
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    ap.add_argument("--at", choices=("truth", "solution"), default="truth",
                    help="the residuals at the true motion, or at the run's own solution (motion.npz)")
    args = ap.parse_args()
    rows = []
    for run in args.runs:
        r = measure(run, args.at)
        rows.append(r)
        print(json.dumps(r))
    pooled = {}
    for term, key in (("cor", "sigma_px"), ("sil", "sigma_px"), ("still", "sigma_px_s")):
        vals = [r[term][key] for r in rows if r.get(term) and r[term].get(key) is not None]
        if vals:
            pooled[term] = {"median_" + key: float(np.median(vals)), "runs": len(vals)}
    print("pooled:", json.dumps(pooled))
    if args.json:
        args.json.write_text(json.dumps({"runs": rows, "pooled": pooled}, indent=1))


if __name__ == "__main__":
    main()
