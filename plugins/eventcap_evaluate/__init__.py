"""Evaluation of an estimated motion against ground truth (paper Sec. 4): AE, its STD, AE.raw / AE.nonRaw, per-joint
errors and the data rate the method consumed."""
