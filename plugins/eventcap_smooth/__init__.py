"""Frames-only smoothing of per-frame fits over time (the ``frames_smooth`` baseline; not in the paper)."""
