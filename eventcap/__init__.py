"""EventCap: 3D capture of fast human motion at 1000 fps from a single event camera (CVPR 2020)."""

__version__ = "0.1.0"
