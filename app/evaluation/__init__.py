"""Scores against ground truth (``smartroom eval``, benchmarks): pure functions."""
