"""Benchmark scripts: one per figure of docs/results.md, each run as ``python -m benchmarks.NAME``."""
