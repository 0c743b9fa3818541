"""What the viewer recording and the C3D export cost on a finished run: seconds, bytes, MB per second of capture,
and the C3D file read back by ezc3d and by the independent `c3d` package against motion.npz.

    python benchmarks/speed/bench_viewer.py runs/default/<ts>/ [--repeat 2]

The run folder is read as `eventcap view` reads it (config.yaml + run.json + the cache); the files are written into
a temporary copy of it, so the run folder itself is left alone.
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args(argv)

    from eventcap.export.bvh import read_motion_npz
    from eventcap.apps.outputs import check_outputs_config, write_run_outputs
    from eventcap.core.runner import load_finished_run

    runner, result = load_finished_run(args.run_dir)
    base = check_outputs_config(runner)
    tmp = Path(tempfile.mkdtemp(prefix="bench_viewer-"))
    try:
        for name in ("config.yaml", "run.json"):
            shutil.copy(args.run_dir / name, tmp / name)
        for what in ("npz", "rerun", "c3d"):
            only = dataclasses.replace(base, bvh=False, npz=what == "npz", video=False, rerun=what == "rerun",
                                       c3d=what == "c3d")
            for i in range(args.repeat):
                t0 = time.perf_counter()
                summary = write_run_outputs(runner, result, tmp, only)
                dt = time.perf_counter() - t0
                assert not summary["problems"], summary["problems"]
                path = Path(summary["written"][what])
                line = f"{what:6s} run {i + 1}: {dt:6.2f} s (loading the run's artifacts included), " \
                       f"{path.stat().st_size / 1e6:7.2f} MB"
                if what == "rerun":
                    st = summary["rerun"]
                    line += f" ({st['seconds']:.2f} s writing, {st['MB_per_s_of_capture']:.2f} MB per s of capture)"
                    line += "\n       " + ", ".join(f"{k} {v}" for k, v in st["counts"].items())
                    if st["decimated"]:
                        line += f"\n       decimated: {st['decimated']}"
                print(line, flush=True)
        m = read_motion_npz(tmp / "motion.npz")
        span_s = (m["t_us"][-1] - m["t_us"][0]) * 1e-6
        print(f"motion: {m['t_us'].size} frames over {span_s:.3f} s")
        _check_c3d(tmp / "motion.c3d", m, runner, result)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


def _check_c3d(path: Path, m: dict, runner, result) -> None:
    import c3d
    import ezc3d

    from eventcap.body.markers import plug_in_gait_markers
    from eventcap.export.c3d import c3d_labels

    tpl = runner.load_output(result, "template.template")[None]
    markers = plug_in_gait_markers(tpl)
    want = np.concatenate([m["joints"], markers.positions(m["poses"], tpl)], axis=1) * 1000.0
    k = (m["t_us"] - m["t_us"][0]) // 1000
    f = ezc3d.c3d(str(path))
    P = np.transpose(f["data"]["points"][:3], (2, 1, 0))
    labels = list(f["parameters"]["POINT"]["LABELS"]["value"])
    print(f"c3d ezc3d: {len(labels)} labels (== joints + markers: {labels == c3d_labels(markers.names)}), "
          f"rate {f['parameters']['POINT']['RATE']['value'][0]:g} Hz, units {f['parameters']['POINT']['UNITS']['value'][0]}, "
          f"{P.shape[0]} frames, max |c3d - npz| = {np.abs(P[k] - want).max():.5f} mm")
    with open(path, "rb") as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = c3d.Reader(fh)
        xyz = np.stack([p[:, :3] for _, p, _ in r.read_frames()])
        print(f"c3d c3d:   {len(r.point_labels)} labels (same: {[s.strip() for s in r.point_labels] == labels}), "
              f"rate {r.point_rate:g} Hz, units {r.get('POINT:UNITS').string_value.strip()}, {xyz.shape[0]} frames, "
              f"max |c3d - npz| = {np.abs(xyz[k] - want).max():.5f} mm")


if __name__ == "__main__":
    sys.exit(main())
