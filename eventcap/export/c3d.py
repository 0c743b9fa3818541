"""C3D export of a motion: the 3D joint centres and the template's surface markers, for mocap software.

C3D is the file mocap pipelines exchange (Vicon Nexus, Motive, Visual3D, OpenSim read it). It is written with the
pure-Python ``c3d`` package (MIT, on PyPI), and read back in the tests by it and by ``ezc3d`` (a C++ library):

- one point per joint centre, labelled with the skeleton's joint names (``pelvis``, ``l_hip``, ... in SMPL order),
  then, when given, one per surface marker (the 39 Plug-in Gait markers placed on the template's mesh,
  :mod:`eventcap.body.markers`: ``LFHD``, ``C7``, ``LASI``, ``LKNE``, ...); ``POINT:DESCRIPTIONS`` says what each
  point is. (Earlier files carried BODY_25 landmarks, 13 of which were joint centres again: they are gone.)
- ``POINT:RATE`` the tracking frame rate (1000 Hz by default); lengths in ``units`` (``POINT:UNITS``: m, cm or
  mm), axes as ``up_axis`` says (:mod:`eventcap.worldframe`), and ``POINT:X_SCREEN`` / ``POINT:Y_SCREEN`` tell
  viewers which axis is up (``+X``/``+Y`` for y up, ``+X``/``+Z`` for z up).
- C3D needs a constant rate: the frames lie on the grid ``t_us[0] + k * step``; grid frames the run did not
  estimate are *invalid* points (residual -1, the C3D convention for a gap), never interpolated, and the log says
  how many. The residual column (:func:`point_residuals`) is what Vicon means by it, the point's quality: each
  point's uncertainty (the RMS 3D distance to the truth one expects, calibrated: :mod:`eventcap.analysis.uncertainty`)
  in the file's length unit, 0 when the run has none; -1 only where there is no estimate (a gap), which mocap tools
  (Nexus, Visual3D, OpenSim) read as missing data. ``EVENTCAP:RESIDUAL`` says so in the file. C3D keeps a residual
  in one byte, in units of |POINT:SCALE| (which scales nothing else in a float file): the scale is 1 mm in the file's
  unit, so a residual reads in steps of 1 mm from 1 mm up to 255 mm, where it saturates (a point that uncertain is
  not to be trusted anyway; motion.npz keeps the exact value).
- Time origin: the first frame's number is its time on the run's time axis in frames, plus one (C3D counts from 1:
  frame n lies at ``(n - 1) / rate``): the header's first-frame word and ``TRIAL:ACTUAL_START_FIELD`` hold it,
  so a viewer's time axis shows the run's times. ``EVENTCAP:T0_US`` holds the first frame's time in microseconds
  exactly (a string: floats lose microseconds).
- Any length. The header's frame words and ``POINT:FRAMES`` are 16-bit; past frame 65,535 the file follows the
  compatibility rules of the C3D user guide ("Maintaining C3D frame count compatibility"): header frame range
  capped at 65,535, ``POINT:FRAMES`` 65,535, the real count in ``POINT:LONG_FRAMES`` (float) and the last frame
  in ``TRIAL:ACTUAL_END_FIELD`` (two 16-bit words, least significant first). Measured here: the ``c3d`` package
  honours ACTUAL_END_FIELD and LONG_FRAMES; ``ezc3d`` 1.7.2 honours neither but reads such a file to its end, so
  the file ends right after its last frame when the usual padding to a 512-byte block could hold a whole frame
  (fewer than 32 points), or ezc3d would read the padding as frames of zeros. (ezc3d itself writes a 16-bit frame
  count, and its own long files read back as 65,535 frames: why it no longer writes them.)

The file appears atomically (``<stem>.partial.c3d``, then renamed); on error nothing is left behind.
"""

from __future__ import annotations

import logging
import os
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from eventcap.body.skeleton import JOINT_NAMES
from eventcap.worldframe import check_frame, to_export, unit_scale

log = logging.getLogger("eventcap.export.c3d")

#: Frame numbers past this need the long-file parameters (16-bit header words and POINT:FRAMES).
MAX_SHORT_FRAME = 65535
#: The residual's step (|POINT:SCALE|, mm): C3D keeps a residual in one byte, so it reads 1-255 steps.
RESIDUAL_STEP_MM = 1.0
#: Bytes of one point in a float C3D frame (x, y, z, residual word).
_POINT_BYTES = 16


def c3d_labels(marker_names: Sequence[str] = ()) -> list[str]:
    """The point labels of an exported file: the joint centres, then the markers."""
    return list(JOINT_NAMES) + list(marker_names)


def point_residuals(valid: np.ndarray, uncertainty: np.ndarray | None = None) -> np.ndarray:
    """The C3D residual of every point in every frame, (frames, points): -1 marks a point that is not there (a gap).

    valid: (frames, points) bool, the points the run estimated. uncertainty: optional (frames, points), each point's
    uncertainty in the file's length unit (>= 0; NaN: none known). A valid point's residual is its uncertainty, 0
    where it has none (the C3D value of a point without an error estimate); only a point that is not there is -1.
    """
    valid = np.asarray(valid, dtype=bool)
    out = np.where(valid, 0.0, -1.0)
    if uncertainty is None:
        return out
    u = np.asarray(uncertainty, dtype=np.float64)
    if u.shape != valid.shape:
        raise ValueError(f"uncertainty: expected shape {valid.shape} (frames, points), got {u.shape}")
    finite = u[np.isfinite(u)]
    if finite.size and finite.min() < 0.0:
        raise ValueError(f"uncertainty: expected values >= 0 (NaN: none known), got {finite.min():g}")
    return np.where(valid, np.where(np.isfinite(u), u, 0.0), -1.0)


def _c3d():
    try:
        import c3d
    except ImportError:
        raise ImportError("C3D export needs the c3d package (an eventcap dependency): pip install c3d") from None
    return c3d


def _check_times(t_us, step_us: int | None) -> tuple[np.ndarray, int, np.ndarray]:
    t = np.asarray(t_us)
    if t.ndim != 1 or t.size < 1 or not np.issubdtype(t.dtype, np.integer):
        raise ValueError(f"t_us: expected integer microseconds of shape (T,), T >= 1, got {t.dtype} {t.shape}")
    t = t.astype(np.int64)
    if t.size > 1 and np.any(np.diff(t) <= 0):
        i = int(np.argmax(np.diff(t) <= 0)) + 1
        raise ValueError(f"t_us: expected strictly increasing times, frame {i} is at {t[i]} us after {t[i - 1]} us")
    if step_us is None:
        step_us = int(np.median(np.diff(t))) if t.size > 1 else 1000
    step_us = int(step_us)
    if step_us <= 0:
        raise ValueError(f"step_us: expected a positive step, got {step_us}")
    off = (t - t[0]) % step_us
    if np.any(off):
        i = int(np.argmax(off != 0))
        raise ValueError(f"t_us: frame {i} ({t[i]} us) is not on the {step_us} us grid starting at {t[0]} us; "
                         f"C3D needs a constant frame rate")
    return t, step_us, (t - t[0]) // step_us


def _points(t: np.ndarray, joints, markers, marker_names) -> np.ndarray:
    J = np.asarray(joints, dtype=np.float64)
    if J.shape != (t.size, len(JOINT_NAMES), 3):
        raise ValueError(f"joints: expected shape ({t.size}, {len(JOINT_NAMES)}, 3) (T, joints, xyz metres), "
                         f"got {J.shape}")
    parts = [J]
    if markers is not None:
        M = np.asarray(markers, dtype=np.float64)
        if M.shape != (t.size, len(marker_names), 3):
            raise ValueError(f"markers: expected shape ({t.size}, {len(marker_names)}, 3) (T, markers named by "
                             f"marker_names, xyz metres), got {M.shape}")
        parts.append(M)
    elif marker_names:
        raise ValueError("marker_names given without markers")
    P = np.concatenate(parts, axis=1)
    if not np.all(np.isfinite(P)):
        raise ValueError("joints/markers: expected finite values, got NaN or inf")
    return P


def write_c3d(path, t_us, joints, markers=None, step_us: int | None = None, *, marker_names: Sequence[str] = (),
              marker_descriptions: Sequence[str] | None = None, up_axis: str = "y", units: str = "mm",
              uncertainty_mm: np.ndarray | None = None) -> Path:
    """Write the points of a motion as a C3D file; returns the path.

    t_us: (T,) int64 microseconds, strictly increasing (the estimated frames), on the grid ``t_us[0] + k * step_us``
    (default step: the median step; 1000 us -> 1000 Hz). joints: (T, 24, 3) metres, internal world frame (y up).
    markers: optional (T, M, 3) metres named by ``marker_names`` (M,), described by ``marker_descriptions``.
    up_axis ``y | z`` and units ``m | cm | mm``: the file's frame (:mod:`eventcap.worldframe`). uncertainty_mm:
    optional (T, 24 + M) per point, mm (NaN: none known), written as the residual in the file's unit
    (:func:`point_residuals`).
    """
    path = Path(path)
    check_frame(up_axis, units)
    t, step_us, k = _check_times(t_us, step_us)
    marker_names = list(marker_names)
    P = _points(t, joints, markers, marker_names)
    labels = c3d_labels(marker_names)
    n_frames, n = int(k[-1]) + 1, len(labels)
    valid = np.zeros((n_frames, n), dtype=bool)
    valid[k] = True
    unc = None
    if uncertainty_mm is not None:
        u = np.asarray(uncertainty_mm, dtype=np.float64)
        if u.shape != (t.size, n):
            raise ValueError(f"uncertainty_mm: expected shape ({t.size}, {n}) (T, points), got {u.shape}")
        unc = np.full((n_frames, n), np.nan)
        unc[k] = u / 1000.0 * unit_scale(units)
    residuals = point_residuals(valid, unc)
    step = RESIDUAL_STEP_MM / 1000.0 * unit_scale(units)
    residuals = np.where(residuals > 0, np.clip(residuals, step, 255 * step), residuals)  # one byte of |POINT:SCALE|
    gaps = n_frames - t.size
    if gaps:
        log.warning("c3d: %d of %d frames (at %g Hz) were not estimated (gaps between batches); they are marked "
                    "invalid (residual -1)", gaps, n_frames, 1e6 / step_us)
    frames = np.zeros((n_frames, n, 5), np.float32)  # x, y, z, residual, cameras (c3d's layout)
    frames[k, :, :3] = to_export(P, up_axis, units)
    frames[..., 3] = residuals
    descriptions = [f"SMPL joint centre {name}" for name in JOINT_NAMES] + list(
        marker_descriptions if marker_descriptions is not None else [f"marker {m}" for m in marker_names])
    if len(descriptions) != n:
        raise ValueError(f"marker_descriptions: expected {len(marker_names)} descriptions, got "
                         f"{len(descriptions) - len(JOINT_NAMES)}")
    first_frame = _first_frame_number(int(t[0]), step_us)
    writer = _writer(frames, labels, descriptions, 1e6 / step_us, units, up_axis, first_frame, int(t[0]), step)
    tmp = path.with_name(path.stem + ".partial.c3d")
    tmp.unlink(missing_ok=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with open(tmp, "wb") as fh, warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the package's notes about analog-free files
            writer.write(fh)
        if first_frame + n_frames - 1 > MAX_SHORT_FRAME and n * _POINT_BYTES < 512:
            os.truncate(tmp, _data_end(tmp, n_frames, n))  # see the module docstring: ezc3d reads to the end
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def _first_frame_number(t0_us: int, step_us: int) -> int:
    """C3D frame number of the first frame: its time in frames plus one, when that is a whole number of frames up to
    65,535 (readers disagree on how ACTUAL_START_FIELD's high word counts); else 1, and EVENTCAP:T0_US has the time."""
    if t0_us >= 0 and t0_us % step_us == 0 and t0_us // step_us + 1 <= MAX_SHORT_FRAME:
        return t0_us // step_us + 1
    log.info("c3d: the first frame (t = %d us) is not a whole number (up to 65,535) of %d us frames from time zero; "
             "it is frame 1 (EVENTCAP:T0_US holds its time)", t0_us, step_us)
    return 1


def _writer(frames: np.ndarray, labels, descriptions, rate: float, units: str, up_axis: str, first_frame: int,
            t0_us: int, residual_step: float):
    c3d = _c3d()
    # a negative scale: float coordinates; its magnitude is the residual's unit (module doc)
    w = c3d.Writer(point_rate=float(rate), point_scale=-float(residual_step), point_units=units)
    empty = np.zeros((0, 0), np.float32)
    w.add_frames([(f, empty) for f in frames])
    w.set_point_labels(labels)
    text, width = c3d.Writer.pack_labels(descriptions)
    w.point_group.add_str("DESCRIPTIONS", "What each point is.", text, width, len(descriptions))
    w.set_screen_axis("+X", "+Z" if up_axis == "z" else "+Y")
    w.set_start_frame(first_frame)
    g = w.add_group(w.numeric_key_next, "EVENTCAP", "EventCap export")
    g.add_str("T0_US", "Time of the first frame on the run's time axis, microseconds", str(t0_us), len(str(t0_us)))
    g.add_str("UP_AXIS", "Vertical axis of the world frame", up_axis, 1)
    text = (f"residual: the point's uncertainty in {units} (expected RMS 3D distance to the truth after a per-frame "
            "rigid alignment, calibrated: within 2 of it 90-97 % of the time), 1 mm steps up to 255 mm (saturated); "
            "0: none known; -1: no estimate (gap)")
    g.add_str("RESIDUAL", "What the points' residual is", text, len(text))
    return w


def _data_end(path: Path, n_frames: int, n_points: int) -> int:
    """Byte offset just past the last frame of a C3D file written by :func:`_writer` (header word 9: the first
    data block, 1-based, of 512 bytes)."""
    with open(path, "rb") as fh:
        head = fh.read(20)
    data_block = int(np.frombuffer(head[16:18], "<u2")[0])
    return (data_block - 1) * 512 + n_frames * n_points * _POINT_BYTES
