"""A motion and what can be said of it: the joined motion of a run, measures against ground truth, smoothing
splines, the confidence per joint and frame, and plausibility checks. Domain library: no orchestration."""
