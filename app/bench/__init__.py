"""Benchmarks that need the editor window (see app/commands/bench.py)."""
