"""World joint positions of a BVH file as the independent `bvh` package reads it: the reference the export tests compare
our files with."""

from __future__ import annotations

import bvh
import numpy as np

from eventcap.body.skeleton import JOINT_NAMES


def positions_via_bvh_package(path) -> dict[str, np.ndarray]:
    """World joint positions (T, 3) per joint name from a file parsed by the `bvh` package, with the BVH
    conventions: rotation channels are intrinsic in listed order, offsets in the parent's frame, root position
    channels added to the root offset."""
    mocap = bvh.Bvh(open(path).read())
    data = np.array(mocap.frames, dtype=np.float64)
    assert data.shape[0] == mocap.nframes
    T = data.shape[0]
    world_R: dict[str, np.ndarray] = {}
    world_p: dict[str, np.ndarray] = {}
    col = 0
    for name in mocap.get_joints_names():
        channels = mocap.joint_channels(name)
        offset = np.array(mocap.joint_offset(name))
        R = np.broadcast_to(np.eye(3), (T, 3, 3))
        local_p = np.broadcast_to(offset, (T, 3)).copy()
        for ch in channels:
            v = data[:, col]
            col += 1
            if ch.endswith("rotation"):
                R = R @ axis_rotation(ch[0], v)
            else:
                local_p[:, "XYZ".index(ch[0])] += v
        parent = mocap.joint_parent(name)
        if parent is None:
            world_R[name], world_p[name] = R, local_p
        else:
            pn = parent.name
            world_p[name] = world_p[pn] + np.einsum("tij,j->ti", world_R[pn], offset)
            world_R[name] = world_R[pn] @ R
    assert col == data.shape[1]
    return world_p


def stacked(positions: dict[str, np.ndarray]) -> np.ndarray:
    """(T, 24, 3): the per-name positions in our joint order."""
    return np.stack([positions[n] for n in JOINT_NAMES], axis=1)


def axis_rotation(axis: str, deg: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations by ``deg`` degrees about the axis "X", "Y" or "Z" (BVH channel letters)."""
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    if axis == "X":
        R[..., 0, 0] = 1
        R[..., 1, 1], R[..., 1, 2], R[..., 2, 1], R[..., 2, 2] = c, -s, s, c
    elif axis == "Y":
        R[..., 1, 1] = 1
        R[..., 0, 0], R[..., 0, 2], R[..., 2, 0], R[..., 2, 2] = c, s, -s, c
    else:
        R[..., 2, 2] = 1
        R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1] = c, -s, s, c
    return R
