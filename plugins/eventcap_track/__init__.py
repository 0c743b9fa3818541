"""Event trajectory generation (paper Sec. 3.1): feature tracking and B-spline trajectory slicing."""
