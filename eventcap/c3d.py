"""C3D export of a motion: the 3D joints (and the template's landmarks) as labelled markers, in millimetres.

C3D is the file mocap pipelines exchange (Vicon Nexus, Motive, Visual3D, OpenSim read it). The file is written with
``ezc3d`` (a kept C++ library with Python bindings, on PyPI):

- one point per joint, labelled with the skeleton's joint names (``pelvis``, ``l_hip``, ... in SMPL order), then,
  when given, one per template landmark labelled ``lm_<name>`` (``lm_nose``, ``lm_r_eye``, ...: the BODY_25 points
  the detectors report; the prefix keeps labels unique where a landmark shares a joint's name);
- ``POINT:RATE`` the tracking frame rate (1000 Hz by default), ``POINT:UNITS`` ``mm``, ``POINT:DESCRIPTIONS`` what each
  point is; the world frame is the run's own (metres there, y up; ``POINT:X_SCREEN = +X``, ``POINT:Y_SCREEN = +Y``
  tell C3D viewers which axis is up);
- C3D needs a constant rate: the frames lie on the grid ``t_us[0] + k * step``; grid frames the run did not estimate
  (failed or unselected batches) are *invalid* points (residual -1, the C3D convention for a gap), not interpolated,
  and the log says how many. ``EVENTCAP:T0_US`` holds the time of the first frame on the run's time axis.

The file appears atomically (``<stem>.partial.c3d``, then renamed); on error nothing is left behind.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from .body.skeleton import JOINT_NAMES, LANDMARK_NAMES

log = logging.getLogger("eventcap.c3d")

#: Prefix of the template landmarks' labels (BODY_25 names; several equal joint names).
LANDMARK_PREFIX = "lm_"


def c3d_labels(with_landmarks: bool) -> list[str]:
    """The point labels of an exported file: the joints, then (optionally) the landmarks."""
    return list(JOINT_NAMES) + ([LANDMARK_PREFIX + n for n in LANDMARK_NAMES] if with_landmarks else [])


def _ezc3d():
    try:
        import ezc3d
    except ImportError:
        raise ImportError("C3D export needs the ezc3d package (an eventcap dependency): pip install ezc3d") from None
    return ezc3d


def write_c3d(path, t_us, joints, landmarks=None, step_us: int | None = None) -> Path:
    """Write the markers of a motion as a C3D file; returns the path.

    t_us: (T,) int64 microseconds, strictly increasing (the estimated frames). joints: (T, 24, 3) metres.
    landmarks: optional (T, L, 3) metres in ``skeleton.LANDMARK_NAMES`` order. step_us: the frame step (default:
    the median step of ``t_us``; 1000 us -> 1000 Hz). Times off the grid ``t_us[0] + k * step_us`` are refused.
    """
    path = Path(path)
    t = np.asarray(t_us)
    if t.ndim != 1 or t.size < 1 or not np.issubdtype(t.dtype, np.integer):
        raise ValueError(f"t_us: expected integer microseconds of shape (T,), T >= 1, got {t.dtype} {t.shape}")
    t = t.astype(np.int64)
    if t.size > 1 and np.any(np.diff(t) <= 0):
        i = int(np.argmax(np.diff(t) <= 0)) + 1
        raise ValueError(f"t_us: expected strictly increasing times, frame {i} is at {t[i]} us after {t[i - 1]} us")
    J = np.asarray(joints, dtype=np.float64)
    if J.shape != (t.size, len(JOINT_NAMES), 3):
        raise ValueError(f"joints: expected shape ({t.size}, {len(JOINT_NAMES)}, 3) (T, joints, xyz metres), "
                         f"got {J.shape}")
    points = [J]
    if landmarks is not None:
        L = np.asarray(landmarks, dtype=np.float64)
        if L.shape != (t.size, len(LANDMARK_NAMES), 3):
            raise ValueError(f"landmarks: expected shape ({t.size}, {len(LANDMARK_NAMES)}, 3), got {L.shape}")
        points.append(L)
    P = np.concatenate(points, axis=1)
    if not np.all(np.isfinite(P)):
        raise ValueError("joints/landmarks: expected finite values, got NaN or inf")
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
    k = (t - t[0]) // step_us
    n_frames = int(k[-1]) + 1
    labels = c3d_labels(landmarks is not None)
    n = len(labels)

    ezc3d = _ezc3d()
    data = np.zeros((4, n, n_frames))
    data[3] = 1.0
    data[:3, :, k] = np.transpose(P * 1000.0, (2, 1, 0))  # (xyz, point, frame), mm
    residuals = np.full((1, n, n_frames), -1.0)  # -1: not estimated (the C3D convention for an invalid point)
    residuals[:, :, k] = 0.0
    gaps = n_frames - t.size
    if gaps:
        log.warning("c3d: %d of %d frames (at %g Hz) were not estimated (gaps between batches); they are marked "
                    "invalid (residual -1)", gaps, n_frames, 1e6 / step_us)
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [1e6 / step_us]
    c["parameters"]["POINT"]["LABELS"]["value"] = labels
    c["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    descriptions = [f"SMPL joint {name}" for name in JOINT_NAMES]
    if landmarks is not None:
        descriptions += [f"template landmark {name} (BODY_25)" for name in LANDMARK_NAMES]
    c.add_parameter("POINT", "DESCRIPTIONS", descriptions)
    c.add_parameter("POINT", "X_SCREEN", ["+X"])
    c.add_parameter("POINT", "Y_SCREEN", ["+Y"])
    c.add_parameter("EVENTCAP", "T0_US", [str(int(t[0]))])  # a string: floats lose microseconds
    c["data"]["points"] = data
    c["data"]["meta_points"]["residuals"] = residuals
    c["data"]["meta_points"]["camera_masks"] = np.zeros((7, n, n_frames), dtype=bool)

    tmp = path.with_name(path.stem + ".partial.c3d")  # ezc3d appends .c3d to any other name
    tmp.unlink(missing_ok=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        c.write(str(tmp))
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path
