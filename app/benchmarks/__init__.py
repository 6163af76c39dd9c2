"""Benchmarks behind ``smartroom bench``: speed is measured here, never in unit tests."""
