"""The spline solve (not in the paper): a continuous-time pose trajectory over windows of batches."""
