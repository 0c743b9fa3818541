"""What the spline solve of one unit's window needs, decided once (:class:`WindowPlan`, :func:`plan_window`).

A unit of the solve (a batch, or a chunk of batches) keeps batches ka..kz and solves the window of batches a..z
around them (``half_window`` batches of margin on each side, shifted inwards at the ends of the recording:
eventcap_spline._impl.unit_role). Its plan holds everything the solve of that window reads: the detections at
every detection frame of the window, the event tracks of the batches E_cor uses, the tracking times of the kept
batches, the events, the spline (its knots), the problem's layout (each term's samples), the detections around the
window whose fits give the smoothing evidence, and the times the window's curve is output at. The functions
downstream take the plan; nothing re-derives it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from eventcap.analysis.motion import tracking_times_us
from eventcap.core.stage import StageFailed
from eventcap.energy.detections import FrameDetections, detection_times, select_detections
from eventcap.energy.factor import Layout
from eventcap.energy.problem import SplinePoses, coupling_band
from eventcap.energy.settings import ContactConfig
from eventcap.energy.spline import UniformCubicBSpline
from eventcap.energy.terms import TermSet
from eventcap.energy.window import Tracks, WindowInputs


@dataclass(frozen=True, eq=False)
class WindowPlan:
    """The window of one unit of the spline solve and its data (module doc), built once by :func:`plan_window`."""

    where: str  #: how messages name the unit ("batch 3", "chunk 1 (batches 10..19)")
    window: tuple[int, int]  #: (a, z): the window's first and last batch
    kept: tuple[int, int]  #: (ka, kz): the batches the unit keeps
    first: int  #: the first kept batch that has tracks (its tracking rate sets the output's)
    scope: tuple[int, ...]  #: the batches whose tracks E_cor uses (stages.solve.tracks.scope)
    t_det_us: np.ndarray  #: (D,) the detection frames within the window's span
    detections: FrameDetections  #: their detections
    tracks: Tracks  #: the scope's tracks at the correspondence frames
    kept_times_us: tuple[np.ndarray, ...]  #: the tracking times of each kept batch that has tracks
    events: np.ndarray  #: the recording's events from the first to the last detection frame
    spline: UniformCubicBSpline  #: the window's curve: knots every knot_ms from its first detection frame
    layout: Layout  #: the problem's sizes (each term's samples) and coupling band
    context: tuple[np.ndarray, FrameDetections] | None  #: the detections around the window (smoothing evidence)
    capture_frames_us: np.ndarray  #: the recording's intensity frames (batch boundaries): the capture's measures
    t_out_us: np.ndarray  #: the times the window's curve is output at (the window's batches' tracking times)
    contact: ContactConfig  #: when a sole point counts as in contact (the floor terms' evidence)

    @property
    def what(self) -> str:
        """How messages name the window."""
        return f"{self.where} (window of batches {self.window[0]}..{self.window[1]})"

    @property
    def knots_us(self) -> np.ndarray:
        s = self.spline
        return s.t0_us + s.h_us * np.arange(s.n_seg + 1, dtype=np.int64)

    def inputs(self) -> WindowInputs:
        """A fresh :class:`WindowInputs` of the window (the solve offers its evidence on it)."""
        s = self.spline
        return WindowInputs(s.t0_us, s.t1_us, knots_us=self.knots_us, t_det_us=self.t_det_us,
                            detections=self.detections, tracks=self.tracks, track_times_us=self.kept_times_us,
                            events=self.events, contact=self.contact)


def plan_window(inputs, config, terms: TermSet, where: str, role: tuple[int, int, int, int], log) -> WindowPlan:
    """The plan of a unit's window (role: the window a..z keeping batches ka..kz, eventcap_spline._impl.unit_role)
    from the stage's inputs (the recording in the detections' world), its config and its decoded terms. StageFailed
    naming the unit when its data are unusable (no tracks, too few tracking frames, missing detections)."""
    rec, batches, detections = inputs["recording"], inputs["batches"], inputs["detections"]
    a, z, ka, kz = role
    sliced = inputs["sliced"]
    # every batch's tracks, as the runner hands them (runner.BatchSequence: .batches names them, loaded on access)
    index = {bb.index: i for i, bb in enumerate(sliced.batches)}
    kept = [k for k in range(ka, kz + 1) if k in index]  # batches= may select part of a chunk
    if not kept:
        raise StageFailed(f"{where}: no tracks of {'batch' if ka == kz else 'batches'} {ka}"
                          f"{'' if ka == kz else f'..{kz}'} among the {len(sliced)} given", status="invalid_input")
    first = kept[0]
    own = sliced[index[first]]
    t_us = np.asarray(own.t_us, dtype=np.int64)
    if t_us.size < 2:
        raise StageFailed(f"{where}: {t_us.size} tracking frame(s); need at least 2", status="invalid_input")
    # own: the tracks of the batches the window keeps (this batch alone at window_step 1); window: all of its batches
    scope = kept if config.tracks.scope == "own" else [k for k in range(a, z + 1) if k in index]
    t_det, det = window_detections(detections, batches, a, z, where)
    part = (lambda k: own if k == first else sliced[index[k]])
    t_cor, xy, valid = window_tracks([part(k) for k in scope], int(config.tracks.step), where)
    h_us = int(round(config.knot_ms * 1000))
    spline = UniformCubicBSpline(int(t_det[0]), h_us, int(math.ceil((t_det[-1] - t_det[0]) / h_us)))
    frames = np.unique(np.concatenate([batches.t0_us, batches.t1_us]))
    plan = WindowPlan(
        where=where, window=(a, z), kept=(ka, kz), first=first, scope=tuple(scope), t_det_us=t_det, detections=det,
        tracks=Tracks(t_cor, xy, valid, float(config.tracks.edge_margin_px)),
        kept_times_us=tuple(np.asarray(part(k).t_us, dtype=np.int64) for k in kept),
        events=rec.events.window(int(t_det[0]), int(t_det[-1]) + 1), spline=spline, layout=Layout(),  # below
        context=prior_context(config, frames, t_det, detections, where, log), capture_frames_us=frames,
        t_out_us=window_times(sliced, index, batches, first, a, z, t_us), contact=config.contact)
    return _with_layout(plan, terms)


def _with_layout(plan: WindowPlan, terms: TermSet) -> WindowPlan:
    """The plan with its problem's layout: each term's samples in the window, and how far coupled samples reach."""
    times = terms.samples(plan.inputs())
    spline, n_seg = plan.spline, plan.spline.n_seg
    band = max([coupling_band(SplinePoses(n_seg, spline), plan.tracks.t_us)]
               + [coupling_band(SplinePoses(n_seg, spline), times[t.name]) for t in terms.on
                  if t.factor_class.couples_neighbours and times[t.name].size > 1])
    return replace(plan, layout=Layout(n_seg=n_seg, sizes=tuple((k, int(t.size)) for k, t in times.items()), band=band))


def window_detections(detections, batches, a: int, z: int, where: str) -> tuple[np.ndarray, FrameDetections]:
    """Every detection within the span of batches a..z (at its intensity frames, and between them where the
    detector looked; its batch boundaries when fewer than 2) and their detections. StageFailed when they are
    missing or unusable."""
    t_det = detection_times(detections, int(batches.t0_us[a]), int(batches.t1_us[z]))
    if t_det.size < 2:
        t_det = np.unique(np.concatenate([batches.t0_us[a:z + 1], batches.t1_us[a:z + 1]]))
    try:
        det = select_detections(detections, t_det)
    except ValueError as exc:
        raise StageFailed(f"{where}: {exc}", status="missing_detections") from exc
    problems = det.problems()
    if problems:
        raise StageFailed(f"{where}: detections unusable: " + "; ".join(problems), status="invalid_input")
    return t_det, det


def cor_frames(n_frames: int, step: int) -> np.ndarray:
    """Indices of the tracking frames whose poses E_cor compares: every ``step``-th, always with the last."""
    idx = np.arange(0, n_frames, step)
    return idx if idx[-1] == n_frames - 1 else np.append(idx, n_frames - 1)


def window_tracks(parts, step: int, where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tracks of several consecutive batches as one set for E_cor: (t_us (n_cor,), xy (n_cor, H, 2), valid
    (n_cor, H)). Each batch contributes its correspondence frames (every ``step``-th tracking frame and its last,
    :func:`cor_frames`) and its own columns of tracks, valid only within its own frames; neighbouring batches share
    their boundary frame."""
    times, cols = [], []
    for part in parts:
        t = np.asarray(part.t_us, dtype=np.int64)
        if t.size < 2:
            raise StageFailed(f"{where}: {t.size} tracking frame(s) in a batch of the window; need at least 2",
                              status="invalid_input")
        idx = cor_frames(t.size, step)
        times.append(t[idx])
        cols.append((idx, np.asarray(part.xy, dtype=np.float64), np.asarray(part.valid)))
    t_cor = np.unique(np.concatenate(times))
    H = sum(xy.shape[1] for _, xy, _ in cols)
    xy_all = np.full((t_cor.size, H, 2), np.nan)
    valid_all = np.zeros((t_cor.size, H), dtype=bool)
    o = 0
    for t_p, (idx, xy, valid) in zip(times, cols):
        rows = np.searchsorted(t_cor, t_p)
        h = xy.shape[1]
        xy_all[rows, o:o + h] = xy[idx]
        valid_all[rows, o:o + h] = valid[idx]
        o += h
    bad = valid_all & ~np.all(np.isfinite(xy_all), axis=-1)
    if bad.any():
        raise StageFailed(f"{where}: a track has a non-finite position where it is marked valid", status="invalid_input")
    return t_cor, xy_all, valid_all


def window_times(sliced, index, batches, b: int, a: int, z: int, t_us: np.ndarray) -> np.ndarray:
    """The window's batches' tracking times (one grid for the whole recording, eventcap.analysis.motion.tracking_times_us), so
    overlapping windows give the same times. They follow from the batches at the step of batch b (the unit's first)
    when that step reproduces its own times (a whole number of µs: 1 kHz); else they are read from the batches' tracks."""
    rate = 1e6 / int(np.median(np.diff(t_us)))
    whole_us = np.array_equal(tracking_times_us(int(batches.t0_us[b]), int(batches.t1_us[b]), rate), t_us)
    return np.unique(np.concatenate([
        np.asarray(sliced[index[k]].t_us, dtype=np.int64) if k in index and not whole_us
        else tracking_times_us(int(batches.t0_us[k]), int(batches.t1_us[k]), rate) for k in range(a, z + 1)]))


def prior_context(config, frames: np.ndarray, t_det, detections, where: str, log):
    """(times, detections) of the detections within ``smoothing.seconds`` of the window's detection frames t_det
    (at the intensity frames, and between them where the detector looked), whose fits give the window's evidence
    of the motion (the prior's process power, the context pull); None (and a log line) when the intensity frames
    (frames: the recording's batch boundaries) come less often than ``smoothing.min_fps``. StageFailed when their
    detections are missing."""
    fps = 1e6 / float(np.median(np.diff(frames))) if frames.size > 1 else 0.0
    if fps < float(config.smoothing.min_fps):
        log.info("%s: no smoothing evidence from the fits around the window (no prior gains, no context pull): "
                 "intensity frames at %.1f fps, below stages.solve.smoothing.min_fps (%g)", where, fps,
                 float(config.smoothing.min_fps))
        return None
    reach = int(round(float(config.smoothing.seconds) * 1e6))
    t_ctx = detection_times(detections, int(t_det[0]) - reach, int(t_det[-1]) + reach)
    try:
        return t_ctx, select_detections(detections, t_ctx)
    except ValueError as exc:
        raise StageFailed(f"{where}: the prior's context: {exc}", status="missing_detections") from exc


__all__ = ["WindowPlan", "cor_frames", "plan_window", "prior_context", "window_detections", "window_times",
           "window_tracks"]
