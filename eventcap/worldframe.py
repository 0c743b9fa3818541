"""The world frame of the files a run hands over (BVH, C3D): which axis is up, which length unit, and the time origin.

Inside, the world is right-handed, y up, in metres (:mod:`eventcap.body.skeleton`: the actor's rest pose stands on
y = 0 facing +z, its left +x). Mocap tools differ: Vicon Nexus, Visual3D, OpenSim's C3D import and Motive's
Z-up option expect z up; Blender imports BVH as y up by default. ``up_axis="z"`` rotates the world by +90 degrees
about x, ``(x, y, z) -> (x, -z, y)``: still right-handed, the vertical becomes +z, the actor's rest facing
direction becomes -y and its left stays +x. ``units`` scales every length (``m`` 1, ``cm`` 100, ``mm`` 1000).
Times: the run's time axis (microseconds from the recording's time zero); each file states the time of its first
frame (the time origin of its own frame count).
"""

from __future__ import annotations

import numpy as np

UP_AXES: tuple[str, ...] = ("y", "z")
UNITS: dict[str, float] = {"m": 1.0, "cm": 100.0, "mm": 1000.0}

#: Rotation from the internal y-up world into each export frame.
_ROTATIONS = {"y": np.eye(3), "z": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])}


def check_frame(up_axis: str, units: str, where: str = "") -> None:
    """A ValueError naming ``where``.up_axis / .units when they are not one of the allowed values."""
    if up_axis not in UP_AXES:
        raise ValueError(f"{where}up_axis: expected one of {' | '.join(UP_AXES)}, got {up_axis!r}")
    if units not in UNITS:
        raise ValueError(f"{where}units: expected one of {' | '.join(UNITS)}, got {units!r}")


def rotation(up_axis: str) -> np.ndarray:
    """The 3x3 rotation taking internal (y-up) world coordinates into the ``up_axis`` frame."""
    check_frame(up_axis, "m")
    return _ROTATIONS[up_axis].copy()


def unit_scale(units: str) -> float:
    """Length units per metre."""
    check_frame("y", units)
    return UNITS[units]


def to_export(points: np.ndarray, up_axis: str = "y", units: str = "m") -> np.ndarray:
    """Points (..., 3) in internal metres, y up -> the export frame (rotated, scaled)."""
    return (np.asarray(points, dtype=np.float64) @ rotation(up_axis).T) * unit_scale(units)


def describe(up_axis: str, units: str) -> str:
    """One line naming the frame, written into files that take a comment."""
    facing = "-y" if up_axis == "z" else "+z"
    return (f"right-handed, {up_axis} up, lengths in {units}; rest pose facing {facing}, actor's left +x; "
            f"origin: the run's world origin (the floor point the template's rest pose stands on)")


def upright(rec, detections):
    """The recording in the world its detections were made in: with the camera turned upright by the detect stage
    (``Detections.world_R``: a recording without extrinsics, its world turned to the person's vertical), else as it
    is. Every stage that places the body in the world (the solves, the refinement, the confidence, the outputs) reads
    the recording through this, so that they share one world."""
    import dataclasses

    R = None if detections is None else detections.world_R
    if R is None:
        return rec
    return dataclasses.replace(rec, camera=rec.camera.with_pose(np.asarray(R, dtype=np.float64), rec.camera.t))
