"""A picture of one millisecond: the fastest moment of a capture in the camera image, with the events of that
millisecond and the skeletons of the truth and of the rows of an `eventcap benchmark` run there.

    python benchmarks/figures/fig_fast_moment.py --bench runs/benchmark/ladder [--motion karate_kick] [--seed 0]
                                   [--rows "a default,a frames_smooth"] [--runs NAME=RUNDIR ...]
                                   [--joints l_wrist,r_wrist,l_ankle,r_ankle,l_foot,r_foot] [--out FILE]

Each row's `motion.npz` comes from its run folder ``<bench>/runs/<motion>-s<seed>/<row>/`` (the row's name without
spaces, ``/`` as ``_``), or from ``--runs NAME=RUNDIR`` given directly; the recording (events, camera, intensity frame
times, ground truth) from the first run's own config, brought back from the cache with only its template and source
nodes (benchmarks/diagnostics/diag_depth.py ``from_run``: nothing is recomputed, whatever changed in the code since).

The moment is the millisecond where an end effector of the truth (``--joints``) moves fastest relative to the pelvis,
by central differences over 10 ms as the evaluate stage takes them (eventcap.analysis.metrics), among the times every
row estimated. Panels: the camera image with the events of that millisecond (t ± 0.5 ms, red: positive, blue:
negative polarity; the events of t ± ``--context-ms`` in pale tints behind them) and the projected skeletons of the
truth (black) and each row at that millisecond; a zoom around the fast limb (with the truth's path of the end
effector over ± 10 ms); a side view of the skeletons (camera depth across, up; benchmarks/figures/fig_side_view.py),
since a kick towards the camera moves mostly in depth, which the image does not show; and that end effector's speed
over ± 150 ms, truth and rows, with the intensity frames' exposures shaded. Writes ``<bench>/fig_fast_moment_<motion>-s<seed>.png`` (or ``--out``) and prints each row's error
of the end effector at that millisecond (image px, 3D mm, root-relative mm) and its speed there.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "diagnostics"))

import numpy as np  # noqa: E402

from diag_depth import from_run  # noqa: E402
from fig_side_view import side  # noqa: E402
from eventcap.analysis.metrics import central_derivative, root_relative, truth_at  # noqa: E402
from eventcap.body.skeleton import JOINT_INDEX, JOINT_NAMES, PARENTS  # noqa: E402

DEFAULT_JOINTS = "l_wrist,r_wrist,l_ankle,r_ankle,l_foot,r_foot"
ROW_COLORS = ("tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:olive", "tab:cyan")


def row_folder(name: str) -> str:
    """A row's run folder name: the row's name without spaces, ``/`` as ``_`` (``a default`` -> ``adefault``)."""
    return name.replace(" ", "").replace("/", "_")


def find_runs(args) -> dict[str, Path]:
    """{row label: run folder} from --runs, or from --bench and --rows; refuses what is missing, naming it."""
    runs: dict[str, Path] = {}
    if args.runs:
        for item in args.runs:
            name, sep, rd = item.partition("=")
            if not sep or not name or not rd:
                raise SystemExit(f"--runs: expected NAME=RUNDIR, got {item!r}")
            runs[name] = Path(rd)
    else:
        if not args.bench:
            raise SystemExit("give --bench DIR (with --rows) or --runs NAME=RUNDIR ...")
        seq = Path(args.bench) / "runs" / f"{args.motion}-s{args.seed}"
        for name in (r.strip() for r in args.rows.split(",")):
            if name:
                runs[name] = seq / row_folder(name)
    for name, rd in runs.items():
        for f in ("motion.npz", "config.yaml"):
            if not (rd / f).is_file():
                raise SystemExit(f"row {name!r}: no {f} in {rd}")
    if not runs:
        raise SystemExit("no rows given")
    return runs


def load_motion(rd: Path) -> tuple[np.ndarray, np.ndarray]:
    """(t_us (T,), joints (T, 24, 3) m) of a run's motion.npz, NaN where the motion has a gap (``estimated`` False)."""
    with np.load(rd / "motion.npz") as z:
        t_us, joints = np.asarray(z["t_us"], np.int64), np.asarray(z["joints"], np.float64).copy()
        if "estimated" in z.files:
            joints[~np.asarray(z["estimated"], bool)] = np.nan
    return t_us, joints


def speed(t_us: np.ndarray, x: np.ndarray, window_us: float) -> np.ndarray:
    """|dx/dt| (m/s) by the evaluate stage's central differences; NaN where the window leaves the motion."""
    return np.linalg.norm(central_derivative(x, t_us, window_us)[0], axis=-1)


def draw_skeleton(ax, uv: np.ndarray, color, lw: float, ms: float, label: str, z: int, alpha: float) -> None:
    """Bones (child to parent) and joints of one projected skeleton (24, 2) px."""
    for j in range(1, uv.shape[0]):
        p = PARENTS[j]
        ax.plot(uv[[j, p], 0], uv[[j, p], 1], color=color, lw=lw, alpha=alpha, zorder=z, solid_capstyle="round")
    ax.plot(uv[:, 0], uv[:, 1], "o", color=color, ms=ms, alpha=alpha, zorder=z + 1, label=label, mec="none")


def limb(j: int) -> list[int]:
    """An end effector, the joint it hangs from and the joints that hang from it (ankle: knee, ankle, foot)."""
    return [j, int(PARENTS[j])] + [int(c) for c in np.flatnonzero(PARENTS == j)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bench", help="a benchmark folder holding runs/<motion>-s<seed>/<row>/")
    ap.add_argument("--motion", default="karate_kick")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rows", default="a default,a frames_smooth",
                    help="comma-separated row names (with or without spaces)")
    ap.add_argument("--runs", nargs="+", metavar="NAME=RUNDIR", help="run folders given directly (instead of --rows)")
    ap.add_argument("--joints", default=DEFAULT_JOINTS, help="the end effectors among which the fastest is picked")
    ap.add_argument("--window-ms", type=float, default=10.0, help="central-difference window of the speed (ms)")
    ap.add_argument("--context-ms", type=float, default=5.0,
                    help="half-width (ms) of the pale event context behind the millisecond's events; 0: none")
    ap.add_argument("--out", help="the PNG to write (default <bench>/fig_fast_moment_<motion>-s<seed>.png)")
    args = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    runs = find_runs(args)
    ees = [n.strip() for n in args.joints.split(",") if n.strip()]
    bad = [n for n in ees if n not in JOINT_INDEX or n == "pelvis"]
    if bad:
        raise SystemExit(f"--joints: {', '.join(bad)} not among {', '.join(JOINT_NAMES[1:])}")
    rec = from_run(next(iter(runs.values())))
    gt, cam = rec.ground_truth, rec.camera
    if gt is None:
        raise SystemExit(f"the recording of {next(iter(runs.values()))} has no ground truth")
    window_us = args.window_ms * 1000.0

    motions = {name: load_motion(rd) for name, rd in runs.items()}
    # the times every row estimated (the truth is taken on the first row's grid, inside them all)
    t = motions[next(iter(runs))][0]
    for tm, J in motions.values():
        t = t[np.isin(t, tm[np.isfinite(J).all(axis=(1, 2))])]
    truth, inside = truth_at(gt.t_us, gt.joints, t)
    t = t[inside]
    if t.size < 3:
        raise SystemExit("the rows share fewer than 3 estimated times inside the ground truth")
    ee_idx = [JOINT_INDEX[n] for n in ees]
    v_true_all = speed(t, root_relative(truth)[:, ee_idx], window_us)  # (T, E)
    if not np.isfinite(v_true_all).any():
        raise SystemExit(f"no {args.window_ms:g} ms central difference fits inside the rows' common times")
    i_peak, e_peak = np.unravel_index(np.nanargmax(v_true_all), v_true_all.shape)
    tp, j, jname = int(t[i_peak]), ee_idx[e_peak], ees[e_peak]
    v_peak = float(v_true_all[i_peak, e_peak])

    # each row: its skeleton at the moment and the end effector's speed (on its own times, against the truth there)
    G_at = truth[i_peak]
    rows = {}
    for name, (tm, J) in motions.items():
        k = int(np.searchsorted(tm, tp))
        rel = root_relative(J)[:, j]
        v = speed(tm, rel, window_us)
        rows[name] = {"J": J[k], "t": tm, "v": v, "v_at": float(v[k])}

    # the image: events of the millisecond, and (pale) the context around it
    W, H = cam.width, cam.height
    img = np.ones((H, W, 3))
    if args.context_ms > 0:
        ctx = rec.events.window(tp - int(args.context_ms * 1000), tp + int(args.context_ms * 1000) + 1)
        for p, col in ((1, (1.0, 0.8, 0.8)), (-1, (0.8, 0.85, 1.0))):
            e = ctx[ctx["p"] == p]
            img[e["y"], e["x"]] = col
    ev = rec.events.window(tp - 500, tp + 501)  # t - 0.5 ms <= t_e <= t + 0.5 ms
    n_pos, n_neg = int((ev["p"] == 1).sum()), int((ev["p"] == -1).sum())
    for p, col in ((1, (0.85, 0.0, 0.0)), (-1, (0.0, 0.2, 0.95))):
        e = ev[ev["p"] == p]
        img[e["y"], e["x"]] = col
    both = np.zeros((H, W), int)
    for p in (1, -1):
        e = ev[ev["p"] == p]
        both[e["y"], e["x"]] += 1
    img[both == 2] = (0.6, 0.0, 0.6)

    uv_true = cam.project(G_at)
    uv_rows = {name: cam.project(r["J"]) for name, r in rows.items()}
    # the truth's path of the end effector over +-10 ms, for the zoom
    near = (gt.t_us >= tp - 10_000) & (gt.t_us <= tp + 10_000)
    path = cam.project(gt.joints[near, j])

    fig = plt.figure(figsize=(19, 5.8))
    gs = fig.add_gridspec(1, 4, width_ratios=[1.35, 1.0, 0.7, 1.2], wspace=0.25)
    ax_img, ax_zoom, ax_side, ax_v = (fig.add_subplot(gs[k]) for k in range(4))
    colors = {name: ROW_COLORS[i % len(ROW_COLORS)] for i, name in enumerate(rows)}
    for ax, lw, ms, alpha in ((ax_img, 1.0, 2.5, 0.9), (ax_zoom, 1.6, 5.0, 0.6)):
        ax.imshow(img, interpolation="nearest", zorder=0)  # pixel centres at integers, as the camera's coordinates
        draw_skeleton(ax, uv_true, "k", 1.8 * lw, 1.2 * ms, "truth", 10, alpha)
        for i, (name, uv) in enumerate(uv_rows.items()):
            draw_skeleton(ax, uv, colors[name], lw, ms, name, 12 + 2 * i, alpha)
    ax_img.set_xlim(-0.5, W - 0.5)
    ax_img.set_ylim(H - 0.5, -0.5)
    # the zoom: the fast limb of the truth and the rows, with a margin, square
    near_j = limb(j)
    pts = np.concatenate([uv_true[near_j], path] + [uv[near_j] for uv in uv_rows.values()])
    pts = pts[np.isfinite(pts).all(axis=1)]
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    c, half = (lo + hi) / 2, max(10.0, (hi - lo).max() / 2 + 5.0)
    ax_zoom.plot(path[:, 0], path[:, 1], color="magenta", lw=1.2, zorder=30, label=f"truth's {jname}, t-10 to t+10 ms")
    ax_zoom.plot(*path[-1], ">", color="magenta", ms=5, zorder=31)
    for name, uv in [("truth", uv_true)] + list(uv_rows.items()):
        ax_zoom.plot(*uv[j], "x", color=colors.get(name, "k"), ms=9, mew=2.0, zorder=32)
    ax_zoom.set_xlim(c[0] - half, c[0] + half)
    ax_zoom.set_ylim(c[1] + half, c[1] - half)
    ax_img.add_patch(Rectangle((c[0] - half, c[1] - half), 2 * half, 2 * half, fill=False, ec="0.3", lw=0.8,
                               ls=":", zorder=20))
    ax_img.legend(fontsize=7, loc="upper left", framealpha=0.85)
    ax_zoom.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.07), ncol=2, framealpha=0.85)
    ctx_txt = f"; pale: ±{args.context_ms:g} ms" if args.context_ms > 0 else ""
    ax_img.set_title(f"camera image ({W}x{H} px) at t = {tp / 1000:.0f} ms, projected skeletons\n{n_pos} + (red) and "
                     f"{n_neg} − (blue) events in t ± 0.5 ms{ctx_txt}", fontsize=8)
    ax_zoom.set_title(f"zoom on the {jname} ({2 * half:.0f} px across)\nx: the {jname} of each; magenta: its true "
                      f"path over ±10 ms", fontsize=8)
    for ax in (ax_img, ax_zoom):
        ax.tick_params(labelsize=7)

    # a side view: what the image cannot show, the depth along the line of sight
    for name, J in [(n, r["J"]) for n, r in rows.items()] + [("truth", G_at)]:  # the truth on top, see-through
        sv = side(J, cam.R)
        for q in range(1, sv.shape[0]):
            ax_side.plot(sv[[q, PARENTS[q]], 0], sv[[q, PARENTS[q]], 1], color=colors.get(name, "k"),
                         lw=2.2 if name == "truth" else 1.2, alpha=0.55 if name == "truth" else 0.9)
        ax_side.plot(*sv[j], "x", color=colors.get(name, "k"), ms=8, mew=2.0)
    ax_side.set_aspect("equal")
    ax_side.grid(alpha=0.3)
    ax_side.tick_params(labelsize=7)
    ax_side.set_xlabel("depth rel. pelvis (m, away from the camera →)", fontsize=8)
    ax_side.set_ylabel("up rel. pelvis (m)", fontsize=8)
    ax_side.set_title(f"side view at t (x: {jname})\nthe depth the image does not show", fontsize=8)

    # the end effector's speed around the moment, with the intensity frames' exposures
    a, b = tp - 150_000, tp + 150_000
    v_gt = speed(gt.t_us, root_relative(gt.joints)[:, j], window_us)
    sel = (gt.t_us >= a) & (gt.t_us <= b)
    ax_v.plot(gt.t_us[sel] / 1000, v_gt[sel], color="k", lw=2.4, label="truth")
    for name, r in rows.items():
        s = (r["t"] >= a) & (r["t"] <= b)
        ax_v.plot(r["t"][s] / 1000, r["v"][s], color=colors[name], lw=1.3, label=name)
    if rec.frames is not None:
        label = "intensity frame (exposure shaded)"
        for tf, ex in zip(rec.frames.t_us, rec.frames.exposure_us):
            if a - ex <= tf <= b + ex:
                ax_v.axvline(tf / 1000, color="0.5", lw=0.8, ls=":", label=label)
                if ex > 0:
                    ax_v.axvspan((tf - ex / 2) / 1000, (tf + ex / 2) / 1000, color="0.85", zorder=0)
                label = None  # one legend entry
    ax_v.axvline(tp / 1000, color="tab:red", lw=1.0, label=f"t = {tp / 1000:.0f} ms")
    ax_v.set_xlim(a / 1000, b / 1000)
    ax_v.set_xlabel("time (ms)", fontsize=8)
    ax_v.set_ylabel(f"{jname} speed rel. pelvis (m/s, {args.window_ms:g} ms differences)", fontsize=8)
    ax_v.grid(alpha=0.3)
    ax_v.tick_params(labelsize=7)
    ax_v.legend(fontsize=7, loc="best", framealpha=0.85)
    fps = ""
    if rec.frames is not None and rec.frames.t_us.size > 1:
        fps = f", intensity frames at {1e6 / np.median(np.diff(rec.frames.t_us)):.0f} fps"
    speeds = ", ".join(f"{name} {r['v_at']:.2f}" for name, r in rows.items())
    fig.suptitle(f"{args.motion} seed {args.seed}{fps}: the fastest moment, t = {tp / 1000:.0f} ms, {jname} at "
                 f"{v_peak:.2f} m/s in the truth (rel. pelvis); there {speeds} m/s", fontsize=10)

    if args.out:
        out = Path(args.out)
    elif args.bench:
        out = Path(args.bench) / f"fig_fast_moment_{args.motion}-s{args.seed}.png"
    else:
        first = next(iter(runs.values()))
        out = first.parents[2] if first.parent.parent.name == "runs" else first
        out = out / f"fig_fast_moment_{args.motion}-s{args.seed}.png"
    fig.savefig(out, dpi=120, bbox_inches="tight")
    plt.close(fig)

    print(f"{args.motion} seed {args.seed}: fastest moment t = {tp / 1000:.0f} ms, {jname} at {v_peak:.3f} m/s "
          f"(truth, rel. pelvis, {args.window_ms:g} ms differences); {n_pos} + / {n_neg} − events in ±0.5 ms")
    # how much of the true motion the image shows: the end effector's image speed and its speed along the line of sight
    h = int(window_us / 2)
    kk = np.searchsorted(gt.t_us, [tp - h, tp + h])
    img_speed = np.linalg.norm(cam.project(gt.joints[kk[1], j]) - cam.project(gt.joints[kk[0], j])) / (2 * h / 1000)
    depth_speed = (cam.depth(gt.joints[kk[1], j]) - cam.depth(gt.joints[kk[0], j])) / (2 * h * 1e-6)
    v_abs = np.linalg.norm(gt.joints[kk[1], j] - gt.joints[kk[0], j]) / (2 * h * 1e-6)
    print(f"truth {jname} at t: {img_speed:.2f} px/ms in the image, {v_abs:.2f} m/s in the world of which "
          f"{depth_speed:+.2f} m/s along the line of sight (camera depth, + away)")
    rel_true = G_at[j] - G_at[0]
    for name, r in rows.items():
        J = r["J"]
        px = float(np.linalg.norm(uv_rows[name][j] - uv_true[j]))
        mm = 1000 * float(np.linalg.norm(J[j] - G_at[j]))
        mm_rel = 1000 * float(np.linalg.norm((J[j] - J[0]) - rel_true))
        print(f"{name:<16} {jname} error {px:6.2f} px, {mm:6.1f} mm (root-relative {mm_rel:6.1f} mm); "
              f"speed {r['v_at']:.3f} m/s ({r['v_at'] - v_peak:+.3f} m/s against the truth)")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
