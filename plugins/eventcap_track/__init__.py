"""Event trajectory generation (paper Sec. 3.1): EDI sharpening, feature tracking and B-spline trajectory slicing."""
