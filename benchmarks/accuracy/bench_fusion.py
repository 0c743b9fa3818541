"""Can events average the detector's noise across intensity frames? Two upper bounds on any method's gain over linear.

    python benchmarks/accuracy/bench_fusion.py [--motions a,b] [--duration 2] [--tracks oracle,eklt] [--extra "..."]

The batch solve of Sec. 3.2 keeps (or re-fits) the two detection frames of each batch, so it can only remove the
*interpolation* error between them, which at 25 fps is a few mm (bench_interpolation.py) against ~34 mm of
detector error at the frames. A method could gain more only by linking *many* detection frames through the events
and averaging their noise. This script measures how far that could go, in two steps:

1. ``ideal``: exact relative motion between all intensity frames (perfect events). The fit error at frame k is
   replaced by the mean fit error over a window of W frames around k (in pose-parameter space, where the fits
   of neighbouring frames would be tied together by exact odometry); poses between frames are interpolated as in
   ``linear``. W = 1 is the ``linear`` baseline; W = all averages every frame of the sequence, leaving only the
   detector's per-sequence 3D bias and the fits' common error. Needs only the detections: seconds.
2. one table per ``--tracks`` tracker: *event odometry* from a real solve. For every batch, Eq. 3-8 is solved
   with the detection at frame N switched off (the solve's mode ``odometry``: every frame starts at S_0's fit and
   E_temp holds every part without correspondences), so S_N follows from S_0's fit and the event correspondences
   alone; S_N - S_0 is the batch's odometry. (Starting between the two fits as the batch mode does let frame N's
   fit leak into the odometry of parts the events miss, which measured worse.)
   Its error on its own is printed too: the true pose at frame k moved by the step, against the truth at k+1.
   Then a pose graph over the intensity-frame poses X_k, per pose parameter, minimises
   sum_k |X_k - fit_k|^2 + rho * sum_k |X_{k+1} - X_k - odometry_k|^2, and each batch's solved trajectory is
   shifted onto it (the end mismatch spread linearly). rho = 0 keeps the fits. rho is swept, and the best column,
   chosen against the ground truth, is an optimistic bound; the "estimated" column uses a weight estimated from
   the data alone (:func:`eventcap_solve.fusion.innovation_rho`). The ``fuse`` pipeline (``pipeline=fused``) does
   the same inside the normal runner.

AE as everywhere: mean per-joint error after per-frame Procrustes alignment, mm, over every 1 kHz frame. The
pipeline up to the detections runs through the normal runner and cache (`stages/solve=linear`,
`pipeline=no_refine`), so reruns recompute nothing upstream. About 40 s per motion for EKLT and 2-3 min for oracle
tracks (100 tracks per batch) at 2 s of capture on the 2-core machine.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "plugins"))
sys.path.insert(0, str(ROOT / "benchmarks" / "accuracy"))

import numpy as np  # noqa: E402
import zarr  # noqa: E402
from bench_solve import run  # noqa: E402
from eventcap.artifacts.pose import Detections  # noqa: E402
from eventcap.artifacts.recording import Recording  # noqa: E402
from eventcap.artifacts.tracking import SlicedTracks  # noqa: E402
from eventcap.body.kinematics import joint_positions  # noqa: E402
from eventcap.analysis.metrics import mean_joint_error, pose_at  # noqa: E402
from eventcap_solve._impl import problem_for  # noqa: E402
from eventcap_solve.batch import interpolate_poses, select_detections, solve_batch, unwrap_root  # noqa: E402
from eventcap_solve.spec import BatchSolveConfig  # noqa: E402
from eventcap_solve.fusion import innovation_rho, place, pose_graph  # noqa: E402

MOTIONS = "karate_kick,boxing_combo,javelin_throw,dance_spin,fast_wave,jumping_jack"
WINDOWS = (1, 2, 3, 5, 9, 0)  # 0 = every frame of the sequence
RHOS = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0)


def load(motion: str, track: str, args) -> tuple[Recording, Detections, list[SlicedTracks]]:
    """The recording, detections and sliced tracks of one capture, through the runner and cache."""
    rd = Path(args.out) / f"{motion}-s{args.seed}-{track}"
    run([f"source.motion={motion}", f"source.duration_s={args.duration}", f"source.seed={args.seed}",
         f"stages/track={track}", "stages/solve=linear", "pipeline=no_refine", f"cache_dir={args.cache}",
         "export=[source.recording,slice.sliced,detect.detections]", "log_level=WARNING", *args.extra.split()], rd)
    rec = Recording.from_zarr(zarr.open_group(str(rd / "source.recording.zarr"), mode="r"))
    det = Detections.from_zarr(zarr.open_group(str(rd / "detect.detections.zarr"), mode="r"))
    sliced = [SlicedTracks.from_zarr(zarr.open_group(str(f), mode="r"))
              for f in sorted((rd / "slice.sliced").glob("batch*.zarr"))]
    return rec, det, sliced


def frame_times(sliced: list[SlicedTracks]) -> np.ndarray:
    """(K+1,) µs: the intensity-frame times the K batches run between."""
    return np.asarray([int(s.t_us[0]) for s in sliced] + [int(sliced[-1].t_us[-1])], dtype=np.int64)


def frame_fits(problem, det: Detections, sliced: list[SlicedTracks]) -> np.ndarray:
    """(K+1, 33) per-frame fits (E_2D + E_3D) at the K+1 intensity frames, root angles unwrapped along the
    sequence: exactly the poses ``linear`` interpolates."""
    times = frame_times(sliced)
    ends = select_detections(det, times)
    fits = []
    for d in range(len(times)):
        S, _, _ = problem.fit_frame(ends, d)
        fits.append(unwrap_root(S, fits[-1]) if fits else S)
    return np.stack(fits)


def odometry(problem, det: Detections, s: SlicedTracks) -> np.ndarray:
    """(N+1, 33) one batch's event-only trajectory relative to its S_0 (the problem's mode is ``odometry``)."""
    t_us = np.asarray(s.t_us, dtype=np.int64)
    res = solve_batch(problem, t_us, np.asarray(s.xy, dtype=np.float64), np.asarray(s.valid),
                      select_detections(det, t_us[[0, -1]]))
    return res.poses - res.poses[0]


def ae_mm(rec: Recording, sliced: list[SlicedTracks], anchors: np.ndarray, shapes: np.ndarray | None) -> float:
    """AE over every tracking frame of poses anchored at the intensity frames: between anchors k and k+1 either the
    linear interpolation (shapes None) or batch k's relative trajectory shapes[k] with its end mismatch spread
    linearly."""
    rest = rec.template.rest_joints
    errs = []
    for k, s in enumerate(sliced):
        t = np.asarray(s.t_us, dtype=np.int64)
        if shapes is None:
            P = interpolate_poses(anchors[k], anchors[k + 1], t)
        else:
            P = place(anchors[k], anchors[k + 1], shapes[k], t)
        true = joint_positions(pose_at(rec.ground_truth, t), rest)
        errs.append(mean_joint_error(joint_positions(P, rest), true))
    return float(np.concatenate(errs).mean() * 1000.0)


def odometry_error_mm(rec: Recording, sliced: list[SlicedTracks], steps: np.ndarray) -> tuple[float, float]:
    """How good the odometry is on its own: AE (mm) of the true pose at frame k moved by batch k's step, against the
    true pose at frame k+1; and, for scale, of not moving at all (the motion over a batch)."""
    rest = rec.template.rest_joints
    truth = pose_at(rec.ground_truth, frame_times(sliced))
    after = joint_positions(truth[1:], rest)
    moved = mean_joint_error(joint_positions(truth[:-1] + steps, rest), after).mean()
    still = mean_joint_error(joint_positions(truth[:-1], rest), after).mean()
    return float(moved * 1000.0), float(still * 1000.0)


def ideal_row(rec: Recording, sliced: list[SlicedTracks], fits: np.ndarray) -> list[float]:
    """AE for each window of WINDOWS: fit errors averaged over the window, relative motion exact."""
    truth = pose_at(rec.ground_truth, frame_times(sliced))
    err = fits - truth
    n = len(truth)
    row = []
    for w in WINDOWS:
        if w == 0:
            fused = truth + err.mean(axis=0)
        else:  # frames k - (w-1)//2 .. k + w//2 (W = 2: k and k+1), clipped at the ends of the sequence
            lo = np.clip(np.arange(n) - (w - 1) // 2, 0, n)
            hi = np.clip(np.arange(n) + w // 2 + 1, 0, n)
            fused = truth + np.stack([err[a:b].mean(axis=0) for a, b in zip(lo, hi)])
        row.append(ae_mm(rec, sliced, fused, None))
    return row


def print_table(title: str, head: list[str], rows: dict[str, list[float]]) -> None:
    print(f"\n{title}")
    print(f"{'motion':<14} " + " ".join(f"{h:>9}" for h in head))
    for motion, r in rows.items():
        print(f"{motion:<14} " + " ".join(f"{x:9.1f}" for x in r))
    mean = np.mean(np.array(list(rows.values())), axis=0)
    print(f"{'mean':<14} " + " ".join(f"{x:9.1f}" for x in mean))
    print(f"{'vs linear':<14} " + " ".join(f"{100 * (x / mean[0] - 1):+8.0f}%" for x in mean))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--motions", default=MOTIONS)
    ap.add_argument("--duration", type=float, default=2.0, help="seconds of capture per motion")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tracks", default="oracle,eklt", help="trackers for the odometry rows ('' = ideal only)")
    ap.add_argument("--cache", default=str(ROOT / "runs" / "bench-cache"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_fusion"))
    ap.add_argument("--extra", default="", help="more hydra overrides, space separated (e.g. source.speed=2)")
    args = ap.parse_args()
    trackers = [t for t in args.tracks.split(",") if t]
    ideal, odo, odo_err, rho_est = {}, {t: {} for t in trackers}, {t: {} for t in trackers}, {t: {} for t in trackers}
    for motion in args.motions.split(","):
        for i, track in enumerate(trackers or ["eklt"]):
            rec, det, sliced = load(motion, track, args)
            problem, _ = problem_for(rec.template, rec.camera, sliced[0].t_us.size, BatchSolveConfig(mode="odometry"))
            fits = frame_fits(problem, det, sliced)
            if i == 0:
                ideal[motion] = ideal_row(rec, sliced, fits)
                print(f"{motion}: ideal " + " ".join(f"{x:.1f}" for x in ideal[motion]), flush=True)
            if not trackers:
                continue
            t0 = time.perf_counter()
            shapes = np.stack([odometry(problem, det, s) for s in sliced])
            rho_est[track][motion] = innovation_rho(fits, shapes[:, -1])
            odo[track][motion] = [ae_mm(rec, sliced, fits, None)] + [
                ae_mm(rec, sliced, pose_graph(fits, shapes[:, -1], rho), shapes)
                for rho in (*RHOS, rho_est[track][motion])]
            err, still = odometry_error_mm(rec, sliced, shapes[:, -1])
            odo_err[track][motion] = [err, still]
            print(f"{motion}: {track} odometry of {len(sliced)} batches in {time.perf_counter() - t0:.0f} s "
                  f"(error per batch {err:.1f} mm; the motion itself {still:.1f} mm; estimated rho "
                  f"{rho_est[track][motion]:.2f}); AE "
                  + " ".join(f"{x:.1f}" for x in odo[track][motion]), flush=True)
    print_table("1. ideal: exact relative motion, fit errors averaged over W intensity frames (AE mm; W=1 is linear)",
                ["W=1", "W=2", "W=3", "W=5", "W=9", "W=all"], ideal)
    for track in trackers:
        print_table(f"2. {track} tracks: solved event odometry + pose graph (AE mm; rho = weight of the odometry)",
                    ["linear"] + [f"rho={r:g}" for r in RHOS] + ["estimated"], odo[track])
        e = np.mean(np.array(list(odo_err[track].values())), axis=0)
        print(f"   odometry error per batch {e[0]:.1f} mm, against {e[1]:.1f} mm for not moving at all; estimated rho "
              + " ".join(f"{r:.2f}" for r in rho_est[track].values()))
    Path(args.out).mkdir(parents=True, exist_ok=True)
    (Path(args.out) / f"results-s{args.seed}.json").write_text(json.dumps(
        {"windows": list(WINDOWS), "rhos": list(RHOS), "ideal": ideal, "odometry": odo,
         "odometry_error_mm": odo_err, "rho_estimated": rho_est, "args": vars(args)}, indent=1))


if __name__ == "__main__":
    main()
