"""``eventcap benchmark benchmark=real``: public recordings of people, run as a new user runs them (issue 53).

Each recording of the preset's ``recordings`` (conf/benchmark/real.yaml) runs through the README's command for a
recording, ``eventcap run source=recording source.path=FILE`` (the tool picks the event-only pipeline and the real
detector by itself, :func:`eventcap.apps.compose.job_config`), plus the recording's own overrides. There is no ground
truth; per recording the report gives what a user gets and how well it explains what the camera recorded:

- a motion, or the refusal and its cause (the run's first failure);
- the share of joint-frames observed (``confidence`` >= 0.5 in motion.npz, over every frame of the recording's
  motion, gaps included) and of frames estimated;
- the plausibility findings (plausibility.json: speeds beyond human limits, flips, joints behind the camera);
- the seams between chunks where the two chunks solved their shared stretch differently (the stitch's stats: how
  many of them, and the largest disagreement in pose and in place): the motion there hands over between two
  solutions, which no plausibility limit need catch;
- the share of the projected silhouette's outline within 2 px of an event of its millisecond and the 2D
  reprojection error against the accepted detections (:mod:`eventcap.analysis.event_fit`).

A recording whose file is not on disk is reported as such, with how to fetch it (its ``fetch`` entry): only the
files whose licence allows it ship in ``tests/data/real/``; the rest are listed in docs/results/real.md.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

_KEYS = {"name", "file", "sensor", "shows", "person", "source", "licence", "fetch", "overrides"}


@dataclass(frozen=True)
class RealRecording:
    """One recording of the real suite: where its file is, what it shows, where it comes from and its licence."""

    name: str
    path: Path
    sensor: str = ""
    shows: str = ""
    person: str = ""  # what a person can see of a person in it: whole body | upper body | hands | none
    source: str = ""
    licence: str = ""
    fetch: str = ""
    overrides: tuple[str, ...] = field(default_factory=tuple)


def parse_recordings(items: Sequence[Mapping[str, Any]], data_dir: Path, root: Path) -> list[RealRecording]:
    """The preset's ``recordings``, checked; a ``file`` is looked for under the project (a shipped cut, e.g.
    ``tests/data/real/...``), else under ``data_dir`` (fetched ones)."""
    out = []
    for i, r in enumerate(items or ()):
        if not isinstance(r, Mapping) or not r.get("name") or not r.get("file"):
            raise ValueError(f"recordings[{i}]: expected a mapping with a name and a file, got {r!r}")
        unknown = sorted(set(r) - _KEYS)
        if unknown:
            raise ValueError(f"recordings[{i}] ({r['name']}): unknown key {unknown[0]!r}; known: {', '.join(sorted(_KEYS))}")
        f = Path(str(r["file"]))
        path = f if f.is_absolute() else (root / f if (root / f).exists() else data_dir / f)
        if any(o.name == r["name"] for o in out):
            raise ValueError(f"recordings[{i}]: name {r['name']!r} repeats an earlier recording")
        out.append(RealRecording(str(r["name"]), path, *(str(r.get(k) or "") for k in
                                                         ("sensor", "shows", "person", "source", "licence", "fetch")),
                                 tuple(str(o) for o in r.get("overrides") or ())))
    if not out:
        raise ValueError("recordings: the real suite needs at least one recording")
    return out


def compose_recording_run(config_dir: Path, overrides: Sequence[str]) -> tuple[dict[str, Any], str]:
    """The run config of ``eventcap run <overrides>`` on a recording, made to fit it as the CLI does (event-only
    pipeline, real detector: :func:`eventcap.apps.compose.job_config`)."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from eventcap.apps.compose import job_config

    with initialize_config_dir(config_dir=str(config_dir), version_base="1.3"):
        cfg = compose(config_name="config", overrides=list(overrides))
        cfg, data = job_config(cfg, OmegaConf.to_container(cfg, resolve=True), list(overrides))
        return data, OmegaConf.to_yaml(cfg, resolve=True)


def real_figures(runner, result, run_dir: Path) -> dict[str, Any]:
    """What a run on a real recording gave (see the module docstring); every figure None where there is no motion."""
    out: dict[str, Any] = {"has_motion": False, "observed_share": None, "estimated_share": None, "plausibility": [],
                           "outline_share": None, "outline_share_10ms": None, "outline_frames": 0,
                           "reproj_median_px": None,
                           "reproj_p90_px": None, "reproj_points": 0}
    npz = run_dir / "motion.npz"
    if not npz.is_file():
        return out
    with np.load(npz) as z:
        t_us, poses = np.asarray(z["t_us"], np.int64), np.asarray(z["poses"], np.float64)
        est = np.asarray(z["estimated"], bool)
        conf = np.asarray(z["confidence"], np.float64) if "confidence" in z.files else None
    out["has_motion"] = bool(est.any())
    out["estimated_share"] = float(est.mean()) if est.size else 0.0
    if conf is not None:
        out["observed_share"] = float((np.nan_to_num(conf) >= 0.5).mean())
    pl = run_dir / "plausibility.json"
    if pl.is_file():
        out["plausibility"] = [{"kind": f["kind"], "count": f["count"], "total": f["total"], "peak": f["peak"],
                                "unit": f["unit"], "message": f["message"]}
                               for f in json.loads(pl.read_text()).get("findings", [])]
    rec, template, det = _context(runner, result)
    if rec is None or template is None:
        return out
    from eventcap.analysis.event_fit import outline_event_share, reprojection_error

    share = outline_event_share(rec.camera, template, t_us, poses, rec.events.events)
    out.update(outline_share=share.share if share.frames else None, outline_frames=share.frames)
    # a sparse sensor (a DVS128 gives ~15 events per ms over the whole image) cannot outline a body in 1 ms: the
    # same share over 10 ms says whether the outline lies where the person moved
    wide = outline_event_share(rec.camera, template, t_us, poses, rec.events.events, window_us=10000)
    out["outline_share_10ms"] = wide.share if wide.frames else None
    if det is not None:
        r = reprojection_error(rec.camera, template, t_us, poses, det)
        out.update(reproj_median_px=r["median_px"], reproj_p90_px=r["p90_px"], reproj_points=r["points"])
    return out


def _seams(r: Mapping[str, Any]) -> str:
    """A run's seams between chunks as the stitch counted them (its stats, which the benchmark collects with every
    run: :func:`eventcap.apps.benchmark.stage_times`): "apart of all (largest: pose; place mm)", "-" without them."""
    st = (r.get("stats") or {}).get("stitch") or {}
    if "seam_pose_mm_max" not in st:
        return "-"
    return (f"{int(st.get('seams_apart', 0))} of {int(st.get('seams', 0))} ({st['seam_pose_mm_max']:.0f}; "
            f"{st['seam_shift_mm_max']:.0f} mm)")


def _context(runner, result):
    """The recording in the world the motion was solved in, its template and the detections of a finished run."""
    from eventcap.apps.outputs import _first_output, _upstream
    from eventcap.artifacts.pose import Detections
    from eventcap.artifacts.recording import Recording
    from eventcap.body.template import Template
    from eventcap.worldframe import upright

    prefer = _upstream(runner, "cut") if "cut" in runner.by_name else []
    det = _first_output(runner, result, Detections)
    rec = _first_output(runner, result, Recording, prefer)
    if rec is None:
        return None, None, det
    rec = upright(rec, det)
    template = rec.template if rec.template is not None else _first_output(runner, result, Template, prefer)
    return rec, template, det


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.0f}%"


def format_real(records: Sequence[Mapping[str, Any]]) -> str:
    """The per-recording table of the real suite."""
    head = ["recording", "person", "result", "observed", "plausibility", "chunk seams apart (largest: pose; place)",
            "outline <= 2 px (1 ms; 10 ms)", "reprojection px"]
    rows = []
    for r in records:
        if r.get("has_motion"):
            result = "motion" + ("" if r.get("ok") else " (incomplete)")
        else:
            result = f"refused: {r.get('error') or 'no motion'}"
        pl = "; ".join(f"{f['kind']} {f['count']}/{f['total']}" for f in r.get("plausibility") or []) or \
            ("none" if r.get("has_motion") else "-")
        reproj = "-" if r.get("reproj_median_px") is None else \
            f"{r['reproj_median_px']:.1f} (p90 {r['reproj_p90_px']:.1f})"
        outline = "-" if r.get("outline_share") is None else \
            f"{_pct(r['outline_share'])}; {_pct(r.get('outline_share_10ms'))} ({r.get('outline_frames', 0)} moments)"
        rows.append([r["motion_name"], r.get("person") or "", result, _pct(r.get("observed_share")), pl, _seams(r),
                     outline, reproj])
    widths = [max(len(str(x)) for x in col) for col in zip(head, *rows)]
    lines = ["| " + " | ".join(h.ljust(w) for h, w in zip(head, widths)) + " |",
             "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
    lines += ["| " + " | ".join(str(c).ljust(w) for c, w in zip(row, widths)) + " |" for row in rows]
    n = len(records)
    got = sum(bool(r.get("has_motion")) for r in records)
    clean = sum(bool(r.get("has_motion")) and not r.get("plausibility") for r in records)
    apart = sum(bool(r.get("has_motion")) and not r.get("plausibility")
                and bool(((r.get("stats") or {}).get("stitch") or {}).get("seams_apart")) for r in records)
    lines.append(f"{got} of {n} recordings gave a motion, {clean} of them with no plausibility finding"
                 + (f" ({apart} of these with chunk seams apart: the motion hands over between two solutions there)"
                    if apart else ""))
    return "\n".join(lines)
