"""Benchmarks that run without a window (see app/commands/bench.py)."""
