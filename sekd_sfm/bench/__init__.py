"""Benchmarks: speed, homography, pose and SfM evaluations."""
