"""Evaluation: ground truth, pose metrics, stock COLMAP, comparisons and benchmarks."""
