"""How faithfully the shipped CMU clips are retargeted onto the template, and how long it takes.

For every clip in eventcap/body/assets/cmu/, the whole clip is retargeted on a 1 kHz grid (as a capture does) and
compared with the BVH's own forward kinematics at the same times (its joint rotations slerped to the grid):

- elbow and knee flexion: the angle between the upper and the lower segment (shoulder-elbow and elbow-wrist,
  hip-knee and knee-ankle), of the simulated truth (the retargeted poses through our forward kinematics) against
  the clip's; mean absolute difference in degrees over the four joints and every sample, and the worst joint's mean;
- peak wrist speeds, of the truth against the clip's, both in m/s after scaling the clip to the template (central
  differences on the 1 kHz grid, the larger of the two wrists);
- samples where a joint limit clipped the fit (more than 2 degrees past its bound), and the retarget time.

Also prints the clip table of the README: frames, fps, duration and the clip's own peak wrist / ankle speeds in
metres per second (CMU unit = 1/0.45 inch; central differences at 120 fps).

    python benchmarks/accuracy/bench_retarget.py            # all shipped clips (about a minute on 2 shared cores)
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from eventcap.body.bvh_clip import UNITS_M, forward_kinematics, read_bvh, resample
from eventcap.body.clips import clip_path, shipped_clips
from eventcap.body.kinematics import joint_positions
from eventcap.body.retarget import map_joints, retarget
from eventcap.body.skeleton import DEFAULT_REST_JOINTS, JOINT_INDEX

LIMBS = {"l_elbow": ("l_shoulder", "l_elbow", "l_wrist"), "r_elbow": ("r_shoulder", "r_elbow", "r_wrist"),
         "l_knee": ("l_hip", "l_knee", "l_ankle"), "r_knee": ("r_hip", "r_knee", "r_ankle")}


def flexion(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Angle (degrees) between segment a->b and segment b->c: 0 for a straight limb."""
    u, v = b - a, c - b
    cos = np.sum(u * v, -1) / (np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def peak_speed(p: np.ndarray, rate_hz: float) -> float:
    return float(np.max(np.linalg.norm(p[2:] - p[:-2], axis=-1)) * rate_hz / 2.0)


def clip_row(name: str) -> dict:
    """The clip's own numbers, in metres at its own frame rate."""
    c = read_bvh(clip_path(name))
    m = map_joints(c)
    pos, _ = forward_kinematics(c, c.rotations, c.root_positions)
    pos = pos * UNITS_M["cmu"]
    sp = {j: peak_speed(pos[:, m[j]], c.fps) for j in ("l_wrist", "r_wrist", "l_ankle", "r_ankle")}
    return {"frames": c.n_frames, "fps": c.fps, "duration": c.duration_s,
            "wrist": max(sp["l_wrist"], sp["r_wrist"]), "ankle": max(sp["l_ankle"], sp["r_ankle"])}


def measure(name: str, rate_hz: float) -> dict:
    c = read_bvh(clip_path(name))
    m = map_joints(c)
    t = np.arange(int(np.floor(c.duration_s * rate_hz)) + 1) / rate_hz
    t0 = time.perf_counter()
    out = retarget(c, t)
    seconds = time.perf_counter() - t0
    ours = joint_positions(out.poses, DEFAULT_REST_JOINTS)
    q, r = resample(c, t)
    theirs, _ = forward_kinematics(c, q, r)
    theirs = theirs * out.stats["scale"]
    diffs = {k: np.abs(flexion(*(ours[:, JOINT_INDEX[j]] for j in js))
                       - flexion(*(theirs[:, m[j]] for j in js))).mean() for k, js in LIMBS.items()}
    wrist = lambda P, idx: max(peak_speed(P[:, idx["l_wrist"]], rate_hz), peak_speed(P[:, idx["r_wrist"]], rate_hz))
    return {"flex_mean": float(np.mean(list(diffs.values()))), "flex_worst": max(diffs, key=diffs.get),
            "flex_worst_deg": float(max(diffs.values())), "wrist_truth": wrist(ours, JOINT_INDEX),
            "wrist_clip": wrist(theirs, m), "clipped": out.stats["clipped_samples"], "samples": t.size,
            "most": ", ".join(list(out.stats["clipped_dofs"])[:2]), "seconds": seconds}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clips", nargs="*", default=None, help="clip names (default: every shipped clip)")
    ap.add_argument("--rate", type=float, default=1000.0, help="retarget grid (Hz)")
    a = ap.parse_args()
    names = a.clips or shipped_clips()
    print("clip         frames  fps    s    peak wrist  peak ankle (m/s, the clip's own)")
    for n in names:
        row = clip_row(n)
        print(f"{n:12s} {row['frames']:5d} {row['fps']:5.0f} {row['duration']:5.2f} {row['wrist']:9.1f} "
              f"{row['ankle']:10.1f}")
    print(f"\nretargeted on a {a.rate:.0f} Hz grid (the machine is shared: times are indicative)")
    print("clip         elbow/knee flexion |diff| deg   peak wrist m/s      clipped samples   retarget   most held")
    print("             mean   (worst joint)            truth   clip")
    for n in names:
        r = measure(n, a.rate)
        print(f"{n:12s} {r['flex_mean']:5.1f}  ({r['flex_worst']} {r['flex_worst_deg']:4.1f})      "
              f"{r['wrist_truth']:6.1f} {r['wrist_clip']:6.1f}      {r['clipped']:5d} of {r['samples']:5d}   "
              f"{r['seconds']:5.1f} s    {r['most']}")


if __name__ == "__main__":
    main()
