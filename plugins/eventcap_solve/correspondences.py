"""The event correspondences of E_cor and the indicator φ of E_temp now live in the shared energy library
(:mod:`eventcap.energy.correspondences`); this module keeps the plugin's old import path."""

from eventcap.energy.correspondences import (  # noqa: F401
    DEPTH_JUMP_M,
    EDGE_MARGIN_PX,
    MIN_BLEND_DET,
    PHI_SCOPES,
    Correspondences,
    check_tracks,
    edge_distance,
    find_correspondences,
    joint_parts,
    rest_point,
    temporal_indicator,
)

__all__ = ["DEPTH_JUMP_M", "EDGE_MARGIN_PX", "MIN_BLEND_DET", "PHI_SCOPES", "Correspondences", "check_tracks",
           "edge_distance", "find_correspondences", "joint_parts", "rest_point", "temporal_indicator"]
