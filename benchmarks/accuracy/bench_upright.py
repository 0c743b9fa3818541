"""An upright world for a recording without extrinsics: the world the run sets against the true one.

    python benchmarks/accuracy/bench_upright.py [--tilt 25] [--height 2.2] [--motion karate_kick] [--duration 1] [--seed 2]
                                       [--detector blazepose] [--ups person,level]

A synthetic capture whose camera looks ``--tilt`` degrees down from ``--height`` metres is simulated, then written
again WITHOUT its extrinsics and ground truth (the camera's rotation the identity, its centre the origin), as a file
from a real camera would come: the run must choose a world itself. Each ``source.up`` variant is run on that file
with the default command (``eventcap run source=recording source.path=...``), and measured against the truth the run
never saw:

- ``up error``: the angle between the run's world up and the true one (degrees; both in camera axes);
- ``pitch`` / ``roll``: the camera tilt the run's world implies (the truth: pitch -tilt, roll 0);
- ``head above``: the share of estimated frames whose head is above the pelvis along the run's y;
- ``MPJPE cam``: the root-relative joint error in camera axes (mm): the same for any choice of world if the world
  did not matter to the solve; it differs through what assumes y is up (the floor and foot-contact factors);
- ``feet spread``: the standard deviation of the lowest foot joint's height (ankles, feet) along the run's y over the frames (mm):
  a level floor under a tilted world shows as feet that rise and fall with their depth.

Writes ``<out>/upright_side_view.png``: each variant's skeleton at 6 moments, seen from the side in its own world.
Nothing here is asserted; the figures go into the notes.
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def eventcap(args: list[str], log: Path) -> int:
    p = subprocess.run([sys.executable, "-m", "eventcap.apps.cli", *args], cwd=ROOT, capture_output=True, text=True)
    log.write_text(p.stdout + p.stderr)
    return p.returncode


def simulate(args, out: Path) -> Path:
    zarr_path = out / "sim" / "source.recording.zarr"
    if not zarr_path.exists():
        code = eventcap(["run", "pipeline=simulate", "source=synthetic", "export=[source.recording]",
                         f"source.motion={args.motion}", f"source.duration_s={args.duration}",
                         f"source.seed={args.seed}", f"source.camera_tilt_deg={args.tilt}",
                         f"source.camera_height_m={args.height}", f"hydra.run.dir={out / 'sim'}",
                         f"cache_dir={args.cache}"], out / "sim.log")
        if code:
            raise SystemExit(f"simulation failed: see {out / 'sim.log'}")
    return zarr_path


def strip(sim: Path, out: Path):
    """The recording without extrinsics and ground truth (what a real camera's file gives); returns (path, truth)."""
    import zarr

    from eventcap.artifacts.recording import Recording

    rec = Recording.from_zarr(zarr.open_group(str(sim), mode="r"))
    bare = dataclasses.replace(rec, camera=rec.camera.with_pose(np.eye(3), np.zeros(3)), ground_truth=None,
                               template=None, name="uncalibrated", source="bench_upright: extrinsics removed")
    path = out / "uncalibrated.zarr"
    if path.exists():
        shutil.rmtree(path)
    bare.to_zarr(zarr.open_group(str(path), mode="w"))
    return path, rec


def run_variant(args, out: Path, path: Path, up: str) -> Path:
    run_dir = out / f"up_{up}"
    code = eventcap(["run", "source=recording", f"source.path={path}", f"source.up={up}",
                     f"stages/detect={args.detector}", "outputs.video=false", "export=[detect.detections]",
                     f"hydra.run.dir={run_dir}", f"cache_dir={args.cache}"], out / f"up_{up}.log")
    if code or not (run_dir / "motion.npz").exists():
        raise SystemExit(f"run source.up={up} failed: see {out / f'up_{up}.log'}")
    return run_dir


def measure(run_dir: Path, truth, up: str) -> dict:
    import zarr

    from eventcap.artifacts.pose import Detections
    from eventcap.body.skeleton import JOINT_INDEX
    from eventcap.camera import level_rotation, tilt_from_up
    from eventcap.analysis.metrics import truth_at

    det = Detections.from_zarr(zarr.open_group(str(run_dir / "detect.detections.zarr"), mode="r"))
    R = det.world_R if det.world_R is not None else (level_rotation() if up != "camera" else np.eye(3))
    m = np.load(run_dir / "motion.npz")
    est = m["estimated"]
    t, J = m["t_us"][est], m["joints"][est]
    gt = truth.ground_truth
    Jt, inside = truth_at(gt.t_us, gt.joints, t)
    J = J[inside]
    cam_true = truth.camera
    up_true, up_run = cam_true.R @ (0.0, 1.0, 0.0), R @ (0.0, 1.0, 0.0)
    pc_est = J @ R.T  # camera at the origin of the run's world
    pc_true = Jt @ cam_true.R.T + cam_true.t
    err = np.linalg.norm((pc_est - pc_est[:, :1]) - (pc_true - pc_true[:, :1]), axis=-1).mean() * 1000
    head, pelvis = JOINT_INDEX["head"], JOINT_INDEX["pelvis"]
    feet = [JOINT_INDEX[n] for n in ("l_ankle", "r_ankle", "l_foot", "r_foot")]
    soles = J[:, feet, 1].min(axis=1)
    pitch, roll = tilt_from_up(up_run)
    return {"up": up, "up_error_deg": float(np.degrees(np.arccos(np.clip(up_true @ up_run, -1, 1)))),
            "pitch": pitch, "roll": roll, "head_above": float((J[:, head, 1] > J[:, pelvis, 1]).mean()),
            "mpjpe_cam_mm": float(err), "feet_spread_mm": float(np.std(soles) * 1000), "frames": int(J.shape[0])}


def figure(out: Path, ups: list[str], path: Path) -> Path:
    """Each variant's skeleton in its own world, seen from the side (the world's horizontal along the camera's view
    across the page, the world's y up), at 6 moments, with the lowest foot height over the capture as a line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import zarr

    from eventcap.artifacts.pose import Detections
    from eventcap.body.skeleton import JOINT_INDEX, PARENTS
    from eventcap.camera import level_rotation

    fig, axes = plt.subplots(1, len(ups), figsize=(6 * len(ups), 4.5), squeeze=False)
    for ax, up in zip(axes[0], ups):
        run_dir = out / f"up_{up}"
        det = Detections.from_zarr(zarr.open_group(str(run_dir / "detect.detections.zarr"), mode="r"))
        R = det.world_R if det.world_R is not None else level_rotation()
        m = np.load(run_dir / "motion.npz")
        J = m["joints"][m["estimated"]]
        view = R.T @ np.array([0.0, 0.0, 1.0])  # the camera's optical axis in the world
        ahead = np.array([view[0], 0.0, view[2]]) / max(np.hypot(view[0], view[2]), 1e-9)
        feet = [JOINT_INDEX[n] for n in ("l_ankle", "r_ankle", "l_foot", "r_foot")]
        floor = float(np.median(J[:, feet, 1].min(axis=1)))
        for k, f in enumerate(np.linspace(0, J.shape[0] - 1, 6).astype(int)):
            x, y = J[f] @ ahead, J[f, :, 1]
            x = x - x[0] + 1.2 * k
            for j, p in enumerate(PARENTS):
                if p >= 0:
                    ax.plot([x[j], x[p]], [y[j], y[p]], color=f"C{k}", lw=1.5)
        ax.axhline(floor, color="grey", lw=0.8, ls="--")
        ax.set_title(f"source.up={up}: world y up, away from the camera to the right")
        ax.set_aspect("equal")
        ax.set_xlabel("m (each moment shifted 1.2 m)")
    png = out / "upright_side_view.png"
    fig.tight_layout()
    fig.savefig(png, dpi=90)
    return png


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tilt", type=float, default=25.0)
    ap.add_argument("--height", type=float, default=2.2)
    ap.add_argument("--motion", default="karate_kick")
    ap.add_argument("--duration", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--detector", default="blazepose")
    ap.add_argument("--ups", default="person,level")
    ap.add_argument("--cache", default=str(ROOT / "runs" / "cache"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_upright"))
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path, truth = strip(simulate(args, out), out)
    print(f"truth: camera pitch {-args.tilt:g} deg, roll 0; {args.motion} seed {args.seed}, {args.duration:g} s")
    print(f"{'source.up':<10} {'up err':>7} {'pitch':>6} {'roll':>6} {'head above':>10} {'MPJPE cam':>9} "
          f"{'feet spread':>11}  (deg; share; mm)")
    for up in args.ups.split(","):
        r = measure(run_variant(args, out, path, up), truth, up)
        print(f"{r['up']:<10} {r['up_error_deg']:7.1f} {r['pitch']:6.1f} {r['roll']:6.1f} {r['head_above']:10.2f} "
              f"{r['mpjpe_cam_mm']:9.1f} {r['feet_spread_mm']:11.1f}", flush=True)
    print(f"figure: {figure(out, args.ups.split(','), path)}")


if __name__ == "__main__":
    main()
