"""E_cor's tracks against the truth (issue "the events add", item 5): is a track's 1 ms displacement the motion of
the surface point under it?

    python benchmarks/accuracy/cor_at_truth.py RUN_DIR [--pick truth|estimate]

RUN_DIR: a finished run on a synthetic capture (its sliced tracks and ground truth come back from the cache). Every
correspondence E_cor would make from the run's sliced tracks, found on the mesh at the TRUE poses (``--pick truth``)
or at the run's own estimate (``estimate``: what the solve associates), its surface point moved by the TRUE poses
over the correspondence's two tracking frames, against the track's own displacement. Per bin of the track's own
speed: the least-squares ratio of the true displacement to the track's, and the residual's median and RMS (px).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import zarr

from eventcap.artifacts.recording import Recording
from eventcap.artifacts.tracking import SlicedTracks
from eventcap.body.kinematics import global_transforms
from eventcap.energy.correspondences import find_correspondences

BINS = ((0.0, 0.1), (0.1, 0.3), (0.3, 0.6), (0.6, np.inf))


def interp_poses(t, t_ref, poses) -> np.ndarray:
    t = np.asarray(t, dtype=np.float64)
    return np.stack([np.interp(t, t_ref, poses[:, k]) for k in range(poses.shape[1])], -1)


def posed_px(cam, template, S, corr, frames) -> np.ndarray:
    """Each correspondence's surface point posed with S at its frame (frames: (P,) indices into S), in pixels."""
    G = np.einsum("pj,pjab->pab", corr.weights, global_transforms(S, template)[frames])
    return cam.project(np.einsum("pab,pb->pa", G[:, :3, :3], corr.rest_points) + G[:, :3, 3])


def displacements(run: Path, pick: str) -> tuple[np.ndarray, np.ndarray]:
    """(true (P, 2), track's (P, 2)) forward displacements of every correspondence, px."""
    r = json.loads((run / "run.json").read_text())
    cache = Path(r["cache_dir"]) / "entries"
    src = r["nodes"]["source"]
    rec = Recording.from_zarr(zarr.open_group(str(cache / src["stage"] / src["keys"][0] / "data" / "recording"),
                                              mode="r"), where=str(run))
    gt, cam, tpl = rec.ground_truth, rec.camera, rec.template
    motion = np.load(run / "motion.npz")
    out_true, out_trk = [], []
    sl = r["nodes"]["slice"]
    for key in sl["keys"]:
        st = SlicedTracks.from_zarr(zarr.open_group(str(cache / sl["stage"] / key / "data" / "sliced"), mode="r"),
                                    where=key)
        truth = interp_poses(st.t_us, gt.t_us, gt.poses)
        at = truth if pick == "truth" else interp_poses(st.t_us, motion["t_us"], motion["poses"])
        c = find_correspondences(tpl, cam, at, st.xy.astype(np.float64), st.valid)
        if c.n == 0:
            continue
        sign = np.sign(c.frame - c.source)[:, None]
        out_true.append(sign * (posed_px(cam, tpl, truth, c, c.frame) - posed_px(cam, tpl, truth, c, c.source)))
        out_trk.append(sign * (c.target_px - c.source_px))
    return np.concatenate(out_true), np.concatenate(out_trk)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path)
    ap.add_argument("--pick", choices=("truth", "estimate"), default="truth")
    a = ap.parse_args(argv)
    d_true, d_trk = displacements(a.run, a.pick)
    e = np.linalg.norm(d_trk - d_true, axis=1)
    speed = np.linalg.norm(d_trk, axis=1)
    print(f"{a.run} (picked at the {a.pick}): {e.size} correspondences, residual median {np.median(e):.3f} px")
    print("| track's own speed px/ms | correspondences | true / track's (LS) | residual median / RMS px |")
    print("|---|---|---|---|")
    for lo, hi in BINS:
        m = (speed >= lo) & (speed < hi)
        if m.sum():
            ratio = np.einsum("ij,ij->", d_true[m], d_trk[m]) / max(float((speed[m] ** 2).sum()), 1e-12)
            print(f"| {lo:g}-{hi:g} | {m.sum()} | {ratio:.2f} | {np.median(e[m]):.3f} / "
                  f"{np.sqrt(np.mean(e[m] ** 2)):.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
