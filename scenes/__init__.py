"""Scenes the project makes itself: rendered piecewise-planar scenes with ground-truth cameras."""
