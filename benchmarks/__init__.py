"""Benchmarks: `python -m benchmarks` runs every `bench_*.py` here and charts speed against accuracy."""
